//! Lagged, smoothed Coulomb friction against obstacles (IPC: Li et al. 2020, Section 5).
//!
//! Each vertex-obstacle pair in contact at the start of a step gets a friction potential
//! `D = mu lambda f0(|u|)` of its tangential displacement `u = T^T (x - x^n)` over the step,
//! with the normal force `lambda` and the tangent basis `T` lagged at `x^n` (semi-implicit:
//! they stay fixed during the step's Newton solve, so `D` is a potential and Newton minimises
//! it with the rest). `f0` smooths `|u|` below `eps = eps_v dt`: friction grows from zero as
//! the sliding speed grows to `eps_v` and is Coulomb's `mu lambda` above it, so sticking is a
//! very viscous regime below `eps_v`.

use nalgebra::{Matrix2, Matrix3, Matrix3x2, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use crate::{ContactError, ContactHessian, ContactModel};

/// Friction as a scene gives it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct FrictionSpec {
    /// The coefficient of friction of each obstacle, in the obstacles' order, or a single
    /// one for all of them.
    pub mu: Vec<f64>,
    /// The sliding speed (m/s) below which friction is smoothed towards zero (IPC's
    /// `eps_v`); 1e-3 m/s by default.
    #[serde(default = "default_threshold")]
    pub velocity_threshold: f64,
    /// The coefficient between two parts of the body's own surface, with self-contact; by
    /// default `mu`'s when it gives one for all, else 0 (frictionless).
    #[serde(default)]
    pub self_mu: Option<f64>,
}

deform_setters::setters!(FrictionSpec { mu: Vec<f64>, velocity_threshold: f64, self_mu: Option<f64> });

fn default_threshold() -> f64 {
    1e-3
}

/// One contact pair's lagged friction: a vertex against an analytic obstacle, or a
/// primitive of the body's surface against one of a mesh obstacle's.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct FrictionPair {
    /// The body's vertices of the pair with their weights in its contact point: one vertex
    /// of weight 1 against an analytic obstacle; the closest points' barycentric weights
    /// against a mesh (the obstacle's own points are fixed and left out); between two parts
    /// of the body's surface, all four vertices with the signed weights whose sum is the
    /// gap between the closest points, so the "point" is that gap and its tangential change
    /// is the two sides' relative slip.
    pub vertices: Vec<(usize, f64)>,
    /// The obstacle's index among those friction acts against: the analytic obstacles,
    /// then the mesh obstacles, then the body's own surface (with self-contact).
    pub obstacle: usize,
    /// `mu lambda`: the friction force when sliding (N).
    pub limit: f64,
    /// The tangent basis at the start of the step (orthonormal columns).
    pub basis: Matrix3x2<f64>,
    /// Where the weighted contact point would be at the step's end if it stuck to the
    /// obstacle: its position at the start, moved as the obstacle moves during the step.
    pub start: Vector3<f64>,
}

impl FrictionPair {
    /// The weighted contact point at `x`.
    fn point(&self, x: &[f64]) -> Vector3<f64> {
        self.vertices
            .iter()
            .map(|&(v, w)| Vector3::new(x[3 * v], x[3 * v + 1], x[3 * v + 2]) * w)
            .sum()
    }
}

/// The friction of a step, lagged at its start.
#[derive(Debug, Clone, PartialEq, Default)]
#[non_exhaustive]
pub struct FrictionLag {
    /// The pairs in contact at the start, with a non-zero coefficient.
    pub pairs: Vec<FrictionPair>,
    /// `eps_v dt` (m): the tangential displacement over the step below which friction is
    /// smoothed.
    pub threshold: f64,
}

deform_setters::setters!(FrictionLag { pairs: Vec<FrictionPair>, threshold: f64 });

impl FrictionSpec {
    /// Coefficients `mu` (one per obstacle, meshes last, or one for all), the default
    /// velocity threshold and no friction between parts of the body.
    pub fn new(mu: Vec<f64>) -> Self {
        let (velocity_threshold, self_mu) = (default_threshold(), None);
        Self {
            mu,
            velocity_threshold,
            self_mu,
        }
    }

