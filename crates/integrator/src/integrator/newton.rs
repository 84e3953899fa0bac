//! The Backward-Euler step and its Newton loop: the step and its retries, the static
//! solve, the first iterate, the residual and the convergence tests (including the
//! residual's rounding floor).

use super::*;

impl Integrator {
    /// Advances `state` by one step of `options.dt` (Backward Euler), retrying with halved
    /// substeps on failure when `max_retries > 0`. On error `state` is unchanged.
    ///
    /// # Errors
    /// [`StepError`] with the report up to the failure.
    pub fn step(&mut self, state: &mut State) -> Result<StepReport, StepError> {
        self.step_observed(state, &mut NoObserver)
    }

    /// [`step`](Self::step), with every Newton iteration going to `observer` (its `step`
    /// method is the run executor's to call, [`Integrator::run`]).
    ///
    /// # Errors
    /// [`StepError`] with the report up to the failure.
    pub fn step_observed(
        &mut self,
        state: &mut State,
        observer: &mut dyn Observer,
    ) -> Result<StepReport, StepError> {
        let start = Instant::now();
        let dt = self.options.dt;
        let mut report = self.advance(state, dt, observer)?;
        report.step = self.steps_taken;
        report.seconds = start.elapsed().as_secs_f64();
        self.steps_taken += 1;
        Ok(report)
    }

    /// `dt` in one Newton solve or, when that fails, in substeps: each failure halves the
    /// substep and the step goes on from where it got, so at most `max_retries` solves fail
    /// and the cost of retrying is linear in `max_retries`.
    pub(super) fn advance(
        &mut self,
        state: &mut State,
        dt: f64,
        observer: &mut dyn Observer,
    ) -> Result<StepReport, StepError> {
        let (mut current, mut h, mut remaining) = (state.clone(), dt, dt);
        let (mut retries, mut smallest) = (0, dt);
        let mut iterations: Vec<IterationReport> = Vec::new();
        loop {
            let sub = h.min(remaining);
            let solved = self.newton(&current, Mode::Dynamic { dt: sub }, observer);
            // Surfaces squeezed deep into the barrier stiffen it for what follows.
            if let Some(c) = self.contact.as_mut() {
                c.adapt();
            }
            match solved {
                Ok((next, mut report)) => {
                    current = next;
                    remaining -= sub;
                    smallest = smallest.min(sub);
                    iterations.append(&mut report.iterations);
                    if remaining <= 1e-12 * dt {
                        *state = current;
                        return Ok(StepReport {
                            iterations,
                            retries,
                            dt: smallest,
                            ..report
                        });
                    }
                }
                Err(e) if retries < self.options.max_retries && retryable(&e) => {
                    iterations.extend(e.report().iterations.iter().cloned());
                    retries += 1;
                    h = sub / 2.0;
                }
                Err(e) => return Err(e.with_earlier(&iterations, retries)),
            }
        }
    }

    /// Static equilibrium under gravity and the constraints at `state.t`: `f_e(x) + M g = 0`
    /// on the free DOFs, by the same Newton machinery (with the potential `E - (M g) . x`
    /// for the line search). Velocities are set to zero.
    ///
    /// # Errors
    /// [`StepError`] with the report.
    pub fn solve_static(&mut self, state: &mut State) -> Result<StepReport, StepError> {
        let start = Instant::now();
        let (next, mut report) = self.newton(state, Mode::Static, &mut NoObserver)?;
        *state = next;
        report.seconds = start.elapsed().as_secs_f64();
        Ok(report)
    }

    /// Newton on the unknown `u` (`v` when dynamic, `x` when static), in named stages:
    /// [`residual`](Self::residual), the convergence test, the
    /// [`Newton matrix`](Self::newton_matrix), the [`direction`](Self::direction) (solve,
    /// fallback, projection switch), the [`line search`](Self::line_search), the record.
    /// Its vectors live in the integrator's [`Work`], allocated once.
    pub(super) fn newton(
        &mut self,
        state: &State,
        mode: Mode,
        observer: &mut dyn Observer,
    ) -> Result<(State, StepReport), StepError> {
        let mut work = std::mem::take(&mut self.work);
        work.resize(self.asm.num_dofs(), self.dofs.num_free());
        let result = self.newton_in(state, mode, observer, &mut work);
        self.work = work;
        result
    }

