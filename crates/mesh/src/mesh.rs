//! The validated tetrahedral mesh and its rest shape.

use std::collections::BTreeMap;

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use crate::error::MeshError;
use crate::topology::{TET_EDGES, check_conforming};

/// What to do with vertices that no tetrahedron uses.
///
/// Mesh files often carry such vertices (geometry points, midside nodes of quadratic
/// elements whose corners are all that deform keeps). They carry no mass and no stiffness,
/// so they would make the system singular: by default they are dropped and the vertices
/// renumbered in their original order; [`BuildReport::kept_vertices`] maps new to old.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum Unreferenced {
    /// Remove them and renumber the rest, keeping their relative order.
    #[default]
    Drop,
    /// Fail with [`MeshError::UnreferencedVertices`].
    Error,
}

/// Options of [`TetMesh::try_with_options`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
#[non_exhaustive]
pub struct MeshOptions {
    /// A tetrahedron is degenerate when its volume is below this times its longest edge cubed.
    /// A regular tetrahedron has volume `0.118 L^3`; the default `1e-10` only rejects
    /// elements that are flat to rounding, slivers are a quality issue, not an error.
    pub degenerate_tolerance: f64,
    /// Policy for vertices that no element uses.
    pub unreferenced: Unreferenced,
    /// Accept faces shared by more than two elements (a non-manifold mesh: touching solids,
    /// or elements stacked on one another). Off by default, since a solid's face belongs to
    /// at most two elements; duplicate and overlapping elements are always rejected.
    pub allow_nonmanifold: bool,
}

deform_setters::setters!(MeshOptions {
    degenerate_tolerance: f64,
    unreferenced: Unreferenced,
    allow_nonmanifold: bool
});

impl Default for MeshOptions {
    fn default() -> Self {
        Self {
            degenerate_tolerance: 1e-10,
            unreferenced: Unreferenced::Drop,
            allow_nonmanifold: false,
        }
    }
}

/// What construction changed in its input.
#[derive(Debug, Clone, PartialEq, Default)]
#[non_exhaustive]
pub struct BuildReport {
    /// Number of negatively oriented tetrahedra that were reoriented (local vertices 1 and 2 swapped).
    pub reoriented: usize,
    /// For each vertex of the mesh, its index in the input; `None` when no vertex was dropped.
    pub kept_vertices: Option<Vec<usize>>,
    /// Number of vertices dropped because no element used them.
    pub dropped_vertices: usize,
}

/// A linear tetrahedral mesh in its rest configuration.
///
/// Invariants established by the constructors: at least one element, every coordinate
/// finite, every element has four distinct in-range vertices, positive volume above the
/// degeneracy tolerance, positive orientation (`det Dm > 0`), and every vertex is used.
///
/// Per element `e` with vertices `[i0, i1, i2, i3]`: `Dm = [X1 - X0, X2 - X0, X3 - X0]`,
/// `W = det(Dm) / 6`, and for positions `x` the deformation gradient is `F = Ds Dm^-1`.
#[derive(Debug, Clone, PartialEq)]
pub struct TetMesh {
    rest: Vec<Vector3<f64>>,
    tets: Vec<[usize; 4]>,
    regions: Vec<u32>,
    region_names: BTreeMap<u32, String>,
    dm_inv: Vec<Matrix3<f64>>,
    volumes: Vec<f64>,
    report: BuildReport,
}

impl TetMesh {
    /// Validates and builds a mesh with default [`MeshOptions`] and every element in region 0.
    ///
    /// # Errors
    /// Any [`MeshError`] naming the offending vertex or element.
    pub fn try_new(rest: Vec<Vector3<f64>>, tets: Vec<[usize; 4]>) -> Result<Self, MeshError> {
        Self::try_with_options(rest, tets, None, &MeshOptions::default())
    }

