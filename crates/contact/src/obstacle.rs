//! Analytic obstacles: convex solids described by their signed distance.

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

/// A fixed convex solid that bodies stay outside of, acting on the body's surface vertices.
///
/// Its signed distance `phi` is positive outside, convex and 1-Lipschitz, which is what the
/// conservative collision detection of [`Obstacle::time_of_approach`] relies on. A plane is
/// exact for a tetrahedral body (a tet meets a half-space only if one of its vertices does);
/// for a sphere or a box, an edge or face of the body could cut a corner of the obstacle
/// that is sharper than the body's mesh, between two vertices that stay outside.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub enum Obstacle {
    /// The half-space behind a plane through `point`; bodies stay on the side `normal`
    /// points to (the ground: `Plane(point: (0, 0, 0), normal: (0, 0, 1))`).
    Plane {
        /// A point of the plane (m).
        point: [f64; 3],
        /// The outward normal (any length but zero).
        normal: [f64; 3],
    },
    /// A solid ball.
    Sphere {
        /// Its centre (m).
        center: [f64; 3],
        /// Its radius (m).
        radius: f64,
    },
    /// A solid axis-aligned box.
    Box {
        /// The corner of least coordinates (m).
        min: [f64; 3],
        /// The corner of greatest coordinates (m).
        max: [f64; 3],
    },
}

/// Signed distance, its gradient and its Hessian at a point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DistanceJet {
    /// `phi(p)`.
    pub distance: f64,
    /// `grad phi(p)` (unit length).
    pub gradient: Vector3<f64>,
    /// `hess phi(p)` (positive semidefinite: the distance is convex).
    pub hessian: Matrix3<f64>,
}

impl Obstacle {
    /// Why the obstacle is malformed, if it is (a zero or non-finite normal, a radius that
    /// is not positive, an empty box).
    pub fn check(&self) -> Result<(), String> {
        let finite = |a: &[f64]| a.iter().all(|v| v.is_finite());
        match self {
            Obstacle::Plane { point, normal } => {
                if !finite(point) || !finite(normal) || Vector3::from(*normal).norm() == 0.0 {
                    return Err(format!(
                        "a plane needs a finite point and a non-zero normal, got {point:?}, {normal:?}"
                    ));
                }
            }
            Obstacle::Sphere { center, radius } => {
                if !(finite(center) && *radius > 0.0 && radius.is_finite()) {
                    return Err(format!(
                        "a sphere needs a finite centre and a positive radius, got {center:?}, {radius}"
                    ));
                }
            }
            Obstacle::Box { min, max } => {
                if !finite(min) || !finite(max) || (0..3).any(|i| !(min[i] < max[i])) {
                    return Err(format!(
                        "a box needs min < max on every axis, got {min:?}, {max:?}"
                    ));
                }
            }
        }
        Ok(())
    }

    /// The signed distance from `p`: positive outside, negative inside.
    pub fn distance(&self, p: &Vector3<f64>) -> f64 {
        match self {
            Obstacle::Plane { point, normal } => {
                let n = Vector3::from(*normal).normalize();
                n.dot(&(p - Vector3::from(*point)))
            }
            Obstacle::Sphere { center, radius } => (p - Vector3::from(*center)).norm() - radius,
            Obstacle::Box { min, max } => {
                let (lo, hi) = (Vector3::from(*min), Vector3::from(*max));
                let outside = (p - p.sup(&lo).inf(&hi)).norm();
                if outside > 0.0 {
                    return outside;
                }
                // Inside: minus the distance to the nearest face.
                (0..3)
                    .map(|i| (lo[i] - p[i]).max(p[i] - hi[i]))
                    .fold(f64::NEG_INFINITY, f64::max)
            }
        }
    }

    /// The signed distance with its gradient and Hessian at `p`.
    pub fn jet(&self, p: &Vector3<f64>) -> DistanceJet {
        match self {
            Obstacle::Plane { point, normal } => {
                let n = Vector3::from(*normal).normalize();
                DistanceJet {
                    distance: n.dot(&(p - Vector3::from(*point))),
                    gradient: n,
                    hessian: Matrix3::zeros(),
                }
            }
            Obstacle::Sphere { center, radius } => {
                let q = p - Vector3::from(*center);
                let r = q.norm();
                let n = q / r;
                DistanceJet {
                    distance: r - radius,
                    gradient: n,
                    hessian: (Matrix3::identity() - n * n.transpose()) / r,
                }
            }
            Obstacle::Box { min, max } => box_jet(p, &Vector3::from(*min), &Vector3::from(*max)),
        }
    }

