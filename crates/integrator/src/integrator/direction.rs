//! Newton's direction: the Newton matrix (`c_m M + c_k K`, with the damping's shift and
//! contact's blocks), the policy's linear solve with the direct fallback and the switch to
//! the projected tangent, and counterfactual candidate solves.

use super::*;

impl Integrator {
    /// Newton's K at the iterate `(x, u)` alone (see [`Integrator::newton_matrix`]), when
    /// the residual came from the line search's trial.
    pub(super) fn newton_stiffness(
        &mut self,
        mode: Mode,
        x: &[f64],
        u: &[f64],
        tangent: Tangent,
    ) -> Result<(), StageError> {
        let shift = self.damping_shift(mode, u, tangent);
        let outputs = Outputs {
            stiffness: Some(&mut self.k),
            tangent,
            stiffness_shift: shift,
            ..Outputs::default()
        };
        self.asm.evaluate(x, outputs)?;
        self.add_contact(x, None, true)?;
        Ok(())
    }

    /// Rayleigh stiffness damping of this solve: `gamma` at the step (0 when static).
    pub(super) fn stiffness_damping(&self, mode: Mode) -> f64 {
        match mode {
            Mode::Dynamic { dt } => self.options.stiffness_damping(dt),
            Mode::Static => 0.0,
        }
    }