    /// Validates and builds a mesh with explicit per-element region tags (e.g. Gmsh physical
    /// groups; 0 means none) and options.
    ///
    /// # Errors
    /// Any [`MeshError`] naming the offending vertex or element.
    pub fn try_with_options(
        mut rest: Vec<Vector3<f64>>,
        mut tets: Vec<[usize; 4]>,
        regions: Option<Vec<u32>>,
        options: &MeshOptions,
    ) -> Result<Self, MeshError> {
        let tol = options.degenerate_tolerance;
        if !(tol.is_finite() && tol >= 0.0) {
            return Err(MeshError::InvalidParameter {
                field: "degenerate_tolerance",
                reason: format!("must be finite and >= 0, got {tol}"),
            });
        }
        if tets.is_empty() {
            return Err(MeshError::NoElements);
        }
        let regions = match regions {
            Some(r) if r.len() != tets.len() => {
                return Err(MeshError::LengthMismatch {
                    what: "regions",
                    found: r.len(),
                    expected: tets.len(),
                });
            }
            Some(r) => r,
            None => vec![0; tets.len()],
        };
        for (vertex, p) in rest.iter().enumerate() {
            if let Some(axis) = (0..3).find(|&a| !p[a].is_finite()) {
                return Err(MeshError::NonFiniteCoordinate {
                    vertex,
                    axis,
                    value: p[axis],
                });
            }
        }
        let n = rest.len();
        let mut used = vec![false; n];
        for (element, t) in tets.iter().enumerate() {
            for (a, &i) in t.iter().enumerate() {
                if i >= n {
                    return Err(MeshError::IndexOutOfRange {
                        element,
                        index: i,
                        num_vertices: n,
                    });
                }
                if t[..a].contains(&i) {
                    return Err(MeshError::RepeatedVertex { element, vertex: i });
                }
                used[i] = true;
            }
        }

        let mut report = BuildReport::default();
        if let Some(first) = used.iter().position(|u| !u) {
            match options.unreferenced {
                Unreferenced::Error => {
                    return Err(MeshError::UnreferencedVertices {
                        count: used.iter().filter(|u| !**u).count(),
                        first,
                    });
                }
                Unreferenced::Drop => {
                    let mut new_index = vec![usize::MAX; n];
                    let mut kept = Vec::with_capacity(n);
                    for (old, _) in used.iter().enumerate().filter(|(_, u)| **u) {
                        new_index[old] = kept.len();
                        kept.push(old);
                    }
                    rest = kept.iter().map(|&old| rest[old]).collect();
                    for t in &mut tets {
                        for i in t.iter_mut() {
                            *i = new_index[*i];
                        }
                    }
                    report.dropped_vertices = n - kept.len();
                    report.kept_vertices = Some(kept);
                }
            }
        }

        let mut dm_inv = Vec::with_capacity(tets.len());
        let mut volumes = Vec::with_capacity(tets.len());
        for (element, t) in tets.iter_mut().enumerate() {
            let mut dm = edge_matrix(&rest, t);
            let mut det = dm.determinant();
            let volume = det.abs() / 6.0;
            let longest = longest_edge(&rest, t);
            let threshold = tol * longest.powi(3);
            if !(volume > threshold) {
                return Err(MeshError::DegenerateElement {
                    element,
                    volume,
                    tolerance: tol,
                    threshold,
                });
            }
            if det < 0.0 {
                t.swap(1, 2);
                report.reoriented += 1;
                dm = edge_matrix(&rest, t);
                det = -det;
            }
            // det > threshold > 0 here, so the inverse exists; fall back loudly otherwise.
            let inv = dm.try_inverse().ok_or(MeshError::DegenerateElement {
                element,
                volume,
                tolerance: tol,
                threshold,
            })?;
            dm_inv.push(inv);
            volumes.push(det / 6.0);
        }
        check_conforming(&tets, options.allow_nonmanifold)?;

        Ok(Self {
            rest,
            tets,
            regions,
            region_names: BTreeMap::new(),
            dm_inv,
            volumes,
            report,
        })
    }

    /// Attaches names to region tags (Gmsh physical names); replaces any earlier names.
    pub fn with_region_names(mut self, names: BTreeMap<u32, String>) -> Self {
        self.region_names = names;
        self
    }

    /// Number of vertices `N`; the system has `3N` degrees of freedom.
    pub fn num_vertices(&self) -> usize {
        self.rest.len()
    }

