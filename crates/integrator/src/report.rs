//! What each Newton iteration and each step did, and why a step failed.

use deform_assembly::AssemblyError;
use deform_contact::{ContactError, ContactSummary};
use deform_solvers::{SetupStats, SolveStats, SolverError, SolverSpec, WorkWeights};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// One Newton iteration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct IterationReport {
    /// Newton iteration index within the step.
    pub iteration: usize,
    /// Norm of the (free) residual before this iteration's solve.
    pub residual: f64,
    /// Elastic energy at the iterate.
    pub energy: f64,
    /// The linear solver used (the direct fallback when `fallback`).
    pub solver: SolverSpec,
    /// What its set-up (factorisation, preconditioner) did and cost.
    pub setup: SetupStats,
    /// The linear solve's statistics.
    pub solve: SolveStats,
    /// The chosen solver failed and the direct solver was used instead.
    pub fallback: bool,
    /// Line-search step length (1 = full Newton step).
    pub step_length: f64,
    /// Where contact's continuous collision detection capped the line search (its first
    /// trial): 1 when it did not (and without contact).
    #[serde(default = "one")]
    pub step_bound: f64,
    /// Max-norm of the position update of this iteration.
    pub update: f64,
    /// Wall time of the iteration (assembly, solve, line search), seconds.
    pub seconds: f64,
    /// The same, per stage of the Newton iteration.
    #[serde(default)]
    pub stages: StageSeconds,
    /// Outcomes of the counterfactual candidates on the same system (empty unless
    /// `Integrator::set_candidates` was called).
    #[serde(default)]
    pub candidates: Vec<CandidateOutcome>,
    /// Solves of this iteration whose result was not used, with what they cost: the chosen
    /// solver's failed attempt before the direct fallback, an exact-tangent solve before
    /// `Projection::WhenNeeded` switched to the projected tangent. Counted in
    /// [`StepReport::work`] and [`StepReport::solver_seconds`].
    #[serde(default)]
    pub discarded: Vec<CandidateOutcome>,
}

crate::setters!(IterationReport { iteration: usize, residual: f64, energy: f64, solver: SolverSpec, setup: SetupStats, solve: SolveStats, fallback: bool, step_length: f64, step_bound: f64, update: f64, seconds: f64, stages: StageSeconds, candidates: Vec<CandidateOutcome>, discarded: Vec<CandidateOutcome> });

impl IterationReport {
    /// Iteration `iteration` solved by `solver` with `solve`, everything else zero or empty
    /// (a record to build on with the setters, e.g. in a test of a policy).
    pub fn new(iteration: usize, solver: SolverSpec, solve: SolveStats) -> Self {
        Self {
            iteration,
            residual: 0.0,
            energy: 0.0,
            solver,
            setup: SetupStats::default(),
            solve,
            fallback: false,
            step_length: 1.0,
            step_bound: 1.0,
            update: 0.0,
            seconds: 0.0,
            stages: StageSeconds::default(),
            candidates: Vec::new(),
            discarded: Vec::new(),
        }
    }
}

fn one() -> f64 {
    1.0
}

/// Wall time of each stage of a Newton iteration, seconds.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[non_exhaustive]
pub struct StageSeconds {
    /// The residual, with the assembly of energy, forces and K (energy and forces come
    /// from the line search's accepted trial when the residual needs no K: without
    /// Rayleigh stiffness damping).
    pub residual: f64,
    /// The Newton matrix `c_m M + c_k K` on the free DOFs (and K, when the residual came
    /// from the line search).
    pub matrix: f64,
    /// The direction: linear solves (the fallback and discarded ones included) and the
    /// counterfactual candidates.
    pub direction: f64,
    /// The line search (energy, and forces when the residual needs no K, at each trial).
    pub line_search: f64,
}

impl CandidateOutcome {
    /// Its deterministic work (see [`StepReport::work`]); failed parts count what they spent.
    pub fn work(&self, weights: WorkWeights) -> f64 {
        self.setup.as_ref().map_or(0.0, |s| s.work(weights))
            + self.solve.as_ref().map_or(0.0, |s| s.work(weights))
    }

    /// Its wall time (set-up and solve).
    pub fn seconds(&self) -> f64 {
        self.setup.as_ref().map_or(0.0, |s| s.seconds)
            + self.solve.as_ref().map_or(0.0, |s| s.seconds)
    }
}

impl IterationReport {
    /// Deterministic work of the iteration's linear solves, discarded ones included.
    pub fn work(&self, weights: WorkWeights) -> f64 {
        self.setup.work(weights)
            + self.solve.work(weights)
            + self.discarded.iter().map(|d| d.work(weights)).sum::<f64>()
    }

    /// Wall time of the iteration's linear solves, discarded ones included.
    pub fn solver_seconds(&self) -> f64 {
        self.setup.seconds
            + self.solve.seconds
            + self
                .discarded
                .iter()
                .map(CandidateOutcome::seconds)
                .sum::<f64>()
    }
}

/// What a counterfactual candidate solver did on an iteration's linear system.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct CandidateOutcome {
    /// Its configuration.
    pub solver: SolverSpec,
    /// Its set-up cost (`None` when it failed there).
    pub setup: Option<SetupStats>,
    /// Its solve statistics (`None` when it failed).
    pub solve: Option<SolveStats>,
    /// Why it failed, if it did.
    pub error: Option<String>,
    /// `||x - x_chosen|| / ||x_chosen||`: distance to the solution the step used.
    pub distance: f64,
}

