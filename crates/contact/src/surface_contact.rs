//! Self-contact of a body's boundary surface: IPC's barrier on the distances of
//! point-triangle and edge-edge pairs (Li et al. 2020), with the mollifier on edge pairs,
//! a bounding-volume broad phase, and conservative advancement for continuous collision
//! detection of a linear step.

use std::fmt;

use nalgebra::{Isometry3, Matrix3, Point3, SMatrix, SVector, SymmetricEigen, Vector3};
use serde::{Deserialize, Serialize};
use std::ops::AddAssign;

use crate::bvh::{Aabb, Bvh};
use crate::distance::{Form, closest_weights, edge_edge, mollifier, point_triangle, squared_jet};
use crate::jet::{Jet, JetPoint, variables};
use crate::obstacle::{carried, relative_path};
use crate::{Barrier, ContactError, ContactHessian, ContactSummary, STEP_MARGIN};

/// Two primitives of the surface that a self-contact distance is measured between.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum SurfacePair {
    /// A surface vertex and a surface triangle (not one of its own).
    PointTriangle {
        /// The vertex.
        vertex: usize,
        /// The triangle's vertices.
        triangle: [usize; 3],
    },
    /// Two surface edges with no vertex in common.
    EdgeEdge {
        /// The first edge's vertices.
        first: [usize; 2],
        /// The second edge's vertices.
        second: [usize; 2],
    },
    /// A surface edge that passes through a triangle (surfaces that intersect).
    EdgeTriangle {
        /// The edge's vertices.
        edge: [usize; 2],
        /// The triangle's vertices.
        triangle: [usize; 3],
    },
}

impl fmt::Display for SurfacePair {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SurfacePair::PointTriangle { vertex, triangle } => {
                write!(f, "surface vertex {vertex} and triangle {triangle:?}")
            }
            SurfacePair::EdgeEdge { first, second } => {
                write!(f, "surface edges {first:?} and {second:?}")
            }
            SurfacePair::EdgeTriangle { edge, triangle } => {
                write!(f, "surface edge {edge:?} through triangle {triangle:?}")
            }
        }
    }
}

/// A pair that friction lags at a step's start ([`SelfContact::lagged_pairs`]).
struct LaggedPair {
    candidate: Candidate,
    /// Its four vertices (the body's below `body`, an obstacle's from there).
    indices: [usize; 4],
    /// Its obstacle among the meshes, or the meshes' count for the body's own surface.
    obstacle: usize,
    /// Its points at the step's start, their distance and its form.
    points: [Vector3<f64>; 4],
    distance: f64,
    form: Form,
    /// Its obstacle's coefficient of friction (non-zero).
    mu: f64,
}

/// A candidate pair by index: (surface vertex, triangle) or (edge, edge).
#[derive(Debug, Clone, Copy)]
enum Candidate {
    PointTriangle(usize, usize),
    EdgeEdge(usize, usize),
}

/// The mollifier's threshold relative to the product of the edges' squared rest lengths
/// (IPC's `eps_x = 1e-3 |e0|^2 |e1|^2`).
const MOLLIFIER: f64 = 1e-3;

/// Where the obstacles' vertices are taken while a step's path is followed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Place {
    /// Where they are at the current step's end, still (Newton's iterates and line search).
    End,
    /// From where they were at the step's start to where they are at its end, on the
    /// straight path that the body's first displacement follows too.
    Sweep,
    /// Where they were at the step's start, still (a path in a moving mesh's frame, or the
    /// lag of friction at the step's start).
    Start,
}

/// Most advancement steps of one pair's collision detection; the bound reached by then is
/// kept (it is safe at every step). A pair that slides past itself at distance `d` with
/// relative speed `L` needs about `L / d` steps to reach the step's end: a cap of 500
/// held every line search of the soft tube's collapse near 0.1 (pairs at 1e-7 m sliding
/// by 1e-3 m), and Newton took 300 iterations a step. Only such pairs take many.
const MAX_ADVANCES: usize = 50_000;

