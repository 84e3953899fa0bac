//! The run executor: the one loop that steps a simulation.
//!
//! As in argmin, the integrator does one step ([`Integrator::step`]), the executor owns the
//! loop ([`Integrator::run`]): it steps until [`Until`] holds, hands every iteration and step
//! to an [`Observer`] passed per call, accumulates what the steps cost and returns a
//! [`RunSummary`] with a typed [`Termination`]. Every loop over steps (simulation, datasets,
//! fits, tuning, benchmarks) uses it, so each figure of a run is summed in one place.

use std::time::Instant;

use deform_solvers::WorkWeights;
use serde::{Deserialize, Serialize};

use crate::integrator::Integrator;
use crate::observer::Observer;
use crate::report::{StepError, StepReport};
use crate::state::State;

/// When a run ends.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Until {
    /// After this many steps.
    Steps(usize),
    /// When the state's time reaches this (s); the last step is a whole step.
    Time(f64),
}

/// How to run.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub struct RunOptions {
    /// When to stop.
    pub until: Until,
    /// How [`RunSummary::work`] weighs flops (see [`WorkWeights`]).
    pub weights: WorkWeights,
    /// Keep every [`StepReport`] in [`RunSummary::reports`].
    pub keep_reports: bool,
}

crate::setters!(RunOptions {
    until: Until,
    weights: WorkWeights,
    keep_reports: bool,
});

impl RunOptions {
    /// `steps` steps, plain flops as work, no reports kept.
    pub fn steps(steps: usize) -> Self {
        Self {
            until: Until::Steps(steps),
            weights: WorkWeights::default(),
            keep_reports: false,
        }
    }

    /// Until simulated time `t` (s), plain flops as work, no reports kept.
    pub fn time(t: f64) -> Self {
        Self {
            until: Until::Time(t),
            ..Self::steps(0)
        }
    }

    /// The same with work weighted by `weights`.
    pub fn with_weights(mut self, weights: WorkWeights) -> Self {
        self.weights = weights;
        self
    }

    /// The same, keeping every step's report.
    pub fn keeping_reports(mut self) -> Self {
        self.keep_reports = true;
        self
    }
}

/// Why a run ended.
#[derive(Debug, Clone, Default)]
pub enum Termination {
    /// [`Until`] was reached.
    #[default]
    Completed,
    /// The observer asked to stop after step `after` (0-based index of the run's steps).
    Stopped {
        /// The last step taken.
        after: usize,
    },
    /// Step `step` (0-based index of the run's steps) failed; the state is the one before it.
    Failed {
        /// The failed step.
        step: usize,
        /// Why, with the report up to the failure.
        error: Box<StepError>,
    },
}

/// What a run did: totals over its completed steps (a failed step is not counted), and why
/// it ended.
#[derive(Debug, Clone, Default)]
#[non_exhaustive]
pub struct RunSummary {
    /// Steps completed.
    pub steps: usize,
    /// Deterministic work: flops weighted by [`RunOptions::weights`].
    pub work: f64,
    /// Deterministic flops (set-up plus solves).
    pub flops: u64,
    /// Newton iterations.
    pub newton_iterations: usize,
    /// Linear-solver iterations.
    pub linear_iterations: usize,
    /// Iterations whose chosen solver failed and the direct one was used instead.
    pub fallbacks: usize,
    /// Step halvings (retries).
    pub retries: usize,
    /// Linear-solver wall time (set-ups and solves, discarded ones included), seconds.
    pub solver_seconds: f64,
    /// Wall time inside the steps (the Newton loops), seconds.
    pub step_seconds: f64,
    /// Wall time of the whole run, observers included, seconds.
    pub seconds: f64,
    /// Why it ended.
    pub termination: Termination,
    /// Every step's report, when [`RunOptions::keep_reports`].
    pub reports: Vec<StepReport>,
}

impl RunSummary {
    /// Whether a step failed.
    pub fn failed(&self) -> bool {
        matches!(self.termination, Termination::Failed { .. })
    }

    /// The summary, or the failure as an error.
    ///
    /// # Errors
    /// [`RunError`] naming the failed step, when one failed.
    pub fn into_result(self) -> Result<Self, RunError> {
        match self.termination {
            Termination::Failed { step, error } => Err(RunError {
                step,
                source: error,
            }),
            _ => Ok(self),
        }
    }

    fn add(&mut self, report: &StepReport, weights: WorkWeights) {
        self.steps += 1;
        self.work += report.work(weights);
        self.flops += report.flops();
        self.newton_iterations += report.newton_iterations();
        self.linear_iterations += report.linear_iterations();
        self.fallbacks += report.fallbacks();
        self.retries += report.retries;
        self.solver_seconds += report.solver_seconds();
        self.step_seconds += report.seconds;
    }
}

/// A run that failed at a step.
#[derive(Debug, Clone, thiserror::Error)]
#[error("step {step}: {source}")]
pub struct RunError {
    /// The failed step (0-based index of the run's steps).
    pub step: usize,
    /// Why.
    pub source: Box<StepError>,
}

impl Integrator {
    /// Runs from `state` until `options.until`, every iteration and step going to
    /// `observer`. On return `state` is the last good state (the one before a failed step).
    /// Never fails as a call: a failed step ends the run with [`Termination::Failed`]
    /// ([`RunSummary::into_result`] turns that into an error).
    pub fn run(
        &mut self,
        state: &mut State,
        options: &RunOptions,
        observer: &mut dyn Observer,
    ) -> RunSummary {
        let started = Instant::now();
        let mut summary = RunSummary::default();
        // Time targets stop within a hundredth of a step, so rounding never adds one.
        let done = |s: &State, taken: usize, dt: f64| match options.until {
            Until::Steps(n) => taken >= n,
            Until::Time(t) => s.t >= t - 1e-2 * dt,
        };
        while !done(state, summary.steps, self.options().dt) {
            let index = summary.steps;
            let report = match self.step_observed(state, observer) {
                Ok(report) => report,
                Err(error) => {
                    summary.termination = Termination::Failed {
                        step: index,
                        error: Box::new(error),
                    };
                    break;
                }
            };
            summary.add(&report, options.weights);
            let flow = observer.step(&report, state);
            if options.keep_reports {
                summary.reports.push(report);
            }
            if flow.is_break() {
                summary.termination = Termination::Stopped { after: index };
                break;
            }
        }
        summary.seconds = started.elapsed().as_secs_f64();
        summary
    }
}