    /// The largest `s` in `[0, 1]` (conservatively) such that `p + t dp` keeps a signed
    /// distance above `target` for all `t` in `[0, s]`, from a start `p` whose distance is
    /// above `target`.
    ///
    /// The distance along the path is convex in `t` (the obstacle is convex), so its tangent
    /// at `t_k` lies below it: Newton's iteration from the left, `t_{k+1} = t_k + (phi - target)
    /// / -phi'`, never passes the first time the distance reaches `target` and converges to it
    /// quadratically. Where the slope is not negative the distance no longer decreases.
    pub fn time_of_approach(&self, p: &Vector3<f64>, dp: &Vector3<f64>, target: f64) -> f64 {
        let mut t = 0.0;
        let mut last_gap = f64::INFINITY;
        for _ in 0..100 {
            let jet = self.jet(&(p + dp * t));
            let gap = jet.distance - target;
            let slope = jet.gradient.dot(dp);
            if gap <= 0.0 {
                return t;
            }
            // Past the path's closest approach, which stayed above the target.
            if slope >= 0.0 {
                return 1.0;
            }
            // Converged to rounding: the gap stopped shrinking.
            if gap >= last_gap {
                return t;
            }
            last_gap = gap;
            t += gap / -slope;
            if t >= 1.0 {
                return 1.0;
            }
        }
        t
    }
}

impl Obstacle {
    /// The same solid moved by `d`.
    pub fn translated(&self, d: &Vector3<f64>) -> Obstacle {
        let add = |a: &[f64; 3]| -> [f64; 3] { (Vector3::from(*a) + d).into() };
        match self {
            Obstacle::Plane { point, normal } => Obstacle::Plane {
                point: add(point),
                normal: *normal,
            },
            Obstacle::Sphere { center, radius } => Obstacle::Sphere {
                center: add(center),
                radius: *radius,
            },
            Obstacle::Box { min, max } => Obstacle::Box {
                min: add(min),
                max: add(max),
            },
        }
    }
}

/// An obstacle that moves: translated at `velocity` from time `start` until `stop` (for
/// ever without one), resting before and after. A scene's bodies are pressed, pushed or
/// struck by it; friction against it acts on the velocity relative to it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObstacleMotion {
    /// The obstacle's index in `obstacles`.
    pub obstacle: usize,
    /// Its velocity while it moves (m/s).
    pub velocity: [f64; 3],
    /// When it starts moving (s).
    #[serde(default)]
    pub start: f64,
    /// When it stops (s).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stop: Option<f64>,
}

impl ObstacleMotion {
    /// How far the obstacle has moved at time `t`.
    pub fn offset(&self, t: f64) -> Vector3<f64> {
        let end = self.stop.map_or(t, |stop| t.min(stop));
        Vector3::from(self.velocity) * (end - self.start).max(0.0)
    }

    /// Why the motion is malformed for `obstacles` obstacles, if it is.
    pub fn check(&self, obstacles: usize) -> Result<(), String> {
        if self.obstacle >= obstacles {
            return Err(format!(
                "obstacle {} does not exist ({obstacles} obstacles)",
                self.obstacle
            ));
        }
        if !self.velocity.iter().all(|v| v.is_finite()) || !self.start.is_finite() {
            return Err(format!(
                "velocity {:?} and start {} must be finite",
                self.velocity, self.start
            ));
        }
        match self.stop {
            Some(stop) if !(stop >= self.start && stop.is_finite()) => Err(format!(
                "stop {stop} must be finite and not before start {}",
                self.start
            )),
            _ => Ok(()),
        }
    }
}

/// A triangle surface: flat `3V` positions and vertex triples, normals outward.
pub type Surface = (Vec<f64>, Vec<[usize; 3]>);

impl Obstacle {
    /// The obstacle's surface as triangles, for viewing beside the body (ParaView): a plane
    /// as a square of side `extent` centred at its point, a sphere as a latitude-longitude
    /// mesh, a box as its twelve triangles.
    pub fn surface(&self, extent: f64) -> Surface {
        match self {
            Obstacle::Plane { point, normal } => {
                let n = Vector3::from(*normal).normalize();
                // Any unit vector not parallel to n, then the plane's two axes.
                let helper = if n.x.abs() < 0.9 {
                    Vector3::x()
                } else {
                    Vector3::y()
                };
                let a = n.cross(&helper).normalize() * (0.5 * extent);
                let b = n.cross(&a);
                let c = Vector3::from(*point);
                let corners = [c - a - b, c + a - b, c + a + b, c - a + b];
                let x = corners.iter().flat_map(|p| [p.x, p.y, p.z]).collect();
                (x, vec![[0, 1, 2], [0, 2, 3]])
            }
            Obstacle::Sphere { center, radius } => sphere_surface(center, *radius, 16, 32),
            Obstacle::Box { min, max } => {
                let corner =
                    |i: usize| [0, 1, 2].map(|k| if i >> k & 1 == 1 { max[k] } else { min[k] });
                let x = (0..8).flat_map(corner).collect();
                // Two triangles per face, counter-clockwise seen from outside.
                let faces = [
                    [0, 2, 6, 4],
                    [1, 5, 7, 3],
                    [0, 4, 5, 1],
                    [2, 3, 7, 6],
                    [0, 1, 3, 2],
                    [4, 6, 7, 5],
                ];
                let t = faces
                    .iter()
                    .flat_map(|f| [[f[0], f[2], f[1]], [f[0], f[3], f[2]]])
                    .collect();
                (x, t)
            }
        }
    }
}

