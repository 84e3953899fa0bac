//! Mass matrices and Rayleigh damping on K's pattern.

use deform_mesh::topology::BlockPattern;
use deform_mesh::{ConsistentMass, TetMesh};

use rayon::iter::{IndexedParallelIterator, IntoParallelIterator, ParallelIterator};

use crate::assembly::check_len;

/// Rows of a reduced matrix per parallel task of [`Assembly::combine_reduced`].
const REDUCED_ROWS: usize = 1024;
/// Entries per parallel task of a product with a lumped mass.
const LUMPED_ROWS: usize = 8192;
use crate::{Assembly, AssemblyError, DofMap, ReducedMatrix, StiffnessMatrix};

/// A mass matrix: lumped (diagonal, `rho W / 4` per element corner) or consistent
/// (`M_ab = rho W (1 + delta_ab) / 20` per element, one scalar per 3x3 block of K's pattern).
/// Both are the mesh crate's ([`TetMesh::lumped_mass`], [`TetMesh::consistent_mass`]).
#[derive(Debug, Clone, PartialEq)]
pub enum Mass {
    /// One mass per vertex.
    Lumped(Vec<f64>),
    /// One scalar per block of the stiffness pattern (block `(i, j)` is `m_k I3`).
    Consistent(ConsistentMass),
}

impl Mass {
    /// The lumped mass of `mesh` for `density` (kg/m^3).
    pub fn lumped(mesh: &TetMesh, density: f64) -> Self {
        Mass::Lumped(mesh.lumped_mass(density))
    }

    /// The consistent mass of `mesh` for `density` on the block pattern of its assembly.
    ///
    /// # Panics
    /// If `pattern` is not the pattern of `mesh` (use [`Assembly::pattern`]).
    #[track_caller]
    pub fn consistent(mesh: &TetMesh, density: f64, pattern: &BlockPattern) -> Self {
        Mass::Consistent(mesh.consistent_mass(density, pattern))
    }

    /// The scalar `m` of block `blk` (in row `v`, `columns` the pattern's) where the mass
    /// matrix has `m I3`, or `None` where it has no block (a lumped mass off the diagonal).
    fn block(&self, columns: &[usize], v: usize, blk: usize) -> Option<f64> {
        match self {
            Mass::Lumped(m) if columns[blk] == v => Some(m[v]),
            Mass::Lumped(_) => None,
            Mass::Consistent(m) => Some(m.values[blk]),
        }
    }
}

impl Assembly {
    /// `y = M x`.
    ///
    /// # Errors
    /// [`AssemblyError::DimensionMismatch`] for bad lengths.
    pub fn mass_apply(&self, mass: &Mass, x: &[f64], y: &mut [f64]) -> Result<(), AssemblyError> {
        let n = self.num_dofs();
        check_len("x", x.len(), n)?;
        check_len("y", y.len(), n)?;
        self.check_mass(mass)?;
        match mass {
            Mass::Lumped(m) => {
                // Each entry alone: the same bits in any chunking.
                let rows = |(c, ys): (usize, &mut [f64])| {
                    for (k, yi) in ys.iter_mut().enumerate() {
                        let i = c * LUMPED_ROWS + k;
                        *yi = m[i / 3] * x[i];
                    }
                };
                if crate::assembly::inline(y.len() / LUMPED_ROWS) {
                    y.chunks_mut(LUMPED_ROWS).enumerate().for_each(rows);
                } else {
                    use rayon::slice::ParallelSliceMut;
                    y.par_chunks_mut(LUMPED_ROWS).enumerate().for_each(rows);
                }
            }
            Mass::Consistent(m) => m.apply(&self.geometry.pattern, x, y),
        }
        Ok(())
    }

    /// Per-vertex masses of a lumped matrix, or the row sums of a consistent one.
    pub fn vertex_masses(&self, mass: &Mass) -> Vec<f64> {
        match mass {
            Mass::Lumped(m) => m.clone(),
            Mass::Consistent(m) => m.row_sums(&self.geometry.pattern),
        }
    }

    fn check_mass(&self, mass: &Mass) -> Result<(), AssemblyError> {
        match mass {
            Mass::Lumped(m) => check_len("lumped mass", m.len(), self.num_vertices()),
            Mass::Consistent(m) => check_len(
                "consistent mass",
                m.values.len(),
                self.geometry.pattern.num_blocks(),
            ),
        }
    }