    pub(super) fn newton_in(
        &mut self,
        state: &State,
        mode: Mode,
        observer: &mut dyn Observer,
        w: &mut Work,
    ) -> Result<(State, StepReport), StepError> {
        let newton = self.options.newton;
        let (t1, dt) = match mode {
            Mode::Dynamic { dt } => (state.t + dt, dt),
            Mode::Static => (state.t, 0.0),
        };
        self.refresh_external(t1, 1e-9 * self.options.dt);
        self.lag_friction(state, mode);
        let mut report = StepReport {
            t: t1,
            dt,
            policy: self.policy.name(),
            ..StepReport::default()
        };
        let (mut x, mut u) = self
            .initial_iterate(state, mode, t1)
            .map_err(|e| e.into_step_error(&report))?;
        let mut tangent = newton.project.first_tangent();
        // Solves whose result was not used (a failed choice before the fallback, an
        // exact-tangent attempt before projection), charged to the next iteration's report.
        let mut discarded: Vec<CandidateOutcome> = Vec::new();
        // The energy at `x` when the line search's accepted trial left it, with the forces,
        // in `w.f`: the residual is then formed without assembling again, and K is assembled
        // only if Newton goes on (a converged check needs no K).
        let mut evaluated: Option<f64> = None;
        let mut iteration = 0;
        while iteration <= newton.max_iterations {
            let started = Instant::now();
            let mut stages = StageSeconds::default();
            let k_at_x = evaluated.is_none();
            let (energy, rn) = match evaluated.take() {
                Some(energy) => self
                    .form_residual(mode, state, &u, w)
                    .map(|rn| (energy, rn)),
                None => self.residual(mode, state, &x, &u, tangent, w),
            }
            .map_err(|e| e.into_step_error(&report))?;
            stages.residual = started.elapsed().as_secs_f64();
            if iteration == 0 {
                report.initial_residual = rn;
            }
            report.final_residual = rn;
            report.energy = energy;
            let converged = self.converged(iteration, rn, &report);
            if converged || self.at_rounding_floor(iteration, rn, &report) {
                (report.converged, report.rounding_floor) = (true, !converged);
                report.contact = self.contact.as_ref().and_then(|c| c.last);
                let v = match mode {
                    Mode::Dynamic { .. } => u,
                    Mode::Static => vec![0.0; x.len()],
                };
                return Ok((State { x, v, t: t1 }, report));
            }
            if iteration == newton.max_iterations {
                break;
            }
            let clock = Instant::now();
            if !k_at_x {
                self.newton_stiffness(mode, &x, &u, tangent)
                    .map_err(|e| e.into_step_error(&report))?;
            }
            let (c_m, c_k) = self
                .newton_matrix(mode)
                .map_err(|e| fail_assembly(e, &report))?;
            stages.matrix = clock.elapsed().as_secs_f64();
            let clock = Instant::now();
            let point = NewtonPoint::new(&x, tangent, (c_m, c_k), mode, &newton, &report);
            let context = IterationContext {
                step: self.steps_taken,
                iteration,
                dt,
                residual: rn,
                initial_residual: report.initial_residual,
            };
            let found = self.direction(point, &context, &report, &mut discarded, w)?;
            stages.direction = clock.elapsed().as_secs_f64();
            let Some(found) = found else {
                // The exact tangent failed; this iteration again with the projected one.
                tangent = Tangent::Projected;
                continue;
            };
            let clock = Instant::now();
            w.du.iter_mut().for_each(|v| *v = 0.0);
            self.dofs
                .scatter(&w.du_free, &mut w.du)
                .expect("sizes match");
            let bound = self.step_bound(mode, state, &u, w);
            let step_length = if newton.line_search && found.slope < 0.0 {
                let (step_length, at_trial) = self
                    .line_search(mode, state, &u, (energy, found.slope, tangent), bound, w)
                    .map_err(|e| fail_assembly(e, &report))?;
                evaluated = at_trial;
                step_length
            } else {
                bound
            };
            stages.line_search = clock.elapsed().as_secs_f64();
            for (ui, di) in u.iter_mut().zip(&w.du) {
                *ui += step_length * di;
            }
            self.positions_into(mode, state, &u, &mut x);
            let update = position_update(mode, &w.du, step_length);
            if !update.is_finite() {
                return Err(StepError::NonFinite {
                    what: "update",
                    report: Box::new(report),
                });
            }
            // Record: the iteration's report goes to the observer, the policy and the step.
            let it = IterationReport {
                iteration,
                residual: rn,
                energy,
                solver: found.solver,
                setup: found.setup,
                solve: found.solve,
                fallback: found.fallback,
                step_length,
                step_bound: bound,
                update,
                seconds: started.elapsed().as_secs_f64(),
                stages,
                candidates: found.candidates,
                discarded: std::mem::take(&mut discarded),
            };
            observer.iteration(&it);
            self.policy.observe(
                &context.policy(self.dofs.num_free(), &report.iterations),
                &it,
            );
            report.iterations.push(it);
            iteration += 1;
        }
        Err(StepError::NotConverged {
            report: Box::new(report),
        })
    }

