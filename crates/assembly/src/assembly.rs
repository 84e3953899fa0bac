//! `Assembly`: energy, forces and the stiffness matrix of one mesh, in parallel and
//! bit-for-bit independent of the thread count.
//!
//! Every evaluation runs in two phases, block by block of [`BLOCK`] elements. The element
//! phase computes each element's energy, forces and ten upper 3x3 stiffness blocks into its
//! own slot of a buffer, in parallel over the block's elements. The gather phase adds those
//! slots into the outputs through maps built once per mesh (vertex -> element slots, CSR
//! block -> element blocks), in parallel over the vertices the block touches, each sum in
//! element order. No output depends on how the work was split, nor on the block size: the
//! buffer holds one block, so its memory does not grow with the mesh.

use deform_materials::{Material, Matrix9, Model};
use deform_mesh::TetMesh;
use deform_mesh::topology::{BlockPattern, VertexElements};
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use sprs::CsMat;

use crate::kernel::{corner_products, gradient, stiffness_blocks, upper_slot};
use crate::matrix::{PatternId, StiffnessMatrix};
use crate::{AssemblyError, MaterialField};

/// Elements per parallel task.
pub(crate) const CHUNK: usize = 512;
/// Vertices per parallel task in the gathers.
const VERTEX_CHUNK: usize = 256;
/// Elements per block of an evaluation: the element buffer holds one block (824 B an
/// element, 13.5 MB, within this machine's 32 MB L3 cache, so the gather reads what the
/// element phase has just written from the cache) instead of the whole mesh (5.2 GB for the
/// 6.3 M tets of the n = 64 beam). At 786k tets, 16,384-element blocks took 0.165-0.218 s
/// where 131,072-element blocks took 0.204-0.273 s (alternating runs).
pub(crate) const BLOCK: usize = 32 * CHUNK;

/// Which tangent the stiffness matrix uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Tangent {
    /// The exact `d2E/dx2` (indefinite where the energy is not convex).
    #[default]
    Exact,
    /// Each element's `dP/dF` projected to positive semi-definite (eigenvalue clamp), so K is
    /// positive semi-definite.
    Projected,
}

/// What one [`Assembly::evaluate`] call computes; `None` fields are skipped.
#[derive(Debug, Default)]
pub struct Outputs<'a> {
    /// Receives the total elastic energy `E(x)`.
    pub energy: Option<&'a mut f64>,
    /// Receives the elastic forces `f = -dE/dx` (length `3N`).
    pub forces: Option<&'a mut [f64]>,
    /// Refilled with `K = d2E/dx2`.
    pub stiffness: Option<&'a mut StiffnessMatrix>,
    /// The tangent used for `stiffness`.
    pub tangent: Tangent,
}

/// Per-mesh geometry and scatter maps, immutable after construction.
#[derive(Debug, Clone)]
pub(crate) struct Geometry {
    pub num_vertices: usize,
    pub tets: Vec<[usize; 4]>,
    pub grads: Vec<[Vector3<f64>; 4]>,
    pub volumes: Vec<f64>,
    pub regions: Vec<u32>,
    pub pattern: BlockPattern,
    pub pattern_id: PatternId,
    /// K's scalar CSR row pointers (its column indices follow from `pattern`).
    pub indptr: Vec<usize>,
    /// Vertex `v`'s element slots `4 e + a`, in element order.
    pub vertex_ptr: Vec<usize>,
    pub vertex_slots: Vec<u32>,
    /// For the `j`-th vertex slot `(e, a)` of vertex `v` and each `b`, the position of block
    /// `(t[a], t[b])` within row `v` of the block pattern: `row_targets[4 j + b]`.
    pub row_targets: Vec<u32>,
}

/// What the element phase writes for one element.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ElementOut {
    pub energy: f64,
    pub forces: [Vector3<f64>; 4],
    pub blocks: [Matrix3<f64>; 10],
}

impl Default for ElementOut {
    fn default() -> Self {
        Self {
            energy: 0.0,
            forces: [Vector3::zeros(); 4],
            blocks: [Matrix3::zeros(); 10],
        }
    }
}