/// The body's surface, in contact with itself, with fixed triangle-mesh obstacles, or both.
///
/// Vertex indices below `body` are the body's (positions from `x`); from `body` on, the
/// obstacles' (positions in `fixed`, one mesh after another), so that one pair machinery
/// serves both: a pair with an obstacle's primitive is a self-contact pair whose obstacle
/// points do not move and get no force.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct SelfContact {
    triangles: Vec<[usize; 3]>,
    edges: Vec<[usize; 2]>,
    vertices: Vec<usize>,
    /// Each edge's squared rest length.
    rest_length2: Vec<f64>,
    /// The body's vertex count: indices from here on are the obstacles'.
    body: usize,
    /// The body's triangles come first in `triangles`, this many.
    body_triangles: usize,
    /// The obstacles' vertex positions at the current step's end, at its start, and at
    /// rest (before any motion).
    fixed: Vec<Vector3<f64>>,
    fixed_start: Vec<Vector3<f64>>,
    fixed_rest: Vec<Vector3<f64>>,
    /// Each mesh obstacle's rigid motion over the current step; `None` while it rests.
    mesh_steps: Vec<Option<Isometry3<f64>>>,
    /// Where each obstacle mesh's vertices start in `fixed`.
    mesh_starts: Vec<usize>,
    /// Whether pairs of two body primitives count (self-contact).
    self_pairs: bool,
}

fn point(x: &[f64], v: usize) -> Vector3<f64> {
    Vector3::new(x[3 * v], x[3 * v + 1], x[3 * v + 2])
}

impl SelfContact {
    /// Self-contact of the surface `triangles` (vertex indices into `rest`, flat `3N`).
    #[cfg(test)]
    pub(crate) fn new(triangles: Vec<[usize; 3]>, rest: &[f64]) -> Result<Self, ContactError> {
        Self::with_meshes(triangles, rest, true, &[])
    }

    /// The body's surface `triangles` (vertex indices into `rest`, flat `3N`) against the
    /// fixed triangle meshes `meshes`, and against itself when `self_pairs`.
    pub(crate) fn with_meshes(
        triangles: Vec<[usize; 3]>,
        rest: &[f64],
        self_pairs: bool,
        meshes: &[crate::Surface],
    ) -> Result<Self, ContactError> {
        let n = rest.len() / 3;
        Self::check_triangles(&triangles, n, "surface")?;
        let body_triangles = triangles.len();
        let mut triangles = triangles;
        let (mut fixed, mut mesh_starts) = (Vec::new(), Vec::new());
        for (m, (positions, mesh_triangles)) in meshes.iter().enumerate() {
            let field = format!("meshes[{m}]");
            if let Some(k) = positions.iter().position(|c| !c.is_finite()) {
                return Err(ContactError::Invalid {
                    field,
                    reason: format!("vertex {} has a non-finite coordinate", k / 3),
                });
            }
            Self::check_triangles(mesh_triangles, positions.len() / 3, &field)?;
            let first = n + fixed.len();
            mesh_starts.push(fixed.len());
            fixed.extend(positions.chunks_exact(3).map(Vector3::from_column_slice));
            triangles.extend(mesh_triangles.iter().map(|t| t.map(|v| v + first)));
        }
        let mut surface = Self {
            triangles,
            edges: Vec::new(),
            vertices: Vec::new(),
            rest_length2: Vec::new(),
            body: n,
            body_triangles,
            fixed_start: fixed.clone(),
            fixed_rest: fixed.clone(),
            fixed,
            mesh_steps: vec![None; mesh_starts.len()],
            mesh_starts,
            self_pairs,
        };
        surface.edges = surface.edges_of_triangles();
        let mut vertices: Vec<usize> = surface.triangles.iter().flatten().copied().collect();
        vertices.sort_unstable();
        vertices.dedup();
        surface.vertices = vertices;
        surface.rest_length2 = surface
            .edges
            .iter()
            .map(|e| {
                let at = |v| surface.at(rest, v, Place::End);
                (at(e[1]) - at(e[0])).norm_squared()
            })
            .collect();
        Ok(surface)
    }

    fn edges_of_triangles(&self) -> Vec<[usize; 2]> {
        let mut edges: Vec<[usize; 2]> = self
            .triangles
            .iter()
            .flat_map(|t| [[t[0], t[1]], [t[1], t[2]], [t[2], t[0]]])
            .map(|[a, b]| [a.min(b), a.max(b)])
            .collect();
        edges.sort_unstable();
        edges.dedup();
        edges
    }

    fn check_triangles(
        triangles: &[[usize; 3]],
        n: usize,
        field: &str,
    ) -> Result<(), ContactError> {
        if let Some((i, t)) = triangles.iter().enumerate().find(|(_, t)| {
            t.iter().any(|&v| v >= n) || t[0] == t[1] || t[1] == t[2] || t[0] == t[2]
        }) {
            return Err(ContactError::Invalid {
                field: format!("{field}[{i}]"),
                reason: format!(
                    "triangle {t:?} repeats a vertex or names one beyond the {n} given"
                ),
            });
        }
        Ok(())
    }

