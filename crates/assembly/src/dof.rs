//! Dirichlet conditions by elimination: a map between all `3N` degrees of freedom and the
//! free ones, for vectors and for K.
//!
//! Constrained vertices (fixed, or kinematic ones whose positions follow a prescribed path)
//! are removed from the linear system. The integrator sets their positions (and velocities)
//! before evaluating forces, so Newton updates are zero there and the reduced system
//! `A_ff dv_f = r_f` is exact; the coupling `A_fc` only enters through the forces, which are
//! evaluated at the prescribed positions.

use sprs::CsMat;

use crate::AssemblyError;
use crate::assembly::check_len;

/// Which degrees of freedom are free, and where they go in reduced vectors.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DofMap {
    num_vertices: usize,
    constrained: Vec<bool>,
    /// Full DOF of each reduced DOF, increasing.
    free: Vec<usize>,
    /// Reduced index of each full DOF, `usize::MAX` when constrained.
    reduced: Vec<usize>,
}

impl DofMap {
    /// All three DOFs of each listed vertex are constrained (duplicates are fine).
    ///
    /// # Errors
    /// [`AssemblyError::VertexOutOfRange`].
    pub fn new(num_vertices: usize, constrained_vertices: &[usize]) -> Result<Self, AssemblyError> {
        let mut constrained = vec![false; num_vertices];
        for &v in constrained_vertices {
            if v >= num_vertices {
                return Err(AssemblyError::VertexOutOfRange {
                    vertex: v,
                    num_vertices,
                });
            }
            constrained[v] = true;
        }
        let mut free = Vec::with_capacity(3 * num_vertices);
        let mut reduced = vec![usize::MAX; 3 * num_vertices];
        for v in 0..num_vertices {
            if !constrained[v] {
                for c in 0..3 {
                    reduced[3 * v + c] = free.len();
                    free.push(3 * v + c);
                }
            }
        }
        Ok(Self {
            num_vertices,
            constrained,
            free,
            reduced,
        })
    }

    /// Number of free DOFs.
    pub fn num_free(&self) -> usize {
        self.free.len()
    }

    /// Number of DOFs in total, `3N`.
    pub fn num_dofs(&self) -> usize {
        3 * self.num_vertices
    }

    /// Whether vertex `v` is constrained.
    pub fn is_constrained(&self, v: usize) -> bool {
        self.constrained[v]
    }

    /// The constrained vertices, increasing.
    pub fn constrained_vertices(&self) -> Vec<usize> {
        (0..self.num_vertices)
            .filter(|&v| self.constrained[v])
            .collect()
    }

    /// The full index of each free DOF.
    pub fn free_dofs(&self) -> &[usize] {
        &self.free
    }

    /// `reduced = full` restricted to the free DOFs.
    ///
    /// # Errors
    /// [`AssemblyError::DimensionMismatch`].
    pub fn restrict(&self, full: &[f64], reduced: &mut [f64]) -> Result<(), AssemblyError> {
        check_len("full vector", full.len(), self.num_dofs())?;
        check_len("reduced vector", reduced.len(), self.num_free())?;
        const ENTRIES: usize = 8192;
        let gather = |(r, free): (&mut [f64], &[usize])| {
            for (r, &i) in r.iter_mut().zip(free) {
                *r = full[i];
            }
        };
        if crate::assembly::inline(reduced.len() / ENTRIES) {
            gather((reduced, &self.free));
        } else {
            use rayon::iter::{IndexedParallelIterator, ParallelIterator};
            use rayon::slice::{ParallelSlice, ParallelSliceMut};
            let parts = reduced
                .par_chunks_mut(ENTRIES)
                .zip(self.free.par_chunks(ENTRIES));
            parts.for_each(gather);
        }
        Ok(())
    }