/// Energy, forces and stiffness of one mesh with its materials.
///
/// ```
/// use deform_assembly::{Assembly, MaterialField};
/// use deform_materials::MaterialSpec;
/// use deform_mesh::generate::BoxGrid;
///
/// let mesh = BoxGrid::beam(1).build().unwrap();
/// let model = ron::from_str::<MaterialSpec>("NeoHookean(Young(e: 1e6, nu: 0.4))").unwrap().build().unwrap();
/// let mut asm = Assembly::new(&mesh, MaterialField::Uniform(model)).unwrap();
/// let x = mesh.rest_positions_flat();
/// assert_eq!(asm.energy(&x).unwrap(), 0.0);
/// let mut k = asm.stiffness_matrix();
/// asm.stiffness(&x, deform_assembly::Tangent::Exact, &mut k).unwrap();
/// assert_eq!(k.rows(), 3 * mesh.num_vertices());
/// ```
#[derive(Debug, Clone)]
pub struct Assembly {
    pub(crate) geometry: Geometry,
    pub(crate) materials: MaterialField,
    work: Vec<ElementOut>,
    /// Each vertex's next element slot during an evaluation (allocated once).
    cursor: Vec<usize>,
    /// Elements per block of an evaluation (a multiple of `CHUNK`).
    block: usize,
}

impl Assembly {
    /// Precomputes shape gradients, the stiffness pattern and the gather maps of `mesh`.
    ///
    /// # Errors
    /// [`AssemblyError::MaterialField`] when the field does not fit the mesh,
    /// [`AssemblyError::TooLarge`] beyond 200 million elements.
    pub fn new(mesh: &TetMesh, materials: MaterialField) -> Result<Self, AssemblyError> {
        let ne = mesh.num_tets();
        if ne > 200_000_000 {
            return Err(AssemblyError::TooLarge(ne));
        }
        materials.validate(ne)?;
        let pattern = BlockPattern::new(mesh);
        // K's scalar row pointers: three rows of three columns per block for each vertex.
        let mut indptr = vec![0];
        for w in pattern.offsets().windows(2) {
            for _ in 0..3 {
                indptr.push(indptr[indptr.len() - 1] + 3 * (w[1] - w[0]));
            }
        }
        let adjacency = VertexElements::new(mesh);
        let vertex_ptr = adjacency.offsets().to_vec();
        let mut vertex_slots = Vec::with_capacity(4 * ne);
        for v in 0..mesh.num_vertices() {
            vertex_slots.extend(adjacency.of(v).iter().map(|&(e, a)| (4 * e + a) as u32));
        }
        let tets = mesh.tets();
        let mut row_targets = Vec::with_capacity(4 * vertex_slots.len());
        for v in 0..mesh.num_vertices() {
            let start = pattern.offsets()[v];
            for &slot in &vertex_slots[vertex_ptr[v]..vertex_ptr[v + 1]] {
                let t = &tets[slot as usize / 4];
                for &j in t {
                    let k = pattern
                        .find(v, j)
                        .expect("element pairs are in the pattern");
                    row_targets.push((k - start) as u32);
                }
            }
        }
        let geometry = Geometry {
            num_vertices: mesh.num_vertices(),
            tets: mesh.tets().to_vec(),
            grads: (0..ne).map(|e| mesh.shape_gradients(e)).collect(),
            volumes: mesh.volumes().to_vec(),
            regions: mesh.regions().to_vec(),
            pattern,
            pattern_id: PatternId::fresh(),
            indptr,
            vertex_ptr,
            vertex_slots,
            row_targets,
        };
        Ok(Self {
            geometry,
            materials,
            work: Vec::new(),
            cursor: Vec::new(),
            block: BLOCK,
        })
    }

    /// Sets how many elements an evaluation computes before adding them into its outputs
    /// (rounded up to a multiple of 512; 16,384 by default): the element buffer's memory,
    /// 824 bytes an element. Results do not depend on it, bit for bit.
    pub fn set_block_elements(&mut self, elements: usize) {
        self.block = elements.max(1).div_ceil(CHUNK) * CHUNK;
        self.work = Vec::new();
    }

    /// Number of vertices.
    pub fn num_vertices(&self) -> usize {
        self.geometry.num_vertices
    }

    /// Number of elements.
    pub fn num_elements(&self) -> usize {
        self.geometry.tets.len()
    }