    /// With positive stiffness damping and the exact tangent, the shift that makes the
    /// assembled K Newton's `K + s D_u K` (see [`Integrator::newton_matrix`]); `None`
    /// otherwise, or when `u` is 0 (no derivative along it).
    pub(super) fn damping_shift<'a>(
        &self,
        mode: Mode,
        u: &'a [f64],
        tangent: Tangent,
    ) -> Option<StiffnessShift<'a>> {
        let Mode::Dynamic { dt } = mode else {
            return None;
        };
        let gamma = self.options.stiffness_damping(dt);
        let speed = u.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        (gamma > 0.0 && tangent == Tangent::Exact && speed > 0.0).then(|| StiffnessShift {
            direction: u,
            step: self.difference_step / speed,
            scale: dt * gamma / (dt + gamma),
        })
    }

    /// Stage 3: the Newton matrix `c_m M + c_k K` on the free DOFs, refilled in place;
    /// returns `(c_m, c_k)`.
    ///
    /// It is the residual's Jacobian in `u`. Dynamic: `c_m = 1 + dt alpha`,
    /// `c_k = dt (dt + gamma)`, and with positive stiffness damping and the exact tangent the K
    /// assembled at the iterate is `K + s D_u K` with `s = dt gamma / (dt + gamma)`: `D_u K`
    /// (by a forward difference in the same element pass, [`StiffnessShift`]) is the
    /// derivative of the damping force `-gamma K(x) u` in `x`. Without it Newton converges
    /// only linearly when `gamma != 0` (a fitted coarse model took 1.6x the iterations). It
    /// is left out with the projected tangent (whose derivative is not the energy's), in
    /// matrix-free solves, which apply the element tangents' `c_m M + c_k K`, and for
    /// negative gamma: that damping gives energy back (Backward Euler's own dissipation, at
    /// a coarse step), `s` is negative (`-dt` at `gamma = -dt/2`), and on fast states the
    /// exact matrix sent Newton into inverted elements (a 4x-step coarse fit failed at its
    /// first rollout, also with a line search on the residual's norm) where `c_m M + c_k K`,
    /// positive definite, converges slowly, or on the fastest states not at all: there the
    /// residual wanders, and the step's equation may have no solution near the start.
    pub(super) fn newton_matrix(&mut self, mode: Mode) -> Result<(f64, f64), AssemblyError> {
        let o = &self.options;
        let (c_m, c_k) = match mode {
            Mode::Dynamic { dt } => (1.0 + dt * o.alpha, dt * o.stiffness_damping(dt) + dt * dt),
            Mode::Static => (0.0, 1.0),
        };
        self.asm
            .combine_reduced(c_m, &self.mass, c_k, &self.k, &self.dofs, &mut self.a_free)?;
        if let Some(c) = &mut self.contact {
            let scale = contact_scale(mode);
            self.a_free
                .add_vertex_blocks(&self.dofs, &c.hessian.vertex, scale)?;
            c.coupled = if c.hessian.coupling.is_empty() {
                None
            } else {
                Some(
                    self.a_free
                        .with_couplings(&self.dofs, &c.hessian.coupling, scale)?,
                )
            };
        }
        Ok((c_m, c_k))
    }

    /// `D_v K = d/de K(x + e v)` at `e = 0` into `out`, from `k`, the exact-tangent K at `x`:
    /// the derivative of `K(x) w` in `x` along `v` is `D_v K w` (symmetric: a third derivative
    /// of the energy). A forward difference whose largest displacement is 1e-7 of the rest
    /// shape's size, the one Newton's matrix uses ([`StiffnessShift`]): one assembly.
    ///
    /// # Errors
    /// As [`Assembly::evaluate`] at `x`.
    pub fn stiffness_derivative(
        &mut self,
        x: &[f64],
        v: &[f64],
        k: &StiffnessMatrix,
        out: &mut StiffnessMatrix,
    ) -> Result<(), AssemblyError> {
        if k.nnz() != out.nnz() {
            return Err(AssemblyError::PatternMismatch);
        }
        let speed = v.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        if speed == 0.0 {
            out.values_mut().fill(0.0);
            return Ok(());
        }
        let shift = StiffnessShift {
            direction: v,
            step: self.difference_step / speed,
            scale: 1.0,
        };
        let outputs = Outputs {
            stiffness: Some(out),
            stiffness_shift: Some(shift),
            ..Outputs::default()
        };
        self.asm.evaluate(x, outputs)?;
        // `K + D_v K` less K: rounding of about 1e-16 |K| against |D_v K|.
        for (d, k) in out.values_mut().iter_mut().zip(k.csr().data()) {
            *d -= k;
        }
        Ok(())
    }

    /// Stage 4: the policy's solver on `-r` into `w.du_free`, the direct fallback when it
    /// fails, the candidates' counterfactual solves. `None` when the exact tangent failed
    /// (indefinite, or not a descent direction) and `Projection::WhenNeeded` switches to the
    /// projected one; the failed work goes to `discarded`.
    pub(super) fn direction(
        &mut self,
        point: NewtonPoint<'_>,
        context: &IterationContext,
        report: &StepReport,
        discarded: &mut Vec<CandidateOutcome>,
        w: &mut Work,
    ) -> Result<Option<Direction>, StepError> {
        // `WhenNeeded` switches to the projected tangent once per step at most.
        let can_project = self.options.newton.project == Projection::WhenNeeded
            && point.tangent == Tangent::Exact;
        for (b, r) in w.rhs.iter_mut().zip(&w.r_free) {
            *b = -r;
        }
        let decision = self
            .policy
            .choose(&context.policy(self.dofs.num_free(), &report.iterations));
        w.du_free.iter_mut().for_each(|v| *v = 0.0);
        let attempt = self.linear_solve(point, &decision, &w.rhs, &mut w.du_free);
        let attempt = match attempt {
            Err(failed)
                if self.options.fallback_to_direct
                    && decision.solver != fallback_spec()
                    && !(can_project && failed.error.is_indefinite()) =>
            {
                discarded.push(failed.outcome(&decision.solver));
                w.du_free.iter_mut().for_each(|v| *v = 0.0);
                self.linear_solve(
                    point,
                    &Decision::solver(fallback_spec()),
                    &w.rhs,
                    &mut w.du_free,
                )
                .map(|(setup, solve)| (setup, solve, true))
            }
            other => other.map(|(setup, solve)| (setup, solve, false)),
        };
        let (setup, solve, fallback) = match attempt {
            Ok(done) => done,
            Err(failed) if can_project && failed.error.is_indefinite() => {
                discarded.push(failed.outcome(&decision.solver));
                return Ok(None);
            }
            Err(failed) => {
                return Err(StepError::Solver {
                    source: failed.error,
                    report: Box::new(report.clone()),
                });
            }
        };
        // An indefinite exact tangent can also give an ascent direction without failing.
        let slope: f64 = w.r_free.iter().zip(&w.du_free).map(|(a, b)| a * b).sum();
        if can_project && slope >= 0.0 {
            discarded.push(CandidateOutcome {
                solver: decision.solver.clone(),
                setup: Some(setup),
                solve: Some(solve),
                error: Some(format!("not a descent direction (r . du = {slope:e})")),
                distance: f64::INFINITY,
            });
            return Ok(None);
        }
        let candidates = if self.candidates.is_empty() {
            Vec::new()
        } else {
            self.run_candidates(point, &w.rhs, &w.du_free)
        };
        Ok(Some(Direction {
            solver: if fallback {
                fallback_spec()
            } else {
                decision.solver
            },
            setup,
            solve,
            fallback,
            slope,
            candidates,
        }))
    }

    /// Factorises (or sets up) and solves with the kept solver of `spec`.
    pub(super) fn linear_solve(
        &mut self,
        point: NewtonPoint<'_>,
        decision: &Decision,
        rhs: &[f64],
        x: &mut [f64],
    ) -> Result<(SetupStats, SolveStats), FailedSolve> {
        let (system, solvers, _) = self.system(point);
        system.solve(solvers, decision, rhs, x)
    }

    /// The Newton system at `point`, and the kept solver instances (the policy's and the
    /// counterfactual candidates'), borrowed apart.
    pub(super) fn system<'a>(
        &'a mut self,
        point: NewtonPoint<'a>,
    ) -> (System<'a>, &'a mut KeptSolvers, &'a mut KeptSolvers) {
        (
            System {
                asm: &self.asm,
                mass: &self.mass,
                dofs: &self.dofs,
                rest: &self.rest,
                options: &self.options,
                a_free: self
                    .contact
                    .as_ref()
                    .and_then(|c| c.coupled.as_ref())
                    .unwrap_or(&self.a_free.matrix),
                contact: self.contact.as_ref().map(|c| &c.hessian),
                secant: self.contact.as_ref().map(|c| Secant {
                    model: &c.model,
                    dofs: &self.dofs,
                    x: point.x,
                    scale: point.position_scale,
                    c_contact: point.c_contact,
                    rounds: self.options.newton.barrier_secant,
                }),
                point,
            },
            &mut self.solvers,
            &mut self.candidates,
        )
    }

    /// Runs every counterfactual candidate on the current system.
    pub(super) fn run_candidates(
        &mut self,
        point: NewtonPoint<'_>,
        rhs: &[f64],
        chosen: &[f64],
    ) -> Vec<CandidateOutcome> {
        let specs: Vec<SolverSpec> = self.candidates.iter().map(|(s, _)| s.clone()).collect();
        let chosen_norm = chosen.iter().map(|v| v * v).sum::<f64>().sqrt();
        let (system, _, candidates) = self.system(point);
        specs
            .iter()
            .map(|spec| {
                let mut x = vec![0.0; rhs.len()];
                let outcome =
                    system.solve(candidates, &Decision::solver(spec.clone()), rhs, &mut x);
                match outcome {
                    Ok((setup, solve)) => {
                        let diff = x
                            .iter()
                            .zip(chosen)
                            .map(|(a, b)| (a - b).powi(2))
                            .sum::<f64>()
                            .sqrt();
                        CandidateOutcome {
                            solver: spec.clone(),
                            setup: Some(setup),
                            solve: Some(solve),
                            error: None,
                            distance: diff / chosen_norm.max(f64::MIN_POSITIVE),
                        }
                    }
                    Err(failed) => failed.outcome(spec),
                }
            })
            .collect()
    }
}