    /// The coefficient of each of `obstacles` obstacles.
    ///
    /// # Errors
    /// [`ContactError::Invalid`] when the count is neither 1 nor `obstacles`, or a value is
    /// negative or not finite.
    pub fn coefficients(&self, obstacles: usize) -> Result<Vec<f64>, ContactError> {
        let invalid = |field: &str, reason: String| ContactError::Invalid {
            field: format!("friction.{field}"),
            reason,
        };
        if let Some(m) = self.mu.iter().find(|m| !(m.is_finite() && **m >= 0.0)) {
            return Err(invalid("mu", format!("{m} must be finite and >= 0")));
        }
        if !(self.velocity_threshold > 0.0 && self.velocity_threshold.is_finite()) {
            return Err(invalid(
                "velocity_threshold",
                format!("{} must be positive and finite", self.velocity_threshold),
            ));
        }
        if let Some(m) = self.self_mu.filter(|m| !(m.is_finite() && *m >= 0.0)) {
            return Err(invalid("self_mu", format!("{m} must be finite and >= 0")));
        }
        match self.mu.len() {
            1 => Ok(vec![self.mu[0]; obstacles]),
            n if n == obstacles => Ok(self.mu.clone()),
            n => Err(invalid(
                "mu",
                format!("{n} coefficients for {obstacles} obstacles (give one, or one each)"),
            )),
        }
    }

    /// The coefficient between parts of the body's own surface (see
    /// [`FrictionSpec::self_mu`]).
    pub fn self_coefficient(&self) -> f64 {
        match (self.self_mu, self.mu.as_slice()) {
            (Some(m), _) => m,
            (None, [m]) => *m,
            (None, _) => 0.0,
        }
    }
}

/// `f1(y) = f0'(y)`: `2 y/eps - (y/eps)^2` below `eps`, 1 above (the gradient uses
/// `f1(s) / s` in closed form).
#[cfg(test)]
fn f1(y: f64, eps: f64) -> f64 {
    if y >= eps {
        1.0
    } else {
        let r = y / eps;
        2.0 * r - r * r
    }
}

/// `f0(y)`: `-y^3 / (3 eps^2) + y^2 / eps + eps / 3` below `eps`, `y` above (`C^1`).
fn f0(y: f64, eps: f64) -> f64 {
    if y >= eps {
        y
    } else {
        -y * y * y / (3.0 * eps * eps) + y * y / eps + eps / 3.0
    }
}

impl ContactModel {
    /// Lags friction at the start of a step of `dt` from positions `x`: every pair closer
    /// than `dhat` with a positive coefficient, its normal force `-b'(d)` and tangent basis.
    /// Empty without friction.
    pub fn lag_friction(&self, x: &[f64], dt: f64) -> FrictionLag {
        let Some((mu, eps_v)) = self.friction() else {
            return FrictionLag::default();
        };
        let b = self.barrier();
        let mut pairs = Vec::new();
        for &v in self.vertices() {
            let p = Vector3::new(x[3 * v], x[3 * v + 1], x[3 * v + 2]);
            for (i, &m) in mu[..self.obstacles().len()].iter().enumerate() {
                // Where the obstacle was at the step's start: a vertex that sticks to a
                // moving obstacle moves with it.
                let o = self.before(i);
                let d = o.distance(&p);
                if m == 0.0 || !(d > 0.0 && d < b.dhat) {
                    continue;
                }
                let n = o.jet(&p).gradient;
                pairs.push(FrictionPair {
                    vertices: vec![(v, 1.0)],
                    obstacle: i,
                    limit: m * -b.first(d),
                    basis: tangent_basis(&n),
                    start: self
                        .step_motion(i)
                        .map_or(p, |m| (m * nalgebra::Point3::from(p)).coords),
                });
            }
        }
        if let Some(surface) = self.surface() {
            let meshes = &mu[self.obstacles().len()..];
            surface.friction_pairs(x, b, meshes, self.obstacles().len(), &mut pairs);
        }
        FrictionLag {
            pairs,
            threshold: eps_v * dt,
        }
    }

    /// The friction potential of `lag` at positions `x`: returns its energy, adds its forces
    /// to `forces` and appends its Hessian's blocks (positive semidefinite as they are: each
    /// pair's is `w w^T` times a PSD 3x3) to `hessian`, between vertices for pairs against
    /// a mesh.
    pub fn add_friction(
        &self,
        lag: &FrictionLag,
        x: &[f64],
        forces: Option<&mut [f64]>,
        hessian: Option<&mut ContactHessian>,
    ) -> f64 {
        self.add_friction_with(lag, x, forces, hessian, &[])
    }

