//! Self-contact of a body's boundary surface: IPC's barrier on the distances of
//! point-triangle and edge-edge pairs (Li et al. 2020), with the mollifier on edge pairs,
//! a bounding-volume broad phase, and conservative advancement for continuous collision
//! detection of a linear step.

use std::fmt;

use nalgebra::{SMatrix, SymmetricEigen, Vector3};
use serde::{Deserialize, Serialize};

use crate::bvh::{Aabb, Bvh};
use crate::distance::{Form, edge_edge, mollifier, point_triangle, squared_jet};
use crate::jet::{Jet, variables};
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
        }
    }
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

/// Most advancement steps of one pair's collision detection; the bound reached by then is
/// kept (it is safe at every step).
const MAX_ADVANCES: usize = 500;

/// The surface whose self-contact is modelled.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct SelfContact {
    triangles: Vec<[usize; 3]>,
    edges: Vec<[usize; 2]>,
    vertices: Vec<usize>,
    /// Each edge's squared rest length.
    rest_length2: Vec<f64>,
}

fn point(x: &[f64], v: usize) -> Vector3<f64> {
    Vector3::new(x[3 * v], x[3 * v + 1], x[3 * v + 2])
}

impl SelfContact {
    /// Self-contact of the surface `triangles` (vertex indices into `rest`, flat `3N`).
    pub(crate) fn new(triangles: Vec<[usize; 3]>, rest: &[f64]) -> Result<Self, ContactError> {
        let n = rest.len() / 3;
        if let Some((i, t)) = triangles.iter().enumerate().find(|(_, t)| {
            t.iter().any(|&v| v >= n) || t[0] == t[1] || t[1] == t[2] || t[0] == t[2]
        }) {
            return Err(ContactError::Invalid {
                field: format!("surface[{i}]"),
                reason: format!(
                    "triangle {t:?} repeats a vertex or names one beyond the {n} given"
                ),
            });
        }
        let mut edges: Vec<[usize; 2]> = triangles
            .iter()
            .flat_map(|t| [[t[0], t[1]], [t[1], t[2]], [t[2], t[0]]])
            .map(|[a, b]| [a.min(b), a.max(b)])
            .collect();
        edges.sort_unstable();
        edges.dedup();
        let mut vertices: Vec<usize> = triangles.iter().flatten().copied().collect();
        vertices.sort_unstable();
        vertices.dedup();
        let rest_length2 = edges
            .iter()
            .map(|e| (point(rest, e[1]) - point(rest, e[0])).norm_squared())
            .collect();
        Ok(Self {
            triangles,
            edges,
            vertices,
            rest_length2,
        })
    }

    /// The surface's triangles.
    pub(crate) fn triangles(&self) -> &[[usize; 3]] {
        &self.triangles
    }