    /// Newton's first iterate `(x, u)` for a step ending at `t1`: `v^n` (dynamic) or `x^n`
    /// (static), constrained DOFs at their targets.
    ///
    /// # Errors
    /// [`ContactError::Overrun`] when obstacles that move pass through the body whatever
    /// its first iterate.
    pub(super) fn initial_iterate(
        &self,
        state: &State,
        mode: Mode,
        t1: f64,
    ) -> Result<(Vec<f64>, Vec<f64>), StageError> {
        let mut x = state.x.clone();
        let mut u = match mode {
            Mode::Dynamic { .. } => state.v.clone(),
            Mode::Static => state.x.clone(),
        };
        match mode {
            Mode::Dynamic { dt } => {
                self.apply_constraints(&mut x, Some((&mut u, &state.x)), t1, dt);
                self.feasible_velocity(state, dt, &mut u)?;
                for i in 0..x.len() {
                    x[i] = state.x[i] + dt * u[i];
                }
            }
            Mode::Static => {
                self.apply_constraints(&mut x, None, t1, 0.0);
                u.copy_from_slice(&x);
            }
        }
        Ok((x, u))
    }

    /// Stage 1: assembles energy, forces, K (Newton's, see [`Integrator::newton_matrix`]) and,
    /// with stiffness damping, `K u` at `x`, and [forms the residual](Self::form_residual);
    /// returns the energy and the residual's 2-norm.
    pub(super) fn residual(
        &mut self,
        mode: Mode,
        state: &State,
        x: &[f64],
        u: &[f64],
        tangent: Tangent,
        w: &mut Work,
    ) -> Result<(f64, f64), StageError> {
        let mut energy = 0.0;
        let shift = self.damping_shift(mode, u, tangent);
        let damped = self.stiffness_damping(mode) != 0.0;
        self.asm.evaluate(
            x,
            Outputs {
                energy: Some(&mut energy),
                forces: Some(&mut w.f),
                stiffness: Some(&mut self.k),
                tangent,
                stiffness_product: damped.then_some((u, &mut w.ku[..])),
                stiffness_shift: shift,
            },
        )?;
        energy += self.add_contact(x, Some(&mut w.f), true)?;
        Ok((energy, self.form_residual(mode, state, u, w)?))
    }

    /// The residual (the gradient of the merit function in `u`) on the free DOFs, into
    /// `w.r_free`, from the elastic forces in `w.f` (and `K u` in `w.ku`, for stiffness
    /// damping); returns its 2-norm.
    pub(super) fn form_residual(
        &self,
        mode: Mode,
        state: &State,
        u: &[f64],
        w: &mut Work,
    ) -> Result<f64, StageError> {
        let external = self.external();
        match mode {
            Mode::Dynamic { dt } => {
                let gamma = self.options.stiffness_damping(dt);
                let alpha = self.options.alpha;
                self.asm.mass_apply(&self.mass, u, &mut w.fd)?;
                update_from(&mut w.fd, &w.ku, |d, ku| {
                    *d = -(alpha * *d + if gamma == 0.0 { 0.0 } else { gamma * ku });
                });
                update_from2(&mut w.dv, u, &state.v, |d, ui, vi| *d = ui - vi);
                self.asm.mass_apply(&self.mass, &w.dv, &mut w.r)?;
                let inputs = [&w.f[..], &w.fd, external];
                update_from3(&mut w.r, inputs, |r, f, fd, e| *r -= dt * (f + fd + e));
            }
            Mode::Static => {
                update_from2(&mut w.r, &w.f, external, |r, f, e| *r = -(f + e));
            }
        }
        self.dofs
            .restrict(&w.r, &mut w.r_free)
            .expect("sizes match");
        let rn = norm(&w.r_free);
        if !rn.is_finite() {
            return Err(StageError::NonFinite("residual"));
        }
        Ok(rn)
    }