    /// [`ContactModel::add_friction`] with the curvature Newton takes: a pair flagged in
    /// `secant` (by index in `lag.pairs`; missing entries are not) gets the secant curvature
    /// `limit f1(s) / s` in every tangent direction instead of the exact one, which has
    /// none along the slip when sliding. The secant model majorises the potential (its
    /// force falls to zero at the sticking position, where the exact model's stays at the
    /// limit), so a pair that Newton would carry through its sticking position and beyond
    /// lands at it instead. See [`ContactModel::flag_reversals`].
    pub fn add_friction_with(
        &self,
        lag: &FrictionLag,
        x: &[f64],
        mut forces: Option<&mut [f64]>,
        mut hessian: Option<&mut ContactHessian>,
        secant: &[bool],
    ) -> f64 {
        let eps = lag.threshold;
        let mut energy = 0.0;
        for (k, pair) in lag.pairs.iter().enumerate() {
            let u: Vector2<f64> = pair.basis.transpose() * (pair.point(x) - pair.start);
            let s = u.norm();
            energy += pair.limit * f0(s, eps);
            // `grad_u = limit phi(s) u` with `phi = f1(s) / s` (finite at 0: 2 / eps).
            let (phi, dphi) = if s >= eps {
                (1.0 / s, -1.0 / (s * s))
            } else {
                (2.0 / eps - s / (eps * eps), -1.0 / (eps * eps))
            };
            // The contact point is `sum w_v x_v`: vertex `v` gets `w_v` of its force, and
            // `w_a w_b` of its Hessian in block `(a, b)`.
            if let Some(f) = forces.as_deref_mut() {
                let g = pair.basis * (u * (pair.limit * phi));
                for &(v, w) in &pair.vertices {
                    for k in 0..3 {
                        f[3 * v + k] -= w * g[k];
                    }
                }
            }
            if let Some(h) = hessian.as_deref_mut() {
                let mut h2 = Matrix2::identity() * phi;
                let flagged = s >= eps && secant.get(k).copied().unwrap_or(false);
                if s > 0.0 && !flagged {
                    h2 += u * u.transpose() * (dphi / s);
                }
                let block: Matrix3<f64> = pair.basis * h2 * pair.basis.transpose() * pair.limit;
                for &(a, wa) in &pair.vertices {
                    for &(b, wb) in &pair.vertices {
                        match a == b {
                            true => h.vertex.push((a, block * (wa * wb))),
                            false => h.coupling.push((a, b, block * (wa * wb))),
                        }
                    }
                }
            }
        }
        energy
    }

    /// Sets in `secant` (one entry per pair of `lag`) which pairs the displacement `dx`
    /// from positions `x` carries past their sticking position: sliding pairs whose slip
    /// reverses (`u . (u + du) < 0`), where the exact curvature, none along the slip,
    /// modelled friction's force as constant beyond that position; returns how many. Newton
    /// sets them from each direction and takes their secant curvature in its next matrix
    /// ([`ContactModel::add_friction_with`]); a pair the next direction does not reverse
    /// (one that slides on, or one that reached its sticking position, where friction is
    /// smooth) is exact again, so the iterations converge as Newton's do. Without the flags
    /// the line search cut such steps to 1/128 for tens of iterations: a torus across a
    /// ridge failed its step 30 at mu 0.5.
    ///
    /// # Panics
    /// If `secant` does not have one entry per pair.
    pub fn flag_reversals(
        &self,
        lag: &FrictionLag,
        x: &[f64],
        dx: &[f64],
        secant: &mut [bool],
    ) -> usize {
        assert_eq!(secant.len(), lag.pairs.len(), "one flag per pair");
        let mut flagged = 0;
        for (pair, flag) in lag.pairs.iter().zip(secant.iter_mut()) {
            let u: Vector2<f64> = pair.basis.transpose() * (pair.point(x) - pair.start);
            if u.norm() < lag.threshold {
                *flag = false;
                continue;
            }
            let du: Vector2<f64> = pair.basis.transpose() * pair.point(dx);
            *flag = u.dot(&(u + du)) < 0.0;
            flagged += usize::from(*flag);
        }
        flagged
    }
}