    /// The body's surface triangles.
    pub(crate) fn triangles(&self) -> &[[usize; 3]] {
        &self.triangles[..self.body_triangles]
    }

    /// Whether pairs of two body primitives count.
    pub(crate) fn self_pairs(&self) -> bool {
        self.self_pairs
    }

    /// Places mesh obstacle `mesh` for a step: at `from` (a rigid motion of where it rests)
    /// at the step's start, at `to` at its end.
    pub(crate) fn place_mesh(&mut self, mesh: usize, from: &Isometry3<f64>, to: &Isometry3<f64>) {
        let first = self.mesh_starts[mesh];
        let end = self
            .mesh_starts
            .get(mesh + 1)
            .copied()
            .unwrap_or(self.fixed.len());
        for k in first..end {
            let rest = Point3::from(self.fixed_rest[k]);
            self.fixed_start[k] = (from * rest).coords;
            self.fixed[k] = (to * rest).coords;
        }
        self.mesh_steps[mesh] = (from != to).then(|| to * from.inverse());
    }

    /// Whether a mesh obstacle moves during the current step.
    pub(crate) fn moving(&self) -> bool {
        self.mesh_steps.iter().any(Option::is_some)
    }

    /// Vertex `v`'s position: the body's from `x`, an obstacle's from `fixed` (or
    /// `fixed_start`, as `place` says).
    fn at(&self, x: &[f64], v: usize, place: Place) -> Vector3<f64> {
        match (v.checked_sub(self.body), place) {
            (None, _) => point(x, v),
            (Some(k), Place::End) => self.fixed[k],
            (Some(k), _) => self.fixed_start[k],
        }
    }

    /// Vertex `v`'s displacement along `dx`: an obstacle's is its step's when swept, else
    /// none.
    fn moved(&self, dx: &[f64], v: usize, place: Place) -> Vector3<f64> {
        match (v.checked_sub(self.body), place) {
            (None, _) => point(dx, v),
            (Some(k), Place::Sweep) => self.fixed[k] - self.fixed_start[k],
            (Some(_), _) => Vector3::zeros(),
        }
    }

    /// Whether a pair of primitives on these sides (true: the body's) is modelled: the body
    /// against an obstacle always, the body against itself with self-contact, never two
    /// obstacles.
    fn counts(&self, first_on_body: bool, second_on_body: bool) -> bool {
        match (first_on_body, second_on_body) {
            (true, true) => self.self_pairs,
            (false, false) => false,
            _ => true,
        }
    }

    /// Whether both primitives of `c` are the body's.
    fn on_body(&self, c: Candidate) -> bool {
        self.indices(c).iter().all(|&v| v < self.body)
    }

    /// The error for a pair whose distance is not positive; an obstacle's vertices are
    /// numbered within its mesh.
    fn touching(&self, c: Candidate, distance: f64) -> ContactError {
        self.named(self.pair(c), &self.indices(c), distance)
    }

    /// The error for `pair` on `vertices` at `distance`: self-contact's, or a mesh
    /// obstacle's with its vertices numbered within its mesh.
    fn named(&self, pair: SurfacePair, vertices: &[usize], distance: f64) -> ContactError {
        let Some(&v) = vertices.iter().find(|&&v| v >= self.body) else {
            return ContactError::SelfContact { pair, distance };
        };
        let mesh = self.mesh_of(v);
        let first = self.body + self.mesh_starts[mesh];
        let local = |i: usize| if i >= self.body { i - first } else { i };
        let pair = match pair {
            SurfacePair::PointTriangle { vertex, triangle } => SurfacePair::PointTriangle {
                vertex: local(vertex),
                triangle: triangle.map(local),
            },
            SurfacePair::EdgeEdge { first, second } => SurfacePair::EdgeEdge {
                first: first.map(local),
                second: second.map(local),
            },
            SurfacePair::EdgeTriangle { edge, triangle } => SurfacePair::EdgeTriangle {
                edge: edge.map(local),
                triangle: triangle.map(local),
            },
        };
        ContactError::MeshObstacle {
            mesh,
            pair,
            distance,
        }
    }

