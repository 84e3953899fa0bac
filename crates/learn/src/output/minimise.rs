//! The minimiser: argmin's L-BFGS on the coefficients' log-distances to their bounds, with a
//! trust region on trial points, backing off from trial points that do not simulate, and the
//! public fits built on it ([`fit_output_error`], [`fit_output_error_field`]).

use super::*;

/// argmin sees `p_i = ln |c_i - l_i|` of the coefficients off their bound `l_i` (zero for
/// the material's, `-dt / 2` for Rayleigh gamma): every trial point keeps its side of the
/// bound, and a coefficient that starts on it stays there. With estimated starts
/// ([`OutputErrorOptions::starts`]) their offsets follow, in units of the data's motion per
/// step (positions) and that over `dt` (velocities), so all parameters have comparable
/// scales.
pub(super) struct LogProblem<'p, 'a> {
    pub(super) objective: &'p OutputError<'a>,
    /// The starting coefficients (their sides of the bounds).
    pub(super) start: Vec<f64>,
    /// The bounds.
    pub(super) lower: Vec<f64>,
    /// The optimiser's starting point ([`LogProblem::parameters`]).
    pub(super) p0: Vec<f64>,
    /// The offset per unit of each start-offset parameter (empty without estimated starts):
    /// the data's motion per step for positions, that over `dt` for velocities.
    pub(super) units: Vec<f64>,
    /// The last loss and gradient (in `p`) of a point that simulated, which a trial point
    /// that does not simulate falls back on.
    pub(super) last_good: RefCell<Option<(f64, Vec<f64>)>>,
    /// Calls of [`LogProblem::evaluate`] so far, simulated or not.
    pub(super) calls: std::cell::Cell<usize>,
    /// The best loss that counted as progress and the evaluation that found it
    /// ([`OutputErrorOptions::patience`]).
    pub(super) progress: std::cell::Cell<(f64, usize)>,
    /// The trust region of trial points: the best point so far (its coefficients' log
    /// parameters), its loss and the radius ([`TRUST_RADIUS`]).
    pub(super) trust: RefCell<(Vec<f64>, f64, f64)>,
}

/// The first trust radius (in natural log) of [`LogProblem`]: a trial point that moves a
/// coefficient by more than a factor of 10 from the best point so far is not simulated but
/// treated as failed (a loss far above, the last good gradient), so the line search backs
/// off at no cost. L-BFGS's first step has no curvature to scale it: it went to the 1e6x
/// bound and spent hundreds of Newton iterations on trials no data could be about. Each new
/// best point doubles the radius, up to [`MAX_LOG_DISTANCE`].
pub(super) const TRUST_RADIUS: f64 = std::f64::consts::LN_10;

/// The relative drop of the best loss that counts as progress for
/// [`OutputErrorOptions::patience`].
pub const STALL_IMPROVEMENT: f64 = 1e-6;

/// Calls of [`LogProblem::evaluate`] allowed per evaluation of the budget. A trial point
/// asks for its cost and then its gradient (two calls, one simulation); a point that is not
/// finite, or whose projection is cached, simulates nothing, so the budget alone would let a
/// line search that keeps proposing such points (moving only a coefficient pressed against
/// its bound) run for ever.
pub(super) const CALLS_PER_EVALUATION: usize = 4;

/// The loss a trial point that cannot be simulated gets, over the last good loss: far
/// above, so the line search brackets and backs off (an infinite loss would stop it).
pub(super) const FAILED_TRIAL_FACTOR: f64 = 1e6;

/// How far (in natural log) a coefficient may move from where the fit started: a factor of
/// 1e6 (its offset from the bound, for gamma). A trial point further out is evaluated on
/// this bound (projected), where the loss is continued flat outwards: the gradient's
/// outward component is zero, so a coefficient pressed against it (gamma at `-dt / 2`
/// within a millionth of its start's offset) stays there while the others keep improving,
/// and a line search that overshoots (a trial mu of 1e13 Pa) never simulates a model no
/// data can be about.
pub(super) const MAX_LOG_DISTANCE: f64 = 13.815510557964274;

