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

use deform_materials::{Material, Matrix9, Model, mat3, vec9};
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
/// Passes over fewer chunks than this run on the calling thread (see [`inline`]).
const PARALLEL_MIN_CHUNKS: usize = 4;

/// Whether a pass over `chunks` chunks runs on the calling thread. Handing work to rayon's
/// pool wakes a worker, tens of microseconds on this 2-core VM: more than a pass over a few
/// hundred tets takes (a coarse model's 192 tets took 0.4 us per tet in the pool). The
/// chunks and their order are the same either way, so the results are too.
pub(crate) fn inline(chunks: usize) -> bool {
    chunks < PARALLEL_MIN_CHUNKS
}

/// Elements per block of an evaluation: the element buffer holds one block (920 B an
/// element with the stiffness product's 96, 15 MB, within this machine's 32 MB L3 cache, so
/// the gather reads what the element phase has just written from the cache) instead of the
/// whole mesh (5.8 GB for the 6.3 M tets of the n = 64 beam). At 786k tets, 16,384-element blocks took 0.165-0.218 s
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
    /// The tangent used for `stiffness` and `stiffness_product`.
    pub tangent: Tangent,
    /// `(w, out)`: receives `K(x) w` (length `3N`), element by element without K: the
    /// Rayleigh stiffness-damping force's product, for a residual that needs no assembled K.
    pub stiffness_product: Option<(&'a [f64], &'a mut [f64])>,
    /// When set, `stiffness` receives `K + scale D_w K` instead of K ([`StiffnessShift`]).
    pub stiffness_shift: Option<StiffnessShift<'a>>,
}

/// K's derivative along a direction `w` added to the assembled K: `K + scale D_w K`, with
/// `D_w K = d/de K(x + e w)` at `e = 0` (symmetric: a third derivative of the energy) by a
/// forward difference of `step` in `e`, element by element in the same pass (each element's
/// tangent at `F` and at `F + step dF_w`). Newton's matrix of Rayleigh stiffness damping
/// `-gamma K(x) v` needs it: the damping force's derivative in `x` is `-gamma D_v K`.
#[derive(Debug, Clone, Copy)]
pub struct StiffnessShift<'a> {
    /// The direction `w` (length `3N`).
    pub direction: &'a [f64],
    /// The forward difference's step in `e`: `step max|w|` is the largest displacement.
    pub step: f64,
    /// The derivative's factor.
    pub scale: f64,
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
    /// The element's `K_e w_e` ([`Outputs::stiffness_product`]).
    pub product: [Vector3<f64>; 4],
    pub blocks: [Matrix3<f64>; 10],
}

