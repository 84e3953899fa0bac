//! Topology derived from the connectivity: faces, boundary surface, edges, vertex-to-element
//! adjacency and the block sparsity pattern of the stiffness matrix.
//!
//! Everything here is deterministic: outputs are sorted or in element order, never in hash order.

use crate::TetMesh;
use crate::error::MeshError;

/// The six edges of a tetrahedron as local index pairs.
pub(crate) const TET_EDGES: [[usize; 2]; 6] = [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]];

/// Local faces of a positively oriented tetrahedron, each ordered so that its right-hand
/// normal points out of the element. Face `k` is opposite local vertex `k`.
pub const TET_FACES: [[usize; 3]; 4] = [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]];

/// The faces of a mesh, classified by how many elements share them.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Faces {
    /// Faces used by exactly one element, oriented outward, in element order (then local face order).
    pub boundary: Vec<[usize; 3]>,
    /// The element each boundary face belongs to.
    pub boundary_elements: Vec<usize>,
    /// Pairs of elements sharing an interior face (smaller element first), sorted.
    pub interior: Vec<[usize; 2]>,
    /// Faces used by more than two elements: a non-manifold mesh. Vertex triples, sorted.
    pub nonmanifold: Vec<[usize; 3]>,
}

/// Classifies all element faces.
pub fn faces(mesh: &TetMesh) -> Faces {
    let mut keyed: Vec<([usize; 3], usize, usize)> = Vec::with_capacity(4 * mesh.num_tets());
    for (e, t) in mesh.tets().iter().enumerate() {
        for (k, f) in TET_FACES.iter().enumerate() {
            let mut key = [t[f[0]], t[f[1]], t[f[2]]];
            key.sort_unstable();
            keyed.push((key, e, k));
        }
    }
    keyed.sort_unstable();
    let mut out = Faces::default();
    let mut boundary: Vec<(usize, usize)> = Vec::new();
    let mut i = 0;
    while i < keyed.len() {
        let mut j = i + 1;
        while j < keyed.len() && keyed[j].0 == keyed[i].0 {
            j += 1;
        }
        match j - i {
            1 => boundary.push((keyed[i].1, keyed[i].2)),
            2 => out.interior.push([keyed[i].1, keyed[i + 1].1]),
            _ => out.nonmanifold.push(keyed[i].0),
        }
        i = j;
    }
    boundary.sort_unstable();
    for (e, k) in boundary {
        let t = &mesh.tets()[e];
        let f = TET_FACES[k];
        out.boundary.push([t[f[0]], t[f[1]], t[f[2]]]);
        out.boundary_elements.push(e);
    }
    out.interior.sort_unstable();
    out
}

/// Checks that positively oriented `tets` form a conforming solid: no two elements with the
/// same four vertices, no two on the same side of a shared face, and (unless
/// `allow_nonmanifold`) no face shared by more than two. Errors name the elements.
pub(crate) fn check_conforming(
    tets: &[[usize; 4]],
    allow_nonmanifold: bool,
) -> Result<(), MeshError> {
    let mut sorted: Vec<([usize; 4], usize)> = tets
        .iter()
        .enumerate()
        .map(|(e, t)| {
            let mut k = *t;
            k.sort_unstable();
            (k, e)
        })
        .collect();
    sorted.sort_unstable();
    let duplicate = sorted.windows(2).filter(|w| w[0].0 == w[1].0);
    if let Some(w) = duplicate.min_by_key(|w| w[1].1) {
        return Err(MeshError::DuplicateElement {
            element: w[1].1,
            first: w[0].1,
        });
    }
    // Each face with its side: the parity of its outward orientation against the sorted
    // key. Two elements on opposite sides of a face see it with opposite orientations.
    let mut keyed: Vec<([usize; 3], bool, usize)> = Vec::with_capacity(4 * tets.len());
    for (e, t) in tets.iter().enumerate() {
        for f in TET_FACES {
            let [a, b, c] = [t[f[0]], t[f[1]], t[f[2]]];
            let odd = ((a > b) as u8 + (a > c) as u8 + (b > c) as u8) % 2 == 1;
            let mut key = [a, b, c];
            key.sort_unstable();
            keyed.push((key, odd, e));
        }
    }
    keyed.sort_unstable();
    for group in keyed.chunk_by(|x, y| x.0 == y.0) {
        match group {
            [(face, side_a, first), (_, side_b, second)] if side_a == side_b => {
                let (first, second, face) = (*first, *second, *face);
                return Err(MeshError::OverlappingElements {
                    first,
                    second,
                    face,
                });
            }
            [_, _, _, ..] if !allow_nonmanifold => {
                let mut elements: Vec<usize> = group.iter().map(|g| g.2).collect();
                elements.sort_unstable();
                return Err(MeshError::NonManifoldFace {
                    face: group[0].0,
                    elements,
                });
            }
            _ => {}
        }
    }
    Ok(())
}

/// Outward-oriented boundary triangles, in element order.
pub fn boundary_faces(mesh: &TetMesh) -> Vec<[usize; 3]> {
    faces(mesh).boundary
}

/// Sorted indices of the vertices on the boundary surface.
pub fn surface_vertices(mesh: &TetMesh) -> Vec<usize> {
    let mut v: Vec<usize> = boundary_faces(mesh).into_iter().flatten().collect();
    v.sort_unstable();
    v.dedup();
    v
}

/// Unique edges `[i, j]` with `i < j`, sorted.
pub fn edges(mesh: &TetMesh) -> Vec<[usize; 2]> {
    let mut out: Vec<[usize; 2]> = Vec::with_capacity(6 * mesh.num_tets());
    for t in mesh.tets() {
        for [a, b] in TET_EDGES {
            let (i, j) = (t[a].min(t[b]), t[a].max(t[b]));
            out.push([i, j]);
        }
    }
    out.sort_unstable();
    out.dedup();
    out
}