    /// Stage 2: `||r|| <= max(abs, rel ||r_0||)` (at iteration 0 only `abs`), or the last
    /// position update below `update` (when set) with the residual below its start. A
    /// zero update with the default `update` of 0 once counted, and so did one that left the
    /// residual where it was: a step that went nowhere (a NaN direction zeroed by the line
    /// search) was accepted as converged.
    pub(super) fn converged(&self, iteration: usize, rn: f64, report: &StepReport) -> bool {
        let n = &self.options.newton;
        let last_update = report
            .iterations
            .last()
            .map_or(f64::INFINITY, |it| it.update);
        let small_update = n.update > 0.0 && last_update <= n.update;
        rn <= n.abs.max(n.rel * report.initial_residual) && (iteration > 0 || rn <= n.abs)
            || (iteration > 0 && small_update && rn < report.initial_residual)
    }

    /// Stage 2, when the tolerance is out of reach: well past the start (`rn <= 1e-8 r_0`),
    /// two full Newton iterations that did not halve the residual mean it is at its rounding
    /// floor, where Newton converges quadratically otherwise; more iterations would only
    /// end at the cap.
    pub(super) fn at_rounding_floor(&self, iteration: usize, rn: f64, report: &StepReport) -> bool {
        let its = &report.iterations;
        iteration >= 2
            && its.len() >= 2
            && rn <= 1e-8 * report.initial_residual
            && rn >= 0.5 * its[its.len() - 2].residual
            && its[its.len() - 2..].iter().all(|it| it.step_length == 1.0)
    }
}

/// The integrator's vectors for Newton, allocated once and resized when the mesh changes.
#[derive(Debug, Default)]
pub(super) struct Work {
    /// Elastic forces, damping forces, residual, `v - v^n`, `M (v - v^n)`, and `K u` for
    /// stiffness damping (full `3N`).
    pub(super) f: Vec<f64>,
    pub(super) ku: Vec<f64>,
    pub(super) fd: Vec<f64>,
    pub(super) r: Vec<f64>,
    pub(super) dv: Vec<f64>,
    pub(super) mdv: Vec<f64>,
    /// The direction, the line search's trial iterate and its positions (full `3N`).
    pub(super) du: Vec<f64>,
    pub(super) trial: Vec<f64>,
    pub(super) xt: Vec<f64>,
    /// Residual, right-hand side and direction on the free DOFs.
    pub(super) r_free: Vec<f64>,
    pub(super) rhs: Vec<f64>,
    pub(super) du_free: Vec<f64>,
}

impl Work {
    pub(super) fn resize(&mut self, n: usize, free: usize) {
        for v in [
            &mut self.f,
            &mut self.ku,
            &mut self.fd,
            &mut self.r,
            &mut self.dv,
            &mut self.mdv,
            &mut self.du,
            &mut self.trial,
            &mut self.xt,
        ] {
            v.resize(n, 0.0);
        }
        for v in [&mut self.r_free, &mut self.rhs, &mut self.du_free] {
            v.resize(free, 0.0);
        }
    }
}

/// What the policy sees of an iteration.
pub(super) struct IterationContext {
    pub(super) step: usize,
    pub(super) iteration: usize,
    pub(super) dt: f64,
    pub(super) residual: f64,
    pub(super) initial_residual: f64,
}

