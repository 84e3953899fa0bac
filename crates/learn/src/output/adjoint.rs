//! The adjoint of the rollouts: the forward pass that keeps each converged step, and the
//! backward pass that solves `A lambda = dL/dv` per step (contact and friction terms included)
//! for the exact gradient of the loss in the coefficients.

use super::*;

/// Forward: the rollout of `len` steps from `first`, the state at step `start` (that state
/// first).
pub(super) fn forward(
    sim: &mut Integrator,
    first: State,
    (trajectory, start, len): (usize, usize, usize),
    allow_retries: bool,
) -> Result<Vec<State>, FitError> {
    let mut states = vec![first];
    let mut s = states[0].clone();
    let mut retried = None;
    let summary = sim.run(
        &mut s,
        &RunOptions::steps(len),
        &mut OnStep(|r: &StepReport, state: &State| {
            if r.retries > 0 && !allow_retries && retried.is_none() {
                retried = Some((states.len() - 1, r.retries));
            }
            states.push(state.clone());
        }),
    );
    summary.into_result().map_err(|e| FitError::Step {
        trajectory,
        step: start + e.step,
        source: e.source,
    })?;
    if let Some((k, retries)) = retried {
        return Err(FitError::Retried {
            trajectory,
            step: start + k,
            retries,
        });
    }
    Ok(states)
}

/// One forward rollout and its loss derivatives, for the backward pass.
pub(super) struct Rollout<'a> {
    pub(super) trajectory: usize,
    pub(super) start: usize,
    /// The states, the start first.
    pub(super) states: &'a [State],
    /// `dL/dx` and `dL/dv` of each state (entry 0 unused).
    pub(super) dl_dx: &'a [Vec<f64>],
    pub(super) dl_dv: &'a [Vec<f64>],
}

/// The adjoint's matrices, allocated once per evaluation and refilled at every step.
pub(super) struct Adjoint {
    pub(super) kmat: StiffnessMatrix,
    /// With stiffness damping: `D_v K`, the derivative of K along the step's end velocity,
    /// and scratch for the Newton matrix's stiffness part (see [`Adjoint::damping_terms`]).
    pub(super) damped: Option<(StiffnessMatrix, StiffnessMatrix)>,
    pub(super) reduced: ReducedMatrix,
    pub(super) mass: Mass,
    pub(super) grouping: Grouping,
    /// The unscaled vertex masses when the gradient has mass scales (after the material's).
    pub(super) unscaled: Option<Vec<f64>>,
    /// The gradient ends with `alpha, gamma`, then this many coefficients of friction.
    pub(super) damping: bool,
    pub(super) friction: usize,
}

impl Adjoint {
    pub(super) fn new(
        sim: &Integrator,
        grouping: Grouping,
        unscaled: Option<Vec<f64>>,
        (damping, friction): (bool, usize),
    ) -> Result<Self, FitError> {
        let kmat = sim.assembly().stiffness_matrix();
        let damped = (sim.options().gamma != 0.0).then(|| (kmat.clone(), kmat.clone()));
        Ok(Self {
            reduced: sim.dofs().reduced_matrix(&kmat)?,
            damped,
            kmat,
            mass: sim.mass().clone(),
            grouping,
            unscaled,
            damping,
            friction,
        })
    }

    /// With stiffness damping, the derivative of the damping force `-gamma K(x) v` in `x`:
    /// `D_v K = d/de K(x + e v)` (symmetric, a third derivative of the energy along `v`) by
    /// [`Integrator::stiffness_derivative`] into the first matrix of `damped`, and the
    /// Newton matrix's stiffness part `K + s D_v K` into the second (with `s = dt gamma / (dt
    /// + gamma)`, so that `A = (1 + dt alpha) M + dt (dt + gamma) (K + s D_v K)`).
    pub(super) fn damping_terms(
        &mut self,
        sim: &mut Integrator,
        next: &State,
        s: f64,
    ) -> Result<(), deform_assembly::AssemblyError> {
        let Some((dvk, a)) = &mut self.damped else {
            return Ok(());
        };
        sim.stiffness_derivative(&next.x, &next.v, &self.kmat, dvk)?;
        let k = self.kmat.csr().data();
        for ((a, h), k) in a.values_mut().iter_mut().zip(dvk.csr().data()).zip(k) {
            *a = k + s * h;
        }
        Ok(())
    }