    /// Refuses positions where two primitives that share no vertex are closer than `dhat`
    /// (at rest they would push apart: the barrier must be zero there).
    pub(crate) fn check_separated(&self, x: &[f64], dhat: f64) -> Result<(), ContactError> {
        // The closest pair is the one to name: one that touches is no matter of dhat.
        let mut closest: Option<(f64, Candidate)> = None;
        for c in self.candidates(x, None, dhat, Place::End) {
            if !self.on_body(c) {
                continue;
            }
            let d = self.distance(c, &self.points(c, x, Place::End)).0;
            if d < dhat && closest.is_none_or(|(least, _)| d < least) {
                closest = Some((d, c));
            }
        }
        let Some((d, c)) = closest else {
            return Ok(());
        };
        let pair = self.pair(c);
        Err(if d <= 0.0 {
            ContactError::Invalid {
                field: "self_contact".into(),
                reason: format!(
                    "{pair} touch at rest (distance {d:e} m): no dhat separates them; self-contact needs the body's surface apart at rest"
                ),
            }
        } else {
            ContactError::Invalid {
                field: "dhat".into(),
                reason: format!(
                    "{pair} are {d:e} m apart at rest, closer than dhat = {dhat:e} m; give a smaller dhat"
                ),
            }
        })
    }

    fn indices(&self, c: Candidate) -> [usize; 4] {
        match c {
            Candidate::PointTriangle(v, t) => {
                let t = self.triangles[t];
                [self.vertices[v], t[0], t[1], t[2]]
            }
            Candidate::EdgeEdge(a, b) => {
                let (a, b) = (self.edges[a], self.edges[b]);
                [a[0], a[1], b[0], b[1]]
            }
        }
    }

    fn points(&self, c: Candidate, x: &[f64], place: Place) -> [Vector3<f64>; 4] {
        self.indices(c).map(|v| self.at(x, v, place))
    }

    fn pair(&self, c: Candidate) -> SurfacePair {
        let i = self.indices(c);
        match c {
            Candidate::PointTriangle(..) => SurfacePair::PointTriangle {
                vertex: i[0],
                triangle: [i[1], i[2], i[3]],
            },
            Candidate::EdgeEdge(..) => SurfacePair::EdgeEdge {
                first: [i[0], i[1]],
                second: [i[2], i[3]],
            },
        }
    }

    fn distance(&self, c: Candidate, p: &[Vector3<f64>; 4]) -> (f64, Form) {
        match c {
            Candidate::PointTriangle(..) => point_triangle(&p[0], &p[1], &p[2], &p[3]),
            Candidate::EdgeEdge(..) => edge_edge(&p[0], &p[1], &p[2], &p[3]),
        }
    }

    /// The mesh obstacle that fixed vertex `v` belongs to.
    fn mesh_of(&self, v: usize) -> usize {
        self.mesh_starts.partition_point(|&s| s <= v - self.body) - 1
    }

    /// Appends the lagged friction of the surface pairs within `dhat` at `x` (the start of
    /// a step) to `pairs`: each pair's contact point is its closest points' weighted sum
    /// (the gap between them for a pair of the body's own), its normal force `-b'(d)`
    /// (times the mollifier on edge pairs). `mu` holds the meshes' coefficients, then the
    /// body's own surface's when it is in self-contact; they are numbered from `first` among
    /// the obstacles friction acts against.
    pub(crate) fn friction_pairs(
        &self,
        x: &[f64],
        barrier: Barrier,
        mu: &[f64],
        first: usize,
        pairs: &mut Vec<crate::FrictionPair>,
    ) {
        for pair in self.lagged_pairs(x, barrier.dhat, mu) {
            let (indices, p, d) = (pair.indices, pair.points, pair.distance);
            let w = closest_weights(pair.form, &p);
            let gap: Vector3<f64> = (0..4).map(|k| p[k] * w[k]).sum();
            let mollified = match pair.candidate {
                Candidate::PointTriangle(..) => 1.0,
                Candidate::EdgeEdge(..) => self.mollified(pair.candidate, &variables(&p)).value,
            };
            let force = -barrier.first(d) * mollified;
            let vertices: Vec<(usize, f64)> = (0..4)
                .filter(|&k| indices[k] < self.body && w[k] != 0.0)
                .map(|k| (indices[k], w[k]))
                .collect();
            // Sticking, the gap keeps its start: the body's part of the point moves as the
            // obstacle's part does over the step.
            let obstacle_moves: Vector3<f64> = (0..4)
                .filter(|&k| indices[k] >= self.body)
                .map(|k| self.moved(x, indices[k], Place::Sweep) * w[k])
                .sum();
            let start = vertices
                .iter()
                .map(|&(v, wv)| point(x, v) * wv)
                .sum::<Vector3<f64>>()
                - obstacle_moves;
            pairs.push(crate::FrictionPair {
                vertices,
                obstacle: first + pair.obstacle,
                limit: pair.mu * force,
                basis: crate::friction::tangent_basis(&(gap / d)),
                start,
            });
        }
    }