    /// Writes the free DOFs of `full` from `reduced`; constrained DOFs are left untouched.
    ///
    /// # Errors
    /// [`AssemblyError::DimensionMismatch`].
    pub fn scatter(&self, reduced: &[f64], full: &mut [f64]) -> Result<(), AssemblyError> {
        check_len("full vector", full.len(), self.num_dofs())?;
        check_len("reduced vector", reduced.len(), self.num_free())?;
        for (r, &i) in reduced.iter().zip(&self.free) {
            full[i] = *r;
        }
        Ok(())
    }

    /// The reduced matrix `A_ff` (rows and columns of the free DOFs) with its pattern, and the
    /// map through which [`DofMap::restrict_matrix`] refills it from a full matrix of the same
    /// pattern.
    ///
    /// # Errors
    /// [`AssemblyError::DimensionMismatch`] when `full` is not `3N x 3N` CSR,
    /// [`AssemblyError::TooLarge`] beyond 2^32 entries.
    pub fn reduced_matrix(&self, full: &CsMat<f64>) -> Result<ReducedMatrix, AssemblyError> {
        check_len("matrix rows", full.rows(), self.num_dofs())?;
        check_len("matrix columns", full.cols(), self.num_dofs())?;
        if !full.is_csr() {
            return Err(AssemblyError::PatternMismatch);
        }
        let (indptr, indices) = (full.indptr(), full.indices());
        let indptr = indptr.raw_storage();
        let mut rptr = Vec::with_capacity(self.num_free() + 1);
        let mut ridx = Vec::new();
        if full.nnz() > u32::MAX as usize {
            return Err(AssemblyError::TooLarge(full.nnz()));
        }
        let mut gather: Vec<u32> = Vec::new();
        rptr.push(0);
        for &i in &self.free {
            for p in indptr[i]..indptr[i + 1] {
                let j = self.reduced[indices[p]];
                if j != usize::MAX {
                    ridx.push(j);
                    gather.push(p as u32);
                }
            }
            rptr.push(ridx.len());
        }
        let data = gather.iter().map(|&p| full.data()[p as usize]).collect();
        let n = self.num_free();
        Ok(ReducedMatrix {
            matrix: CsMat::new((n, n), rptr.clone(), ridx, data),
            gather,
            full_nnz: full.nnz(),
            row_ptr: rptr,
        })
    }

    /// Refills `reduced` from `full` (same pattern as when `reduced` was made).
    ///
    /// # Errors
    /// [`AssemblyError::PatternMismatch`] when `full` has a different number of entries.
    pub fn restrict_matrix(
        &self,
        full: &CsMat<f64>,
        reduced: &mut ReducedMatrix,
    ) -> Result<(), AssemblyError> {
        if full.nnz() != reduced.full_nnz {
            return Err(AssemblyError::PatternMismatch);
        }
        let data = full.data();
        let fill = |(r, p): (&mut [f64], &[u32])| {
            for (r, &p) in r.iter_mut().zip(p) {
                *r = data[p as usize];
            }
        };
        let values = reduced.matrix.data_mut();
        const VALUES: usize = 16_384;
        if crate::assembly::inline(values.len() / VALUES) {
            fill((values, &reduced.gather));
        } else {
            use rayon::iter::{IndexedParallelIterator, ParallelIterator};
            use rayon::slice::{ParallelSlice, ParallelSliceMut};
            (values.par_chunks_mut(VALUES))
                .zip(reduced.gather.par_chunks(VALUES))
                .for_each(fill);
        }
        Ok(())
    }
}

/// The free-DOF block of a matrix and the gather map that refills it.
#[derive(Debug, Clone)]
pub struct ReducedMatrix {
    /// `A_ff` in CSR.
    pub matrix: CsMat<f64>,
    /// Position in the full matrix's values of each reduced value (32 bits: half the
    /// memory of the indices at 6.3 M tets, where a full matrix has 147 M values).
    pub(crate) gather: Vec<u32>,
    pub(crate) full_nnz: usize,
    /// The matrix's row pointers, kept beside it so that rows can be refilled in parallel
    /// while its values are borrowed mutably.
    pub(crate) row_ptr: Vec<usize>,
}

