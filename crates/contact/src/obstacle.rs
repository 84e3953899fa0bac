//! Analytic obstacles: convex solids described by their signed distance.

use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
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
    /// A solid box turned by `rotation` about its centre (a ramp, a paddle; a `Box` that an
    /// [`ObstacleMotion`] turns becomes one).
    OrientedBox {
        /// Its centre (m).
        center: [f64; 3],
        /// Half its size along each of its own axes (m).
        half_extents: [f64; 3],
        /// Its turn from the world's axes as a rotation vector: the axis times the angle
        /// (rad).
        rotation: [f64; 3],
    },
}

/// Signed distance, its gradient and its Hessian at a point.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
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
                if !finite(point) || !finite(normal) || Vector3::from(*normal).amax() == 0.0 {
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
            Obstacle::OrientedBox {
                center,
                half_extents: h,
                rotation,
            } => {
                if !finite(center)
                    || !finite(rotation)
                    || !h.iter().all(|v| *v > 0.0 && v.is_finite())
                {
                    return Err(format!(
                        "an oriented box needs a finite centre and rotation and positive half extents, got {center:?}, {h:?}, {rotation:?}"
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
                let n = unit_normal(normal);
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
            Obstacle::OrientedBox { .. } => self.jet(p).distance,
        }
    }

    /// The signed distance with its gradient and Hessian at `p`.
    pub fn jet(&self, p: &Vector3<f64>) -> DistanceJet {
        match self {
            Obstacle::Plane { point, normal } => {
                let n = unit_normal(normal);
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
            Obstacle::OrientedBox {
                center,
                half_extents,
                rotation,
            } => {
                // The box's own frame: `q = R^T (p - c)`; the jet turns back with `R`.
                let r = Rotation3::new(Vector3::from(*rotation));
                let h = Vector3::from(*half_extents);
                let q = r.inverse() * (p - Vector3::from(*center));
                let jet = box_jet(&q, &-h, &h);
                let r = r.into_inner();
                DistanceJet {
                    distance: jet.distance,
                    gradient: r * jet.gradient,
                    hessian: r * jet.hessian * r.transpose(),
                }
            }
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
        self.moved(&Isometry3::from_parts(
            Translation3::from(*d),
            UnitQuaternion::identity(),
        ))
    }

    /// The same solid moved rigidly by `m` (a point `p` of it goes to `m p`). An
    /// axis-aligned box that `m` turns becomes an [`Obstacle::OrientedBox`].
    pub fn moved(&self, m: &Isometry3<f64>) -> Obstacle {
        let at = |a: &[f64; 3]| -> [f64; 3] { (m * nalgebra::Point3::from(*a)).coords.into() };
        let turned = m.rotation != UnitQuaternion::identity();
        match self {
            Obstacle::Plane { point, normal } => Obstacle::Plane {
                point: at(point),
                normal: (m.rotation * Vector3::from(*normal)).into(),
            },
            Obstacle::Sphere { center, radius } => Obstacle::Sphere {
                center: at(center),
                radius: *radius,
            },
            Obstacle::Box { min, max } if !turned => Obstacle::Box {
                min: at(min),
                max: at(max),
            },
            Obstacle::Box { min, max } => {
                let (lo, hi) = (Vector3::from(*min), Vector3::from(*max));
                Obstacle::OrientedBox {
                    center: ((lo + hi) * 0.5).into(),
                    half_extents: ((hi - lo) * 0.5).into(),
                    rotation: [0.0; 3],
                }
                .moved(m)
            }
            Obstacle::OrientedBox {
                center,
                half_extents,
                rotation,
            } => Obstacle::OrientedBox {
                center: at(center),
                half_extents: *half_extents,
                rotation: (m.rotation * UnitQuaternion::new(Vector3::from(*rotation)))
                    .scaled_axis()
                    .into(),
            },
        }
    }

    /// The solid's centre (a plane's point): where a motion turns it about by default.
    pub fn centre(&self) -> Vector3<f64> {
        match self {
            Obstacle::Plane { point, .. } => Vector3::from(*point),
            Obstacle::Sphere { center, .. } | Obstacle::OrientedBox { center, .. } => {
                Vector3::from(*center)
            }
            Obstacle::Box { min, max } => (Vector3::from(*min) + Vector3::from(*max)) * 0.5,
        }
    }
}

/// An obstacle that moves rigidly: from time `start` until `stop` (for ever without one)
/// it translates at `velocity` and turns at `angular_velocity` about `pivot`, which moves
/// with it; it rests before and after. A scene's bodies are pressed, pushed, struck or
/// swept by it; friction against it acts on the velocity relative to it.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct ObstacleMotion {
    /// The obstacle's index: among `obstacles`, then among `meshes` (a mesh obstacle `m`
    /// is `obstacles.len() + m`), as friction's coefficients count them.
    pub obstacle: usize,
    /// Its velocity while it moves (m/s).
    #[serde(default)]
    pub velocity: [f64; 3],
    /// Its angular velocity while it moves: the axis times the rate (rad/s).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub angular_velocity: [f64; 3],
    /// The point it turns about, where it is at `start` (m); by default the obstacle's
    /// centre ([`Obstacle::centre`], a mesh's bounding-box centre).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pivot: Option<[f64; 3]>,
    /// When it starts moving (s).
    #[serde(default)]
    pub start: f64,
    /// When it stops (s).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stop: Option<f64>,
}

deform_setters::setters!(ObstacleMotion { obstacle: usize, velocity: [f64; 3], angular_velocity: [f64; 3], pivot: Option<[f64; 3]>, start: f64, stop: Option<f64> });

fn is_zero(v: &[f64; 3]) -> bool {
    *v == [0.0; 3]
}

impl ObstacleMotion {
    /// How long the obstacle has moved by time `t` (s).
    fn elapsed(&self, t: f64) -> f64 {
        let end = self.stop.map_or(t, |stop| t.min(stop));
        (end - self.start).max(0.0)
    }

    /// How far the pivot has moved at time `t`.
    pub fn offset(&self, t: f64) -> Vector3<f64> {
        Vector3::from(self.velocity) * self.elapsed(t)
    }

    /// Where the motion has taken the obstacle at time `t`, from where it rests before
    /// `start`: a point `p` of it is at `placement(t, c) * p`, with `c` the pivot to use
    /// when the motion names none.
    pub fn placement(&self, t: f64, centre: &Vector3<f64>) -> Isometry3<f64> {
        let c = self.pivot.map_or(*centre, Vector3::from);
        let tau = self.elapsed(t);
        let turn = UnitQuaternion::new(Vector3::from(self.angular_velocity) * tau);
        // p -> c + v tau + R (p - c).
        let shift = c + Vector3::from(self.velocity) * tau - turn * c;
        Isometry3::from_parts(Translation3::from(shift), turn)
    }

    /// Why the motion is malformed for `obstacles` obstacles, if it is.
    pub fn check(&self, obstacles: usize) -> Result<(), String> {
        if self.obstacle >= obstacles {
            return Err(format!(
                "obstacle {} does not exist ({obstacles} obstacles)",
                self.obstacle
            ));
        }
        let finite = |v: &[f64; 3]| v.iter().all(|v| v.is_finite());
        if !finite(&self.velocity)
            || !finite(&self.angular_velocity)
            || !self.pivot.as_ref().is_none_or(finite)
            || !self.start.is_finite()
        {
            return Err(format!(
                "velocity {:?}, angular velocity {:?}, pivot {:?} and start {} must be finite",
                self.velocity, self.angular_velocity, self.pivot, self.start
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
                let n = unit_normal(normal);
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
            Obstacle::OrientedBox {
                center,
                half_extents: h,
                rotation,
            } => {
                let (x, t) = Obstacle::Box {
                    min: h.map(|v| -v),
                    max: *h,
                }
                .surface(extent);
                let m = Isometry3::new(Vector3::from(*center), Vector3::from(*rotation));
                let x = x
                    .chunks_exact(3)
                    .flat_map(|p| {
                        let q = m * nalgebra::Point3::new(p[0], p[1], p[2]);
                        [q.x, q.y, q.z]
                    })
                    .collect();
                (x, t)
            }
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

/// The straight path, in the frame of an obstacle that moves by `step` over a step, of a
/// point that starts at `p` and moves by `dp`: from `p` to `step^-1 (p + dp)`.
pub(crate) fn relative_path(
    step: &Isometry3<f64>,
    p: &Vector3<f64>,
    dp: &Vector3<f64>,
) -> Vector3<f64> {
    step.inverse_transform_point(&Point3::from(p + dp)).coords - p
}

/// The displacement of a point from `p` that goes a fraction `s` along its path `relative`
/// in an obstacle's frame and then moves with the obstacle (by `step`).
pub(crate) fn carried(
    step: &Isometry3<f64>,
    p: &Vector3<f64>,
    relative: &Vector3<f64>,
    s: f64,
) -> Vector3<f64> {
    (step * Point3::from(p + relative * s)).coords - p
}

/// A plane's normal of any finite non-zero length as a unit vector. Lengths whose square
/// overflows or underflows (1e200, 1e-200) are scaled by their largest entry first; others
/// are normalised directly, so their bits are those of `normalize`.
fn unit_normal(normal: &[f64; 3]) -> Vector3<f64> {
    let n = Vector3::from(*normal);
    let length = n.norm();
    if length.is_finite() && length > 1e-150 {
        n.normalize()
    } else {
        (n / n.amax()).normalize()
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
            // The same box turned about its centre.
            Obstacle::OrientedBox {
                center: [-0.125, 0.125, -0.1],
                half_extents: [0.375, 0.375, 0.2],
                rotation: TURN,
            },
        ]
    }

    const TURN: [f64; 3] = [0.3, -0.5, 0.8];

    /// `p` in the frame of the axis-aligned box of [`obstacles`] for its turned copy.
    fn unturned(p: &Vector3<f64>) -> Vector3<f64> {
        let c = Vector3::new(-0.125, 0.125, -0.1);
        Rotation3::new(Vector3::from(TURN)).inverse() * (p - c) + c
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
                    let near = match o {
                        Obstacle::Box { .. } => near_box_region_boundary(&(p + e)),
                        Obstacle::OrientedBox { .. } => near_box_region_boundary(&unturned(&(p + e))),
                        _ => false,
                    };
                    if near {
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

    proptest! {
        /// A solid moved rigidly has at the moved point the distance it had at the point,
        /// its gradient turned; a box moved with no turn stays axis-aligned.
        #[test]
        fn moved_solids_keep_their_distances(
            p in proptest::array::uniform3(-1.5f64..1.5),
            turn in proptest::array::uniform3(-2.0f64..2.0),
            shift in proptest::array::uniform3(-1.0f64..1.0),
        ) {
            let m = Isometry3::new(Vector3::from(shift), Vector3::from(turn));
            let p = Vector3::from(p);
            let q = (m * nalgebra::Point3::from(p)).coords;
            for o in obstacles() {
                let (a, b) = (o.jet(&p), o.moved(&m).jet(&q));
                prop_assert!((a.distance - b.distance).abs() < 1e-12, "{o:?}: {} {}", a.distance, b.distance);
                prop_assert!((m.rotation * a.gradient - b.gradient).norm() < 1e-9, "{o:?}");
                let translated = o.translated(&Vector3::from(shift));
                let turned = matches!((&o, &translated), (Obstacle::Box { .. }, Obstacle::OrientedBox { .. }));
                prop_assert!(!turned, "{o:?} became {translated:?}");
            }
        }
    }

    /// A motion turns its obstacle about the pivot, which moves at the velocity, between
    /// `start` and `stop` only.
    #[test]
    fn motions_turn_about_their_pivot_between_start_and_stop() {
        let m = ObstacleMotion {
            obstacle: 0,
            velocity: [0.1, 0.0, 0.0],
            angular_velocity: [0.0, 0.0, std::f64::consts::PI],
            pivot: Some([1.0, 0.0, 0.0]),
            start: 0.5,
            stop: Some(1.0),
        };
        let centre = Vector3::zeros();
        let at = |t: f64, p: [f64; 3]| (m.placement(t, &centre) * nalgebra::Point3::from(p)).coords;
        assert_eq!(at(0.2, [2.0, 0.0, 0.0]), Vector3::new(2.0, 0.0, 0.0));
        // Half a turn in 1 s: a quarter by 1.0 s, and no further after.
        for t in [1.0, 3.0] {
            let pivot = at(t, [1.0, 0.0, 0.0]);
            assert!(
                (pivot - Vector3::new(1.05, 0.0, 0.0)).norm() < 1e-12,
                "{pivot}"
            );
            let arm = at(t, [2.0, 0.0, 0.0]) - pivot;
            assert!((arm - Vector3::new(0.0, 1.0, 0.0)).norm() < 1e-12, "{arm}");
        }
        // Without a pivot it turns about the centre it is given.
        let about = ObstacleMotion {
            pivot: None,
            ..m.clone()
        };
        let c = Vector3::new(0.0, 0.0, 5.0);
        let p = (about.placement(1.0, &c) * nalgebra::Point3::from(c)).coords;
        assert!((p - c - Vector3::new(0.05, 0.0, 0.0)).norm() < 1e-12);
        assert!(
            ObstacleMotion {
                pivot: Some([f64::NAN; 3]),
                ..m
            }
            .check(1)
            .is_err()
        );
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

    /// "Any length but zero": normals whose squared length overflows or underflows give the
    /// plane of the unit normal, bit for bit.
    #[test]
    fn a_plane_normal_of_any_length_gives_the_same_plane() {
        let plane = |normal| Obstacle::Plane {
            point: [0.1, -0.2, 0.3],
            normal,
        };
        let p = Vector3::new(0.4, 0.5, 0.9);
        let unit = plane([0.0, 0.6, 0.8]);
        for normal in [[0.0, 6e199, 8e199], [0.0, 6e-201, 8e-201], [0.0, 6.0, 8.0]] {
            let o = plane(normal);
            assert!(o.check().is_ok(), "{normal:?}");
            assert_eq!(o.distance(&p), unit.distance(&p), "{normal:?}");
            assert_eq!(o.jet(&p).gradient, unit.jet(&p).gradient, "{normal:?}");
        }
        assert!(plane([0.0; 3]).check().is_err());
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
            Obstacle::OrientedBox {
                center: [0.0; 3],
                half_extents: [1.0, 0.0, 1.0],
                rotation: [0.0; 3],
            },
        ];
        for o in bad {
            assert!(o.check().is_err(), "{o:?}");
        }
        assert!(obstacles().iter().all(|o| o.check().is_ok()));
    }
}