impl LogProblem<'_, '_> {
    pub(super) fn new<'p, 'a>(objective: &'p OutputError<'a>, start: &[f64]) -> LogProblem<'p, 'a> {
        let offsets = objective.num_start_parameters();
        let units = if offsets > 0 {
            // Per rollout, the positions then the velocities of every DOF.
            let n = objective.sim.borrow().assembly().num_dofs();
            let x = objective.motion_scale();
            let v = x / objective.sim.borrow().options().dt;
            let rollout = [vec![x; n], vec![v; n]].concat();
            rollout.repeat(offsets / (2 * n))
        } else {
            Vec::new()
        };
        let mut problem = LogProblem {
            objective,
            start: start.to_vec(),
            lower: objective.bounds(),
            p0: Vec::new(),
            units,
            last_good: RefCell::new(None),
            calls: std::cell::Cell::new(0),
            progress: std::cell::Cell::new((f64::INFINITY, 0)),
            trust: RefCell::new((Vec::new(), f64::INFINITY, TRUST_RADIUS)),
        };
        let off = |i: usize| (problem.start[i] - problem.lower[i]).abs().ln();
        let mut p0: Vec<f64> = problem.active().map(off).collect();
        problem.trust.borrow_mut().0 = p0.clone();
        p0.resize(p0.len() + problem.units.len(), 0.0);
        problem.p0 = p0;
        problem
    }

    /// Whether `p` moves a coefficient beyond the trust radius of the best point so far.
    pub(super) fn outside_trust(&self, p: &[f64]) -> bool {
        let (centre, _, radius) = &*self.trust.borrow();
        centre.iter().zip(p).any(|(c, p)| (p - c).abs() > *radius)
    }

    /// Moves the trust region to `p` and widens it when `loss` is the best so far.
    pub(super) fn update_trust(&self, p: &[f64], loss: f64) {
        let (centre, best, radius) = &mut *self.trust.borrow_mut();
        if loss < *best {
            if best.is_finite() {
                *radius = (2.0 * *radius).min(MAX_LOG_DISTANCE);
            }
            *best = loss;
            let n = centre.len();
            centre.copy_from_slice(&p[..n]);
        }
    }

    /// The start offsets of parameters `p` (`None` without estimated starts).
    pub(super) fn start_offsets(&self, p: &[f64]) -> Option<Vec<f64>> {
        if self.units.is_empty() {
            return None;
        }
        let q = &p[p.len() - self.units.len()..];
        Some(q.iter().zip(&self.units).map(|(v, u)| v * u).collect())
    }

    /// Loss and gradient in `p`; at a point that cannot be simulated, a loss far above the
    /// last good one with its gradient (pointing back towards it).
    pub(super) fn evaluate(&self, p: &[f64]) -> Result<(f64, Vec<f64>), FitError> {
        let budget = self.objective.options.max_evaluations;
        self.calls.set(self.calls.get() + 1);
        if self.calls.get() > CALLS_PER_EVALUATION * budget {
            return Err(FitError::Trials {
                calls: self.calls.get() - 1,
            });
        }
        let c = self.coefficients(p);
        let offsets = self.start_offsets(p);
        let not_finite = p.iter().any(|v| !v.is_finite());
        let untrusted = !not_finite && self.outside_trust(p);
        let evaluated = if not_finite {
            Err(FitError::Coefficients {
                coefficients: c.clone(),
                reason: "a trial step that is not finite".into(),
            })
        } else if untrusted {
            Err(FitError::Coefficients {
                coefficients: c.clone(),
                reason: "a trial step beyond the trust region".into(),
            })
        } else {
            self.objective.evaluate_with_starts(&c, offsets.as_deref())
        };
        let (loss, mut g) = match evaluated {
            Ok((loss, g, gs)) => {
                let mut g: Vec<f64> = self
                    .active()
                    .map(|i| g[i] * (c[i] - self.lower[i]))
                    .collect();
                // d offset / d q is the offset's unit.
                g.extend(gs.iter().zip(&self.units).map(|(g, u)| g * u));
                *self.last_good.borrow_mut() = Some((loss, g.clone()));
                self.update_trust(p, loss);
                self.check_progress(loss)?;
                (loss, g)
            }
            Err(e) if e.is_failed_simulation() || not_finite || untrusted => {
                let Some((loss, g)) = self.last_good.borrow().clone() else {
                    return Err(e);
                };
                if !untrusted {
                    *self.objective.failed_trials.borrow_mut() += 1;
                }
                (FAILED_TRIAL_FACTOR * loss.abs().max(f64::MIN_POSITIVE), g)
            }
            Err(e) => return Err(e),
        };
        // Flat beyond the bounded log-step (see MAX_LOG_DISTANCE); the start offsets after
        // the coefficients are not bounded.
        if !not_finite {
            let coefficients = self.p0.len() - self.units.len();
            for (g, (p, q)) in g.iter_mut().zip(p.iter().zip(&self.p0)).take(coefficients) {
                if (p - q).abs() > MAX_LOG_DISTANCE {
                    *g = 0.0;
                }
            }
        }
        Ok((loss, g))
    }

