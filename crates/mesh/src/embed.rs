//! Points located in a tet mesh: each point's element and barycentric weights, found through
//! a uniform grid of element bounding boxes. A point outside every element goes to the
//! nearest one (its closest point on that element) and is counted. This is how a fine
//! model's states are carried onto a coarse mesh of the same body: the coarse rest vertices
//! are located in the fine rest mesh once, and every fine state is interpolated there.
//!
//! ```
//! use deform_mesh::embed::Embedding;
//! use deform_mesh::generate::BoxGrid;
//!
//! let (fine, coarse) = (BoxGrid::beam(2).build().unwrap(), BoxGrid::beam(1).build().unwrap());
//! let e = Embedding::locate(&fine, coarse.rest_positions());
//! assert!(e.outside.is_empty());
//! let x = e.interpolate(&fine, &fine.rest_positions_flat());
//! for (a, b) in x.iter().zip(coarse.rest_positions_flat()) {
//!     assert!((a - b).abs() < 1e-14);
//! }
//! ```

use nalgebra::Vector3;

use crate::TetMesh;
use crate::mesh::bounding_box;

/// Barycentric weights below `-INSIDE` count as outside (relative to the element).
const INSIDE: f64 = 1e-10;

/// Where each point lies in a mesh.
#[derive(Debug, Clone, PartialEq)]
pub struct Embedding {
    /// The element of each point.
    pub element: Vec<usize>,
    /// Its barycentric weights in that element's vertex order (non-negative, sum 1).
    pub weights: Vec<[f64; 4]>,
    /// Points outside every element, ascending; they carry the weights of their closest
    /// point on the nearest element.
    pub outside: Vec<usize>,
    /// The largest distance of an outside point from its element (0 when none).
    pub max_distance: f64,
}

impl Embedding {
    /// Locates `points` in `mesh`. Deterministic: a point on a face shared by several
    /// elements goes to the lowest-numbered one.
    pub fn locate(mesh: &TetMesh, points: &[Vector3<f64>]) -> Self {
        let grid = Grid::new(mesh);
        let mut e = Embedding {
            element: Vec::with_capacity(points.len()),
            weights: Vec::with_capacity(points.len()),
            outside: Vec::new(),
            max_distance: 0.0,
        };
        for (i, p) in points.iter().enumerate() {
            let contains = |&t: &usize| {
                let w = barycentric(mesh, t, p);
                w.iter().all(|&l| l >= -INSIDE).then_some((t, w))
            };
            // Its cell, then (for points a rounding away from a cell wall) the neighbours.
            let inside = grid.candidates(p).iter().find_map(contains);
            let inside = inside.or_else(|| grid.neighbourhood(p).iter().find_map(contains));
            let (t, w) = inside.unwrap_or_else(|| {
                let (t, q, d) = nearest(mesh, p);
                e.outside.push(i);
                e.max_distance = e.max_distance.max(d);
                (t, barycentric(mesh, t, &q))
            });
            // Rounding may leave -1e-17 weights: clamp and renormalise.
            let w = w.map(|l| l.max(0.0));
            let sum: f64 = w.iter().sum();
            e.element.push(t);
            e.weights.push(w.map(|l| l / sum));
        }
        e
    }

    /// An embedding given by whoever made the meshes: the element of each point in `mesh`
    /// and its barycentric weights there, used as given (no clamping: a point just outside
    /// a faceted surface keeps its slightly negative weight, so a linear field is still
    /// reproduced exactly).
    ///
    /// # Errors
    /// The first point whose element is out of range or whose weights are not finite or do
    /// not sum to 1 (to 1e-6), or a length mismatch, as a message naming the point.
    pub fn given(
        mesh: &TetMesh,
        element: Vec<usize>,
        weights: Vec<[f64; 4]>,
    ) -> Result<Self, String> {
        if element.len() != weights.len() {
            return Err(format!(
                "{} elements for {} weight rows",
                element.len(),
                weights.len()
            ));
        }
        for (i, (&t, w)) in element.iter().zip(&weights).enumerate() {
            if t >= mesh.num_tets() {
                return Err(format!(
                    "point {i}: element {t} is out of range for {} tets",
                    mesh.num_tets()
                ));
            }
            let sum: f64 = w.iter().sum();
            if !w.iter().all(|l| l.is_finite()) || (sum - 1.0).abs() > 1e-6 {
                return Err(format!(
                    "point {i}: weights {w:?} must be finite and sum to 1"
                ));
            }
        }
        Ok(Self {
            element,
            weights,
            outside: Vec::new(),
            max_distance: 0.0,
        })
    }

    /// Number of located points.
    pub fn len(&self) -> usize {
        self.element.len()
    }

    /// Whether there are no points.
    pub fn is_empty(&self) -> bool {
        self.element.is_empty()
    }

    /// A per-vertex field of `mesh` (flat, 3 values per vertex: positions, velocities)
    /// interpolated at the points: flat, 3 per point.
    ///
    /// # Panics
    /// If `field` is shorter than `3 * mesh.num_vertices()`.
    pub fn interpolate(&self, mesh: &TetMesh, field: &[f64]) -> Vec<f64> {
        let mut out = Vec::with_capacity(3 * self.len());
        for (&t, w) in self.element.iter().zip(&self.weights) {
            let tet = mesh.tets()[t];
            for d in 0..3 {
                out.push((0..4).map(|a| w[a] * field[3 * tet[a] + d]).sum());
            }
        }
        out
    }
}