    /// `out = c_m M + c_k K` on K's pattern: the Rayleigh damping matrix `alpha M + gamma K`,
    /// or the Backward-Euler matrix `(1 + dt alpha) M + (dt gamma + dt^2) K`. `k` and `out`
    /// must have this mesh's pattern (from [`Assembly::stiffness_matrix`]).
    ///
    /// # Errors
    /// [`AssemblyError::PatternMismatch`], or a mass of the wrong size.
    pub fn combine(
        &self,
        c_m: f64,
        mass: &Mass,
        c_k: f64,
        k: &StiffnessMatrix,
        out: &mut StiffnessMatrix,
    ) -> Result<(), AssemblyError> {
        if !self.owns(k) || !self.owns(out) {
            return Err(AssemblyError::PatternMismatch);
        }
        self.check_mass(mass)?;
        let p = &self.geometry.pattern;
        let offsets = p.offsets();
        let values = out.values_mut();
        for (o, kv) in values.iter_mut().zip(k.data()) {
            *o = c_k * kv;
        }
        for v in 0..p.num_rows() {
            let (start, len) = (offsets[v], offsets[v + 1] - offsets[v]);
            for blk in start..offsets[v + 1] {
                let Some(m) = mass.block(p.columns(), v, blk) else {
                    continue;
                };
                for r in 0..3 {
                    values[9 * start + 3 * len * r + 3 * (blk - start) + r] += c_m * m;
                }
            }
        }
        Ok(())
    }

    /// [`Assembly::combine`] restricted to the free DOFs of `dofs`, straight into `out` (from
    /// [`DofMap::reduced_matrix`] of K's pattern): the same values as `combine` then
    /// [`DofMap::restrict_matrix`], without the full matrix between them (2.3 GB at the
    /// n = 64 beam).
    ///
    /// # Errors
    /// [`AssemblyError::PatternMismatch`] for a `k` or `out` of another pattern or a `dofs`
    /// of another mesh, or a mass of the wrong size.
    pub fn combine_reduced(
        &self,
        c_m: f64,
        mass: &Mass,
        c_k: f64,
        k: &StiffnessMatrix,
        dofs: &DofMap,
        out: &mut ReducedMatrix,
    ) -> Result<(), AssemblyError> {
        if !self.owns(k)
            || out.full_nnz != k.nnz()
            || dofs.num_dofs() != self.num_dofs()
            || out.matrix.rows() != dofs.num_free()
        {
            return Err(AssemblyError::PatternMismatch);
        }
        self.check_mass(mass)?;
        let p = &self.geometry.pattern;
        let (offsets, columns, indptr) = (p.offsets(), p.columns(), &self.geometry.indptr);
        let (k, free) = (k.data(), dofs.free_dofs());
        let ReducedMatrix {
            matrix,
            gather,
            row_ptr: ptr,
            ..
        } = out;
        let fill = |(r0, r1, values): (usize, usize, &mut [f64])| {
            for row in r0..r1 {
                let i = free[row];
                let (v, r) = (i / 3, i % 3);
                for q in ptr[row]..ptr[row + 1] {
                    let (at, value) = (gather[q] as usize, &mut values[q - ptr[r0]]);
                    *value = c_k * k[at];
                    // Row i's entries are its blocks' columns, three per block (see `combine`).
                    let local = at - indptr[i];
                    if local % 3 == r
                        && let Some(m) = mass.block(columns, v, offsets[v] + local / 3)
                    {
                        *value += c_m * m;
                    }
                }
            }
        };
        // Rows are independent: the same values on any number of threads.
        let chunks = crate::dof::row_chunks(ptr, matrix.data_mut(), REDUCED_ROWS);
        if crate::assembly::inline(chunks.len()) {
            chunks.into_iter().for_each(fill);
        } else {
            chunks.into_par_iter().for_each(fill);
        }
        Ok(())
    }

    /// Rayleigh damping forces `f_d = -(alpha M + gamma K) v`, with `K` already assembled
    /// (not read when `gamma` is 0).
    ///
    /// # Errors
    /// Bad lengths, or (when `gamma` is not 0) a matrix without this mesh's pattern.
    pub fn damping_forces(
        &self,
        alpha: f64,
        gamma: f64,
        mass: &Mass,
        k: &StiffnessMatrix,
        v: &[f64],
        out: &mut [f64],
    ) -> Result<(), AssemblyError> {
        if gamma == 0.0 {
            // Without K (its pattern check and product cost a few ms at 98k tets, and the
            // Newton loop's residual and merit function call this several times a step).
            self.mass_apply(mass, v, out)?;
            out.iter_mut().for_each(|o| *o *= -alpha);
            return Ok(());
        }
        if !self.owns(k) {
            return Err(AssemblyError::PatternMismatch);
        }
        self.mass_apply(mass, v, out)?;
        let (indptr, indices, data) = (k.indptr(), k.indices(), k.data());
        let indptr = indptr.raw_storage();
        for (i, o) in out.iter_mut().enumerate() {
            let mut kv = 0.0;
            for p in indptr[i]..indptr[i + 1] {
                kv += data[p] * v[indices[p]];
            }
            *o = -(alpha * *o + gamma * kv);
        }
        Ok(())
    }
}