impl IterationContext {
    pub(super) fn policy<'a>(
        &self,
        num_free: usize,
        history: &'a [IterationReport],
    ) -> PolicyContext<'a> {
        PolicyContext {
            step: self.step,
            iteration: self.iteration,
            dt: self.dt,
            num_free,
            residual: self.residual,
            initial_residual: self.initial_residual,
            history,
        }
    }
}

/// Why the residual stage failed.
pub(super) enum StageError {
    Assembly(AssemblyError),
    Contact(ContactError),
    NonFinite(&'static str),
}

impl StageError {
    pub(super) fn into_step_error(self, report: &StepReport) -> StepError {
        match self {
            StageError::Assembly(e) => fail_assembly(e, report),
            StageError::Contact(source) => StepError::Contact {
                source,
                report: Box::new(report.clone()),
            },
            StageError::NonFinite(what) => StepError::NonFinite {
                what,
                report: Box::new(report.clone()),
            },
        }
    }
}

/// The max-norm of the position update of a Newton step `du` taken with `step_length`
/// (`du` is a velocity update when dynamic: positions move `dt` times it).
pub(super) fn position_update(mode: Mode, du: &[f64], step_length: f64) -> f64 {
    let scale = match mode {
        Mode::Dynamic { dt } => dt,
        Mode::Static => 1.0,
    };
    du.iter()
        .fold(0.0f64, |m, v| m.max((scale * step_length * v).abs()))
}

pub(super) fn fail_assembly(source: AssemblyError, report: &StepReport) -> StepError {
    StepError::Assembly {
        source,
        report: Box::new(report.clone()),
    }
}

/// Where the Newton matrix `c_m M + c_k K` is linearised, for matrix-free solves.
#[derive(Clone, Copy)]
pub(super) struct NewtonPoint<'a> {
    pub(super) x: &'a [f64],
    pub(super) tangent: Tangent,
    pub(super) c_m: f64,
    pub(super) c_k: f64,
    /// The factor of contact's Hessian blocks ([`contact_scale`]).
    pub(super) c_contact: f64,
    /// Iterative solves stop at this residual norm ([`NewtonOptions::linear_floor`]).
    pub(super) floor: f64,
    /// Positions move this times the unknown's update (`dt` dynamic, 1 static).
    pub(super) position_scale: f64,
}

pub(super) fn retryable(e: &StepError) -> bool {
    !matches!(
        e,
        StepError::Assembly {
            source: AssemblyError::NonFinite { .. },
            ..
        }
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An iteration of a step's report that moved `update` and left the residual at
    /// `residual`.
    fn iteration(residual: f64, update: f64) -> IterationReport {
        IterationReport {
            iteration: 0,
            residual,
            energy: 0.0,
            solver: ron::from_str("Direct()").unwrap(),
            setup: Default::default(),
            solve: deform_solvers::SolveStats::new("direct".into(), residual),
            fallback: false,
            step_length: 0.0,
            step_bound: 1.0,
            update,
            seconds: 0.0,
            stages: Default::default(),
            candidates: Vec::new(),
            discarded: Vec::new(),
        }
    }

    /// A step that went nowhere (update 0, residual 8.9 -> 8.9) is not converged: not with
    /// the default `update` of 0 (it was: 0 <= 0), nor with an update tolerance set, since
    /// its residual did not drop. A small update that did lower the residual still counts.
    #[test]
    fn a_step_that_went_nowhere_is_not_converged() {
        let scene = crate::Scene::parse(
            "Scene(name: \"t\", mesh: Beam(1), material: NeoHookean(Young(e: 1e5, nu: 0.4)), density: 1000.0, integrator: (dt: 0.01), steps: 1)",
            std::path::Path::new("t.ron"),
        )
        .unwrap();
        let mut sim = scene.build(std::path::Path::new(".")).unwrap().integrator;
        let mut report = StepReport {
            initial_residual: 8.9,
            ..StepReport::default()
        };
        report.iterations.push(iteration(8.9, 0.0));
        assert!(!sim.converged(1, 8.9, &report));
        sim.options.newton.update = 1e-6;
        assert!(!sim.converged(1, 8.9, &report));
        report.iterations[0].update = 1e-7;
        assert!(sim.converged(1, 1.0, &report));
    }
}
