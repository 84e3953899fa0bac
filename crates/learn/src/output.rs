//! Stage 2 of force-model optimisation: the output error.
//!
//! From data states `(x^n, v^n)`, Backward-Euler rollouts of `rollout` steps predict the
//! following states; the loss is the squared prediction error relative to the motion,
//! `L = sum |x_pred - x_data|^2 / sum |x^n+1 - x^n|^2` (plus a weighted velocity term).
//! Rollout gradients run the adjoint backwards through the steps: with `A_k lambda_k = g_k`,
//! `g_k = adj_v(k+1) + dt adj_x(k+1)`, then `adj_x(k) = dl/dx_k + adj_x(k+1) - dt K lambda_k`
//! and `adj_v(k) = dl/dv_k + M lambda_k` (`dr/dx_k = dt K`, `dr/dv_k = -M`; K with the
//! damping term below).
//! Its exact gradient comes from implicit differentiation of the converged step: with the
//! residual `r(v, c) = 0` and its Jacobian `A = dr/dv` (the Newton matrix at the converged
//! state, with the damping term), `dv/dc = -A^-1 dr/dc`, and in adjoint form
//! `dL/dc = -lambda^T dr/dc` with `A lambda = dL/dv`: one extra solve per pair, whatever the number of parameters. The
//! Jacobian `dr/dc = -dt (J_f - gamma J_k)` comes from the materials' parameter split.
//!
//! The coefficients are the material's term coefficients: the Lame pair of a single model,
//! or every member's effective `(mu, lambda)` (weight folded in) of an ensemble, so model
//! selection runs through the same stage 2. The optimiser sees their logarithms (signs kept,
//! zero coefficients stay zero: a member stage 1 dropped stays dropped); it is argmin's
//! L-BFGS with a More-Thuente line search, an evaluation budget and a cap on trial points
//! that simulate nothing (not finite, or cached); a coefficient beyond the bounded log-step is
//! projected onto it, behind
//! [`fit_output_error`], which reports every iteration and ends with a typed [`Termination`].
//!
//! With stiffness damping `A` and `dr/dx_k` also carry the damping force's derivative in `x`,
//! `dt^2 gamma D_v K` and `dt gamma D_v K` (`D_v K`, the derivative of K along the step's end
//! velocity, by a forward difference: one assembly more per step), so the gradient is that of
//! the converged steps for any gamma (Newton's matrix has the term for gamma > 0 only; the
//! converged steps are the same).

use std::cell::RefCell;
use std::sync::{Arc, Mutex};

use argmin::core::observers::{Observe, ObserverMode};
use argmin::core::{
    CostFunction, Error as ArgminError, Executor, Gradient, IterState, KV, State as _,
    TerminationReason,
};
use argmin::solver::linesearch::MoreThuenteLineSearch;
use argmin::solver::quasinewton::LBFGS;
use deform_assembly::{Grouping, Mass, MaterialField, ReducedMatrix, StiffnessMatrix, Tangent};
use deform_integrator::{Integrator, OnStep, RunOptions, State, StepReport};
use deform_materials::{MaterialError, Model};
use deform_solvers::{Cholesky, Indefinite, LinearSolver, Ordering};
use serde::{Deserialize, Serialize};

use crate::basis::Basis;
use crate::dataset::{Trajectory, state_at};
use crate::fit::FitError;

/// Options of the output-error fit.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OutputErrorOptions {
    /// Weight of the velocity error (times `dt^2`, so it is measured like positions).
    pub velocity_weight: f64,
    /// Steps per rollout: 1 compares one-step predictions from every data state; `k`
    /// predicts `k` steps from every `k`-th data state (noisy inputs then enter once per
    /// rollout instead of once per step).
    pub rollout: usize,
    /// L-BFGS iteration cap.
    pub max_iterations: u64,
    /// Stop when the gradient norm (in log-parameters) is below this.
    pub tolerance: f64,
    /// Stop after this many loss evaluations (each simulates every pair); the best iterate
    /// so far is kept.
    pub max_evaluations: usize,
    /// Stop when this many loss evaluations in a row have not lowered the best loss by a
    /// relative [`STALL_IMPROVEMENT`] (0: never); the best iterate is kept. A fit on a loss
    /// that is not smooth (rollout steps that needed halved substeps, Newton stopped at its
    /// tolerance) stalls well before its budget: the coarse beam's fits at 4x dt reached their
    /// loss to seven digits in 30-50 evaluations and then spent the rest of a budget of 200
    /// (or 900) on line searches that moved it by less than 1e-6.
    pub patience: usize,
    /// Accept rollout steps that converged only in halved substeps (on by default). Such a
    /// step is still the model's prediction (of a finer integration), but not the one
    /// Backward-Euler step the adjoint differentiates, so its gradient is approximate. Off,
    /// such a step fails the evaluation: a trial point of the optimiser is backed off from,
    /// and the fit's starting point fails the fit, naming the step. On by default because
    /// real data need it: a rollout from a noisy state, or a fit that explores negative
    /// stiffness damping (where Newton's matrix leaves out `dt^2 gamma (dK/dx) v`, so on fast
    /// states it converges slowly or not at all), meets steps that only converge in halves,
    /// and refusing them made the documented noisy-data fit fail at its first evaluation.
    pub allow_retries: bool,
    /// Estimate each rollout's initial state with the parameters, under this prior
    /// ([`StartPrior`]); `None` starts every rollout from the data's state. On noisy data a
    /// rollout that starts from a noisy state biases the fit (the loss is then lower at a
    /// wrong material than at the truth); estimating the start removes the bias.
    pub starts: Option<StartPrior>,
}

/// The prior of estimated rollout starts: a start `(x, v)` costs
/// `position |x - x_data|^2 + velocity dt^2 |v - v_data|^2` in the loss's units (a predicted
/// position's squared error). With Gaussian noise this is the maximum a-posteriori
/// estimate when `position` is 1 (the start's positions as noisy as the others) and
/// `velocity` the ratio of the position noise's variance to `dt^2` times the velocity
/// noise's (1/2 for velocities differenced from positions as noisy).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StartPrior {
    /// Weight of the start's position offset.
    pub position: f64,
    /// Weight of the start's velocity offset (times `dt^2`).
    pub velocity: f64,
    /// The factor of both weights on a vertex a partially observed trajectory did not observe
    /// ([`crate::Trajectory::observed`]): its first state there is an estimate
    /// ([`crate::observe::estimate_start`]), not a measurement. On the beam seen through 10
    /// markers (tests/observed.rs, 150 evaluations), 0.01 fitted E to 0.12 % and 1 to 0.81 %.
    pub unobserved: f64,
}

impl Default for StartPrior {
    fn default() -> Self {
        Self {
            position: 1.0,
            velocity: 0.5,
            unobserved: 0.01,
        }
    }
}

impl Default for OutputErrorOptions {
    fn default() -> Self {
        Self {
            velocity_weight: 0.0,
            rollout: 1,
            max_iterations: 50,
            tolerance: 1e-10,
            max_evaluations: 200,
            patience: 40,
            allow_retries: true,
            starts: None,
        }
    }
}

/// How the optimiser stopped.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Termination {
    /// The gradient or cost criterion was met.
    Converged,
    /// The iteration cap was reached.
    MaxIterations,
    /// The budget of loss evaluations ([`OutputErrorOptions::max_evaluations`]) is spent.
    Budget {
        /// The budget.
        evaluations: usize,
    },
    /// The best loss did not drop in [`OutputErrorOptions::patience`] evaluations.
    Stalled {
        /// The evaluations without progress.
        patience: usize,
    },
    /// The optimiser stopped for another reason (line search failure, ...).
    Stopped(String),
}