    /// `out += (df/dx0)^T lambda` for the lagged friction forces `f` at `x1` of the surface
    /// pairs [`SelfContact::friction_pairs`] lags at `x0` (the same pairs, recomputed), with
    /// `mu` and `eps` as there. A pair's force on its vertex `k` is `-w_k L phi(|q|) q` with
    /// `q = P z`, `z = sum_k w_k delta_k` (each vertex's displacement over the step, a mesh
    /// obstacle's its motion's), and `L = mu (-b'(d)) m`; the weights `w`, the normal in
    /// `P = I - n n^T`, and `L` move with `x0`. The distance's gradient in vertex `k` is
    /// `w_k n`, so with its Hessian `H` the weights change as `dw_k = n^T H_k.` and the
    /// normal as `dn = P sum_{w_k > 0} H_k.` (those weights sum to one).
    pub(crate) fn friction_start_vjp(
        &self,
        (x0, x1): (&[f64], &[f64]),
        (barrier, mu, eps): (Barrier, &[f64], f64),
        lambda: &[f64],
        out: &mut [f64],
    ) {
        for pair in self.lagged_pairs(x0, barrier.dhat, mu) {
            let (indices, p) = (pair.indices, pair.points);
            let jets = variables(&p);
            let distance = squared_jet(pair.form, &jets).sqrt();
            let mollified = self.mollified(pair.candidate, &jets);
            let body = indices.map(|v| v < self.body);
            let delta: [Vector3<f64>; 4] = std::array::from_fn(|k| match body[k] {
                true => point(x1, indices[k]) - p[k],
                false => self.moved(x0, indices[k], Place::Sweep),
            });
            let lam: [Vector3<f64>; 4] = std::array::from_fn(|k| match body[k] {
                true => point(lambda, indices[k]),
                false => Vector3::zeros(),
            });
            let grad = pair_start_gradient(
                (&p, &delta, &lam, &body),
                (pair.form, &distance, &mollified),
                (pair.mu, barrier, eps),
            );
            for (k, &v) in indices.iter().enumerate().filter(|(k, _)| body[*k]) {
                for r in 0..3 {
                    out[3 * v + r] += grad[3 * k + r];
                }
            }
        }
    }

    /// Refuses positions where an edge of one surface passes through a triangle of another
    /// that it counts against (the body's and a mesh obstacle's; the body's own with
    /// self-contact): intersecting surfaces whose primitives need not be close to a vertex
    /// or edge, which the distances alone would not see.
    pub(crate) fn check_crossings(&self, x: &[f64]) -> Result<(), ContactError> {
        let at = |v| self.at(x, v, Place::End);
        let boxes = |vs: &[usize]| Aabb::of(vs.iter().map(|&v| at(v)));
        let triangles = Bvh::new(self.triangles.iter().map(|t| boxes(t)).collect());
        for e in &self.edges {
            let mut found = None;
            triangles.query(&boxes(e), |t| {
                let tri = self.triangles[t];
                let counts = self.counts(e[0] < self.body, t < self.body_triangles);
                if found.is_none()
                    && counts
                    && !tri.contains(&e[0])
                    && !tri.contains(&e[1])
                    && crosses(at(e[0]), at(e[1]), tri.map(at))
                {
                    found = Some(tri);
                }
            });
            if let Some(triangle) = found {
                let pair = SurfacePair::EdgeTriangle { edge: *e, triangle };
                let vertices = [e[0], e[1], triangle[0], triangle[1], triangle[2]];
                return Err(self.named(pair, &vertices, 0.0));
            }
        }
        Ok(())
    }

    /// Pairs whose boxes (over `x`, and `x + dx` when given, the obstacles as `place`
    /// says) come within `reach`, in a fixed order.
    fn candidates(
        &self,
        x: &[f64],
        dx: Option<&[f64]>,
        reach: f64,
        place: Place,
    ) -> Vec<Candidate> {
        let swept = |vs: &[usize]| {
            Aabb::of(vs.iter().flat_map(|&v| {
                let p = self.at(x, v, place);
                [p, dx.map_or(p, |dx| p + self.moved(dx, v, place))]
            }))
        };
        let triangles = Bvh::new(self.triangles.iter().map(|t| swept(t)).collect());
        let mut out = Vec::new();
        for (i, &v) in self.vertices.iter().enumerate() {
            triangles.query(&swept(&[v]).inflate(reach), |t| {
                let counts = self.counts(v < self.body, t < self.body_triangles);
                if counts && !self.triangles[t].contains(&v) {
                    out.push(Candidate::PointTriangle(i, t));
                }
            });
        }
        let boxes: Vec<Aabb> = self.edges.iter().map(|e| swept(e)).collect();
        let edges = Bvh::new(boxes.clone());
        for (a, ea) in self.edges.iter().enumerate() {
            edges.query(&boxes[a].inflate(reach), |b| {
                let eb = self.edges[b];
                let counts = self.counts(ea[0] < self.body, eb[0] < self.body);
                if counts && b > a && !eb.contains(&ea[0]) && !eb.contains(&ea[1]) {
                    out.push(Candidate::EdgeEdge(a, b));
                }
            });
        }
        out
    }