    /// The contact potential's Hessian at the end `to` of the step from `from` (the barrier's
    /// and friction's, lagged at `from`), added to the reduced matrix as the integrator adds
    /// it to Newton's (`dt^2` times its blocks): the vertex blocks in place, the couplings of
    /// self-contact and mesh pairs into a new matrix on the wider pattern (returned).
    /// Nothing without contact.
    pub(super) fn add_contact<'s>(
        &mut self,
        sim: &'s Integrator,
        (from, to): (&State, &State),
        dt: f64,
    ) -> Result<ContactTerms<'s>, String> {
        let c = match step_contact(sim, (from, to), dt) {
            Ok(Some(c)) => c,
            Ok(None) => return Ok((None, None)),
            Err(e) => return Err(format!("contact: {e}")),
        };
        let dofs = sim.dofs();
        let text = |e: deform_assembly::AssemblyError| e.to_string();
        let h = &c.hessian;
        self.reduced
            .add_vertex_blocks(dofs, &h.vertex, dt * dt)
            .map_err(text)?;
        let coupled = (!h.coupling.is_empty())
            .then(|| self.reduced.with_couplings(dofs, &h.coupling, dt * dt))
            .transpose()
            .map_err(text)?;
        Ok((Some(c), coupled))
    }

    /// Backward (adjoint) through the rollout's steps, see the module docs; adds
    /// `dL/dc` to `grad` and returns the adjoints `dL/dx`, `dL/dv` of the start state (zero
    /// on constrained DOFs).
    pub(super) fn backward(
        &mut self,
        sim: &mut Integrator,
        solver: &mut Cholesky,
        r: &Rollout<'_>,
        grad: &mut [f64],
    ) -> Result<(Vec<f64>, Vec<f64>), FitError> {
        let dt = sim.options().dt;
        let (alpha, gamma) = (sim.options().alpha, sim.options().gamma);
        let n = sim.assembly().num_dofs();
        let len = r.states.len() - 1;
        let (ti, start) = (r.trajectory, r.start);
        let mut adj_x = r.dl_dx[len].clone();
        let mut adj_v = r.dl_dv[len].clone();
        for k in (0..len).rev() {
            let next = &r.states[k + 1];
            let fail = |e: deform_assembly::AssemblyError| FitError::Assembly {
                trajectory: ti,
                step: start + k + 1,
                source: e,
            };
            let asm = sim.assembly_mut();
            asm.stiffness(&next.x, Tangent::Exact, &mut self.kmat)
                .map_err(fail)?;
            self.damping_terms(sim, next, dt * gamma / (dt + gamma))
                .map_err(fail)?;
            let a_stiffness = self.damped.as_ref().map_or(&self.kmat, |(_, a)| a);
            let dofs = sim.dofs();
            sim.assembly()
                .combine_reduced(
                    1.0 + dt * alpha,
                    &self.mass,
                    dt * gamma + dt * dt,
                    a_stiffness,
                    dofs,
                    &mut self.reduced,
                )
                .map_err(fail)?;
            let (contact, coupled) =
                self.add_contact(sim, (&r.states[k], next), dt)
                    .map_err(|reason| FitError::Data {
                        index: ti,
                        reason: format!("step {}: {reason}", start + k + 1),
                    })?;
            let matrix = coupled.as_ref().unwrap_or(&self.reduced.matrix);
            // g = dL/dv_{k+1} in total: its own term plus the path through x_{k+1}.
            let g: Vec<f64> = (0..n).map(|i| adj_v[i] + dt * adj_x[i]).collect();
            let mut g_free = vec![0.0; dofs.num_free()];
            dofs.restrict(&g, &mut g_free).map_err(fail)?;
            let solve_fail = |source| FitError::Solve {
                trajectory: ti,
                step: start + k,
                source,
            };
            solver.factorize(matrix).map_err(solve_fail)?;
            let mut lambda_free = vec![0.0; g_free.len()];
            solver
                .solve(matrix, &g_free, &mut lambda_free)
                .map_err(solve_fail)?;
            let mut lambda = vec![0.0; n];
            dofs.scatter(&lambda_free, &mut lambda).map_err(fail)?;
            // dL/dc += dt lambda^T (J_f - gamma J_k) at the step's end state.
            let asm = sim.assembly();
            let jf = asm
                .term_vjp(&next.x, None, &lambda, &self.grouping)
                .map_err(fail)?;
            let jk = if gamma != 0.0 {
                asm.term_vjp(&next.x, Some(&next.v), &lambda, &self.grouping)
                    .map_err(fail)?
            } else {
                vec![0.0; jf.len()]
            };
            for ((gj, f), kv) in grad.iter_mut().zip(&jf).zip(&jk) {
                *gj += dt * (f - gamma * kv);
            }
            if let Some(own) = &self.unscaled {
                // dL/ds_v = -lambda_v . m_v (v^k+1 - v^k + dt alpha v^k+1 - dt g).
                let (prev, g) = (&r.states[k].v, sim.gravity());
                let scales = &mut grad[jf.len()..jf.len() + own.len()];
                for (v, (gs, m)) in scales.iter_mut().zip(own).enumerate() {
                    let dr: f64 = (0..3)
                        .map(|d| {
                            let i = 3 * v + d;
                            let u = next.v[i];
                            lambda[i] * (u - prev[i] + dt * alpha * u - dt * g[d])
                        })
                        .sum();
                    *gs -= m * dr;
                }
            }
            if self.damping {
                // dL/dalpha = -dt lambda^T M v, dL/dgamma = -dt lambda^T K v (K as above).
                let mut mv = vec![0.0; n];
                sim.assembly()
                    .mass_apply(&self.mass, &next.v, &mut mv)
                    .map_err(fail)?;
                let mut kv = vec![0.0; n];
                deform_solvers::LinearOperator::apply(self.kmat.csr(), &next.v, &mut kv);
                let dot = |a: &[f64]| lambda.iter().zip(a).map(|(l, x)| l * x).sum::<f64>();
                let first = grad.len() - 2 - self.friction;
                grad[first] -= dt * dot(&mv);
                grad[first + 1] -= dt * dot(&kv);
            }
            // Adjoints of the state at k: x_{k+1} = x_k + dt v_{k+1} passes adj_x on;
            // dr/dx_k = dt (K + gamma D_v K) and dr/dv_k = -M enter through lambda.
            // Constrained DOFs are prescribed: their adjoints vanish.
            let mut k_lambda = vec![0.0; n];
            deform_solvers::LinearOperator::apply(self.kmat.csr(), &lambda, &mut k_lambda);
            if let Some((dvk, _)) = &self.damped {
                let mut h_lambda = vec![0.0; n];
                deform_solvers::LinearOperator::apply(dvk.csr(), &lambda, &mut h_lambda);
                for (k, h) in k_lambda.iter_mut().zip(&h_lambda) {
                    *k += gamma * h;
                }
            }
            // Friction's lag makes the step's forces depend on its start as well.
            let mut lag_term = vec![0.0; n];
            if let Some(c) = &contact {
                let tail = grad.len() - self.friction;
                c.add_friction_gradient(&next.x, &lambda, dt, &mut grad[tail..]);
                c.hessian.add_product(1.0, &lambda, &mut k_lambda);
                let ends = (r.states[k].x.as_slice(), next.x.as_slice());
                (c.model
                    .add_friction_start_vjp(&c.lag, ends, &lambda, &mut lag_term))
                .map_err(|e| FitError::Data {
                    index: ti,
                    reason: format!("step {}: contact: {e}", start + k + 1),
                })?;
            }
            let mut m_lambda = vec![0.0; n];
            sim.assembly()
                .mass_apply(&self.mass, &lambda, &mut m_lambda)
                .map_err(fail)?;
            for i in 0..n {
                adj_x[i] = r.dl_dx[k][i] + adj_x[i] - dt * k_lambda[i] + dt * lag_term[i];
                adj_v[i] = r.dl_dv[k][i] + m_lambda[i];
            }
            for v in sim.dofs().constrained_vertices() {
                for d in 0..3 {
                    adj_x[3 * v + d] = 0.0;
                    adj_v[3 * v + d] = 0.0;
                }
            }
        }
        Ok((adj_x, adj_v))
    }
}