    /// Number of degrees of freedom, `3N`.
    pub fn num_dofs(&self) -> usize {
        3 * self.geometry.num_vertices
    }

    /// The materials.
    pub fn materials(&self) -> &MaterialField {
        &self.materials
    }

    /// Replaces the materials (e.g. new parameters while fitting), keeping the pattern.
    ///
    /// # Errors
    /// [`AssemblyError::MaterialField`] when the field does not fit the mesh.
    pub fn set_materials(&mut self, materials: MaterialField) -> Result<(), AssemblyError> {
        materials.validate(self.num_elements())?;
        self.materials = materials;
        Ok(())
    }

    /// The block sparsity pattern of K.
    pub fn pattern(&self) -> &BlockPattern {
        &self.geometry.pattern
    }

    /// A `3N x 3N` matrix with K's pattern (full symmetric storage) and zero values, to be
    /// refilled by [`Assembly::stiffness`] as often as needed.
    pub fn stiffness_matrix(&self) -> StiffnessMatrix {
        let n = self.num_dofs();
        let (indptr, indices) = self.stiffness_pattern();
        let nnz = indices.len();
        let csr = CsMat::new((n, n), indptr, indices, vec![0.0; nnz]);
        StiffnessMatrix::new(csr, self.geometry.pattern_id)
    }

    /// `k` as a [`StiffnessMatrix`] of this assembly, its values kept, after checking once
    /// that it has this mesh's pattern ([`Assembly::has_pattern`]).
    ///
    /// # Errors
    /// [`AssemblyError::PatternMismatch`].
    pub fn adopt_stiffness_matrix(&self, k: CsMat<f64>) -> Result<StiffnessMatrix, AssemblyError> {
        if self.has_pattern(&k) {
            Ok(StiffnessMatrix::new(k, self.geometry.pattern_id))
        } else {
            Err(AssemblyError::PatternMismatch)
        }
    }

    /// Whether `k` was made for this assembly's pattern (by it or a clone).
    pub(crate) fn owns(&self, k: &StiffnessMatrix) -> bool {
        k.pattern() == self.geometry.pattern_id
    }

    /// Whether `k` has this mesh's pattern. Its column indices are compared with the block
    /// pattern's, which the assembly keeps instead of a scalar copy (1.2 GB at 6.3 M tets).
    pub fn has_pattern(&self, k: &CsMat<f64>) -> bool {
        let p = &self.geometry.pattern;
        let (offsets, columns, indptr) = (p.offsets(), p.columns(), &self.geometry.indptr);
        let indices = k.indices();
        k.is_csr()
            && k.rows() == self.num_dofs()
            && k.cols() == self.num_dofs()
            && k.indptr().raw_storage() == indptr.as_slice()
            && (0..p.num_rows())
                .into_par_iter()
                .with_min_len(VERTEX_CHUNK)
                .all(|v| {
                    let row = &columns[offsets[v]..offsets[v + 1]];
                    (0..3).all(|r| {
                        let found = &indices[indptr[3 * v + r]..indptr[3 * v + r + 1]];
                        // Branch-free: the differences OR-ed over the row (a slice
                        // comparison per block is a call, a short circuit a branch).
                        found.len() == 3 * row.len()
                            && found.chunks_exact(3).zip(row).fold(0, |diff, (f, &j)| {
                                diff | (f[0] ^ (3 * j))
                                    | (f[1] ^ (3 * j + 1))
                                    | (f[2] ^ (3 * j + 2))
                            }) == 0
                    })
                })
    }

    /// Total elastic energy `E(x) = sum_e W_e Psi(F_e)`.
    ///
    /// # Errors
    /// As [`Assembly::evaluate`].
    pub fn energy(&mut self, x: &[f64]) -> Result<f64, AssemblyError> {
        let mut e = 0.0;
        self.evaluate(
            x,
            Outputs {
                energy: Some(&mut e),
                ..Outputs::default()
            },
        )?;
        Ok(e)
    }

    /// Elastic forces `f = -dE/dx` into `f` (length `3N`).
    ///
    /// # Errors
    /// As [`Assembly::evaluate`].
    pub fn forces(&mut self, x: &[f64], f: &mut [f64]) -> Result<(), AssemblyError> {
        self.evaluate(
            x,
            Outputs {
                forces: Some(f),
                ..Outputs::default()
            },
        )
    }