impl Termination {
    /// A short phrase for reports: `converged`, `iteration cap`, `evaluation budget (200)`,
    /// `stalled (no progress in 40 evaluations)` or `stopped: why`.
    pub fn describe(&self) -> String {
        match self {
            Termination::Converged => "converged".to_owned(),
            Termination::MaxIterations => "iteration cap".to_owned(),
            Termination::Budget { evaluations } => format!("evaluation budget ({evaluations})"),
            Termination::Stalled { patience } => {
                format!("stalled (no progress in {patience} evaluations)")
            }
            Termination::Stopped(why) => format!("stopped: {why}"),
        }
    }
}

/// One optimiser iteration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FitIteration {
    /// Iteration index.
    pub iteration: u64,
    /// Loss at the iterate.
    pub loss: f64,
    /// The coefficients (`mu, lambda`) at the iterate.
    pub coefficients: Vec<f64>,
}

/// The result of an output-error fit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OutputErrorFit {
    /// Fitted coefficients (`mu, lambda` for a single model).
    pub coefficients: Vec<f64>,
    /// Loss at the start.
    pub initial_loss: f64,
    /// Loss at the end.
    pub loss: f64,
    /// Every iteration.
    pub iterations: Vec<FitIteration>,
    /// Loss evaluations (each is one Backward-Euler step per pair).
    pub evaluations: usize,
    /// Why it stopped.
    pub termination: Termination,
    /// Trial points the optimiser backed off from because they could not be simulated (a
    /// step failed or needed halved substeps).
    #[serde(default)]
    pub failed_trials: usize,
    /// With estimated starts ([`OutputErrorOptions::starts`]): the RMS correction of the
    /// starts' free positions from the data (m).
    #[serde(default)]
    pub start_correction: Option<f64>,
}

/// Coefficients with their loss and gradient.
type Evaluation = (Vec<f64>, f64, Vec<f64>);

/// Loss and gradient in the coefficients `c` for the pairs of `trajectories`.
pub struct OutputError<'a> {
    sim: RefCell<&'a mut Integrator>,
    /// The uniform material whose term coefficients are fitted.
    base: Model,
    /// Which elements share coefficients (`None`: one set for the whole mesh).
    field: Option<Grouping>,
    /// A smooth field instead: coefficients are weights of these functions.
    basis: Option<Basis>,
    /// The field's regularisation, when any.
    regularisation: Option<Regularisation>,
    /// Per-vertex lumped-mass scales follow the material coefficients.
    mass: bool,
    /// The mesh's vertices (the number of mass scales).
    vertices: usize,
    /// Rayleigh `alpha` and `gamma` follow the mass scales.
    damping: bool,
    /// The coefficients of friction where the fit starts (the scene's), fitted last: none,
    /// or one per frictional obstacle.
    friction: Vec<f64>,
    trajectories: Vec<&'a Trajectory>,
    options: OutputErrorOptions,
    solver: RefCell<Cholesky>,
    /// Forks of the integrator for rollouts side by side (made at the first evaluation).
    lanes: RefCell<Vec<Lane>>,
    cache: RefCell<Option<Evaluation>>,
    evaluations: RefCell<usize>,
    /// Trial points of the optimiser that could not be simulated.
    failed_trials: RefCell<usize>,
    /// Why the fit's own rules stopped the optimiser (its budget, its patience): argmin
    /// reports those errors as text inside its own.
    stopped_by: RefCell<Option<Termination>>,
    progress: RefCell<Box<dyn FnMut(usize, f64) + 'a>>,
}