    /// Adds the self-contact barrier at `x` to `summary`, its forces to `forces` and its
    /// pair Hessians to `hessian`, PSD-projected when `project`.
    pub(crate) fn evaluate(
        &self,
        x: &[f64],
        (barrier, project): (Barrier, bool),
        summary: &mut ContactSummary,
        mut forces: Option<&mut [f64]>,
        mut hessian: Option<&mut ContactHessian>,
    ) -> Result<(), ContactError> {
        for c in self.candidates(x, None, barrier.dhat, Place::End) {
            let p = self.points(c, x, Place::End);
            let (d, form) = self.distance(c, &p);
            if !(d > 0.0) {
                return Err(self.touching(c, d));
            }
            if d >= barrier.dhat {
                continue;
            }
            summary.active += 1;
            summary.min_distance = summary.min_distance.min(d);
            let energy = self.energy(c, &p, form, d, barrier);
            summary.energy += energy.value;
            let vertices = self.indices(c);
            if let Some(f) = forces.as_deref_mut() {
                for (k, v) in vertices.iter().enumerate().filter(|(_, v)| **v < self.body) {
                    for r in 0..3 {
                        f[3 * v + r] -= energy.gradient[3 * k + r];
                    }
                }
            }
            if let Some(h) = hessian.as_deref_mut() {
                let pair = if project {
                    project_psd(energy.hessian)
                } else {
                    energy.hessian
                };
                h.add_pair(&vertices, &pair, self.body);
            }
        }
        Ok(())
    }

    /// A pair's barrier energy with its derivatives in the pair's 12 coordinates.
    fn energy(&self, c: Candidate, p: &[Vector3<f64>; 4], form: Form, d: f64, b: Barrier) -> Jet {
        let x = variables(p);
        let energy = squared_jet(form, &x)
            .sqrt()
            .map(b.value(d), b.first(d), b.second(d));
        match c {
            Candidate::PointTriangle(..) => energy,
            Candidate::EdgeEdge(..) => energy * self.mollified(c, &x),
        }
    }

    /// The factor on a pair's barrier with its derivatives: 1 on a point and a triangle,
    /// IPC's mollifier on two edges (its threshold from their rest lengths).
    fn mollified(&self, c: Candidate, x: &[JetPoint; 4]) -> Jet {
        match c {
            Candidate::PointTriangle(..) => Jet::constant(1.0),
            Candidate::EdgeEdge(e0, e1) => {
                mollifier(x, MOLLIFIER * self.rest_length2[e0] * self.rest_length2[e1])
            }
        }
    }