    /// Refills `k` with `K = d2E/dx2` at `x`.
    ///
    /// # Errors
    /// As [`Assembly::evaluate`].
    pub fn stiffness(
        &mut self,
        x: &[f64],
        tangent: Tangent,
        k: &mut StiffnessMatrix,
    ) -> Result<(), AssemblyError> {
        self.evaluate(
            x,
            Outputs {
                stiffness: Some(k),
                tangent,
                ..Outputs::default()
            },
        )
    }

    /// Computes any of energy, forces and stiffness in one pass over the elements.
    ///
    /// # Errors
    /// [`AssemblyError::DimensionMismatch`] or [`AssemblyError::PatternMismatch`] for bad
    /// arguments, [`AssemblyError::NonFinite`] naming a vertex with a NaN coordinate,
    /// [`AssemblyError::Inadmissible`] naming the first element (by index) outside its
    /// model's domain, [`AssemblyError::NonFiniteElement`] naming the first element whose
    /// result is not finite. On error the outputs are left unspecified.
    pub fn evaluate(&mut self, x: &[f64], out: Outputs<'_>) -> Result<(), AssemblyError> {
        if let Some(k) = &out.stiffness
            && !self.owns(k)
        {
            return Err(AssemblyError::PatternMismatch);
        }
        let tangent = out.tangent;
        let values = out.stiffness.map(|k| (k.values_mut(), tangent));
        self.evaluate_parts(x, out.energy, out.forces, values)
    }

    /// [`Assembly::evaluate`] with K's values written to `values` (one per non-zero of
    /// [`Assembly::stiffness_pattern`], in its order) instead of into a matrix: for callers
    /// that own the value array, such as a numpy array handed to scipy.
    ///
    /// # Errors
    /// As [`Assembly::evaluate`]; [`AssemblyError::DimensionMismatch`] for a `values` of
    /// another length than the pattern's.
    pub fn evaluate_values(
        &mut self,
        x: &[f64],
        energy: Option<&mut f64>,
        forces: Option<&mut [f64]>,
        values: &mut [f64],
        tangent: Tangent,
    ) -> Result<(), AssemblyError> {
        check_len(
            "values",
            values.len(),
            9 * self.geometry.pattern.num_blocks(),
        )?;
        self.evaluate_parts(x, energy, forces, Some((values, tangent)))
    }

    /// K's CSR pattern `(indptr, indices)` (full symmetric storage, sorted columns), made
    /// from the block pattern.
    pub fn stiffness_pattern(&self) -> (Vec<usize>, Vec<usize>) {
        self.geometry.pattern.scalar_csr()
    }

    fn evaluate_parts(
        &mut self,
        x: &[f64],
        energy: Option<&mut f64>,
        forces: Option<&mut [f64]>,
        stiffness: Option<(&mut [f64], Tangent)>,
    ) -> Result<(), AssemblyError> {
        check_positions("x", x, self.num_dofs())?;
        if let Some(f) = &forces {
            check_len("forces", f.len(), self.num_dofs())?;
        }
        let need = Need {
            energy: energy.is_some(),
            forces: forces.is_some(),
            stiffness: stiffness.as_ref().map(|(_, t)| *t),
        };
        let (geo, ne) = (&self.geometry, self.num_elements());
        let block = self.block;
        self.work.resize(ne.min(block), ElementOut::default());
        // Each vertex's next element slot: the gathers consume them block by block.
        self.cursor.clear();
        self.cursor
            .extend_from_slice(&geo.vertex_ptr[..geo.num_vertices]);
        let mut partials = Vec::new();
        let (mut forces, mut values) = (forces, stiffness.map(|(v, _)| v));
        for first in (0..ne).step_by(block) {
            let work = &mut self.work[..(ne - first).min(block)];
            element_phase(geo, &self.materials, x, need, first, work)?;
            if need.energy {
                // Chunk sums, as if over the whole mesh (a block is a multiple of CHUNK).
                partials.extend(
                    work.par_chunks(CHUNK)
                        .map(|c| c.iter().map(|o| o.energy).sum::<f64>())
                        .collect::<Vec<f64>>(),
                );
            }
            if forces.is_some() || values.is_some() {
                let elements = first..first + work.len();
                gather_block(
                    geo,
                    work,
                    elements,
                    values.as_deref_mut(),
                    forces.as_deref_mut(),
                    &mut self.cursor,
                );
            }
        }
        if let Some(e) = energy {
            *e = partials.iter().sum();
        }
        Ok(())
    }
}