impl<'a> OutputError<'a> {
    /// The objective on `sim`'s mesh, constraints and options, whose material (one uniform
    /// model or ensemble) gets the term coefficients being evaluated (see
    /// [`term_coefficients`]). `progress` sees each evaluation.
    ///
    /// # Errors
    /// [`FitError::Invalid`] when the material is not uniform or the scene has contact.
    pub fn new(
        sim: &'a mut Integrator,
        trajectories: &[&'a Trajectory],
        options: OutputErrorOptions,
        progress: impl FnMut(usize, f64) + 'a,
    ) -> Result<Self, FitError> {
        let MaterialField::Uniform(base) = sim.assembly().materials() else {
            return Err(FitError::Invalid(
                "the output-error fit needs a uniform material".into(),
            ));
        };
        Ok(Self {
            base: base.clone(),
            field: None,
            basis: None,
            regularisation: None,
            mass: false,
            vertices: sim.assembly().num_vertices(),
            damping: false,
            friction: Vec::new(),
            sim: RefCell::new(sim),
            trajectories: trajectories.to_vec(),
            options,
            solver: RefCell::new(Cholesky::new(Ordering::Auto, Indefinite::Ldlt)),
            lanes: RefCell::new(Vec::new()),
            cache: RefCell::new(None),
            evaluations: RefCell::new(0),
            failed_trials: RefCell::new(0),
            stopped_by: RefCell::new(None),
            progress: RefCell::new(Box::new(progress)),
        })
    }

    /// Fits a coefficient field instead: one set of term coefficients per label (one label
    /// per element: the element index for a per-element field, a region tag, a cluster);
    /// coefficients are ordered by increasing label, then term. One adjoint solve per step
    /// still gives the whole gradient.
    ///
    /// # Errors
    /// [`FitError::Invalid`] when there is not one label per element.
    pub fn with_field(mut self, labels: &[u32]) -> Result<Self, FitError> {
        let grouping = Grouping::from_labels(self.sim.borrow().assembly(), labels)
            .map_err(|e| FitError::Invalid(format!("field labels: {e}")))?;
        self.field = Some(grouping);
        Ok(self)
    }

    /// Fits a smooth field instead: per term, the weights of `basis`'s functions (ordered by
    /// function, then term; see [`crate::basis`]). The per-element gradient of the adjoint
    /// pass is contracted with the basis.
    ///
    /// # Errors
    /// [`FitError::Invalid`] when the basis was made for another mesh.
    pub fn with_basis(mut self, basis: Basis) -> Result<Self, FitError> {
        let elements = self.sim.borrow().assembly().num_elements();
        if basis.num_elements() != elements {
            return Err(FitError::Invalid(format!(
                "a basis over {} elements for a mesh of {elements}",
                basis.num_elements()
            )));
        }
        self.field = None;
        self.basis = Some(basis);
        Ok(self)
    }

    /// Adds a regularisation of the field (see [`Regularisation`]) to the loss.
    pub fn with_regularisation(mut self, r: Regularisation) -> Self {
        self.regularisation = Some(r);
        self
    }

    /// Also fits Rayleigh damping: the coefficients end with `alpha, gamma`, which a
    /// coarser step needs (its numerical damping is not a stiffness). Through the same
    /// adjoint: `dr/dalpha = dt M v`, `dr/dgamma = dt K v` at each step's end. Alpha is
    /// fitted when it starts positive (the optimiser works in logarithms: a zero stays
    /// zero); gamma stays above `-dt / 2` (a coarse step's negative gamma gives back some of
    /// its numerical dissipation).
    pub fn with_damping(mut self) -> Self {
        self.damping = true;
        self
    }

    /// Also fits the coefficients of friction: the coefficients end with one per
    /// frictional obstacle ([`deform_integrator::ContactModel::frictional`]'s order). A
    /// coefficient that starts at zero stays there (the optimiser works in logarithms).
    /// Through the same adjoint: the friction forces are `mu` times those at unit `mu`,
    /// so `dr/dmu_o = -dt f_o / mu_o` with `f_o` the forces of the pairs lagged against
    /// obstacle `o`.
    ///
    /// # Errors
    /// [`FitError::Invalid`] when the scene has no friction.
    pub fn with_friction(mut self) -> Result<Self, FitError> {
        let mu = (self.sim.borrow().contact())
            .and_then(|c| c.friction())
            .map(|(mu, _)| mu.to_vec());
        let Some(mu) = mu else {
            return Err(FitError::Invalid(
                "contact.friction: the scene has no friction to fit".into(),
            ));
        };
        self.friction = mu;
        Ok(self)
    }

    /// Number of coefficients of friction fitted (none, or one per frictional obstacle).
    fn num_friction(&self) -> usize {
        self.friction.len()
    }

    /// Also fits a scale of each vertex's lumped mass (positive; the total mass is not
    /// held fixed, and is reported by [`Integrator::mass_scale`]): the coefficients gain one
    /// per vertex after the material's. A coarse mesh lumps mass where the fine body does
    /// not have it; the scales move it back. Through the same adjoint:
    /// `dr/ds_v = m_v (v^n+1 - v^n + dt alpha v^n+1 - dt g)` at vertex `v`. The field's
    /// `towards` weight also pulls `ln s_v` towards 0.
    pub fn with_mass_scale(mut self) -> Self {
        self.mass = true;
        self
    }

    /// Number of mass scales (one per vertex, or none).
    fn num_mass(&self) -> usize {
        if self.mass { self.vertices } else { 0 }
    }

    /// Number of coefficient sets: groups, basis functions, or 1.
    fn num_sets(&self) -> usize {
        match (&self.basis, &self.field) {
            (Some(b), _) => b.num_functions(),
            (None, Some(g)) => g.num_groups(),
            (None, None) => 1,
        }
    }

    /// Number of material coefficients: terms times sets.
    fn num_material(&self) -> usize {
        term_coefficients(&self.base).len() * self.num_sets()
    }

    /// The bound each coefficient keeps its side of: 0 (a term coefficient keeps its sign,
    /// alpha stays positive), and `-dt / 2` for gamma (see [`IntegratorOptions::gamma`]).
    ///
    /// [`IntegratorOptions::gamma`]: deform_integrator::IntegratorOptions::gamma
    fn bounds(&self) -> Vec<f64> {
        let mut lower = vec![0.0; self.num_coefficients()];
        if self.damping {
            lower[self.num_material() + self.num_mass() + 1] =
                -0.5 * self.sim.borrow().options().dt;
        }
        lower
    }

    /// Number of coefficients: terms times groups, a scale per vertex with the mass, and 2
    /// with damping.
    pub fn num_coefficients(&self) -> usize {
        self.num_material()
            + self.num_mass()
            + if self.damping { 2 } else { 0 }
            + self.num_friction()
    }

    /// The base material's coefficients in every group (and the integrator's damping): where
    /// a field fit starts.
    pub fn uniform_start(&self) -> Vec<f64> {
        let mut c = term_coefficients(&self.base).repeat(self.num_sets());
        let o = self.sim.borrow();
        if self.mass {
            c.extend(
                o.mass_scale()
                    .map_or(vec![1.0; self.vertices], <[f64]>::to_vec),
            );
        }
        if self.damping {
            c.extend([o.options().alpha, o.options().gamma]);
        }
        c.extend_from_slice(&self.friction);
        c
    }

    /// The material field of coefficients `c`.
    ///
    /// # Errors
    /// [`FitError::Coefficients`] for a wrong length or an invalid pair.
    pub fn materials(&self, c: &[f64]) -> Result<MaterialField, FitError> {
        // Mass scales and damping follow the material's coefficients.
        let c = &c[..self.num_material().min(c.len())];
        match (&self.basis, &self.field) {
            (Some(b), _) => {
                let elements: Vec<u32> = (0..b.num_elements() as u32).collect();
                let terms = term_coefficients(&self.base).len();
                field_of(&self.base, Some(&elements), &b.expand(c, terms))
            }
            (None, None) => field_of(&self.base, None, c),
            (None, Some(g)) => field_of(&self.base, Some(g.groups()), c),
        }
    }

    /// Loss and its gradient at coefficients `c`, every rollout starting from the data.
    ///
    /// # Errors
    /// [`FitError`] when a step or the assembly fails at these coefficients.
    pub fn evaluate(&self, c: &[f64]) -> Result<(f64, Vec<f64>), FitError> {
        self.evaluate_with_starts(c, None)
            .map(|(loss, g, _)| (loss, g))
    }

    /// Rollouts: `(trajectory, start step, steps)` in the order of the loss's sums.
    fn rollouts(&self) -> Vec<(usize, usize, usize)> {
        let horizon = self.options.rollout.max(1);
        let mut out = Vec::new();
        for (ti, t) in self.trajectories.iter().enumerate() {
            let mut start = 0;
            while start < t.steps() {
                let len = horizon.min(t.steps() - start);
                out.push((ti, start, len));
                start += len;
            }
        }
        out
    }

    /// Number of start-state parameters with [`OutputErrorOptions::starts`]: positions
    /// and velocities of every DOF per rollout (a constrained DOF's stay zero).
    pub fn num_start_parameters(&self) -> usize {
        match self.options.starts {
            Some(_) => self.rollouts().len() * 2 * self.sim.borrow().assembly().num_dofs(),
            None => 0,
        }
    }

    /// The RMS motion of a DOF in one data step: the scale of the start offsets.
    fn motion_scale(&self) -> f64 {
        let (mut sum, mut count) = (0.0, 0usize);
        for t in &self.trajectories {
            let frames = t.observed.as_ref().map_or(&t.x, |o| &o.positions);
            for w in frames.windows(2) {
                sum += w[1]
                    .iter()
                    .zip(&w[0])
                    .map(|(a, b)| (a - b).powi(2))
                    .sum::<f64>();
                count += w[0].len();
            }
        }
        (sum / count.max(1) as f64).sqrt().max(f64::MIN_POSITIVE)
    }

    /// Loss and its gradients at coefficients `c` and start offsets `starts` (per rollout,
    /// the positions then the velocities of every DOF added to the data's start; `None`:
    /// zero), see [`OutputErrorOptions::starts`]. The third gradient is the starts'.
    ///
    /// # Errors
    /// [`FitError`] when a step or the assembly fails at these coefficients.
    pub fn evaluate_with_starts(
        &self,
        c: &[f64],
        starts: Option<&[f64]>,
    ) -> Result<(f64, Vec<f64>, Vec<f64>), FitError> {
        let key: Vec<f64> = c.iter().chain(starts.unwrap_or(&[])).copied().collect();
        if let Some((cached, loss, grad)) = self.cache.borrow().as_ref()
            && *cached == key
        {
            let (gc, gs) = grad.split_at(c.len());
            return Ok((*loss, gc.to_vec(), gs.to_vec()));
        }
        if *self.evaluations.borrow() >= self.options.max_evaluations {
            *self.stopped_by.borrow_mut() = Some(Termination::Budget {
                evaluations: self.options.max_evaluations,
            });
            return Err(FitError::Budget {
                evaluations: self.options.max_evaluations,
            });
        }
        // The integrator is about to change: a failure below leaves it at `c`, so the cached
        // point would no longer be what it holds.
        *self.cache.borrow_mut() = None;
        let mut sim = self.sim.borrow_mut();
        self.set_coefficients(&mut sim, c)?;
        let n = sim.assembly().num_dofs();
        self.check_observed(n / 3)?;
        let grouping = match (&self.basis, &self.field) {
            (Some(_), _) => Grouping::per_element(sim.assembly()),
            (None, Some(g)) => g.clone(),
            (None, None) => Grouping::global(sim.assembly()),
        };
        // The adjoint's gradient is per group (per element for a basis, contracted below).
        let terms = term_coefficients(&self.base).len();
        let per_group = terms * grouping.num_groups();
        let dt = sim.options().dt;
        let prior = self.options.starts.unwrap_or_default();
        let pass = Pass {
            starts,
            n,
            free: (0..n / 3)
                .filter(|&v| !sim.dofs().is_constrained(v))
                .collect(),
            wv: self.options.velocity_weight * dt * dt,
            prior: (prior.position, prior.velocity * dt * dt, prior.unobserved),
            allow_retries: self.options.allow_retries,
            gradient_len: c.len() - self.num_material() + per_group,
            grouping,
            mass: self.mass,
            damping: self.damping,
            friction: self.num_friction(),
        };
        let jobs = self.rollouts();
        let shares = if self.ready_lanes(&sim, c, jobs.len())? {
            let mut lanes = self.lanes.borrow_mut();
            pass.side_by_side(&self.trajectories, &jobs, &mut lanes)
        } else {
            let mut solver = self.solver.borrow_mut();
            pass.one_by_one(&self.trajectories, &jobs, &mut sim, &mut solver)
        }?;
        // Summed in rollout order, whichever thread ran each: the same bits for any count.
        let (mut num, mut den) = (0.0, 0.0);
        let mut grad = vec![0.0; pass.gradient_len];
        let mut start_grad = vec![0.0; starts.map_or(0, <[f64]>::len)];
        for (r, t) in shares.iter().enumerate() {
            num += t.num;
            den += t.den;
            for (g, tg) in grad.iter_mut().zip(&t.grad) {
                *g += tg;
            }
            if let Some(sg) = &t.start_grad {
                start_grad[2 * n * r..2 * n * (r + 1)].copy_from_slice(sg);
            }
        }
        if den <= 0.0 {
            return Err(FitError::NoData);
        }
        if let Some(b) = &self.basis {
            let mut weights = b.contract(&grad[..per_group], terms);
            weights.extend_from_slice(&grad[per_group..]);
            grad = weights;
        }
        let mut loss = num / den;
        for gj in grad.iter_mut().chain(&mut start_grad) {
            *gj /= den;
        }
        loss += self.penalty(c, &mut grad);
        *self.evaluations.borrow_mut() += 1;
        (self.progress.borrow_mut())(*self.evaluations.borrow(), loss);
        let all: Vec<f64> = grad.iter().chain(&start_grad).copied().collect();
        *self.cache.borrow_mut() = Some((key, loss, all));
        Ok((loss, grad, start_grad))
    }

    /// Whether `jobs` rollouts run side by side: with more than one thread and one rollout,
    /// a problem below `lanes::SIDE_BY_SIDE_MAX_DOFS` (20,000) and a policy that forks. The lanes (one
    /// per thread, forks of `sim`) then hold coefficients `c`.
    fn ready_lanes(&self, sim: &Integrator, c: &[f64], jobs: usize) -> Result<bool, FitError> {
        if !crate::lanes::worth_it(jobs, sim.dofs().num_free()) {
            return Ok(false);
        }
        let threads = rayon::current_num_threads().min(jobs);
        let mut lanes = self.lanes.borrow_mut();
        while lanes.len() < threads {
            let Some(fork) = sim.fork() else {
                return Ok(false);
            };
            lanes.push(Lane {
                sim: fork,
                solver: Cholesky::new(Ordering::Auto, Indefinite::Ldlt),
            });
        }
        for lane in lanes.iter_mut() {
            self.set_coefficients(&mut lane.sim, c)?;
        }
        Ok(true)
    }

    /// Refuses partially observed trajectories the fit cannot use: their rollouts must run
    /// from their first state over their whole length (the later states are not known where
    /// they were not observed), and their markers must fit the body and the frames.
    fn check_observed(&self, vertices: usize) -> Result<(), FitError> {
        for (index, t) in self.trajectories.iter().enumerate() {
            let Some(observed) = &t.observed else {
                continue;
            };
            let bad = |reason: String| Err(FitError::Data { index, reason });
            if let Err(e) = observed.check(vertices, t.x.len()) {
                return bad(e.to_string());
            }
            if self.options.rollout < t.steps() {
                return bad(format!(
                    "observes {} markers: the fit needs one rollout over its whole length from its first state (rollout >= {} steps)",
                    observed.markers.len(),
                    t.steps()
                ));
            }
        }
        Ok(())
    }

    /// The regularisation's penalty at `c`, its gradient added to `grad`.
    fn penalty(&self, c: &[f64], grad: &mut [f64]) -> f64 {
        let Some(r) = &self.regularisation else {
            return 0.0;
        };
        let m = self.num_material();
        let terms = term_coefficients(&self.base);
        let mut loss = r.add(&c[..m], &terms, &mut grad[..m]);
        let v = self.num_mass();
        if v > 0 && r.towards > 0.0 {
            // ln s_v towards 0, as the material towards the base.
            let w = r.towards / v as f64;
            for (s, g) in c[m..m + v].iter().zip(&mut grad[m..m + v]) {
                loss += w * s.ln().powi(2);
                *g += 2.0 * w * s.ln() / s;
            }
        }
        loss
    }

    /// Puts coefficients `c` (material, mass scales, then damping) into the integrator.
    fn set_coefficients(&self, sim: &mut Integrator, c: &[f64]) -> Result<(), FitError> {
        let (m, v) = (self.num_material(), self.num_mass());
        let invalid = |reason: String| FitError::Coefficients {
            coefficients: c.to_vec(),
            reason,
        };
        if c.len() != self.num_coefficients() {
            let expected = self.num_coefficients();
            return Err(invalid(format!("expected {expected} coefficients")));
        }
        sim.assembly_mut().set_materials(self.materials(c)?)?;
        if self.mass {
            sim.set_mass_scale(Some(&c[m..m + v]))
                .map_err(|e| invalid(e.to_string()))?;
        }
        if self.damping {
            let Some(&[alpha, gamma]) = c.get(m + v..) else {
                return Err(invalid(format!("expected {} coefficients", m + v + 2)));
            };
            let mut options = sim.options().clone();
            (options.alpha, options.gamma) = (alpha, gamma);
            sim.set_options(options)
                .map_err(|e| FitError::Coefficients {
                    coefficients: c.to_vec(),
                    reason: e.to_string(),
                })?;
        }
        if !self.friction.is_empty() {
            let f = self.num_friction();
            sim.set_friction_coefficients(&c[c.len() - f..])
                .map_err(|e| invalid(e.to_string()))?;
        }
        Ok(())
    }
}

/// A penalty on a coefficient field, in log-coefficients (the optimiser's own variables, so
/// it is scale-free): `towards` times the mean over groups of `sum_k (ln c_gk - ln b_k)^2`,
/// pulling every group towards the base material `b` (the homogeneous fit the field starts
/// from), plus `smooth` times the mean over `neighbours` (pairs of groups sharing a face) of
/// `sum_k (ln c_gk - ln c_hk)^2`. Both weights are chosen on validation data.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Regularisation {
    /// Weight of the pull towards the base material.
    pub towards: f64,
    /// Weight of the differences across shared faces.
    pub smooth: f64,
    /// Pairs of neighbouring groups (see [`face_neighbours`]).
    pub neighbours: Vec<[usize; 2]>,
}

