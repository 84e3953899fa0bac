//! Contact in the step: a first iterate reached without touching, the velocity carried by
//! moving obstacles, the barrier's terms in the residual and Newton's matrix, lagged
//! friction, and the collision bound on each line search.

use super::*;

/// A moving obstacle may carry the body's surface at most this fraction of the body's
/// extent in one step: farther, the surface leaves the interior behind and elements invert
/// (an obstacle at 1e3 m/s carried a 10 cm cube's base 5 m in a step).
const CARRY_REACH: f64 = 0.5;

/// The diagonal of the bounding box of the flat positions `x`.
fn extent(x: &[f64]) -> f64 {
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in x.chunks(3) {
        for d in 0..3 {
            (lo[d], hi[d]) = (lo[d].min(p[d]), hi[d].max(p[d]));
        }
    }
    (0..3).map(|d| (hi[d] - lo[d]).powi(2)).sum::<f64>().sqrt()
}

impl Integrator {
    /// With contact, scales the free DOFs of the first iterate's velocity `u` so that the
    /// first iterate `x^n + dt u` is reached from `x^n` without touching an obstacle (the
    /// barrier must be finite there); the constrained ones follow their motions.
    pub(super) fn feasible_velocity(
        &self,
        state: &State,
        dt: f64,
        u: &mut [f64],
    ) -> Result<(), ContactError> {
        let Some(c) = &self.contact else {
            return Ok(());
        };
        if c.model.moving() {
            return self.carried_velocity(&c.model, state, dt, u);
        }
        let dx: Vec<f64> = u.iter().map(|v| dt * v).collect();
        let bound = c.model.step_bound(&state.x, &dx);
        if bound < 1.0 {
            for &i in self.dofs.free_dofs() {
                u[i] *= bound;
            }
        }
        Ok(())
    }

    /// [`Integrator::feasible_velocity`] while obstacles move: vertices they would come too
    /// close to move with them ([`ContactModel::carry`]); if the rest of the path still
    /// comes too close to something, the free velocities are scaled down and carried
    /// again, and at worst the free vertices only move with the obstacles; if even that
    /// comes too close, the step is refused rather than let an obstacle pass through.
    pub(super) fn carried_velocity(
        &self,
        model: &ContactModel,
        state: &State,
        dt: f64,
        u: &mut [f64],
    ) -> Result<(), ContactError> {
        let v0: Vec<f64> = u.to_vec();
        let reach = CARRY_REACH * extent(&state.x);
        for scale in [1.0, 0.5, 0.0] {
            let mut dx: Vec<f64> = v0.iter().map(|v| dt * v).collect();
            for &i in self.dofs.free_dofs() {
                dx[i] *= scale;
            }
            let before = dx.clone();
            model.carry(&state.x, &mut dx, |v| !self.dofs.is_constrained(v));
            // Carried that far, the surface leaves its interior behind: elements invert,
            // and the step would fail in the assembly, naming an element, not the motion.
            let carried = (dx.chunks(3).zip(before.chunks(3)))
                .map(|(a, b)| {
                    (Vector3::from_column_slice(a) - Vector3::from_column_slice(b)).norm()
                })
                .fold(0.0, f64::max);
            if !(carried <= reach) {
                return Err(ContactError::Overrun);
            }
            if model.first_step_bound(&state.x, &dx) >= 1.0 {
                for &i in self.dofs.free_dofs() {
                    u[i] = dx[i] / dt;
                }
                return Ok(());
            }
        }
        Err(ContactError::Overrun)
    }

    /// The contact potential at `x`: adds its forces to `forces`, keeps its Hessian's
    /// blocks for Newton's matrix when asked, and returns its energy (0 without contact).
    pub(super) fn add_contact(
        &mut self,
        x: &[f64],
        forces: Option<&mut [f64]>,
        hessian: bool,
    ) -> Result<f64, ContactError> {
        match self.contact.as_mut() {
            Some(c) => c.evaluate(x, forces, hessian),
            None => Ok(0.0),
        }
    }

    /// Places contact's moving obstacles for a solve from `state` (where they are at its
    /// end) and lags its friction at `state` (none when static).
    pub(super) fn lag_friction(&mut self, state: &State, mode: Mode) {
        if let Some(c) = self.contact.as_mut() {
            let t1 = match mode {
                Mode::Dynamic { dt } => state.t + dt,
                Mode::Static => state.t,
            };
            c.model.set_step(state.t, t1);
            c.set_lag(match mode {
                Mode::Dynamic { dt } => c.model.lag_friction(&state.x, dt),
                Mode::Static => Default::default(),
            });
        }
    }

    /// How far along `w.du` from the iterate `u` the line search may go: the contact's
    /// continuous collision bound (1 without contact). Flags the friction pairs the full
    /// step carries past their sticking position (see [`Contact::flag_reversals`]). Uses
    /// `w.xt` as scratch.
    pub(super) fn step_bound(&mut self, mode: Mode, state: &State, u: &[f64], w: &mut Work) -> f64 {
        if self.contact.is_none() {
            return 1.0;
        }
        self.positions_into(mode, state, u, &mut w.xt);
        let scale = match mode {
            Mode::Dynamic { dt } => dt,
            Mode::Static => 1.0,
        };
        let dx: Vec<f64> = w.du.iter().map(|d| scale * d).collect();
        let c = self.contact.as_mut().expect("checked above");
        c.flag_reversals(&w.xt, &dx);
        c.model.step_bound(&w.xt, &dx)
    }
}

/// The factor of the contact Hessian in Newton's matrix: contact is a force on positions,
/// which move `dt` times the unknown velocity when dynamic (`dt^2`, as for K without
/// damping: Rayleigh damping is of the elastic forces only).
pub(super) fn contact_scale(mode: Mode) -> f64 {
    match mode {
        Mode::Dynamic { dt } => dt * dt,
        Mode::Static => 1.0,
    }
}