    /// Records a simulated `loss`; [`FitError::Stalled`] when the last
    /// [`OutputErrorOptions::patience`] evaluations made no progress.
    pub(super) fn check_progress(&self, loss: f64) -> Result<(), FitError> {
        let evaluation = *self.objective.evaluations.borrow();
        let (best, at) = self.progress.get();
        if loss < best * (1.0 - STALL_IMPROVEMENT) {
            self.progress.set((loss, evaluation));
            return Ok(());
        }
        let patience = self.objective.options.patience;
        if patience > 0 && evaluation >= at + patience {
            *self.objective.stopped_by.borrow_mut() = Some(Termination::Stalled { patience });
            return Err(FitError::Stalled { patience });
        }
        Ok(())
    }

    pub(super) fn active(&self) -> impl Iterator<Item = usize> + '_ {
        (0..self.start.len()).filter(|&i| self.start[i] != self.lower[i])
    }

    pub(super) fn coefficients(&self, p: &[f64]) -> Vec<f64> {
        from_log(&self.start, &self.lower, p)
    }

    /// The optimiser's starting point: the coefficients, and the data's starts.
    pub(super) fn parameters(&self) -> Vec<f64> {
        self.p0.clone()
    }

    /// The RMS position offset of the free DOFs' starts at `p` (m).
    pub(super) fn start_correction(&self, p: &[f64]) -> Option<f64> {
        let o = self.start_offsets(p)?;
        let sim = self.objective.sim.borrow();
        let n = sim.assembly().num_dofs();
        let rollouts = o.len() / (2 * n);
        let free = (0..n).filter(|i| !sim.dofs().is_constrained(i / 3)).count();
        let sum: f64 = o
            .chunks(2 * n)
            .map(|r| r[..n].iter().map(|v| v * v).sum::<f64>())
            .sum();
        Some((sum / (free * rollouts).max(1) as f64).sqrt())
    }
}

/// The coefficients at log-parameters `p` (see [`LogProblem`]; start offsets after them are
/// ignored), each projected onto its bounded log-step ([`MAX_LOG_DISTANCE`]).
pub(super) fn from_log(start: &[f64], lower: &[f64], p: &[f64]) -> Vec<f64> {
    let mut c = start.to_vec();
    let active = (0..c.len()).filter(|&i| start[i] != lower[i]);
    for (i, v) in active.zip(p) {
        let offset = start[i] - lower[i];
        let p0 = offset.abs().ln();
        let v = v.clamp(p0 - MAX_LOG_DISTANCE, p0 + MAX_LOG_DISTANCE);
        c[i] = lower[i] + offset.signum() * v.exp();
    }
    c
}

impl CostFunction for LogProblem<'_, '_> {
    type Param = Vec<f64>;
    type Output = f64;

    fn cost(&self, p: &Vec<f64>) -> Result<f64, ArgminError> {
        Ok(self.evaluate(p)?.0)
    }
}

impl Gradient for LogProblem<'_, '_> {
    type Param = Vec<f64>;
    type Gradient = Vec<f64>;

    fn gradient(&self, p: &Vec<f64>) -> Result<Vec<f64>, ArgminError> {
        Ok(self.evaluate(p)?.1)
    }
}

/// Records every iteration (argmin wants a `'static` observer, hence the shared vector).
pub(super) struct Recorder {
    pub(super) records: Arc<Mutex<Vec<FitIteration>>>,
    /// Those of the [`LogProblem`].
    pub(super) start: Vec<f64>,
    pub(super) lower: Vec<f64>,
}

