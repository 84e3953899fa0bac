//! The output-error loss, evaluated over rollouts side by side: one lane per thread, each an
//! integrator of its own, the terms summed in rollout order (bits independent of threads).

use super::adjoint::*;
use super::*;

/// One thread's integrator (a fork of the objective's) and adjoint solver, kept between
/// evaluations.
pub(super) struct Lane {
    pub(super) sim: Integrator,
    pub(super) solver: Cholesky,
}

/// What one evaluation's rollouts share.
pub(super) struct Pass<'p> {
    pub(super) starts: Option<&'p [f64]>,
    /// DOFs, and the vertices that are not constrained.
    pub(super) n: usize,
    pub(super) free: Vec<usize>,
    /// The velocity term's weight.
    pub(super) wv: f64,
    /// The start prior's position and velocity weights, and the unobserved vertices' factor.
    pub(super) prior: (f64, f64, f64),
    pub(super) allow_retries: bool,
    /// The adjoint's gradient: per group, then mass scales, damping and friction.
    pub(super) gradient_len: usize,
    pub(super) grouping: Grouping,
    pub(super) mass: bool,
    pub(super) damping: bool,
    /// Coefficients of friction fitted (last in the gradient).
    pub(super) friction: usize,
}

/// One rollout's share of the loss's sums and gradients.
pub(super) struct RolloutTerms {
    pub(super) num: f64,
    pub(super) den: f64,
    pub(super) grad: Vec<f64>,
    /// The start offsets' gradient (positions then velocities), when they are fitted.
    pub(super) start_grad: Option<Vec<f64>>,
}

/// A rollout: `(trajectory, start step, steps)`.
pub(super) type Job = (usize, usize, usize);

impl Pass<'_> {
    /// The rollouts in order on the objective's own integrator.
    pub(super) fn one_by_one(
        &self,
        trajectories: &[&Trajectory],
        jobs: &[Job],
        sim: &mut Integrator,
        solver: &mut Cholesky,
    ) -> Result<Vec<RolloutTerms>, FitError> {
        let mut adjoint = None;
        (jobs.iter().enumerate())
            .map(|(r, &job)| self.rollout(trajectories, (r, job), sim, solver, &mut adjoint))
            .collect()
    }

    /// The rollouts side by side (`lanes::side_by_side`). Every rollout starts
    /// from a restarted integrator, so which lane runs it does not change its bits.
    pub(super) fn side_by_side(
        &self,
        trajectories: &[&Trajectory],
        jobs: &[Job],
        lanes: &mut [Lane],
    ) -> Result<Vec<RolloutTerms>, FitError> {
        // Each lane makes the adjoint's matrices at its first rollout.
        let mut lanes: Vec<(&mut Lane, Option<Adjoint>)> =
            lanes.iter_mut().map(|lane| (lane, None)).collect();
        let run = |(lane, adjoint): &mut (&mut Lane, Option<Adjoint>),
                   r: usize,
                   _: &mut dyn FnMut(())| {
            let (sim, solver) = (&mut lane.sim, &mut lane.solver);
            self.rollout(trajectories, (r, jobs[r]), sim, solver, adjoint)
        };
        crate::lanes::side_by_side(&mut lanes, jobs.len(), &run, &mut |_, ()| {})
    }

    /// Rollout `r` of `job` from a restarted integrator (so that its bits do not depend on
    /// the rollouts run before it): the forward steps, their loss terms and the adjoint pass.
    /// `adjoint` holds the adjoint's matrices, made at the evaluation's first rollout.
    pub(super) fn rollout(
        &self,
        trajectories: &[&Trajectory],
        (r, (ti, start, len)): (usize, Job),
        sim: &mut Integrator,
        solver: &mut Cholesky,
        adjoint: &mut Option<Adjoint>,
    ) -> Result<RolloutTerms, FitError> {
        sim.restart();
        let work = match adjoint {
            Some(work) => work,
            None => {
                let unscaled = self.mass.then(|| sim.unscaled_vertex_masses());
                let grouping = self.grouping.clone();
                let tail = (self.damping, self.friction);
                adjoint.insert(Adjoint::new(sim, grouping, unscaled, tail)?)
            }
        };
        let (t, n) = (trajectories[ti], self.n);
        let (wpx, wpv, unobserved) = self.prior;
        // Each rollout runs under its trajectory's conditions (the model's put back after).
        let ran = t.under(sim, |sim| -> Result<RolloutTerms, FitError> {
            // An exactly known first state stays as it is.
            let offset = (self.starts)
                .filter(|_| !(start == 0 && t.exact_start))
                .map(|o| &o[2 * n * r..2 * n * (r + 1)]);
            let mut first = state_at(t, start, sim.options().dt);
            let seen = seen_vertices(t, n / 3);
            let weight = |v: usize| if seen[v] { 1.0 } else { unobserved };
            let mut terms = RolloutTerms {
                num: 0.0,
                den: 0.0,
                grad: vec![0.0; self.gradient_len],
                start_grad: None,
            };
            if let Some(o) = offset {
                for &v in &self.free {
                    let (wx, wv) = (weight(v) * wpx, weight(v) * wpv);
                    for i in 3 * v..3 * v + 3 {
                        first.x[i] += o[i];
                        first.v[i] += o[n + i];
                        terms.num += wx * o[i] * o[i] + wv * o[n + i] * o[n + i];
                    }
                }
            }
            let states = forward(sim, first, (ti, start, len), self.allow_retries)?;
            let sums = (&mut terms.num, &mut terms.den);
            let (dl_dx, dl_dv) = loss_terms(t, start, &states, self.wv, sums);
            let rollout = Rollout {
                trajectory: ti,
                start,
                states: &states,
                dl_dx: &dl_dx,
                dl_dv: &dl_dv,
            };
            let adjoint = work.backward(sim, solver, &rollout, &mut terms.grad)?;
            if let Some(o) = offset {
                let mut g = vec![0.0; 2 * n];
                for &v in &self.free {
                    let (wx, wv) = (weight(v) * wpx, weight(v) * wpv);
                    for i in 3 * v..3 * v + 3 {
                        g[i] = adjoint.0[i] + 2.0 * wx * o[i];
                        g[n + i] = adjoint.1[i] + 2.0 * wv * o[n + i];
                    }
                }
                terms.start_grad = Some(g);
            }
            Ok(terms)
        });
        ran.map_err(|e| FitError::Data {
            index: ti,
            reason: e.to_string(),
        })?
    }
}