impl Regularisation {
    /// The penalty at `c` (terms per group `base.len()`); adds its gradient to `grad`.
    fn add(&self, c: &[f64], base: &[f64], grad: &mut [f64]) -> f64 {
        let terms = base.len().max(1);
        let groups = c.len() / terms;
        let log = |i: usize| c[i].abs().ln();
        let mut penalty = 0.0;
        if self.towards > 0.0 && groups > 0 {
            let w = self.towards / groups as f64;
            for (i, gi) in grad.iter_mut().enumerate() {
                let d = log(i) - base[i % terms].abs().ln();
                penalty += w * d * d;
                *gi += 2.0 * w * d / c[i];
            }
        }
        if self.smooth > 0.0 && !self.neighbours.is_empty() {
            let w = self.smooth / self.neighbours.len() as f64;
            for [g, h] in &self.neighbours {
                for k in 0..terms {
                    let (i, j) = (g * terms + k, h * terms + k);
                    let d = log(i) - log(j);
                    penalty += w * d * d;
                    grad[i] += 2.0 * w * d / c[i];
                    grad[j] -= 2.0 * w * d / c[j];
                }
            }
        }
        penalty
    }
}

/// Pairs of groups (by position in increasing label) whose elements share a face, sorted and
/// without repeats: the neighbours of a field's smoothness penalty.
pub fn face_neighbours(mesh: &deform_mesh::TetMesh, labels: &[u32]) -> Vec<[usize; 2]> {
    let mut distinct = labels.to_vec();
    distinct.sort_unstable();
    distinct.dedup();
    let group = |e: usize| distinct.binary_search(&labels[e]).unwrap_or(0);
    let mut pairs: Vec<[usize; 2]> = deform_mesh::topology::faces(mesh)
        .interior
        .iter()
        .map(|&[a, b]| (group(a), group(b)))
        .filter(|(g, h)| g != h)
        .map(|(g, h)| [g.min(h), g.max(h)])
        .collect();
    pairs.sort_unstable();
    pairs.dedup();
    pairs
}