impl Default for ElementOut {
    fn default() -> Self {
        Self {
            energy: 0.0,
            forces: [Vector3::zeros(); 4],
            product: [Vector3::zeros(); 4],
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
    /// 920 bytes an element. Results do not depend on it, bit for bit.
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
        let row_matches = |v: usize| {
            let row = &columns[offsets[v]..offsets[v + 1]];
            (0..3).all(|r| {
                let found = &indices[indptr[3 * v + r]..indptr[3 * v + r + 1]];
                // Branch-free: the differences OR-ed over the row (a slice comparison per
                // block is a call, a short circuit a branch).
                found.len() == 3 * row.len()
                    && found.chunks_exact(3).zip(row).fold(0, |diff, (f, &j)| {
                        diff | (f[0] ^ (3 * j)) | (f[1] ^ (3 * j + 1)) | (f[2] ^ (3 * j + 2))
                    }) == 0
            })
        };
        let rows = p.num_rows();
        k.is_csr()
            && k.rows() == self.num_dofs()
            && k.cols() == self.num_dofs()
            && k.indptr().raw_storage() == indptr.as_slice()
            && if inline(rows.div_ceil(VERTEX_CHUNK)) {
                (0..rows).all(row_matches)
            } else {
                (0..rows)
                    .into_par_iter()
                    .with_min_len(VERTEX_CHUNK)
                    .all(row_matches)
            }
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
        let parts = Parts {
            energy: out.energy,
            forces: out.forces,
            values: out.stiffness.map(|k| k.values_mut()),
            tangent: out.tangent,
            product: out.stiffness_product,
            shift: out.stiffness_shift,
        };
        self.evaluate_parts(x, parts)
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
        let parts = Parts {
            energy,
            forces,
            values: Some(values),
            tangent,
            product: None,
            shift: None,
        };
        self.evaluate_parts(x, parts)
    }

    /// K's CSR pattern `(indptr, indices)` (full symmetric storage, sorted columns), made
    /// from the block pattern.
    pub fn stiffness_pattern(&self) -> (Vec<usize>, Vec<usize>) {
        self.geometry.pattern.scalar_csr()
    }

    fn evaluate_parts(&mut self, x: &[f64], parts: Parts<'_>) -> Result<(), AssemblyError> {
        let Parts {
            energy,
            forces,
            values,
            tangent,
            product,
            shift,
        } = parts;
        let n = self.num_dofs();
        check_positions("x", x, n)?;
        if let Some(f) = &forces {
            check_len("forces", f.len(), n)?;
        }
        let (w, product) = product.unzip();
        if let (Some(w), Some(out)) = (w, &product) {
            check_positions("stiffness product's w", w, n)?;
            check_len("stiffness product", out.len(), n)?;
        }
        if let Some(s) = &shift {
            check_positions("stiffness shift's direction", s.direction, n)?;
        }
        let need = Need {
            energy: energy.is_some(),
            forces: forces.is_some(),
            stiffness: values.is_some(),
            tangent,
            product: w,
            shift: shift.filter(|_| values.is_some()),
        };
        let (geo, ne) = (&self.geometry, self.num_elements());
        let block = self.block;
        self.work.resize(ne.min(block), ElementOut::default());
        // Each vertex's next element slot: the gathers consume them block by block.
        self.cursor.clear();
        self.cursor
            .extend_from_slice(&geo.vertex_ptr[..geo.num_vertices]);
        let mut partials = Vec::new();
        let (mut forces, mut values, mut product) = (forces, values, product);
        for first in (0..ne).step_by(block) {
            let work = &mut self.work[..(ne - first).min(block)];
            element_phase(geo, &self.materials, x, need, first, work)?;
            if need.energy {
                // Chunk sums, as if over the whole mesh (a block is a multiple of CHUNK).
                let sum = |c: &[ElementOut]| c.iter().map(|o| o.energy).sum::<f64>();
                if inline(work.len().div_ceil(CHUNK)) {
                    partials.extend(work.chunks(CHUNK).map(sum));
                } else {
                    partials.extend(work.par_chunks(CHUNK).map(sum).collect::<Vec<f64>>());
                }
            }
            if forces.is_some() || values.is_some() || product.is_some() {
                let elements = first..first + work.len();
                let vectors = [forces.as_deref_mut(), product.as_deref_mut()];
                gather_block(
                    geo,
                    work,
                    elements,
                    values.as_deref_mut(),
                    vectors,
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

/// The outputs of one evaluation, K's as its value array.
struct Parts<'a> {
    energy: Option<&'a mut f64>,
    forces: Option<&'a mut [f64]>,
    values: Option<&'a mut [f64]>,
    tangent: Tangent,
    product: Option<(&'a [f64], &'a mut [f64])>,
    shift: Option<StiffnessShift<'a>>,
}

/// What the element phase must produce.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Need<'a> {
    pub energy: bool,
    pub forces: bool,
    pub stiffness: bool,
    pub tangent: Tangent,
    /// `w` of the stiffness product.
    pub product: Option<&'a [f64]>,
    pub shift: Option<StiffnessShift<'a>>,
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
    let chunk = |(c, chunk): (usize, &mut [T])| {
        for (i, slot) in chunk.iter_mut().enumerate() {
            body(first + c * CHUNK + i, slot)?;
        }
        Ok(())
    };
    if inline(buffer.len().div_ceil(CHUNK)) {
        return buffer.chunks_mut(CHUNK).enumerate().try_for_each(chunk);
    }
    let first_error = buffer
        .par_chunks_mut(CHUNK)
        .enumerate()
        .map(chunk)
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
        let projected = need.tangent == Tangent::Projected;
        let (p, c) = if need.stiffness {
            let (p, c) = m.first_piola_and_tangent(&f, projected);
            if !finite9(&c) {
                return Err(AssemblyError::NonFiniteElement {
                    element: e,
                    what: "tangent",
                });
            }
            (Some(p), Some(c))
        } else {
            (None, None)
        };
        if need.forces {
            let p = p.unwrap_or_else(|| m.first_piola(&f));
            out.forces = corner_products(&p, g, -w);
        }
        if let Some(v) = need.product {
            // K_e v_e = -(the force differential along v); without K, from the model's
            // directional derivative of P (no 9x9 tangent for the exact one).
            let df = gradient(&corners(v, &geo.tets[e]), g);
            let dp = match &c {
                Some(c) => mat3(&(c * vec9(&df))),
                None if projected => mat3(&(m.dp_df_projected(&f) * vec9(&df))),
                None => m.dp(&f, &df),
            };
            out.product = corner_products(&dp, g, w);
            if !out.product.iter().all(|v| v.iter().all(|c| c.is_finite())) {
                return Err(AssemblyError::NonFiniteElement {
                    element: e,
                    what: "stiffness product",
                });
            }
        }
        if let (true, Some(c)) = (need.stiffness, c) {
            let c = match need.shift {
                Some(shift) => shifted_tangent(geo, m, e, &f, c, projected, shift)?,
                None => c,
            };
            stiffness_blocks(&c, g, w, &mut out.blocks);
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

/// `c + scale (C(F + step dF_w) - c) / step`: element `e`'s tangent `c` at `f` with
/// [`StiffnessShift`]'s derivative added.
fn shifted_tangent(
    geo: &Geometry,
    m: &Model,
    e: usize,
    f: &Matrix3<f64>,
    c: Matrix9,
    projected: bool,
    shift: StiffnessShift<'_>,
) -> Result<Matrix9, AssemblyError> {
    let df = gradient(&corners(shift.direction, &geo.tets[e]), &geo.grads[e]);
    let f2 = f + df * shift.step;
    let c2 = if projected {
        m.dp_df_projected(&f2)
    } else {
        m.dp_df(&f2)
    };
    let shifted = c + (c2 - c) * (shift.scale / shift.step);
    if !finite9(&shifted) {
        return Err(AssemblyError::NonFiniteElement {
            element: e,
            what: "shifted tangent",
        });
    }
    Ok(shifted)
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
    let chunk = |(v0, out): (usize, &mut [f64])| {
        for (i, fi) in out.chunks_exact_mut(3).enumerate() {
            let v = v0 + i;
            let mut acc = Vector3::zeros();
            for &slot in &geo.vertex_slots[geo.vertex_ptr[v]..geo.vertex_ptr[v + 1]] {
                acc += corner(slot as usize);
            }
            fi.copy_from_slice(acc.as_slice());
        }
    };
    let chunks = vertex_chunks(f, |v| 3 * v, geo.num_vertices);
    if inline(chunks.len()) {
        chunks.into_iter().for_each(chunk);
    } else {
        chunks.into_par_iter().for_each(chunk);
    }
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
    [forces, product]: [Option<&mut [f64]>; 2],
    cursor: &mut [usize],
) {
    let tets = &geo.tets[elements.clone()];
    let lo = tets.iter().flatten().copied().min().unwrap_or(0);
    let hi = tets.iter().flatten().copied().max().map_or(0, |v| v + 1);
    let offsets = geo.pattern.offsets();
    let cursors = vertex_range_chunks(&mut cursor[lo..hi], |v| v, lo..hi);
    let rows = optional_chunks(values, |v| 9 * offsets[v], lo..hi, cursors.len());
    let force_chunks = optional_chunks(forces, |v| 3 * v, lo..hi, cursors.len());
    let product_chunks = optional_chunks(product, |v| 3 * v, lo..hi, cursors.len());
    let vectors = force_chunks
        .into_iter()
        .zip(product_chunks)
        .collect::<Vec<_>>();
    let sequential = inline(cursors.len());
    let chunk =
        |(((v0, cursor), mut row_out), (mut force_out, mut product_out)): VertexChunk<'_>| {
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
                let product = product_out.as_deref_mut().map(|o| &mut o[3 * i..3 * i + 3]);
                let slots = (first, end);
                let vectors = [force, product];
                add_vertex_terms(
                    geo, work, &elements, slots, &mut j, len, row, vectors, &mut acc,
                );
                *next = j;
            }
        };
    if sequential {
        cursors.into_iter().zip(rows).zip(vectors).for_each(chunk);
    } else {
        (cursors.into_par_iter().zip(rows).zip(vectors)).for_each(chunk);
    }
}

/// One parallel task of [`gather_block`]: a run of vertices (the first, their cursors), their
/// K rows, their forces and their stiffness products.
type VertexChunk<'a> = (
    ((usize, &'a mut [usize]), Option<&'a mut [f64]>),
    (Option<&'a mut [f64]>, Option<&'a mut [f64]>),
);

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
    [force, product]: [Option<&mut [f64]>; 2],
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
    let start = |out: &Option<&mut [f64]>| match out {
        Some(f) if !fresh => Vector3::new(f[0], f[1], f[2]),
        _ => Vector3::zeros(),
    };
    let (mut f_acc, mut p_acc) = (start(&force), start(&product));
    while *j < end {
        let slot = geo.vertex_slots[*j] as usize;
        let (e, a) = (slot / 4, slot % 4);
        if e >= elements.end {
            break;
        }
        let element = &work[e - elements.start];
        f_acc += element.forces[a];
        p_acc += element.product[a];
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
    if let Some(p) = product {
        p.copy_from_slice(p_acc.as_slice());
    }
}