/// What the element phase must produce.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Need {
    pub energy: bool,
    pub forces: bool,
    pub stiffness: Option<Tangent>,
}

pub(crate) fn check_len(
    what: &'static str,
    found: usize,
    expected: usize,
) -> Result<(), AssemblyError> {
    if found == expected {
        Ok(())
    } else {
        Err(AssemblyError::DimensionMismatch {
            what,
            expected,
            found,
        })
    }
}

/// Length and finiteness of a flat `3N` vector.
pub(crate) fn check_positions(
    what: &'static str,
    x: &[f64],
    expected: usize,
) -> Result<(), AssemblyError> {
    check_len(what, x.len(), expected)?;
    match x.iter().position(|v| !v.is_finite()) {
        Some(i) => Err(AssemblyError::NonFinite {
            what,
            vertex: i / 3,
        }),
        None => Ok(()),
    }
}

/// The four corner vectors of element `t` in a flat vector.
#[inline]
pub(crate) fn corners(v: &[f64], t: &[usize; 4]) -> [Vector3<f64>; 4] {
    t.map(|i| Vector3::new(v[3 * i], v[3 * i + 1], v[3 * i + 2]))
}

/// Runs `body` on the elements `first..first + buffer.len()` in parallel chunks; returns the
/// error of the lowest-indexed failing element, so the reported element does not depend on
/// the thread count.
pub(crate) fn for_each_element<T: Send>(
    first: usize,
    buffer: &mut [T],
    body: impl Fn(usize, &mut T) -> Result<(), AssemblyError> + Sync,
) -> Result<(), AssemblyError> {
    let first_error = buffer
        .par_chunks_mut(CHUNK)
        .enumerate()
        .map(|(c, chunk)| {
            for (i, slot) in chunk.iter_mut().enumerate() {
                body(first + c * CHUNK + i, slot)?;
            }
            Ok(())
        })
        .filter_map(Result::err)
        .collect::<Vec<_>>();
    // Chunks are collected in order; the first error of the first failing chunk is the
    // lowest-indexed failing element.
    first_error.into_iter().next().map_or(Ok(()), Err)
}

/// `F` of element `e` at positions `x`, or the typed error when it is outside the model's
/// domain (e.g. inverted for Neo-Hookean).
pub(crate) fn admissible_gradient(
    geo: &Geometry,
    x: &[f64],
    e: usize,
    m: &Model,
) -> Result<Matrix3<f64>, AssemblyError> {
    let f = gradient(&corners(x, &geo.tets[e]), &geo.grads[e]);
    if m.admissible(&f) {
        Ok(f)
    } else {
        Err(AssemblyError::Inadmissible {
            element: e,
            det: f.determinant(),
            model: m.name(),
        })
    }
}

/// [`for_each_element`] with each element's model: the one place that dispatches on the
/// material field (a uniform field needs no per-element lookup).
pub(crate) fn for_each_element_with_model<T: Send>(
    materials: &MaterialField,
    first: usize,
    buffer: &mut [T],
    body: impl Fn(usize, &mut T, &Model) -> Result<(), AssemblyError> + Sync,
) -> Result<(), AssemblyError> {
    match materials {
        MaterialField::Uniform(m) => for_each_element(first, buffer, |e, out| body(e, out, m)),
        MaterialField::PerElement { models, index } => for_each_element(first, buffer, |e, out| {
            body(e, out, &models[index[e] as usize])
        }),
    }
}