/// Per vertex, whether `t` observed it (every vertex of a wholly observed trajectory; the
/// vertex markers' of a partially observed one).
fn seen_vertices(t: &Trajectory, vertices: usize) -> Vec<bool> {
    let Some(o) = &t.observed else {
        return vec![true; vertices];
    };
    let mut seen = vec![false; vertices];
    for m in &o.markers {
        if let crate::observe::Marker::Vertex(v) = *m {
            seen[v] = true;
        }
    }
    seen
}

/// One thread's integrator (a fork of the objective's) and adjoint solver, kept between
/// evaluations.
struct Lane {
    sim: Integrator,
    solver: Cholesky,
}

/// What one evaluation's rollouts share.
struct Pass<'p> {
    starts: Option<&'p [f64]>,
    /// DOFs, and the vertices that are not constrained.
    n: usize,
    free: Vec<usize>,
    /// The velocity term's weight.
    wv: f64,
    /// The start prior's position and velocity weights, and the unobserved vertices' factor.
    prior: (f64, f64, f64),
    allow_retries: bool,
    /// The adjoint's gradient: per group, then mass scales, damping and friction.
    gradient_len: usize,
    grouping: Grouping,
    mass: bool,
    damping: bool,
    /// Coefficients of friction fitted (last in the gradient).
    friction: usize,
}

/// One rollout's share of the loss's sums and gradients.
struct RolloutTerms {
    num: f64,
    den: f64,
    grad: Vec<f64>,
    /// The start offsets' gradient (positions then velocities), when they are fitted.
    start_grad: Option<Vec<f64>>,
}

/// A rollout: `(trajectory, start step, steps)`.
type Job = (usize, usize, usize);