    /// Refuses positions where two primitives that share no vertex are closer than `dhat`
    /// (at rest they would push apart: the barrier must be zero there).
    pub(crate) fn check_separated(&self, x: &[f64], dhat: f64) -> Result<(), ContactError> {
        for c in self.candidates(x, None, dhat) {
            let d = self.distance(c, &self.points(c, x)).0;
            if d < dhat {
                return Err(ContactError::Invalid {
                    field: "dhat".into(),
                    reason: format!(
                        "{} are {d:e} m apart at rest, closer than dhat = {dhat:e} m; give a smaller dhat",
                        self.pair(c)
                    ),
                });
            }
        }
        Ok(())
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

    fn points(&self, c: Candidate, x: &[f64]) -> [Vector3<f64>; 4] {
        self.indices(c).map(|v| point(x, v))
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

    /// Pairs whose boxes (over `x`, and `x + dx` when given) come within `reach`, in a fixed
    /// order.
    fn candidates(&self, x: &[f64], dx: Option<&[f64]>, reach: f64) -> Vec<Candidate> {
        let swept = |vs: &[usize]| {
            Aabb::of(vs.iter().flat_map(|&v| {
                let p = point(x, v);
                [p, dx.map_or(p, |dx| p + point(dx, v))]
            }))
        };
        let triangles = Bvh::new(self.triangles.iter().map(|t| swept(t)).collect());
        let mut out = Vec::new();
        for (i, &v) in self.vertices.iter().enumerate() {
            triangles.query(&swept(&[v]).inflate(reach), |t| {
                if !self.triangles[t].contains(&v) {
                    out.push(Candidate::PointTriangle(i, t));
                }
            });
        }
        let boxes: Vec<Aabb> = self.edges.iter().map(|e| swept(e)).collect();
        let edges = Bvh::new(boxes.clone());
        for (a, ea) in self.edges.iter().enumerate() {
            edges.query(&boxes[a].inflate(reach), |b| {
                let eb = self.edges[b];
                if b > a && !eb.contains(&ea[0]) && !eb.contains(&ea[1]) {
                    out.push(Candidate::EdgeEdge(a, b));
                }
            });
        }
        out
    }

    /// Adds the self-contact barrier at `x` to `summary`, its forces to `forces` and its
    /// PSD-projected pair Hessians to `hessian`.
    pub(crate) fn evaluate(
        &self,
        x: &[f64],
        barrier: Barrier,
        summary: &mut ContactSummary,
        mut forces: Option<&mut [f64]>,
        mut hessian: Option<&mut ContactHessian>,
    ) -> Result<(), ContactError> {
        for c in self.candidates(x, None, barrier.dhat) {
            let p = self.points(c, x);
            let (d, form) = self.distance(c, &p);
            if !(d > 0.0) {
                return Err(ContactError::SelfContact {
                    pair: self.pair(c),
                    distance: d,
                });
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
                for (k, v) in vertices.iter().enumerate() {
                    for r in 0..3 {
                        f[3 * v + r] -= energy.gradient[3 * k + r];
                    }
                }
            }
            if let Some(h) = hessian.as_deref_mut() {
                h.add_pair(&vertices, &project_psd(energy.hessian));
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
            Candidate::EdgeEdge(e0, e1) => {
                let eps = MOLLIFIER * self.rest_length2[e0] * self.rest_length2[e1];
                energy * mollifier(&x, eps)
            }
        }
    }

    /// The largest `s` in `[0, 1]` (conservatively) such that on the path `x + t dx`,
    /// `t <= s`, no pair's distance falls below [`STEP_MARGIN`] of the least of its start
    /// and `dhat`. A pair that never comes within `dhat` cannot, so only pairs whose swept
    /// boxes come that close are advanced.
    pub(crate) fn step_bound(&self, x: &[f64], dx: &[f64], dhat: f64) -> f64 {
        let mut bound = 1.0f64;
        for c in self.candidates(x, Some(dx), dhat) {
            let p = self.points(c, x);
            let dp = self.points(c, dx);
            bound = bound.min(self.advance(c, &p, &dp, dhat));
            if bound == 0.0 {
                break;
            }
        }
        bound
    }

    /// Conservative advancement of one pair: the distance changes no faster than `L`, a
    /// bound of the points' relative speed, so a step of `(d - target) / L` never passes the
    /// target distance.
    fn advance(
        &self,
        c: Candidate,
        p: &[Vector3<f64>; 4],
        dp: &[Vector3<f64>; 4],
        dhat: f64,
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
        let target = STEP_MARGIN * d0.min(dhat);
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
                break;
            }
        }
        t
    }
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
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Two tetrahedra's surfaces: the second's apex `gap` above the first's top face, an
    /// edge of it crossing over an edge of the first.
    fn pair(gap: f64, jitter: [f64; 24]) -> (SelfContact, Vec<f64>) {
        let mut x = vec![
            0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0, //
            0.5, -0.3, gap, 0.5, 0.3, gap, 0.9, 0.0, 0.7, 0.1, 0.1, 0.8,
        ];
        for (x, j) in x.iter_mut().zip(jitter) {
            *x += j;
        }
        let faces = |o: usize| {
            [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]].map(|f: [usize; 3]| f.map(|v| v + o))
        };
        let triangles = [faces(0), faces(4)].concat();
        (SelfContact::new(triangles, &x).unwrap(), x)
    }