    /// Number of tetrahedra.
    pub fn num_tets(&self) -> usize {
        self.tets.len()
    }

    /// Rest positions `X`.
    pub fn rest_positions(&self) -> &[Vector3<f64>] {
        &self.rest
    }

    /// Rest positions as a flat `3N` vector `[x0, y0, z0, x1, ...]`, the layout of every
    /// state vector in deform.
    pub fn rest_positions_flat(&self) -> Vec<f64> {
        self.rest.iter().flat_map(|p| [p.x, p.y, p.z]).collect()
    }

    /// Element connectivity, positively oriented.
    pub fn tets(&self) -> &[[usize; 4]] {
        &self.tets
    }

    /// Region tag per element (0 when the source had none).
    pub fn regions(&self) -> &[u32] {
        &self.regions
    }

    /// Names of region tags, where the source gave them.
    pub fn region_names(&self) -> &BTreeMap<u32, String> {
        &self.region_names
    }

    /// `Dm^-1` per element.
    pub fn dm_inv(&self) -> &[Matrix3<f64>] {
        &self.dm_inv
    }

    /// Rest volume `W` per element (positive).
    pub fn volumes(&self) -> &[f64] {
        &self.volumes
    }

    /// What construction changed in its input (reoriented elements, dropped vertices).
    pub fn build_report(&self) -> &BuildReport {
        &self.report
    }

    /// Gradients of the four linear shape functions of element `e` with respect to rest
    /// coordinates, so that `F = sum_a x_a grad_a^T`. They sum to zero.
    ///
    /// # Panics
    /// If `e` is out of range.
    #[track_caller]
    pub fn shape_gradients(&self, e: usize) -> [Vector3<f64>; 4] {
        let b = &self.dm_inv[e];
        let g1: Vector3<f64> = b.row(0).transpose();
        let g2: Vector3<f64> = b.row(1).transpose();
        let g3: Vector3<f64> = b.row(2).transpose();
        [-(g1 + g2 + g3), g1, g2, g3]
    }

    /// Deformation gradient `F = Ds Dm^-1` of element `e` for positions `x` (flat `3N`).
    ///
    /// # Panics
    /// If `e` is out of range or `x` is shorter than `3N`.
    #[track_caller]
    pub fn deformation_gradient(&self, e: usize, x: &[f64]) -> Matrix3<f64> {
        let t = &self.tets[e];
        let p = |i: usize| Vector3::new(x[3 * i], x[3 * i + 1], x[3 * i + 2]);
        let x0 = p(t[0]);
        let ds = Matrix3::from_columns(&[p(t[1]) - x0, p(t[2]) - x0, p(t[3]) - x0]);
        ds * self.dm_inv[e]
    }

    /// Axis-aligned bounding box of the rest positions, `(min, max)`.
    pub fn bounding_box(&self) -> (Vector3<f64>, Vector3<f64>) {
        bounding_box(&self.rest)
    }
}

/// `(min, max)` corners of a point set; `(+inf, -inf)` for an empty one.
pub(crate) fn bounding_box(points: &[Vector3<f64>]) -> (Vector3<f64>, Vector3<f64>) {
    let mut lo = Vector3::repeat(f64::INFINITY);
    let mut hi = Vector3::repeat(f64::NEG_INFINITY);
    for p in points {
        lo = lo.inf(p);
        hi = hi.sup(p);
    }
    (lo, hi)
}

/// `[X1 - X0, X2 - X0, X3 - X0]` of element `t`.
pub(crate) fn edge_matrix(points: &[Vector3<f64>], t: &[usize; 4]) -> Matrix3<f64> {
    let x0 = points[t[0]];
    Matrix3::from_columns(&[points[t[1]] - x0, points[t[2]] - x0, points[t[3]] - x0])
}

/// Length of the longest edge of element `t`.
pub(crate) fn longest_edge(points: &[Vector3<f64>], t: &[usize; 4]) -> f64 {
    TET_EDGES
        .iter()
        .map(|[a, b]| (points[t[*a]] - points[t[*b]]).norm())
        .fold(0.0, f64::max)
}