/// A Newton direction found (in `Work::du_free`) and what finding it cost.
pub(super) struct Direction {
    pub(super) solver: SolverSpec,
    pub(super) setup: SetupStats,
    pub(super) solve: SolveStats,
    pub(super) fallback: bool,
    /// `r . du`: negative for a descent direction.
    pub(super) slope: f64,
    pub(super) candidates: Vec<CandidateOutcome>,
}

/// The linear system of a Newton iteration: the assembled reduced matrix, or the same matrix
/// applied element by element at `point` for matrix-free configurations.
pub(super) struct System<'a> {
    pub(super) asm: &'a Assembly,
    pub(super) mass: &'a Mass,
    pub(super) dofs: &'a DofMap,
    /// Rest positions, for geometric orderings of new direct solvers.
    pub(super) rest: &'a [Vector3<f64>],
    pub(super) options: &'a IntegratorOptions,
    pub(super) a_free: &'a CsMat<f64>,
    /// Contact's Hessian blocks at the point (for matrix-free solves).
    pub(super) contact: Option<&'a deform_contact::ContactHessian>,
    /// The barrier's secant rounds, with contact.
    pub(super) secant: Option<Secant<'a>>,
    pub(super) point: NewtonPoint<'a>,
}

impl System<'_> {
    /// Solves with the instance of the decision's solver kept in `list`, on the operator
    /// it asks for.
    pub(super) fn solve(
        &self,
        list: &mut KeptSolvers,
        decision: &Decision,
        rhs: &[f64],
        x: &mut [f64],
    ) -> Result<(SetupStats, SolveStats), FailedSolve> {
        if !decision.solver.is_matrix_free() {
            return solve_with(list, self, self.a_free, decision, rhs, x);
        }
        // The operator adds a diagonal mass: lumped only.
        if self.options.mass != MassKind::Lumped {
            return Err(
                SolverError::Unsupported("matrix-free Newton solves need the lumped mass").into(),
            );
        }
        let p = self.point;
        let tangents = self.asm.tangents(p.x, p.tangent).map_err(|_| {
            FailedSolve::from(SolverError::Unsupported(
                "element tangents failed at this point",
            ))
        })?;
        let op = MatrixFreeNewton::new(self.asm, tangents, self.mass, p.c_m, p.c_k)
            .with_contact(self.contact, p.c_contact);
        let reduced = Restricted::new(&op, self.dofs);
        solve_with(list, self, &reduced, decision, rhs, x)
    }
}