/// Barycentric coordinates of `p` in element `t`.
fn barycentric(mesh: &TetMesh, t: usize, p: &Vector3<f64>) -> [f64; 4] {
    let x0 = mesh.rest_positions()[mesh.tets()[t][0]];
    let l = mesh.dm_inv()[t] * (p - x0);
    [1.0 - l.x - l.y - l.z, l.x, l.y, l.z]
}

/// The element nearest to `p`, the closest point on it and the distance (all elements
/// searched: only points outside the mesh come here).
fn nearest(mesh: &TetMesh, p: &Vector3<f64>) -> (usize, Vector3<f64>, f64) {
    let x = mesh.rest_positions();
    let mut best = (0, *p, f64::INFINITY);
    for (t, tet) in mesh.tets().iter().enumerate() {
        for f in crate::topology::TET_FACES {
            let q = closest_on_triangle(p, &x[tet[f[0]]], &x[tet[f[1]]], &x[tet[f[2]]]);
            let d = (p - q).norm();
            if d < best.2 {
                best = (t, q, d);
            }
        }
    }
    best
}

/// The point of triangle `abc` closest to `p` (by the Voronoi regions of its vertices,
/// edges and face).
fn closest_on_triangle(
    p: &Vector3<f64>,
    a: &Vector3<f64>,
    b: &Vector3<f64>,
    c: &Vector3<f64>,
) -> Vector3<f64> {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(&ap), ac.dot(&ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return *a;
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(&bp), ac.dot(&bp));
    if d3 >= 0.0 && d4 <= d3 {
        return *b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * (d1 / (d1 - d3));
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(&cp), ac.dot(&cp));
    if d6 >= 0.0 && d5 <= d6 {
        return *c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * (d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denom = 1.0 / (va + vb + vc);
    a + ab * (vb * denom) + ac * (vc * denom)
}

/// A uniform grid over the mesh's bounding box; each cell lists the elements whose bounding
/// boxes overlap it, ascending.
struct Grid {
    lo: Vector3<f64>,
    cell: f64,
    dims: [usize; 3],
    cells: Vec<Vec<usize>>,
}

impl Grid {
    fn new(mesh: &TetMesh) -> Self {
        let (lo, hi) = mesh.bounding_box();
        // About one element per cell: the mean element's edge.
        let volume: f64 = mesh.volumes().iter().sum();
        let mut cell = (volume / mesh.num_tets() as f64).cbrt().max(1e-300) * 1.5;
        let dims_for = |cell: f64| {
            [0, 1, 2].map(|d| (((hi[d] - lo[d]) / cell).ceil() as usize).clamp(1, 1 << 10))
        };
        // A thin shell in a large box would ask for far more cells than elements: coarsen the
        // grid until there are at most eight cells per element.
        let mut dims = dims_for(cell);
        while dims.iter().product::<usize>() > 8 * mesh.num_tets() {
            cell *= 1.25;
            dims = dims_for(cell);
        }
        let mut cells = vec![Vec::new(); dims[0] * dims[1] * dims[2]];
        let mut grid = Grid {
            lo,
            cell,
            dims,
            cells: Vec::new(),
        };
        for (t, tet) in mesh.tets().iter().enumerate() {
            let corners: Vec<Vector3<f64>> =
                tet.iter().map(|&v| mesh.rest_positions()[v]).collect();
            let (a, b) = bounding_box(&corners);
            let (a, b) = (grid.index(&a), grid.index(&b));
            for i in a[0]..=b[0] {
                for j in a[1]..=b[1] {
                    for k in a[2]..=b[2] {
                        cells[grid.flat([i, j, k])].push(t);
                    }
                }
            }
        }
        grid.cells = cells;
        grid
    }

    /// The cell of `p`, clamped into the grid.
    fn index(&self, p: &Vector3<f64>) -> [usize; 3] {
        [0, 1, 2].map(|d| {
            let i = ((p[d] - self.lo[d]) / self.cell).floor();
            (i.max(0.0) as usize).min(self.dims[d] - 1)
        })
    }

    fn flat(&self, [i, j, k]: [usize; 3]) -> usize {
        (i * self.dims[1] + j) * self.dims[2] + k
    }

    fn candidates(&self, p: &Vector3<f64>) -> &[usize] {
        &self.cells[self.flat(self.index(p))]
    }

    /// The elements of the 3 x 3 x 3 cells around `p`'s, ascending.
    fn neighbourhood(&self, p: &Vector3<f64>) -> Vec<usize> {
        let c = self.index(p);
        let range = |d: usize| c[d].saturating_sub(1)..=(c[d] + 1).min(self.dims[d] - 1);
        let mut out = Vec::new();
        for i in range(0) {
            for j in range(1) {
                for k in range(2) {
                    out.extend(&self.cells[self.flat([i, j, k])]);
                }
            }
        }
        out.sort_unstable();
        out.dedup();
        out
    }
}
