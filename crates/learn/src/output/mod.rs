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

mod adjoint;
mod loss;
mod minimise;
mod regularisation;

use self::loss::*;
pub use self::minimise::*;
pub use self::regularisation::*;

use crate::basis::Basis;
use crate::dataset::{Trajectory, state_at};
use crate::fit::FitError;
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
use std::cell::RefCell;
use std::sync::{Arc, Mutex};

/// Options of the output-error fit. Build them from `Default` and their setters, which
/// keeps working when a field is added:
///
/// ```
/// use deform_learn::OutputErrorOptions;
///
/// let options = OutputErrorOptions::default().rollout(20).max_iterations(100).starts(Some(Default::default()));
/// assert_eq!(options.rollout, 20);
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
#[non_exhaustive]
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

deform_setters::setters!(OutputErrorOptions {
    velocity_weight: f64,
    rollout: usize,
    max_iterations: u64,
    tolerance: f64,
    max_evaluations: usize,
    patience: usize,
    allow_retries: bool,
    starts: Option<StartPrior>,
});

/// The prior of estimated rollout starts: a start `(x, v)` costs
/// `position |x - x_data|^2 + velocity dt^2 |v - v_data|^2` in the loss's units (a predicted
/// position's squared error). With Gaussian noise this is the maximum a-posteriori
/// estimate when `position` is 1 (the start's positions as noisy as the others) and
/// `velocity` the ratio of the position noise's variance to `dt^2` times the velocity
/// noise's (1/2 for velocities differenced from positions as noisy).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
#[non_exhaustive]
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

deform_setters::setters!(StartPrior {
    position: f64,
    velocity: f64,
    unobserved: f64
});

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
    /// Whether the fit stopped on its iteration cap or evaluation budget, not converged:
    /// more of either might have lowered the loss further.
    pub fn on_limit(&self) -> bool {
        matches!(
            self,
            Termination::MaxIterations | Termination::Budget { .. }
        )
    }

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
#[non_exhaustive]
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
#[non_exhaustive]
pub struct OutputErrorFit {
    /// Fitted coefficients (`mu, lambda` for a single model).
    pub coefficients: Vec<f64>,
    /// Loss at the start.
    pub initial_loss: f64,
    /// Loss at the end.
    pub loss: f64,
    /// The start (iteration 0) and every iteration that moved to an iterate.
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

impl OutputErrorFit {
    /// The optimiser's iterations that moved to an iterate (the start not counted).
    pub fn iteration_count(&self) -> u64 {
        self.iterations.last().map_or(0, |i| i.iteration)
    }
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

#[cfg(test)]
mod tests;