/// One time step (or quasi-static solve).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[non_exhaustive]
pub struct StepReport {
    /// Step index.
    pub step: usize,
    /// Time at the end of the step.
    pub t: f64,
    /// Step size actually used (smaller than asked after retries).
    pub dt: f64,
    /// The policy's name.
    pub policy: String,
    /// Every Newton iteration, across substeps after retries.
    pub iterations: Vec<IterationReport>,
    /// Residual norm at the end.
    pub final_residual: f64,
    /// Residual norm at the start.
    pub initial_residual: f64,
    /// Whether Newton converged.
    pub converged: bool,
    /// It converged at the residual's rounding floor, above the tolerance asked for (which
    /// was out of reach in floating point).
    #[serde(default)]
    pub rounding_floor: bool,
    /// How many times dt was halved.
    pub retries: usize,
    /// Elastic energy at the end.
    pub energy: f64,
    /// Wall time, seconds.
    pub seconds: f64,
    /// The contact potential at the end of the step (active pairs, least distance), with
    /// contact.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub contact: Option<ContactSummary>,
}

impl StepReport {
    /// Newton iterations whose line search contact's collision bound capped.
    pub fn capped_line_searches(&self) -> usize {
        self.iterations
            .iter()
            .filter(|i| i.step_bound < 1.0)
            .count()
    }

    /// Newton iterations.
    pub fn newton_iterations(&self) -> usize {
        self.iterations.len()
    }

    /// Iterations whose chosen solver failed and the direct one was used instead.
    pub fn fallbacks(&self) -> usize {
        self.iterations.iter().filter(|i| i.fallback).count()
    }

    /// Linear-solver iterations summed over the step.
    pub fn linear_iterations(&self) -> usize {
        self.iterations.iter().map(|i| i.solve.iterations).sum()
    }

    /// Deterministic work: set-up and solve flops summed over the step.
    pub fn flops(&self) -> u64 {
        let discarded = |i: &IterationReport| -> u64 {
            i.discarded
                .iter()
                .map(|d| {
                    d.setup.as_ref().map_or(0, |s| s.flops)
                        + d.solve.as_ref().map_or(0, |s| s.flops)
                })
                .sum()
        };
        self.iterations
            .iter()
            .map(|i| i.setup.flops + i.solve.flops + discarded(i))
            .sum()
    }

    /// Deterministic work with flops weighted by `weights` (see
    /// [`deform_solvers::WorkWeights`]); `flops()` is `work(WorkWeights::default())`.
    pub fn work(&self, weights: WorkWeights) -> f64 {
        self.iterations.iter().map(|i| i.work(weights)).sum()
    }

    /// Linear-solve wall time (set-up and solve) summed over the step.
    pub fn solver_seconds(&self) -> f64 {
        self.iterations
            .iter()
            .map(IterationReport::solver_seconds)
            .sum()
    }
}

/// Why a step failed; every variant carries the report up to the failure.
#[derive(Debug, Clone, Error)]
#[non_exhaustive]
pub enum StepError {
    /// Newton did not reach its tolerance within the iteration cap.
    #[error("Newton did not converge in {} iterations (residual {:e} from {:e})", report.newton_iterations(), report.final_residual, report.initial_residual)]
    NotConverged {
        /// The report.
        report: Box<StepReport>,
    },
    /// Assembly failed (inverted element for a model that cannot invert, NaN positions).
    #[error("assembly failed: {source}")]
    Assembly {
        /// The cause.
        source: AssemblyError,
        /// The report.
        report: Box<StepReport>,
    },
    /// The linear solver failed (and no fallback was allowed or the fallback failed too).
    #[error("linear solve failed: {source}")]
    Solver {
        /// The cause.
        source: SolverError,
        /// The report.
        report: Box<StepReport>,
    },
    /// A vertex is inside an obstacle where Newton starts (a kinematic vertex driven into
    /// it, or an initial state inside).
    #[error("contact: {source}")]
    Contact {
        /// The cause.
        source: ContactError,
        /// The report.
        report: Box<StepReport>,
    },
    /// A residual or update became NaN or infinite.
    #[error("non-finite {what} at Newton iteration {}", report.newton_iterations())]
    NonFinite {
        /// What was non-finite.
        what: &'static str,
        /// The report.
        report: Box<StepReport>,
    },
}

impl StepError {
    /// The report up to the failure.
    pub fn report(&self) -> &StepReport {
        match self {
            StepError::NotConverged { report }
            | StepError::Assembly { report, .. }
            | StepError::Solver { report, .. }
            | StepError::Contact { report, .. }
            | StepError::NonFinite { report, .. } => report,
        }
    }

    fn report_mut(&mut self) -> &mut StepReport {
        match self {
            StepError::NotConverged { report }
            | StepError::Assembly { report, .. }
            | StepError::Solver { report, .. }
            | StepError::Contact { report, .. }
            | StepError::NonFinite { report, .. } => report,
        }
    }

    /// Prepends earlier iterations (of retried substeps) to the report.
    pub(crate) fn with_earlier(mut self, earlier: &[IterationReport], retries: usize) -> Self {
        let r = self.report_mut();
        let mut all = earlier.to_vec();
        all.append(&mut r.iterations);
        r.iterations = all;
        r.retries = retries;
        self
    }
}