impl ContactModel {
    /// `out += (df/dx0)^T w`, with `f` the friction forces at `x1` lagged at `x0` by `lag`:
    /// how they change with the step's start through the lag (normal force `-mu b'(d)`,
    /// tangent plane, start point). The adjoint of a step needs it beside the Hessian in
    /// `x1`. A pair's force is `-L phi(|q|) q` with `q = P (x1 - start)` and the tangent
    /// projector `P = I - n n^T` (the basis enters only through `P`), so with `h = phi I +
    /// phi'(|q|) q q^T / |q|` the three paths are `L h P R` (the start point, which moves
    /// with the obstacle: `R` its turn over the step), `mu b''(d) phi q n^T` (the normal
    /// force) and `-L h Q` with `Q = -((n . d) H + n (H d)^T)` (the
    /// normal's turn, `H` the distance's Hessian, `d = x1 - start`).
    ///
    /// Pairs of the body's surface against mesh obstacles or itself also move their closest
    /// points' weights with `x0`; see `SelfContact::friction_start_vjp` (docs/theory.md).
    ///
    /// # Errors
    /// [`ContactError::Invalid`] for a lag that is not this model's (an analytic pair of
    /// several vertices).
    pub fn add_friction_start_vjp(
        &self,
        lag: &FrictionLag,
        (x0, x1): (&[f64], &[f64]),
        w: &[f64],
        out: &mut [f64],
    ) -> Result<(), ContactError> {
        let Some((mu, _)) = self.friction() else {
            return Ok(());
        };
        let (b, eps) = (self.barrier(), lag.threshold);
        let at = |x: &[f64], v: usize| Vector3::new(x[3 * v], x[3 * v + 1], x[3 * v + 2]);
        let analytic = self.obstacles().len();
        for pair in lag.pairs.iter().filter(|p| p.obstacle < analytic) {
            let &[(v, _)] = pair.vertices.as_slice() else {
                return Err(ContactError::Invalid {
                    field: "friction".into(),
                    reason: "a lag against an analytic obstacle has one vertex a pair".into(),
                });
            };
            let jet = self.before(pair.obstacle).jet(&at(x0, v));
            // The start point moves with the obstacle: `d start / d x0` is its turn.
            let turned = self
                .step_motion(pair.obstacle)
                .map_or(Matrix3::identity(), |m| {
                    m.rotation.to_rotation_matrix().into_inner()
                });
            let (n, hd) = (jet.gradient, jet.hessian);
            let d = at(x1, v) - pair.start;
            let p = Matrix3::identity() - n * n.transpose();
            let q = p * d;
            let s = q.norm();
            let (phi, dphi) = if s >= eps {
                (1.0 / s, -1.0 / (s * s))
            } else {
                (2.0 / eps - s / (eps * eps), -1.0 / (eps * eps))
            };
            let mut h = Matrix3::identity() * phi;
            if s > 0.0 {
                h += q * q.transpose() * (dphi / s);
            }
            let turn = -(hd * n.dot(&d) + n * (hd * d).transpose());
            let normal = q * n.transpose() * (mu[pair.obstacle] * b.second(jet.distance) * phi);
            let jacobian = h * (p * turned - turn) * pair.limit + normal;
            let y = jacobian.transpose() * at(w, v);
            for k in 0..3 {
                out[3 * v + k] += y[k];
            }
        }
        if let Some(surface) = self.surface() {
            let meshes = (b, &mu[analytic..], eps);
            surface.friction_start_vjp((x0, x1), meshes, w, out);
        }
        Ok(())
    }
}

/// Two orthonormal vectors orthogonal to the unit vector `n`, as columns.
pub(crate) fn tangent_basis(n: &Vector3<f64>) -> Matrix3x2<f64> {
    let helper = if n.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let a = n.cross(&helper).normalize();
    let b = n.cross(&a);
    Matrix3x2::from_columns(&[a, b])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_smoothing_is_c1_and_its_derivative_is_f1() {
        let eps = 1e-3;
        for y in [1e-5, 3e-4, 7e-4, 0.999e-3, 2e-3] {
            let h = 1e-9;
            let d = (f0(y + h, eps) - f0(y - h, eps)) / (2.0 * h);
            assert!((d - f1(y, eps)).abs() < 1e-6, "{y}: {d} {}", f1(y, eps));
        }
        assert!((f0(eps * (1.0 - 1e-12), eps) - eps).abs() < 1e-14);
        assert!((f1(eps * (1.0 - 1e-9), eps) - 1.0).abs() < 1e-8);
    }

    #[test]
    fn tangent_bases_are_orthonormal_and_tangent() {
        for n in [
            Vector3::z(),
            Vector3::x(),
            Vector3::new(0.3, -0.4, 0.5).normalize(),
        ] {
            let t = tangent_basis(&n);
            assert!((t.transpose() * t - Matrix2::identity()).norm() < 1e-14);
            assert!((t.transpose() * n).norm() < 1e-14);
        }
    }
}