/// Vertex-to-element adjacency in compressed rows: for vertex `v`, the `(element, local)`
/// pairs of the elements that use it, in element order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct VertexElements {
    offsets: Vec<usize>,
    entries: Vec<(usize, usize)>,
}

impl VertexElements {
    /// Builds the adjacency of `mesh`.
    pub fn new(mesh: &TetMesh) -> Self {
        let n = mesh.num_vertices();
        let mut offsets = vec![0usize; n + 1];
        for t in mesh.tets() {
            for &i in t {
                offsets[i + 1] += 1;
            }
        }
        for i in 0..n {
            offsets[i + 1] += offsets[i];
        }
        let mut fill = offsets.clone();
        let mut entries = vec![(0, 0); offsets[n]];
        for (e, t) in mesh.tets().iter().enumerate() {
            for (a, &i) in t.iter().enumerate() {
                entries[fill[i]] = (e, a);
                fill[i] += 1;
            }
        }
        Self { offsets, entries }
    }

    /// The `(element, local vertex)` pairs of vertex `v`, in element order.
    ///
    /// # Panics
    /// If `v` is out of range.
    #[track_caller]
    pub fn of(&self, v: usize) -> &[(usize, usize)] {
        &self.entries[self.offsets[v]..self.offsets[v + 1]]
    }

    /// Row offsets (length `N + 1`).
    pub fn offsets(&self) -> &[usize] {
        &self.offsets
    }
}

/// The sparsity pattern of the stiffness matrix at vertex granularity: block `(i, j)` is
/// present when vertices `i` and `j` share an element (including `i == j`). Each block is
/// a dense 3x3 in the scalar `3N x 3N` matrix. Rows are sorted; the pattern is symmetric.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BlockPattern {
    offsets: Vec<usize>,
    columns: Vec<usize>,
}

impl BlockPattern {
    /// Builds the pattern of `mesh`.
    pub fn new(mesh: &TetMesh) -> Self {
        let n = mesh.num_vertices();
        let edges = edges(mesh);
        let mut degree = vec![1usize; n];
        for [i, j] in &edges {
            degree[*i] += 1;
            degree[*j] += 1;
        }
        let mut offsets = vec![0usize; n + 1];
        for i in 0..n {
            offsets[i + 1] = offsets[i] + degree[i];
        }
        let mut columns = vec![0usize; offsets[n]];
        let mut fill = offsets[..n].to_vec();
        for i in 0..n {
            columns[fill[i]] = i;
            fill[i] += 1;
        }
        for [i, j] in edges {
            columns[fill[i]] = j;
            fill[i] += 1;
            columns[fill[j]] = i;
            fill[j] += 1;
        }
        for i in 0..n {
            columns[offsets[i]..offsets[i + 1]].sort_unstable();
        }
        Self { offsets, columns }
    }

    /// Number of block rows (vertices).
    pub fn num_rows(&self) -> usize {
        self.offsets.len() - 1
    }

    /// Number of stored 3x3 blocks.
    pub fn num_blocks(&self) -> usize {
        self.columns.len()
    }

    /// Block row offsets (length `N + 1`).
    pub fn offsets(&self) -> &[usize] {
        &self.offsets
    }

    /// Block column indices, sorted within each row.
    pub fn columns(&self) -> &[usize] {
        &self.columns
    }

    /// Index of block `(i, j)` in [`Self::columns`], if present.
    pub fn find(&self, i: usize, j: usize) -> Option<usize> {
        let row = &self.columns[self.offsets[i]..self.offsets[i + 1]];
        row.binary_search(&j).ok().map(|k| self.offsets[i] + k)
    }

    /// For each element, the block index of each local pair `(a, b)` at position `4 a + b`:
    /// the precomputed map through which element matrices are scattered.
    pub fn element_blocks(&self, mesh: &TetMesh) -> Vec<[usize; 16]> {
        mesh.tets()
            .iter()
            .map(|t| {
                let mut out = [0usize; 16];
                for a in 0..4 {
                    for b in 0..4 {
                        out[4 * a + b] = self
                            .find(t[a], t[b])
                            .expect("the pattern of a mesh contains every element pair");
                    }
                }
                out
            })
            .collect()
    }

    /// The scalar `3N x 3N` CSR pattern `(indptr, indices)`, full symmetric storage, with
    /// columns sorted. Scalar row `3 i + r` lists, for each block column `j` of row `i`,
    /// the columns `3 j, 3 j + 1, 3 j + 2`.
    pub fn scalar_csr(&self) -> (Vec<usize>, Vec<usize>) {
        let n = self.num_rows();
        let mut indptr = Vec::with_capacity(3 * n + 1);
        let mut indices = Vec::with_capacity(9 * self.num_blocks());
        indptr.push(0);
        for i in 0..n {
            let row = &self.columns[self.offsets[i]..self.offsets[i + 1]];
            for _r in 0..3 {
                for &j in row {
                    indices.extend_from_slice(&[3 * j, 3 * j + 1, 3 * j + 2]);
                }
                indptr.push(indices.len());
            }
        }
        (indptr, indices)
    }

    /// Position in the scalar CSR value array of entry `(3 i + r, 3 j + c)`, where `k` is
    /// the block index of `(i, j)` and `i` its row. Constant-time; used by scatter maps.
    pub fn scalar_index(&self, i: usize, k: usize, r: usize, c: usize) -> usize {
        let row_start = self.offsets[i];
        let row_len = self.offsets[i + 1] - row_start;
        9 * row_start + 3 * row_len * r + 3 * (k - row_start) + c
    }
}