    /// The pairs friction lags at `x`, a step's start (mesh obstacles where they were
    /// then): those closer than `dhat` whose obstacle has a non-zero coefficient in `mu`
    /// (the meshes', then the body's own surface's), in a fixed order. The lag and its
    /// derivative in the start both take them from here.
    fn lagged_pairs<'a>(
        &'a self,
        x: &'a [f64],
        dhat: f64,
        mu: &'a [f64],
    ) -> impl Iterator<Item = LaggedPair> + 'a {
        let own = self.mesh_starts.len();
        self.candidates(x, None, dhat, Place::Start)
            .into_iter()
            .filter_map(move |c| {
                let indices = self.indices(c);
                let obstacle = match indices.iter().find(|&&v| v >= self.body) {
                    Some(&fixed) => self.mesh_of(fixed),
                    None => own,
                };
                let points = self.points(c, x, Place::Start);
                let (distance, form) = self.distance(c, &points);
                let mu = mu.get(obstacle).copied().unwrap_or(0.0);
                (mu != 0.0 && distance > 0.0 && distance < dhat).then_some(LaggedPair {
                    candidate: c,
                    indices,
                    obstacle,
                    points,
                    distance,
                    form,
                    mu,
                })
            })
    }

    /// The largest `s` in `[0, 1]` (conservatively) such that on the path `x + t dx`,
    /// `t <= s`, no pair's distance falls below [`STEP_MARGIN`] of the least of its start
    /// and `dhat`. A pair that never comes within `dhat` cannot, so only pairs whose swept
    /// boxes come that close are advanced. With `sweep`, the mesh obstacles go from where
    /// they were at the step's start to where they are at its end on the same path (a
    /// step's first displacement); else they stay at the end.
    pub(crate) fn step_bound(&self, x: &[f64], dx: &[f64], dhat: f64, sweep: bool) -> f64 {
        let place = if sweep { Place::Sweep } else { Place::End };
        let mut bound = 1.0f64;
        for c in self.candidates(x, Some(dx), dhat, place) {
            let p = self.points(c, x, place);
            let dp = self.indices(c).map(|v| self.moved(dx, v, place));
            bound = bound.min(self.advance(c, &p, &dp, (STEP_MARGIN, dhat)));
            if bound == 0.0 {
                break;
            }
        }
        bound
    }

    /// [`ContactModel::carry`]'s part for the moving mesh obstacles: for each, the body's
    /// surface vertices of a pair with it whose path in its frame (the mesh where it was at
    /// the step's start) would come closer than a fifth of the least of the pair's distance
    /// and `dhat` go along that path only as far as is safe, then move with the mesh.
    pub(crate) fn carry(
        &self,
        x: &[f64],
        dx: &mut [f64],
        movable: &dyn Fn(usize) -> bool,
        dhat: f64,
    ) {
        for (mesh, step) in self.mesh_steps.iter().enumerate() {
            let Some(step) = step else {
                continue;
            };
            let mut relative = vec![0.0; dx.len()];
            let body = self
                .vertices
                .iter()
                .filter(|&&v| v < self.body && movable(v));
            for &v in body {
                let path = relative_path(step, &point(x, v), &point(dx, v));
                relative[3 * v..3 * v + 3].copy_from_slice(path.as_slice());
            }
            let mut fraction = vec![1.0f64; self.body];
            for c in self.candidates(x, Some(&relative), dhat, Place::Start) {
                let indices = self.indices(c);
                if !indices
                    .iter()
                    .any(|&v| v >= self.body && self.mesh_of(v) == mesh)
                {
                    continue;
                }
                let p = self.points(c, x, Place::Start);
                let dp = indices.map(|v| self.moved(&relative, v, Place::Start));
                let s = self.advance(c, &p, &dp, (2.0 * STEP_MARGIN, dhat));
                for &v in indices.iter().filter(|&&v| v < self.body) {
                    fraction[v] = fraction[v].min(s);
                }
            }
            for (v, &s) in fraction.iter().enumerate().filter(|(_, s)| **s < 1.0) {
                let path = point(&relative, v);
                let moved = carried(step, &point(x, v), &path, s);
                dx[3 * v..3 * v + 3].copy_from_slice(moved.as_slice());
            }
        }
    }

    /// Conservative advancement of one pair towards `target = margin min(d0, dhat)` of its
    /// start distance `d0`: the distance changes no faster than `L`, a bound of the points'
    /// relative speed, so a step of `(d - target) / L` never passes the target distance.
    fn advance(
        &self,
        c: Candidate,
        p: &[Vector3<f64>; 4],
        dp: &[Vector3<f64>; 4],
        (margin, dhat): (f64, f64),
    ) -> f64 {
        let mean = (dp[0] + dp[1] + dp[2] + dp[3]) / 4.0;
        let n = dp.map(|d| (d - mean).norm());
        let speed = match c {
            Candidate::PointTriangle(..) => n[0] + n[1].max(n[2]).max(n[3]),
            Candidate::EdgeEdge(..) => n[0].max(n[1]) + n[2].max(n[3]),
        };
        let d0 = self.distance(c, p).0;
        if !(d0 > 0.0) {
            return 0.0;
        }
        if speed == 0.0 {
            return 1.0;
        }
        let target = margin * d0.min(dhat);
        let (mut t, mut d) = (0.0, d0);
        for _ in 0..MAX_ADVANCES {
            let step = (d - target) / speed;
            if t + step >= 1.0 {
                return 1.0;
            }
            t += step;
            let at: [Vector3<f64>; 4] = std::array::from_fn(|k| p[k] + dp[k] * t);
            d = self.distance(c, &at).0;
            if d - target <= 0.05 * (d0 - target) {
                return t;
            }
        }
        t
    }
}