impl ReducedMatrix {
    /// Adds `scale` times each 3x3 block `(v, B)` to the diagonal block of vertex `v`
    /// (blocks of constrained vertices are skipped): the Hessian of a potential on single
    /// vertices, such as contact against an obstacle. Every vertex's diagonal block is in
    /// the pattern of a stiffness matrix.
    ///
    /// # Errors
    /// [`AssemblyError::VertexOutOfRange`] for a vertex beyond `dofs`,
    /// [`AssemblyError::PatternMismatch`] when a diagonal entry is missing.
    pub fn add_vertex_blocks(
        &mut self,
        dofs: &DofMap,
        blocks: &[(usize, nalgebra::Matrix3<f64>)],
        scale: f64,
    ) -> Result<(), AssemblyError> {
        // Positions first (the pattern is borrowed), values after.
        let (ptr, indices) = (&self.row_ptr, self.matrix.indices());
        let mut updates = Vec::with_capacity(9 * blocks.len());
        for (v, b) in blocks {
            if *v >= dofs.num_vertices {
                return Err(AssemblyError::VertexOutOfRange {
                    vertex: *v,
                    num_vertices: dofs.num_vertices,
                });
            }
            if dofs.is_constrained(*v) {
                continue;
            }
            for r in 0..3 {
                let row = dofs.reduced[3 * v + r];
                let cols = &indices[ptr[row]..ptr[row + 1]];
                for c in 0..3 {
                    let at = cols
                        .binary_search(&dofs.reduced[3 * v + c])
                        .map_err(|_| AssemblyError::PatternMismatch)?;
                    updates.push((ptr[row] + at, scale * b[(r, c)]));
                }
            }
        }
        let values = self.matrix.data_mut();
        for (at, value) in updates {
            values[at] += value;
        }
        Ok(())
    }

    /// The matrix plus `scale` times each 3x3 block `(i, j, B)` between two vertices
    /// (blocks touching a constrained vertex are skipped), as a new matrix on the union of
    /// the patterns: the Hessian of a potential that couples vertices no element joins, such
    /// as self-contact. The stored matrix is left as it is.
    ///
    /// # Errors
    /// [`AssemblyError::VertexOutOfRange`] for a vertex beyond `dofs`.
    pub fn with_couplings(
        &self,
        dofs: &DofMap,
        blocks: &[(usize, usize, nalgebra::Matrix3<f64>)],
        scale: f64,
    ) -> Result<CsMat<f64>, AssemblyError> {
        let n = self.matrix.rows();
        let mut extra = sprs::TriMat::with_capacity((n, n), 9 * blocks.len());
        for (i, j, b) in blocks {
            for v in [*i, *j] {
                if v >= dofs.num_vertices {
                    return Err(AssemblyError::VertexOutOfRange {
                        vertex: v,
                        num_vertices: dofs.num_vertices,
                    });
                }
            }
            if dofs.is_constrained(*i) || dofs.is_constrained(*j) {
                continue;
            }
            for r in 0..3 {
                for c in 0..3 {
                    let (row, col) = (dofs.reduced[3 * i + r], dofs.reduced[3 * j + c]);
                    extra.add_triplet(row, col, scale * b[(r, c)]);
                }
            }
        }
        let extra: CsMat<f64> = extra.to_csr();
        Ok(&self.matrix + &extra)
    }
}

/// Values of a CSR matrix with row pointers `ptr` split by rows into chunks of `rows` rows:
/// `(first row, last row + 1, values)` each, for filling rows in parallel.
pub(crate) fn row_chunks<'v>(
    ptr: &[usize],
    values: &'v mut [f64],
    rows: usize,
) -> Vec<(usize, usize, &'v mut [f64])> {
    let n = ptr.len() - 1;
    let mut rest = values;
    let mut chunks = Vec::with_capacity(n.div_ceil(rows.max(1)));
    for r0 in (0..n).step_by(rows.max(1)) {
        let r1 = (r0 + rows).min(n);
        let (head, tail) = rest.split_at_mut(ptr[r1] - ptr[r0]);
        chunks.push((r0, r1, head));
        rest = tail;
    }
    chunks
}