/// A latitude-longitude sphere of `rings` bands and `segments` meridians.
fn sphere_surface(center: &[f64; 3], radius: f64, rings: usize, segments: usize) -> Surface {
    let mut x = vec![center[0], center[1], center[2] + radius];
    for i in 1..rings {
        let theta = std::f64::consts::PI * i as f64 / rings as f64;
        for j in 0..segments {
            let phi = 2.0 * std::f64::consts::PI * j as f64 / segments as f64;
            x.extend([
                center[0] + radius * theta.sin() * phi.cos(),
                center[1] + radius * theta.sin() * phi.sin(),
                center[2] + radius * theta.cos(),
            ]);
        }
    }
    x.extend([center[0], center[1], center[2] - radius]);
    let ring = |i: usize, j: usize| 1 + (i - 1) * segments + j % segments;
    let south = 1 + (rings - 1) * segments;
    let mut t = Vec::new();
    for j in 0..segments {
        t.push([0, ring(1, j), ring(1, j + 1)]);
        t.push([south, ring(rings - 1, j + 1), ring(rings - 1, j)]);
        for i in 1..rings - 1 {
            t.push([ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)]);
            t.push([ring(i, j), ring(i + 1, j + 1), ring(i, j + 1)]);
        }
    }
    (x, t)
}