/// A pair's points at the step's start, their displacements over the step, the adjoint at
/// them, and which are the body's.
type PairPoints<'a> = (
    &'a [Vector3<f64>; 4],
    &'a [Vector3<f64>; 4],
    &'a [Vector3<f64>; 4],
    &'a [bool; 4],
);

/// The gradient in a pair's 12 coordinates at the step's start of `S = lambda . f`, its
/// lagged friction forces at the step's end against the adjoint `lambda` (zero on an
/// obstacle's points), from the distance's jet and the mollifier's (see
/// [`SelfContact::friction_start_vjp`]). `delta` is each point's displacement over the
/// step; `body` says which points are the body's (an obstacle's do not move with the start).
fn pair_start_gradient(
    (p, delta, lambda, body): PairPoints<'_>,
    (form, distance, mollified): (Form, &Jet, &Jet),
    (mu, barrier, eps): (f64, Barrier, f64),
) -> SVector<f64, 12> {
    type Rows = SMatrix<f64, 3, 12>;
    let w = closest_weights(form, p);
    let d = distance.value;
    let n = (0..4).map(|k| p[k] * w[k]).sum::<Vector3<f64>>() / d;
    let projector = Matrix3::identity() - n * n.transpose();
    let h = &distance.hessian;
    // dw_k = n^T H_k. (a 12-row each) and dn = P sum_{w_k > 0} H_k. .
    let dw: [SVector<f64, 12>; 4] =
        std::array::from_fn(|k| h.fixed_view::<3, 12>(3 * k, 0).transpose() * n);
    let mut dn = Rows::zeros();
    for k in (0..4).filter(|&k| w[k] > 0.0) {
        dn += h.fixed_view::<3, 12>(3 * k, 0);
    }
    let dn = projector * dn;
    let z: Vector3<f64> = (0..4).map(|k| delta[k] * w[k]).sum();
    let mut dz = Rows::zeros();
    for k in 0..4 {
        dz += delta[k] * dw[k].transpose();
        if body[k] {
            // The start is where the displacement is measured from.
            dz.fixed_view_mut::<3, 3>(0, 3 * k)
                .add_assign(&(Matrix3::identity() * -w[k]));
        }
    }
    let q = projector * z;
    let dq = projector * dz - dn * n.dot(&z) - n * (z.transpose() * dn);
    let s = q.norm();
    let (phi, dphi) = if s >= eps {
        (1.0 / s, -1.0 / (s * s))
    } else {
        (2.0 / eps - s / (eps * eps), -1.0 / (eps * eps))
    };
    let ds = match s > 0.0 {
        true => dq.transpose() * q / s,
        false => SVector::<f64, 12>::zeros(),
    };
    let g: Vector3<f64> = (0..4).map(|k| lambda[k] * w[k]).sum();
    let mut dg = Rows::zeros();
    for k in 0..4 {
        dg += lambda[k] * dw[k].transpose();
    }
    let (b1, b2) = (barrier.first(d), barrier.second(d));
    let limit = mu * -b1 * mollified.value;
    let dlimit = (distance.gradient * (-b2 * mollified.value) - mollified.gradient * b1) * mu;
    let gq = g.dot(&q);
    let dgq = dg.transpose() * q + dq.transpose() * g;
    -(dlimit * (phi * gq) + ds * (limit * dphi * gq) + dgq * (limit * phi))
}

/// Whether the segment `p q` meets the closed triangle `t`: its end points on opposite
/// sides of (or on) the triangle's plane and the crossing point inside the triangle.
fn crosses(p: Vector3<f64>, q: Vector3<f64>, t: [Vector3<f64>; 3]) -> bool {
    let n = (t[1] - t[0]).cross(&(t[2] - t[0]));
    let (sp, sq) = ((p - t[0]).dot(&n), (q - t[0]).dot(&n));
    if sp * sq > 0.0 || sp == sq {
        return false;
    }
    let x = p + (q - p) * (sp / (sp - sq));
    (0..3).all(|i| {
        let (a, b) = (t[i], t[(i + 1) % 3]);
        (b - a).cross(&(x - a)).dot(&n) >= 0.0
    })
}

/// `m` with its negative eigenvalues set to zero.
fn project_psd(m: SMatrix<f64, 12, 12>) -> SMatrix<f64, 12, 12> {
    let eig = SymmetricEigen::new(m);
    if eig.eigenvalues.min() >= 0.0 {
        return m;
    }
    let clamped = eig.eigenvalues.map(|l| l.max(0.0));
    let v = eig.eigenvectors;
    v * SMatrix::<f64, 12, 12>::from_diagonal(&clamped) * v.transpose()
}

#[cfg(test)]
mod tests;