impl Observe<IterState<Vec<f64>, Vec<f64>, (), (), (), f64>> for Recorder {
    fn observe_iter(
        &mut self,
        state: &IterState<Vec<f64>, Vec<f64>, (), (), (), f64>,
        _kv: &KV,
    ) -> Result<(), ArgminError> {
        // A failed line search ends the run with the parameters taken out of the state:
        // that iteration moved nowhere and has no iterate to record.
        let Some(p) = state.get_param() else {
            return Ok(());
        };
        self.records
            .lock()
            .expect("not poisoned")
            .push(FitIteration {
                // Iteration 0 is the start, recorded before the run.
                iteration: state.get_iter() + 1,
                loss: state.get_cost(),
                coefficients: from_log(&self.start, &self.lower, p),
            });
        Ok(())
    }
}

/// Fits the term coefficients of `sim`'s uniform material (the Lame pair of a single model,
/// each member's effective pair of an ensemble; see [`term_coefficients`]) to the rollout
/// predictions of `trajectories`, starting from `initial`, with L-BFGS.
/// `progress(evaluation, loss)` is called after every loss evaluation. The fitted material
/// is left in `sim`.
///
/// # Errors
/// [`FitError`] when the data or the first evaluation fail.
pub fn fit_output_error(
    sim: &mut Integrator,
    trajectories: &[&Trajectory],
    initial: &[f64],
    options: OutputErrorOptions,
    progress: impl FnMut(usize, f64),
) -> Result<OutputErrorFit, FitError> {
    let objective = OutputError::new(sim, trajectories, options, progress)?;
    minimise(&objective, initial)
}

/// The material field over `base` with term coefficients `c`: uniform for `groups` `None`,
/// else one model per group (`c` by group, then term) with `groups` the group of each
/// element (`0..groups`).
///
/// # Errors
/// [`FitError::Coefficients`] for a wrong length or an invalid pair.
pub fn field_of(
    base: &Model,
    groups: Option<&[u32]>,
    c: &[f64],
) -> Result<MaterialField, FitError> {
    let invalid = |reason: String| FitError::Coefficients {
        coefficients: c.to_vec(),
        reason,
    };
    match groups {
        None => base
            .with_term_coefficients(c)
            .map(MaterialField::Uniform)
            .map_err(|e| invalid(e.to_string())),
        Some(g) => MaterialField::from_term_coefficients(base, g.to_vec(), c)
            .map_err(|e| invalid(e.to_string())),
    }
}

/// A coefficient field to fit: one set of term coefficients per label (one label per
/// element: the element index for a per-element field, a region tag, a cluster).
#[derive(Debug, Clone, PartialEq, Default)]
#[non_exhaustive]
pub struct Field {
    /// The label of each element; empty: one set for the whole mesh (the material stays
    /// uniform).
    pub labels: Vec<u32>,
    /// A smooth field instead of labels (see [`OutputError::with_basis`]).
    pub basis: Option<Basis>,
    /// Where the fit starts (by increasing label, then term); `None`: the integrator's
    /// uniform material in every group.
    pub initial: Option<Vec<f64>>,
    /// The penalty on the field.
    pub regularisation: Regularisation,
    /// Also fit a scale of each vertex's lumped mass (after the material coefficients; see
    /// [`OutputError::with_mass_scale`]).
    pub mass: bool,
    /// Also fit Rayleigh `alpha, gamma` (after the mass scales; see
    /// [`OutputError::with_damping`]).
    pub damping: bool,
    /// Also fit the coefficients of friction (last; see [`OutputError::with_friction`]).
    pub friction: bool,
}

deform_setters::setters!(Field {
    labels: Vec<u32>,
    basis: Option<Basis>,
    initial: Option<Vec<f64>>,
    regularisation: Regularisation,
    mass: bool,
    damping: bool,
    friction: bool,
});

/// [`fit_output_error`] of a coefficient field (see [`OutputError::with_field`]). The fitted
/// field is left in `sim`.
///
/// # Errors
/// [`FitError`] when the labels, the data or the first evaluation fail.
pub fn fit_output_error_field(
    sim: &mut Integrator,
    trajectories: &[&Trajectory],
    field: &Field,
    options: OutputErrorOptions,
    progress: impl FnMut(usize, f64),
) -> Result<OutputErrorFit, FitError> {
    let objective = OutputError::new(sim, trajectories, options, progress)?;
    let objective = match (&field.basis, field.labels.is_empty()) {
        (Some(b), _) => objective.with_basis(b.clone())?,
        (None, true) => objective,
        (None, false) => objective.with_field(&field.labels)?,
    };
    let objective = objective.with_regularisation(field.regularisation.clone());
    let objective = if field.mass {
        objective.with_mass_scale()
    } else {
        objective
    };
    let objective = if field.damping {
        objective.with_damping()
    } else {
        objective
    };
    let objective = if field.friction {
        objective.with_friction()?
    } else {
        objective
    };
    let start = field
        .initial
        .clone()
        .unwrap_or_else(|| objective.uniform_start());
    minimise(&objective, &start)
}