impl Pass<'_> {
    /// The rollouts in order on the objective's own integrator.
    fn one_by_one(
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
    fn side_by_side(
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
    fn rollout(
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
fn loss_terms(
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

/// Forward: the rollout of `len` steps from `first`, the state at step `start` (that state
/// first).
fn forward(
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
struct Rollout<'a> {
    trajectory: usize,
    start: usize,
    /// The states, the start first.
    states: &'a [State],
    /// `dL/dx` and `dL/dv` of each state (entry 0 unused).
    dl_dx: &'a [Vec<f64>],
    dl_dv: &'a [Vec<f64>],
}

/// The adjoint's matrices, allocated once per evaluation and refilled at every step.
struct Adjoint {
    kmat: StiffnessMatrix,
    /// With stiffness damping: `D_v K`, the derivative of K along the step's end velocity,
    /// and scratch for the Newton matrix's stiffness part (see [`Adjoint::damping_terms`]).
    damped: Option<(StiffnessMatrix, StiffnessMatrix)>,
    reduced: ReducedMatrix,
    mass: Mass,
    grouping: Grouping,
    /// The unscaled vertex masses when the gradient has mass scales (after the material's).
    unscaled: Option<Vec<f64>>,
    /// The gradient ends with `alpha, gamma`, then this many coefficients of friction.
    damping: bool,
    friction: usize,
}

impl Adjoint {
    fn new(
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
    fn damping_terms(
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
    fn add_contact<'s>(
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
    fn backward(
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
type ContactTerms<'s> = (Option<StepContact<'s>>, Option<sprs::CsMat<f64>>);

/// The contact of one step of a rollout: the potential as the integrator placed it, the
/// friction lagged at the step's start, the Hessian at its end.
struct StepContact<'s> {
    model: std::borrow::Cow<'s, deform_integrator::ContactModel>,
    lag: deform_integrator::FrictionLag,
    hessian: deform_integrator::ContactHessian,
}

impl StepContact<'_> {
    /// `grad[o] += dt lambda . f_o / mu_o` for each frictional obstacle `o` whose
    /// coefficient is fitted (`grad` holds one per obstacle, or none): `-lambda . dr/dmu_o`
    /// with the step's friction forces `f_o` at `x1` of the pairs lagged against `o`, which
    /// are `mu_o` times those at unit `mu`.
    fn add_friction_gradient(&self, x1: &[f64], lambda: &[f64], dt: f64, grad: &mut [f64]) {
        let Some((mu, _)) = self.model.friction().filter(|_| !grad.is_empty()) else {
            return;
        };
        for (o, g) in grad.iter_mut().enumerate().filter(|&(o, _)| mu[o] > 0.0) {
            let pairs = self.lag.pairs.iter().filter(|p| p.obstacle == o);
            let lag = deform_integrator::FrictionLag {
                pairs: pairs.cloned().collect(),
                threshold: self.lag.threshold,
            };
            let mut f = vec![0.0; x1.len()];
            self.model.add_friction(&lag, x1, Some(&mut f), None);
            let work: f64 = lambda.iter().zip(&f).map(|(l, f)| l * f).sum();
            *g += dt * work / mu[o];
        }
    }
}

/// [`StepContact`] of the step from `from` to `to` (moving obstacles where the integrator
/// had them), or `None` without contact.
fn step_contact<'s>(
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

/// The term coefficients of a material model ([`Model::term_coefficients`]).
pub fn term_coefficients(model: &Model) -> Vec<f64> {
    model.term_coefficients()
}

/// `model` with term coefficients `c` ([`Model::with_term_coefficients`]).
///
/// # Errors
/// [`MaterialError`] when `c` has the wrong length or an invalid pair.
pub fn with_term_coefficients(model: &Model, c: &[f64]) -> Result<Model, MaterialError> {
    model.with_term_coefficients(c)
}

/// argmin sees `p_i = ln |c_i - l_i|` of the coefficients off their bound `l_i` (zero for
/// the material's, `-dt / 2` for Rayleigh gamma): every trial point keeps its side of the
/// bound, and a coefficient that starts on it stays there. With estimated starts
/// ([`OutputErrorOptions::starts`]) their offsets follow, in units of the data's motion per
/// step (positions) and that over `dt` (velocities), so all parameters have comparable
/// scales.
struct LogProblem<'p, 'a> {
    objective: &'p OutputError<'a>,
    /// The starting coefficients (their sides of the bounds).
    start: Vec<f64>,
    /// The bounds.
    lower: Vec<f64>,
    /// The optimiser's starting point ([`LogProblem::parameters`]).
    p0: Vec<f64>,
    /// The offset per unit of each start-offset parameter (empty without estimated starts):
    /// the data's motion per step for positions, that over `dt` for velocities.
    units: Vec<f64>,
    /// The last loss and gradient (in `p`) of a point that simulated, which a trial point
    /// that does not simulate falls back on.
    last_good: RefCell<Option<(f64, Vec<f64>)>>,
    /// Calls of [`LogProblem::evaluate`] so far, simulated or not.
    calls: std::cell::Cell<usize>,
    /// The best loss that counted as progress and the evaluation that found it
    /// ([`OutputErrorOptions::patience`]).
    progress: std::cell::Cell<(f64, usize)>,
    /// The trust region of trial points: the best point so far (its coefficients' log
    /// parameters), its loss and the radius ([`TRUST_RADIUS`]).
    trust: RefCell<(Vec<f64>, f64, f64)>,
}

/// The first trust radius (in natural log) of [`LogProblem`]: a trial point that moves a
/// coefficient by more than a factor of 10 from the best point so far is not simulated but
/// treated as failed (a loss far above, the last good gradient), so the line search backs
/// off at no cost. L-BFGS's first step has no curvature to scale it: it went to the 1e6x
/// bound and spent hundreds of Newton iterations on trials no data could be about. Each new
/// best point doubles the radius, up to [`MAX_LOG_DISTANCE`].
const TRUST_RADIUS: f64 = std::f64::consts::LN_10;

/// The relative drop of the best loss that counts as progress for
/// [`OutputErrorOptions::patience`].
pub const STALL_IMPROVEMENT: f64 = 1e-6;

/// Calls of [`LogProblem::evaluate`] allowed per evaluation of the budget. A trial point
/// asks for its cost and then its gradient (two calls, one simulation); a point that is not
/// finite, or whose projection is cached, simulates nothing, so the budget alone would let a
/// line search that keeps proposing such points (moving only a coefficient pressed against
/// its bound) run for ever.
const CALLS_PER_EVALUATION: usize = 4;

/// The loss a trial point that cannot be simulated gets, over the last good loss: far
/// above, so the line search brackets and backs off (an infinite loss would stop it).
const FAILED_TRIAL_FACTOR: f64 = 1e6;

/// How far (in natural log) a coefficient may move from where the fit started: a factor of
/// 1e6 (its offset from the bound, for gamma). A trial point further out is evaluated on
/// this bound (projected), where the loss is continued flat outwards: the gradient's
/// outward component is zero, so a coefficient pressed against it (gamma at `-dt / 2`
/// within a millionth of its start's offset) stays there while the others keep improving,
/// and a line search that overshoots (a trial mu of 1e13 Pa) never simulates a model no
/// data can be about.
const MAX_LOG_DISTANCE: f64 = 13.815510557964274;

impl LogProblem<'_, '_> {
    fn new<'p, 'a>(objective: &'p OutputError<'a>, start: &[f64]) -> LogProblem<'p, 'a> {
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
    fn outside_trust(&self, p: &[f64]) -> bool {
        let (centre, _, radius) = &*self.trust.borrow();
        centre.iter().zip(p).any(|(c, p)| (p - c).abs() > *radius)
    }

    /// Moves the trust region to `p` and widens it when `loss` is the best so far.
    fn update_trust(&self, p: &[f64], loss: f64) {
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
    fn start_offsets(&self, p: &[f64]) -> Option<Vec<f64>> {
        if self.units.is_empty() {
            return None;
        }
        let q = &p[p.len() - self.units.len()..];
        Some(q.iter().zip(&self.units).map(|(v, u)| v * u).collect())
    }

    /// Loss and gradient in `p`; at a point that cannot be simulated, a loss far above the
    /// last good one with its gradient (pointing back towards it).
    fn evaluate(&self, p: &[f64]) -> Result<(f64, Vec<f64>), FitError> {
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
    fn check_progress(&self, loss: f64) -> Result<(), FitError> {
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

    fn active(&self) -> impl Iterator<Item = usize> + '_ {
        (0..self.start.len()).filter(|&i| self.start[i] != self.lower[i])
    }

    fn coefficients(&self, p: &[f64]) -> Vec<f64> {
        from_log(&self.start, &self.lower, p)
    }

    /// The optimiser's starting point: the coefficients, and the data's starts.
    fn parameters(&self) -> Vec<f64> {
        self.p0.clone()
    }

    /// The RMS position offset of the free DOFs' starts at `p` (m).
    fn start_correction(&self, p: &[f64]) -> Option<f64> {
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
fn from_log(start: &[f64], lower: &[f64], p: &[f64]) -> Vec<f64> {
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
struct Recorder {
    records: Arc<Mutex<Vec<FitIteration>>>,
    /// Those of the [`LogProblem`].
    start: Vec<f64>,
    lower: Vec<f64>,
}

impl Observe<IterState<Vec<f64>, Vec<f64>, (), (), (), f64>> for Recorder {
    fn observe_iter(
        &mut self,
        state: &IterState<Vec<f64>, Vec<f64>, (), (), (), f64>,
        _kv: &KV,
    ) -> Result<(), ArgminError> {
        let coefficients = state
            .get_param()
            .map(|p| from_log(&self.start, &self.lower, p))
            .unwrap_or_default();
        self.records
            .lock()
            .expect("not poisoned")
            .push(FitIteration {
                iteration: state.get_iter(),
                loss: state.get_cost(),
                coefficients,
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
fn minimise(objective: &OutputError<'_>, initial: &[f64]) -> Result<OutputErrorFit, FitError> {
    let options = objective.options;
    let (initial_loss, _) = objective.evaluate(initial)?;
    *objective.stopped_by.borrow_mut() = None;
    let records = Arc::new(Mutex::new(Vec::new()));
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

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;
    use crate::dataset::{DatasetSpec, Split, generate};

    /// The n = 1 beam (tight Newton) and three 3-step trajectories of it.
    fn tiny_beam() -> (
        deform_integrator::Scene,
        crate::dataset::Dataset,
        &'static Path,
    ) {
        let text = r#"Scene(name: "t", mesh: Beam(1), material: NeoHookean(Young(e: 1e5, nu: 0.4)),
            density: 1000.0, constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
            integrator: (dt: 0.01, newton: (rel: 1e-10, abs: 1e-12)), steps: 3)"#;
        let origin = Path::new("t.ron");
        let scene = deform_integrator::Scene::parse(text, origin).unwrap();
        let data = generate(&scene, origin, &DatasetSpec::new(3, 3, 5), |_, _| ()).unwrap();
        (scene, data, origin)
    }

    /// The loss and its gradients have the same bits on 1, 2 or 3 threads (rollouts one by
    /// one on the objective's integrator, or side by side on its forks), with a trajectory
    /// under other conditions, start offsets, fitted damping and a policy that carries a
    /// stale factor from solve to solve (so that a rollout would depend on the one before
    /// it without the restart).
    #[test]
    fn rollouts_give_the_same_bits_on_any_number_of_threads() {
        let (scene, mut data, origin) = tiny_beam();
        data.trajectories[1].conditions.gravity = Some([0.0, 4.0, -2.0]);
        let all: Vec<&Trajectory> = data.trajectories.iter().collect();
        let policy = "StaleFactor(solver: Pcg(preconditioner: StaleCholesky(max_age: 1000), tolerance: (rel: 1e-6)), refactor_above: 1000)";
        let evaluate = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let mut sim = scene.build(origin).unwrap().integrator;
                let spec: deform_integrator::PolicySpec = ron::from_str(policy).unwrap();
                sim.set_policy(spec.build().unwrap());
                let options = OutputErrorOptions {
                    rollout: 2,
                    starts: Some(StartPrior::default()),
                    ..Default::default()
                };
                let objective = OutputError::new(&mut sim, &all, options, |_, _| {})
                    .unwrap()
                    .with_damping();
                let c: Vec<f64> = objective.uniform_start().iter().map(|v| v * 1.2).collect();
                let o: Vec<f64> = (0..objective.num_start_parameters())
                    .map(|i| 1e-4 * ((i % 7) as f64 - 3.0))
                    .collect();
                // A second evaluation reuses the lanes of the first.
                let first = objective.evaluate_with_starts(&c, Some(&o)).unwrap();
                let c: Vec<f64> = c.iter().map(|v| v * 0.9).collect();
                (first, objective.evaluate_with_starts(&c, Some(&o)).unwrap())
            })
        };
        let one = evaluate(1);
        assert!(one.0.0 > 0.0 && one.0.2.iter().any(|g| *g != 0.0));
        assert_eq!(evaluate(2), one);
        assert_eq!(evaluate(3), one);
    }

    /// A fit stops once `patience` simulated evaluations in a row have not lowered the best
    /// loss (here the data's own model, loss 0, and trial points off it); with patience 0
    /// it never does.
    #[test]
    fn a_fit_that_makes_no_progress_stops_after_its_patience() {
        let (scene, data, origin) = tiny_beam();
        let train = data.split(Split::Train);
        for patience in [0, 3] {
            let mut sim = scene.build(origin).unwrap().integrator;
            let options = OutputErrorOptions {
                rollout: 3,
                patience,
                ..Default::default()
            };
            let objective = OutputError::new(&mut sim, &train, options, |_, _| {}).unwrap();
            let start = objective.uniform_start();
            let problem = LogProblem::new(&objective, &start);
            let p0 = problem.parameters();
            let (best, _) = problem.evaluate(&p0).unwrap();
            // Each trial point is new (not cached) and worse than the data's model.
            let trial = |k: usize| {
                let mut p = p0.clone();
                p[0] += 0.1 * k as f64;
                problem.evaluate(&p)
            };
            for k in 1..3 {
                assert!(trial(k).unwrap().0 > best);
            }
            match (patience, trial(3)) {
                (0, result) => assert!(result.is_ok()),
                (_, Err(FitError::Stalled { patience: 3 })) => {}
                (_, other) => panic!("expected a stall, got {other:?}"),
            }
            assert_eq!(*objective.evaluations.borrow(), 4);
        }
    }

    /// Trial points beyond a factor of 10 from the best point so far are not simulated (the
    /// line search backs off at no cost); each new best point doubles the radius. A fit from
    /// a start 30x too stiff still reaches the data's model without a failed trial.
    #[test]
    fn trial_points_stay_within_the_trust_region_of_the_best_point() {
        let (scene, data, origin) = tiny_beam();
        let train = data.split(Split::Train);
        let mut sim = scene.build(origin).unwrap().integrator;
        let options = OutputErrorOptions {
            rollout: 3,
            ..Default::default()
        };
        let objective = OutputError::new(&mut sim, &train, options, |_, _| {}).unwrap();
        let truth = objective.uniform_start();
        let start: Vec<f64> = truth.iter().map(|c| 3.0 * c).collect();
        let problem = LogProblem::new(&objective, &start);
        let p0 = problem.parameters();
        let (l0, _) = problem.evaluate(&p0).unwrap();
        let at = |d: f64| {
            let mut p = p0.clone();
            p[0] -= d;
            p
        };
        // 20x away: not simulated, a loss far above.
        let (far, _) = problem.evaluate(&at(3.0)).unwrap();
        assert_eq!(*objective.evaluations.borrow(), 1);
        assert_eq!(far, FAILED_TRIAL_FACTOR * l0);
        // 3x away (towards the data's model): simulated, better, and the radius doubles.
        let (near, _) = problem.evaluate(&at(3f64.ln())).unwrap();
        assert_eq!(*objective.evaluations.borrow(), 2);
        assert!(near < l0);
        assert!((problem.trust.borrow().2 - 2.0 * TRUST_RADIUS).abs() < 1e-15);
        drop(problem);
        let far_start: Vec<f64> = truth.iter().map(|c| 30.0 * c).collect();
        let fit = minimise(&objective, &far_start).unwrap();
        assert_eq!(fit.failed_trials, 0);
        for (c, t) in fit.coefficients.iter().zip(&truth) {
            assert!(
                (c - t).abs() < 1e-4 * t,
                "{:?} against {truth:?}",
                fit.coefficients
            );
        }
    }

    /// A fit stopped by its own rules says so: the budget and the patience are typed
    /// terminations, not argmin's line-search text around them.
    #[test]
    fn a_fit_stopped_by_its_budget_or_patience_reports_which() {
        let (scene, data, origin) = tiny_beam();
        let train = data.split(Split::Train);
        for (budget, patience) in [(3, 0), (200, 1)] {
            let mut sim = scene.build(origin).unwrap().integrator;
            let options = OutputErrorOptions {
                rollout: 3,
                max_evaluations: budget,
                patience,
                // Never converged: near the optimum the loss stops dropping by 1e-6.
                tolerance: 0.0,
                ..Default::default()
            };
            // Off the data's model (mu and lambda doubled), so the first steps make progress.
            let seen = std::cell::Cell::new(0);
            let count = |_, _| seen.set(seen.get() + 1);
            let objective = OutputError::new(&mut sim, &train, options, count).unwrap();
            let start: Vec<f64> = objective.uniform_start().iter().map(|c| 2.0 * c).collect();
            let fit = minimise(&objective, &start).unwrap();
            // Progress bars count the budget: the final evaluation at the best point, outside
            // it, is not reported.
            assert_eq!(seen.get(), fit.evaluations);
            assert!(seen.get() <= budget);
            assert!(fit.loss < fit.initial_loss);
            let expected = if patience == 0 {
                Termination::Budget { evaluations: 3 }
            } else {
                Termination::Stalled { patience: 1 }
            };
            assert_eq!(fit.termination, expected, "{}", fit.termination.describe());
        }
    }

    /// A trial point the integrator cannot simulate costs far more than the last good one
    /// and carries its gradient, so the line search backs off instead of the fit stopping.
    #[test]
    fn a_trial_point_that_does_not_simulate_is_backed_off_from() {
        let text = r#"Scene(name: "t", mesh: Beam(1), material: NeoHookean(Young(e: 1e5, nu: 0.4)),
            density: 1000.0, constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
            integrator: (dt: 0.01, max_retries: 0, newton: (rel: 1e-10, abs: 1e-12)), steps: 3)"#;
        let origin = Path::new("t.ron");
        let scene = deform_integrator::Scene::parse(text, origin).unwrap();
        let data = generate(&scene, origin, &DatasetSpec::new(3, 3, 5), |_, _| ()).unwrap();
        let mut sim = scene.build(origin).unwrap().integrator;
        // Few Newton iterations: a far stiffer model does not converge in them.
        let mut o = sim.options().clone();
        o.newton.max_iterations = 5;
        sim.set_options(o).unwrap();
        let train = data.split(Split::Train);
        let options = OutputErrorOptions {
            rollout: 3,
            ..Default::default()
        };
        let objective = OutputError::new(&mut sim, &train, options, |_, _| {}).unwrap();
        let start = objective.uniform_start();
        let problem = LogProblem::new(&objective, &start);
        // Far trial points simulated (the trust region is tested on its own).
        problem.trust.borrow_mut().2 = f64::INFINITY;
        let p0 = problem.parameters();
        // Before anything simulated there is nothing to fall back on: the error itself.
        let far: Vec<f64> = p0.iter().map(|p| p + 12.0).collect();
        let error = problem.evaluate(&far).unwrap_err();
        assert!(error.is_failed_simulation(), "{error}");
        let (loss, grad) = problem.evaluate(&p0).unwrap();
        let (penalty, fallback) = problem.evaluate(&far).unwrap();
        assert_eq!(penalty, FAILED_TRIAL_FACTOR * loss.max(f64::MIN_POSITIVE));
        assert_eq!(fallback, grad);
        assert_eq!(*objective.failed_trials.borrow(), 1);
        // Trials that are not finite are not even simulated.
        let evaluations = *objective.evaluations.borrow();
        for beyond in [f64::NAN, f64::INFINITY] {
            let mut p = p0.clone();
            p[0] = beyond;
            assert_eq!(problem.evaluate(&p).unwrap(), (penalty, grad.clone()));
        }
        assert_eq!(*objective.evaluations.borrow(), evaluations);
        assert_eq!(*objective.failed_trials.borrow(), 3);
        // Beyond the bounded log-step the loss is that on the bound, flat outwards.
        let (mut bound, mut beyond) = (p0.clone(), p0.clone());
        bound[0] -= MAX_LOG_DISTANCE;
        beyond[0] -= MAX_LOG_DISTANCE + 3.0;
        let (on, g_on) = problem.evaluate(&bound).unwrap();
        let (out, g_out) = problem.evaluate(&beyond).unwrap();
        assert_eq!(problem.coefficients(&beyond), problem.coefficients(&bound));
        assert_eq!(out, on);
        assert_eq!(g_out[0], 0.0);
        assert_eq!(g_out[1..], g_on[1..]);
        assert!(g_on.iter().all(|g| g.is_finite()));
        // A line search that keeps proposing such points is stopped, not left spinning.
        let calls = CALLS_PER_EVALUATION * options.max_evaluations;
        let mut p = p0.clone();
        p[0] = f64::NAN;
        // Seven calls so far: one failed point before any simulated, then p0, then five more.
        let mut answered = 7;
        while problem.evaluate(&p).is_ok() {
            answered += 1;
            assert!(answered <= calls, "never stopped");
        }
        assert_eq!(answered, calls);
        let error = problem.evaluate(&p0).unwrap_err();
        assert!(matches!(error, FitError::Trials { .. }), "{error}");
    }

    /// The gradient in the start offsets (the last adjoints of each rollout plus the prior's)
    /// equals central differences of the loss, along a random direction, with mass damping
    /// (the adjoint is exact for any gamma, see the module docs).
    #[test]
    fn the_start_gradient_equals_finite_differences() {
        let text = r#"Scene(name: "t", mesh: Beam(1), material: NeoHookean(Young(e: 1e5, nu: 0.4)),
            density: 1000.0, constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
            integrator: (dt: 0.01, alpha: 0.5, newton: (rel: 1e-12, abs: 1e-14)), steps: 3)"#;
        let origin = Path::new("t.ron");
        let scene = deform_integrator::Scene::parse(text, origin).unwrap();
        let data = generate(&scene, origin, &DatasetSpec::new(3, 4, 5), |_, _| ()).unwrap();
        let mut sim = scene.build(origin).unwrap().integrator;
        let train = data.split(Split::Train);
        let options = OutputErrorOptions {
            rollout: 2,
            velocity_weight: 0.3,
            starts: Some(StartPrior::default()),
            ..Default::default()
        };
        let objective = OutputError::new(&mut sim, &train, options, |_, _| {})
            .unwrap()
            .with_damping();
        let c = objective.uniform_start();
        let c: Vec<f64> = c.iter().map(|v| v * 1.3).collect();
        let count = objective.num_start_parameters();
        let dofs = objective.sim.borrow().assembly().num_dofs();
        assert_eq!(
            count,
            2 * 2 * 2 * dofs,
            "2 trajectories of 2 rollouts, positions and velocities"
        );
        let mut rng = crate::rng::Rng::new(3);
        let scale = objective.motion_scale();
        let o: Vec<f64> = (0..count).map(|_| 0.3 * scale * rng.normal()).collect();
        let d: Vec<f64> = (0..count).map(|_| scale * rng.normal()).collect();
        let (_, _, g) = objective.evaluate_with_starts(&c, Some(&o)).unwrap();
        let at = |h: f64| {
            let p: Vec<f64> = o.iter().zip(&d).map(|(o, d)| o + h * d).collect();
            objective.evaluate_with_starts(&c, Some(&p)).unwrap().0
        };
        let h = 1e-4;
        let fd = (at(h) - at(-h)) / (2.0 * h);
        let exact: f64 = g.iter().zip(&d).map(|(g, d)| g * d).sum();
        assert!(
            (fd - exact).abs() <= 1e-5 * exact.abs(),
            "finite differences {fd:e}, adjoint {exact:e}"
        );
        // Constrained DOFs carry no gradient.
        let n = g.len() / 4;
        let clamped = objective.sim.borrow().dofs().constrained_vertices();
        assert!(!clamped.is_empty());
        for v in clamped {
            assert!((0..4).all(|r| (0..3).all(|i| g[r * n + 3 * v + i] == 0.0)));
        }
        // The start offsets are not bounded like the coefficients: one far past
        // MAX_LOG_DISTANCE units (the last free DOF's velocity) keeps its gradient.
        let problem = LogProblem::new(&objective, &c);
        let mut p = problem.parameters();
        let last = p.len() - 1;
        p[last] = 2.0 * MAX_LOG_DISTANCE;
        let (_, g) = problem.evaluate(&p).unwrap();
        assert_ne!(g[last], 0.0);
        drop(problem);
        drop(objective);
        // An exactly known first state stays: its rollout's starts get no gradient (and
        // no offset), the trajectory's later rollouts do.
        let mut exact = train[0].clone();
        exact.exact_start = true;
        let trajectories = [&exact];
        let objective = OutputError::new(&mut sim, &trajectories, options, |_, _| {}).unwrap();
        let count = objective.num_start_parameters();
        let o: Vec<f64> = (0..count).map(|_| 0.3 * scale * rng.normal()).collect();
        let (_, _, g) = objective.evaluate_with_starts(&c[..2], Some(&o)).unwrap();
        let (first, second) = g.split_at(count / 2);
        assert!(first.iter().all(|v| *v == 0.0));
        assert!(second.iter().any(|v| *v != 0.0));
        let (loss, _) = objective.evaluate(&c[..2]).unwrap();
        let mut moved = o.clone();
        moved[..count / 2].iter_mut().for_each(|v| *v = 0.0);
        let (l1, _, _) = objective.evaluate_with_starts(&c[..2], Some(&o)).unwrap();
        let (l2, _, _) = objective
            .evaluate_with_starts(&c[..2], Some(&moved))
            .unwrap();
        assert_eq!(l1, l2, "the first rollout's offsets are ignored");
        assert!(l1 != loss);
    }

    /// A rollout step that converged only in halved substeps is accepted by default (real
    /// data need it) and, when asked, refused naming it: it is not the step the adjoint
    /// differentiates.
    #[test]
    fn a_retried_step_is_accepted_by_default_and_refused_on_request() {
        let (scene, data, origin) = tiny_beam();
        let mut sim = scene.build(origin).unwrap().integrator;
        let mut o = sim.options().clone();
        (o.newton.max_iterations, o.max_retries) = (2, 8);
        sim.set_options(o).unwrap();
        let train = data.split(Split::Train);
        let refuse = OutputErrorOptions {
            allow_retries: false,
            ..Default::default()
        };
        let objective = OutputError::new(&mut sim, &train, refuse, |_, _| {}).unwrap();
        let error = objective.evaluate(&objective.uniform_start()).unwrap_err();
        assert!(
            matches!(error, FitError::Retried { trajectory: 0, step: 0, retries } if retries > 0),
            "{error}"
        );
        assert!(error.is_failed_simulation());
        drop(objective);
        let options = OutputErrorOptions::default();
        assert!(options.allow_retries);
        let objective = OutputError::new(&mut sim, &train, options, |_, _| {}).unwrap();
        assert!(objective.evaluate(&objective.uniform_start()).is_ok());
    }
}
