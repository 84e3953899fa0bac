//! The line search on the incremental potential (the merit function), from the collision
//! bound, with the positions and the damping model of each trial.

use super::*;

impl Integrator {
    /// Stage 5: backtracking (Armijo) on the merit function along `w.du` from `u`, from the
    /// step length `bound` (contact's collision bound, else 1); returns the step length and
    /// the energy at the accepted trial, whose forces (and `K u`, with
    /// stiffness damping) it leaves in `w.f` (and `w.ku`): each trial assembles them, so the
    /// next residual is formed without another pass (with the iterate's `tangent`, which the
    /// damping's `K u` is of). `None` when no trial was assembled.
    pub(super) fn line_search(
        &mut self,
        mode: Mode,
        state: &State,
        u: &[f64],
        (energy, slope, tangent): (f64, f64, Tangent),
        bound: f64,
        w: &mut Work,
    ) -> Result<(f64, Option<f64>), AssemblyError> {
        let gamma = self.stiffness_damping(mode);
        let damping = self.damping_model(mode, w)?;
        let phi0 = self.merit(mode, state, u, energy, 0.0, w);
        // Near the solution the predicted decrease falls below the rounding noise of the
        // merit function; Armijo's test is then meaningless, so take the step.
        let noise = 1e-12 * phi0.abs();
        let mut step_length = bound;
        loop {
            // The trial is assembled even then: its energy and forces are the next residual's.
            let untestable = -slope * step_length <= noise;
            let mut trial = std::mem::take(&mut w.trial);
            let mut xt = std::mem::take(&mut w.xt);
            let du = &w.du;
            update_from2(&mut trial, u, du, |t, ui, di| *t = ui + step_length * di);
            self.positions_into(mode, state, &trial, &mut xt);
            let mut e = 0.0;
            let outputs = Outputs {
                energy: Some(&mut e),
                forces: Some(&mut w.f[..]),
                tangent,
                stiffness_product: (gamma != 0.0).then_some((&trial[..], &mut w.ku[..])),
                ..Outputs::default()
            };
            let assembled = match self.asm.evaluate(&xt, outputs) {
                Ok(()) => true,
                Err(AssemblyError::Inadmissible { .. }) => false,
                Err(e) => return Err(e),
            };
            // Within the bound no vertex reaches an obstacle; the barrier is finite.
            let contact = match assembled {
                true => self.add_contact(&xt, Some(&mut w.f[..]), false).ok(),
                false => None,
            };
            let (phi, evaluated) = match contact {
                Some(c) => {
                    e += c;
                    let (l, q) = damping;
                    let quadratic = step_length * (l + 0.5 * step_length * q);
                    (self.merit(mode, state, &trial, e, quadratic, w), true)
                }
                None => (f64::INFINITY, false),
            };
            (w.trial, w.xt) = (trial, xt);
            if untestable
                || phi <= phi0 + 1e-4 * step_length * slope + noise
                || step_length < 1e-4 * bound
            {
                return Ok((step_length, evaluated.then_some(e)));
            }
            step_length *= 0.5;
        }
    }

    /// The stiffness-damping part of the merit function along `w.du` from the iterate, as
    /// `(l, q)` of `s l + s^2 q / 2` at step length `s`: `l = dt gamma du . K_0 u_0`, its slope
    /// (`K_0 u_0` from the residual's pass, in `w.ku`), and `q = dt gamma du . K du` with
    /// Newton's K (with its `D_u K` term, a model of the curvature like any in a line search).
    /// Zero without stiffness damping; uses `w.fd` as scratch.
    pub(super) fn damping_model(
        &self,
        mode: Mode,
        w: &mut Work,
    ) -> Result<(f64, f64), AssemblyError> {
        let (Mode::Dynamic { dt }, gamma) = (mode, self.stiffness_damping(mode)) else {
            return Ok((0.0, 0.0));
        };
        if gamma == 0.0 {
            return Ok((0.0, 0.0));
        }
        // `damping_forces` with alpha 0 and gamma 1: `-K du`.
        self.asm
            .damping_forces(0.0, 1.0, &self.mass, &self.k, &w.du, &mut w.fd)?;
        let (l, q) = (dot(&w.du, &w.ku), -dot(&w.du, &w.fd));
        Ok((dt * gamma * l, dt * gamma * q))
    }

    /// Positions of the iterate `u`, into `x`.
    pub(super) fn positions_into(&self, mode: Mode, state: &State, u: &[f64], x: &mut [f64]) {
        match mode {
            Mode::Dynamic { dt } => update_from2(x, &state.x, u, |xi, x0, ui| *xi = x0 + dt * ui),
            Mode::Static => x.copy_from_slice(u),
        }
    }

    /// The merit function, whose gradient in `u` at the iterate is the residual: the
    /// incremental potential, with the stiffness-damping part given as `damping` (see
    /// [`Integrator::damping_model`]; 0 at the iterate). Uses `w.dv` and `w.mdv` as scratch.
    pub(super) fn merit(
        &self,
        mode: Mode,
        state: &State,
        u: &[f64],
        energy: f64,
        damping: f64,
        w: &mut Work,
    ) -> f64 {
        let gravity = dot(u, self.external());
        match mode {
            Mode::Dynamic { dt } => {
                update_from2(&mut w.dv, u, &state.v, |d, ui, vi| *d = ui - vi);
                self.asm
                    .mass_apply(&self.mass, &w.dv, &mut w.mdv)
                    .expect("sizes match");
                let kinetic = 0.5 * dot(&w.dv, &w.mdv);
                self.asm
                    .mass_apply(&self.mass, u, &mut w.mdv)
                    .expect("sizes match");
                let mass_damping = 0.5 * dt * self.options.alpha * dot(u, &w.mdv);
                kinetic + energy + mass_damping + damping - dt * gravity
            }
            Mode::Static => energy - gravity,
        }
    }
}