/// A step's contact and, with couplings, the adjoint system on the wider pattern.
pub(super) type ContactTerms<'s> = (Option<StepContact<'s>>, Option<sprs::CsMat<f64>>);

/// The contact of one step of a rollout: the potential as the integrator placed it, the
/// friction lagged at the step's start, the Hessian at its end.
pub(super) struct StepContact<'s> {
    pub(super) model: std::borrow::Cow<'s, deform_integrator::ContactModel>,
    pub(super) lag: deform_integrator::FrictionLag,
    pub(super) hessian: deform_integrator::ContactHessian,
}

impl StepContact<'_> {
    /// `grad[o] += dt lambda . f_o / mu_o` for each frictional obstacle `o` whose
    /// coefficient is fitted (`grad` holds one per obstacle, or none): `-lambda . dr/dmu_o`
    /// with the step's friction forces `f_o` at `x1` of the pairs lagged against `o`, which
    /// are `mu_o` times those at unit `mu`.
    pub(super) fn add_friction_gradient(
        &self,
        x1: &[f64],
        lambda: &[f64],
        dt: f64,
        grad: &mut [f64],
    ) {
        let Some((mu, _)) = self.model.friction().filter(|_| !grad.is_empty()) else {
            return;
        };
        for (o, g) in grad.iter_mut().enumerate().filter(|&(o, _)| mu[o] > 0.0) {
            let pairs = self.lag.pairs.iter().filter(|p| p.obstacle == o);
            let lag = deform_integrator::FrictionLag::default()
                .pairs(pairs.cloned().collect())
                .threshold(self.lag.threshold);
            let mut f = vec![0.0; x1.len()];
            self.model.add_friction(&lag, x1, Some(&mut f), None);
            let work: f64 = lambda.iter().zip(&f).map(|(l, f)| l * f).sum();
            *g += dt * work / mu[o];
        }
    }
}

/// [`StepContact`] of the step from `from` to `to` (moving obstacles where the integrator
/// had them), or `None` without contact.
pub(super) fn step_contact<'s>(
    sim: &'s Integrator,
    (from, to): (&State, &State),
    dt: f64,
) -> Result<Option<StepContact<'s>>, deform_integrator::ContactError> {
    let Some(model) = sim.contact() else {
        return Ok(None);
    };
    let model = crate::fit::placed_for_step(model, from.t, to.t);
    // The exact barrier Hessian (the adjoint solve factorises indefinite systems): the
    // projected one Newton takes is not the residual's derivative where distances curve.
    let mut hessian = deform_integrator::ContactHessian::default();
    model.exact_hessian(&to.x, &mut hessian)?;
    let lag = model.lag_friction(&from.x, dt);
    model.add_friction(&lag, &to.x, None, Some(&mut hessian));
    Ok(Some(StepContact {
        model,
        lag,
        hessian,
    }))
}