    proptest! {
        /// Forces are minus the energy's central differences; the projected Hessian is
        /// symmetric and lies above the differences of the forces (it only drops negative
        /// curvature).
        #[test]
        fn forces_and_hessian_match_differences(
            gap in 0.02f64..0.08,
            jitter in prop::array::uniform24(-0.004f64..0.004),
        ) {
            let b = Barrier { dhat: 0.1, kappa: 10.0 };
            let (surface, x) = pair(gap, jitter);
            let eval = |y: &[f64], f: Option<&mut [f64]>, h: Option<&mut ContactHessian>| {
                let mut s = ContactSummary { energy: 0.0, active: 0, min_distance: f64::INFINITY };
                surface.evaluate(y, b, &mut s, f, h).unwrap();
                s
            };
            let (mut f, mut hess) = (vec![0.0; 24], ContactHessian::default());
            let s = eval(&x, Some(&mut f), Some(&mut hess));
            prop_assert!(s.active >= 2, "{s:?}");
            prop_assert!(!hess.coupling.is_empty());
            let mut dense = nalgebra::DMatrix::zeros(24, 24);
            for (v, m) in &hess.vertex {
                let mut view = dense.view_mut((3 * v, 3 * v), (3, 3));
                view += m;
            }
            for (i, j, m) in &hess.coupling {
                let mut view = dense.view_mut((3 * i, 3 * j), (3, 3));
                view += m;
            }
            prop_assert!((&dense - dense.transpose()).norm() <= 1e-9 * dense.norm());
            let h = 1e-7;
            let mut fd = nalgebra::DMatrix::zeros(24, 24);
            for i in 0..24 {
                let (mut a, mut c) = (x.clone(), x.clone());
                a[i] += h;
                c[i] -= h;
                let g = -(eval(&a, None, None).energy - eval(&c, None, None).energy) / (2.0 * h);
                prop_assert!((g - f[i]).abs() <= 1e-5 * (1.0 + f[i].abs()), "force {i}: {g} {}", f[i]);
                let (mut fa, mut fc) = (vec![0.0; 24], vec![0.0; 24]);
                eval(&a, Some(&mut fa), None);
                eval(&c, Some(&mut fc), None);
                for j in 0..24 {
                    fd[(j, i)] = -(fa[j] - fc[j]) / (2.0 * h);
                }
            }
            let fd = (&fd + fd.transpose()) * 0.5;
            let excess = (&dense - &fd).symmetric_eigenvalues().min();
            prop_assert!(excess >= -1e-5 * fd.norm(), "projected less exact: {excess}");
        }

        /// On the bounded path no edge crosses a triangle of the other body and every
        /// distance stays positive; the bound is not zero.
        #[test]
        fn the_step_bound_keeps_the_path_apart(
            gap in 0.02f64..0.08,
            motion in prop::array::uniform12(-2.0f64..2.0),
        ) {
            let (surface, x) = pair(gap, [0.0; 24]);
            let mut dx = vec![0.0; 24];
            dx[12..].copy_from_slice(&motion);
            dx[14] -= 1.0;
            let s = surface.step_bound(&x, &dx, 0.1);
            prop_assert!(s > 0.0);
            for i in 0..=200 {
                let t = s * i as f64 / 200.0;
                let y: Vec<f64> = x.iter().zip(&dx).map(|(x, d)| x + t * d).collect();
                for c in surface.candidates(&y, None, f64::INFINITY) {
                    let d = surface.distance(c, &surface.points(c, &y)).0;
                    prop_assert!(d > 0.0, "t = {t}: {} at {d}", surface.pair(c));
                }
            }
        }
    }
}