/// The loss terms of a rollout's predicted `states` (from data step `start` of `t`), added
/// to the sums `(num, den)` (the squared errors, with velocities weighted by `wv`, and the
/// squared data motion), and their derivatives `dL/dx`, `dL/dv` per state (entry 0 zero).
pub(super) fn loss_terms(
    t: &Trajectory,
    start: usize,
    states: &[State],
    wv: f64,
    (num, den): (&mut f64, &mut f64),
) -> (Vec<Vec<f64>>, Vec<Vec<f64>>) {
    let (len, n) = (states.len() - 1, states[0].x.len());
    let mut dl_dx = vec![vec![0.0; n]; len + 1];
    let mut dl_dv = vec![vec![0.0; n]; len + 1];
    if let Some(o) = &t.observed {
        // Markers' positions only: a capture gives no velocities.
        for k in 1..=len {
            let (seen, before) = (&o.positions[start + k], &o.positions[start + k - 1]);
            for (m, marker) in o.markers.iter().enumerate() {
                let q = marker.position(&states[k].x);
                for d in 0..3 {
                    let e = q[d] - seen[3 * m + d];
                    *num += e * e;
                    *den += (seen[3 * m + d] - before[3 * m + d]).powi(2);
                    for (v, w) in marker.terms() {
                        dl_dx[k][3 * v + d] += 2.0 * w * e;
                    }
                }
            }
        }
        return (dl_dx, dl_dv);
    }
    for k in 1..=len {
        let (xd, vd) = (&t.x[start + k], &t.v[start + k]);
        for i in 0..n {
            let ex = states[k].x[i] - xd[i];
            let ev = states[k].v[i] - vd[i];
            *num += ex * ex + wv * ev * ev;
            let motion = xd[i] - t.x[start + k - 1][i];
            *den += motion * motion;
            dl_dx[k][i] = 2.0 * ex;
            dl_dv[k][i] = 2.0 * wv * ev;
        }
    }
    (dl_dx, dl_dv)
}