/// The element phase of the elements `first..first + work.len()`, into `work`.
fn element_phase(
    geo: &Geometry,
    materials: &MaterialField,
    x: &[f64],
    need: Need,
    first: usize,
    work: &mut [ElementOut],
) -> Result<(), AssemblyError> {
    for_each_element_with_model(materials, first, work, |e, out, m| {
        let g = &geo.grads[e];
        let w = geo.volumes[e];
        let f = admissible_gradient(geo, x, e, m)?;
        if need.energy {
            out.energy = w * m.psi(&f);
            if !out.energy.is_finite() {
                return Err(AssemblyError::NonFiniteElement {
                    element: e,
                    what: "energy",
                });
            }
        }
        match need.stiffness {
            Some(tangent) => {
                let (p, c) = m.first_piola_and_tangent(&f, tangent == Tangent::Projected);
                if !finite9(&c) {
                    return Err(AssemblyError::NonFiniteElement {
                        element: e,
                        what: "tangent",
                    });
                }
                stiffness_blocks(&c, g, w, &mut out.blocks);
                if need.forces {
                    out.forces = corner_products(&p, g, -w);
                }
            }
            None if need.forces => out.forces = corner_products(&m.first_piola(&f), g, -w),
            None => {}
        }
        if need.forces && !out.forces.iter().all(|v| v.iter().all(|c| c.is_finite())) {
            return Err(AssemblyError::NonFiniteElement {
                element: e,
                what: "force",
            });
        }
        Ok(())
    })
}

/// Whether every entry of `c` is finite: over the contiguous slice and without an early exit,
/// so it compiles to a few vector compares (nalgebra's matrix iterator with `all` took about
/// a tenth of an energy + forces + K assembly).
pub(crate) fn finite9(c: &Matrix9) -> bool {
    let mut bad = false;
    for v in c.as_slice() {
        bad |= !v.is_finite();
    }
    !bad
}

/// Splits a per-vertex output (`stride` values per vertex) into disjoint chunks of
/// `VERTEX_CHUNK` vertices for parallel gathers: `(first vertex, values)`.
pub(crate) fn vertex_chunks(
    values: &mut [f64],
    offsets: impl Fn(usize) -> usize,
    num_vertices: usize,
) -> Vec<(usize, &mut [f64])> {
    vertex_range_chunks(values, offsets, 0..num_vertices)
}

/// [`vertex_chunks`] of the vertices `range`, whose values `values` are (from
/// `offsets(range.start)` to `offsets(range.end)`).
fn vertex_range_chunks<T>(
    values: &mut [T],
    offsets: impl Fn(usize) -> usize,
    range: std::ops::Range<usize>,
) -> Vec<(usize, &mut [T])> {
    let mut chunks = Vec::with_capacity(range.len().div_ceil(VERTEX_CHUNK));
    let mut rest = values;
    let mut v = range.start;
    while v < range.end {
        let end = (v + VERTEX_CHUNK).min(range.end);
        let (head, tail) = rest.split_at_mut(offsets(end) - offsets(v));
        chunks.push((v, head));
        rest = tail;
        v = end;
    }
    chunks
}

/// Sums per-element corner vectors into a flat `3N` vector, each vertex in element order.
pub(crate) fn gather_vertex_vectors(
    geo: &Geometry,
    corner: impl Fn(usize) -> Vector3<f64> + Sync,
    f: &mut [f64],
) {
    let n = geo.num_vertices;
    vertex_chunks(f, |v| 3 * v, n)
        .into_par_iter()
        .for_each(|(v0, out)| {
            for (i, fi) in out.chunks_exact_mut(3).enumerate() {
                let v = v0 + i;
                let mut acc = Vector3::zeros();
                for &slot in &geo.vertex_slots[geo.vertex_ptr[v]..geo.vertex_ptr[v + 1]] {
                    acc += corner(slot as usize);
                }
                fi.copy_from_slice(acc.as_slice());
            }
        });
}

/// [`vertex_range_chunks`] of an optional output, or as many `None`s.
fn optional_chunks(
    out: Option<&mut [f64]>,
    offsets: impl Fn(usize) -> usize,
    range: std::ops::Range<usize>,
    chunks: usize,
) -> Vec<Option<&mut [f64]>> {
    match out {
        Some(o) => vertex_range_chunks(
            &mut o[offsets(range.start)..offsets(range.end)],
            offsets,
            range,
        )
        .into_iter()
        .map(|(_, c)| Some(c))
        .collect(),
        None => (0..chunks).map(|_| None).collect(),
    }
}