/// L-BFGS on the objective in log-coefficients from `initial`; the best iterate is left in
/// the integrator.
pub(super) fn minimise(
    objective: &OutputError<'_>,
    initial: &[f64],
) -> Result<OutputErrorFit, FitError> {
    let options = objective.options;
    let (initial_loss, _) = objective.evaluate(initial)?;
    *objective.stopped_by.borrow_mut() = None;
    let records = Arc::new(Mutex::new(vec![FitIteration {
        iteration: 0,
        loss: initial_loss,
        coefficients: initial.to_vec(),
    }]));
    // More-Thuente finds good first steps where L-BFGS has no curvature yet; the evaluation
    // budget guards against line searches that thrash on a non-smooth loss.
    let problem = LogProblem::new(objective, initial);
    // Estimated starts add thousands of coupled parameters: a longer memory converges in
    // about half the iterations (measured: 140 instead of 280 on the n = 1 beam).
    let memory = if problem.units.is_empty() { 7 } else { 20 };
    let solver = LBFGS::new(MoreThuenteLineSearch::new(), memory)
        .with_tolerance_grad(options.tolerance)
        .and_then(|s| s.with_tolerance_cost(0.0))
        .map_err(|e| FitError::Optimiser(e.to_string()))?;
    let start = problem.parameters();
    let recorder = Recorder {
        records: records.clone(),
        start: problem.start.clone(),
        lower: problem.lower.clone(),
    };
    let result = Executor::new(problem, solver)
        .configure(|s| s.param(start).max_iters(options.max_iterations))
        .add_observer(recorder, ObserverMode::Always)
        .run();
    let evaluations = *objective.evaluations.borrow();
    let best_record = || {
        let recs = records.lock().expect("not poisoned");
        recs.iter()
            .filter(|r| {
                r.loss.is_finite()
                    && r.coefficients.len() == initial.len()
                    && r.loss <= initial_loss
            })
            .min_by(|a, b| a.loss.total_cmp(&b.loss))
            .cloned()
    };
    let mut start_correction = None;
    let (coefficients, loss, termination) = match result {
        Ok(res) if res.state().get_best_param().is_some() => {
            let state = res.state();
            let p = state.get_best_param().expect("checked above");
            let problem = LogProblem::new(objective, initial);
            start_correction = problem.start_correction(p);
            let best = problem.coefficients(p);
            let termination = match state.get_termination_reason() {
                Some(TerminationReason::MaxItersReached) => Termination::MaxIterations,
                Some(TerminationReason::SolverConverged | TerminationReason::TargetCostReached)
                | None => Termination::Converged,
                Some(other) => objective
                    .stopped_by
                    .take()
                    .unwrap_or_else(|| Termination::Stopped(other.text().to_owned())),
            };
            (best, state.get_best_cost(), termination)
        }
        other => {
            // Keep the best iterate seen before the optimiser stopped.
            let why = match other {
                Err(e) => e.to_string(),
                Ok(_) => "no iterate was accepted".to_owned(),
            };
            let termination = objective
                .stopped_by
                .take()
                .unwrap_or(Termination::Stopped(why));
            match best_record() {
                Some(b) => (b.coefficients, b.loss, termination),
                None => (initial.to_vec(), initial_loss, termination),
            }
        }
    };
    // Leave the best coefficients in the integrator (outside the evaluation budget and
    // unseen by `progress`, whose bar counts the budget).
    *objective.evaluations.borrow_mut() = 0;
    *objective.progress.borrow_mut() = Box::new(|_, _| {});
    objective.evaluate(&coefficients)?;
    let iterations = records.lock().expect("not poisoned").clone();
    Ok(OutputErrorFit {
        coefficients,
        initial_loss,
        loss,
        iterations,
        evaluations,
        termination,
        failed_trials: *objective.failed_trials.borrow(),
        start_correction,
    })
}