/// The box's signed distance, gradient and Hessian: outside, the distance to the nearest
/// point (a face, edge or corner region); inside, to the nearest face.
fn box_jet(p: &Vector3<f64>, lo: &Vector3<f64>, hi: &Vector3<f64>) -> DistanceJet {
    let q = p - p.sup(lo).inf(hi);
    let d = q.norm();
    if d > 0.0 {
        let n = q / d;
        // The distance grows like a cylinder's (edge) or a sphere's (corner) across the
        // axes on which `p` is outside, and not along the others.
        let outside = Matrix3::from_diagonal(&q.map(|v| if v != 0.0 { 1.0 } else { 0.0 }));
        return DistanceJet {
            distance: d,
            gradient: n,
            hessian: (outside - n * n.transpose()) / d,
        };
    }
    let (mut best, mut axis, mut sign) = (f64::NEG_INFINITY, 0, 1.0);
    for i in 0..3 {
        for (gap, s) in [(lo[i] - p[i], -1.0), (p[i] - hi[i], 1.0)] {
            if gap > best {
                (best, axis, sign) = (gap, i, s);
            }
        }
    }
    let mut gradient = Vector3::zeros();
    gradient[axis] = sign;
    DistanceJet {
        distance: best,
        gradient,
        hessian: Matrix3::zeros(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn obstacles() -> Vec<Obstacle> {
        vec![
            Obstacle::Plane {
                point: [0.1, -0.2, 0.3],
                normal: [0.3, 0.2, 2.0],
            },
            Obstacle::Sphere {
                center: [0.2, 0.1, -0.1],
                radius: 0.4,
            },
            Obstacle::Box {
                min: [-0.5, -0.25, -0.3],
                max: [0.25, 0.5, 0.1],
            },
        ]
    }

    proptest! {
        /// Central differences of the distance and its gradient match the jet, away from the
        /// box's region boundaries (where the Hessian jumps).
        #[test]
        fn jets_match_differences(p in proptest::array::uniform3(-1.5f64..1.5)) {
            let p = Vector3::from(p);
            for o in obstacles() {
                let jet = o.jet(&p);
                prop_assert!((jet.distance - o.distance(&p)).abs() < 1e-15);
                let h = 1e-6;
                for i in 0..3 {
                    let mut e = Vector3::zeros();
                    e[i] = h;
                    if matches!(o, Obstacle::Box { .. }) && near_box_region_boundary(&(p + e)) {
                        continue;
                    }
                    let (a, b) = (o.jet(&(p + e)), o.jet(&(p - e)));
                    let g = (a.distance - b.distance) / (2.0 * h);
                    prop_assert!((g - jet.gradient[i]).abs() < 1e-7, "{o:?} {p} grad {i}: {g} {}", jet.gradient[i]);
                    let hcol = (a.gradient - b.gradient) / (2.0 * h);
                    for j in 0..3 {
                        prop_assert!((hcol[j] - jet.hessian[(j, i)]).abs() < 1e-5 * (1.0 + jet.hessian.norm()),
                            "{o:?} {p} hess ({j},{i}): {} {}", hcol[j], jet.hessian[(j, i)]);
                    }
                }
                prop_assert!(jet.hessian.symmetric_eigenvalues().min() > -1e-12);
            }
        }

        /// Along any path, the distance stays above the target up to the time of approach, and
        /// where the bound is below 1 the path reaches the target there.
        #[test]
        fn time_of_approach_is_conservative_and_tight(
            p in proptest::array::uniform3(-1.5f64..1.5),
            dp in proptest::array::uniform3(-2.0f64..2.0),
        ) {
            let (p, dp) = (Vector3::from(p), Vector3::from(dp));
            for o in obstacles() {
                let d0 = o.distance(&p);
                if d0 <= 1e-6 {
                    continue;
                }
                let target = 0.1 * d0;
                let s = o.time_of_approach(&p, &dp, target);
                prop_assert!((0.0..=1.0).contains(&s));
                for k in 0..=200 {
                    let t = s * k as f64 / 200.0;
                    prop_assert!(o.distance(&(p + dp * t)) >= target * (1.0 - 1e-9), "{o:?} {p} {dp}: t {t} of {s}");
                }
                if s < 1.0 {
                    let at = o.distance(&(p + dp * s));
                    prop_assert!((at - target).abs() <= 1e-6 * d0, "{o:?}: {at} against {target}");
                }
            }
        }
    }

    /// Whether `p` lies within 1e-5 of a plane bounding the box's Voronoi regions.
    fn near_box_region_boundary(p: &Vector3<f64>) -> bool {
        let (lo, hi) = ([-0.5, -0.25, -0.3], [0.25, 0.5, 0.1]);
        let near_face = (0..3).any(|i| (p[i] - lo[i]).abs() < 1e-5 || (p[i] - hi[i]).abs() < 1e-5);
        // Inside, the nearest face switches where two faces are equally near.
        let inside = (0..3).all(|i| p[i] > lo[i] && p[i] < hi[i]);
        let mut gaps: Vec<f64> = (0..3).flat_map(|i| [p[i] - lo[i], hi[i] - p[i]]).collect();
        gaps.sort_by(f64::total_cmp);
        near_face || (inside && gaps[1] - gaps[0] < 1e-5)
    }

    /// Every surface vertex is on the obstacle, and every triangle's normal points out.
    #[test]
    fn surfaces_lie_on_the_obstacles_facing_out() {
        for o in obstacles() {
            let (x, t) = o.surface(2.0);
            let p = |i: usize| Vector3::new(x[3 * i], x[3 * i + 1], x[3 * i + 2]);
            for i in 0..x.len() / 3 {
                assert!(o.distance(&p(i)).abs() < 1e-12, "{o:?}: vertex {i}");
            }
            for tri in &t {
                let (a, b, c) = (p(tri[0]), p(tri[1]), p(tri[2]));
                let n = (b - a).cross(&(c - a));
                assert!(n.norm() > 0.0, "{o:?}: degenerate {tri:?}");
                let centroid = (a + b + c) / 3.0;
                // A point a little outside the face is outside the obstacle (or further
                // from it, for the sphere's chords).
                let outside = centroid + n.normalize() * 1e-3;
                assert!(
                    o.distance(&outside) > o.distance(&centroid),
                    "{o:?}: {tri:?} faces in"
                );
            }
        }
    }

    #[test]
    fn malformed_obstacles_are_named() {
        let bad = [
            Obstacle::Plane {
                point: [0.0; 3],
                normal: [0.0; 3],
            },
            Obstacle::Sphere {
                center: [0.0; 3],
                radius: -1.0,
            },
            Obstacle::Box {
                min: [0.0; 3],
                max: [1.0, 0.0, 1.0],
            },
            Obstacle::Sphere {
                center: [f64::NAN, 0.0, 0.0],
                radius: 1.0,
            },
        ];
        for o in bad {
            assert!(o.check().is_err(), "{o:?}");
        }
        assert!(obstacles().iter().all(|o| o.check().is_ok()));
    }
}