/// Adds the element phase's `work` of the `elements` into K's `values` and the `forces`,
/// vertex row by vertex row in parallel over the vertices those elements touch. Each
/// vertex's slots are consumed in element order from its `cursor`, and its row (and force)
/// is zeroed at its first slot, so each block of K and each force is the sum of its element
/// terms in element order, whatever the threads and the blocks.
fn gather_block(
    geo: &Geometry,
    work: &[ElementOut],
    elements: std::ops::Range<usize>,
    values: Option<&mut [f64]>,
    forces: Option<&mut [f64]>,
    cursor: &mut [usize],
) {
    let tets = &geo.tets[elements.clone()];
    let lo = tets.iter().flatten().copied().min().unwrap_or(0);
    let hi = tets.iter().flatten().copied().max().map_or(0, |v| v + 1);
    let offsets = geo.pattern.offsets();
    let cursors = vertex_range_chunks(&mut cursor[lo..hi], |v| v, lo..hi);
    let rows = optional_chunks(values, |v| 9 * offsets[v], lo..hi, cursors.len());
    let force_chunks = optional_chunks(forces, |v| 3 * v, lo..hi, cursors.len());
    cursors
        .into_par_iter()
        .zip(rows)
        .zip(force_chunks)
        .for_each(|(((v0, cursor), mut row_out), mut force_out)| {
            let mut acc = Vec::new();
            for (i, next) in cursor.iter_mut().enumerate() {
                let v = v0 + i;
                let (first, end) = (geo.vertex_ptr[v], geo.vertex_ptr[v + 1]);
                let mut j = *next;
                if j == end || geo.vertex_slots[j] as usize / 4 >= elements.end {
                    continue;
                }
                let (row_start, row_end) = (offsets[v], offsets[v + 1]);
                let len = row_end - row_start;
                let row = row_out
                    .as_deref_mut()
                    .map(|o| &mut o[9 * (row_start - offsets[v0])..9 * (row_end - offsets[v0])]);
                let force = force_out.as_deref_mut().map(|o| &mut o[3 * i..3 * i + 3]);
                let slots = (first, end);
                add_vertex_terms(
                    geo, work, &elements, slots, &mut j, len, row, force, &mut acc,
                );
                *next = j;
            }
        });
}

/// The terms of a vertex's slots `*j..end` (its first is `first`) that lie in `elements`,
/// added into its K `row` (3 rows of `3 len` values) and its `force` (zero before the
/// vertex's first slot), through the accumulator `acc` (a 3x3 block per row entry).
#[allow(clippy::too_many_arguments)]
#[inline]
fn add_vertex_terms(
    geo: &Geometry,
    work: &[ElementOut],
    elements: &std::ops::Range<usize>,
    (first, end): (usize, usize),
    j: &mut usize,
    len: usize,
    row: Option<&mut [f64]>,
    force: Option<&mut [f64]>,
    acc: &mut Vec<Matrix3<f64>>,
) {
    let fresh = *j == first;
    acc.clear();
    if let Some(r) = &row {
        if fresh {
            acc.resize(len, Matrix3::zeros());
        } else {
            acc.extend((0..len).map(|k| Matrix3::from_fn(|p, q| r[3 * len * p + 3 * k + q])));
        }
    }
    let mut f_acc = match &force {
        Some(f) if !fresh => Vector3::new(f[0], f[1], f[2]),
        _ => Vector3::zeros(),
    };
    while *j < end {
        let slot = geo.vertex_slots[*j] as usize;
        let (e, a) = (slot / 4, slot % 4);
        if e >= elements.end {
            break;
        }
        let element = &work[e - elements.start];
        f_acc += element.forces[a];
        if row.is_some() {
            for b in 0..4 {
                let (u, transposed) = upper_slot(a, b);
                let m = &element.blocks[u];
                let target = &mut acc[geo.row_targets[4 * *j + b] as usize];
                if transposed {
                    *target += m.transpose();
                } else {
                    *target += m;
                }
            }
        }
        *j += 1;
    }
    if let Some(r) = row {
        for (k, m) in acc.iter().enumerate() {
            for p in 0..3 {
                let at = 3 * len * p + 3 * k;
                r[at..at + 3].copy_from_slice(&[m[(p, 0)], m[(p, 1)], m[(p, 2)]]);
            }
        }
    }
    if let Some(f) = force {
        f.copy_from_slice(f_acc.as_slice());
    }
}