/// Factorises (or sets up) and solves with the instance of the decision's solver kept in
/// `list` (built on first use), refreshed and with its tolerance set as the decision says.
pub(super) fn solve_with(
    list: &mut KeptSolvers,
    system: &System<'_>,
    a: &dyn LinearOperator,
    decision: &Decision,
    rhs: &[f64],
    x: &mut [f64],
) -> Result<(SetupStats, SolveStats), FailedSolve> {
    let spec = &decision.solver;
    let index = match list.iter().position(|(s, _)| s == spec) {
        Some(i) => i,
        None => {
            let mut solver = spec.build()?;
            // The free vertices' rest positions, in row order: geometric nested dissection.
            let coordinates: Vec<[f64; 3]> = system
                .dofs
                .free_dofs()
                .iter()
                .step_by(3)
                .map(|&d| {
                    let p = system.rest[d / 3];
                    [p.x, p.y, p.z]
                })
                .collect();
            solver.set_coordinates(Some(&coordinates));
            list.push((spec.clone(), solver));
            list.len() - 1
        }
    };
    let solver = &mut list[index].1;
    if decision.refresh {
        solver.refresh();
    }
    if let Some(rel) = decision.rel_tolerance {
        solver.set_relative_tolerance(rel)?;
    }
    solver.set_residual_floor(system.point.floor);
    let setup = solver.factorize(a)?;
    // The barrier's secant rounds where there are contacts. A direct solver's factor is of
    // `a` alone: its rounds are a few conjugate-gradient iterations preconditioned by it
    // (docs/theory.md, "Contact").
    let solved = match &system.secant {
        Some(secant) if secant.rounds > 0 && system.contact.is_some_and(|h| !h.is_empty()) => {
            let direct = matches!(spec, SolverSpec::Direct { .. });
            secant::solve(
                secant,
                solver.as_mut(),
                a,
                rhs,
                x,
                system.point.floor,
                direct,
            )
        }
        _ => solver.solve(a, rhs, x),
    };
    match solved {
        Ok(stats) => Ok((setup, stats)),
        Err(error) => Err(FailedSolve {
            setup: Some(setup),
            error,
        }),
    }
}

/// A linear solve that failed, with what it had spent: its set-up, when that succeeded, and
/// the solve's statistics inside the error (`SolverError::stats`).
#[derive(Debug)]
pub(super) struct FailedSolve {
    pub(super) setup: Option<SetupStats>,
    pub(super) error: SolverError,
}

impl FailedSolve {
    /// As a candidate outcome (its cost, why it failed).
    pub(super) fn outcome(&self, spec: &SolverSpec) -> CandidateOutcome {
        CandidateOutcome {
            solver: spec.clone(),
            setup: self.setup.or_else(|| self.error.spent().copied()),
            solve: self.error.stats().cloned(),
            error: Some(self.error.to_string()),
            distance: f64::INFINITY,
        }
    }
}
