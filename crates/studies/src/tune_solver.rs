//! Solver optimisation: a solver's parameters tuned jointly for the least work with the
//! trajectory within `accuracy` of the direct solver's ([`deform_learn::tuning::tune_solver`]).

use deform_solvers::{SolverSpec, WorkWeights};
use serde::{Deserialize, Serialize};

use crate::{Context, Task};
use deform_learn::LearnError;
use deform_learn::tuning::{SolverParameter, SolverTuning, TuningResult, tune_solver};

/// What solver tuning found.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct TuneSolverReport {
    /// The solver as configured.
    pub solver: SolverSpec,
    /// The parameters tuned.
    pub parameters: Vec<SolverParameter>,
    /// Steps of the tuning simulation.
    pub steps: usize,
    /// Factorisation and sweep flops' weights in work.
    pub weights: WorkWeights,
    /// The accuracy bound.
    pub accuracy: f64,
    /// The tuning (its first sample is the configured values).
    pub result: TuningResult,
}

impl TuneSolverReport {
    /// `Parameter value` of each tuned parameter, comma-separated.
    pub fn tuned_values(&self) -> String {
        self.values(&self.result.log10_values)
    }

    /// `Parameter value` of each parameter at the given log10 values.
    pub fn values(&self, log10: &[f64]) -> String {
        self.parameters
            .iter()
            .zip(log10)
            .map(|(n, x)| format!("{n:?} {:.3e}", 10f64.powf(*x)))
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// Tuned work over the configured values' work.
    pub fn work_ratio(&self) -> f64 {
        self.result.best.work / self.result.samples[0].work
    }
}

/// Runs [`Task::TuneSolver`].
///
/// # Errors
/// [`LearnError`].
pub fn run(cx: Context<'_>) -> Result<TuneSolverReport, LearnError> {
    let Task::TuneSolver {
        solver,
        parameters,
        factor_weight,
        sweep_weight,
        accuracy,
        max_iterations,
    } = &cx.experiment.task
    else {
        unreachable!("dispatched on the task")
    };
    let weights = &WorkWeights::factor(*factor_weight).sweep(*sweep_weight);
    let steps = cx.data.meta.trajectories.first().map_or(0, |t| t.steps);
    // The scene's own motion; imported data have none written, so their first trajectory's.
    let scene = match cx.experiment.data {
        crate::Data::Generate(_) => cx.scene.clone(),
        crate::Data::Import(_) => cx.data.scene_of(0, &cx.scene)?,
    };
    let result = tune_solver(
        &scene,
        cx.origin(),
        &SolverTuning {
            solver,
            parameters,
            steps,
            accuracy: *accuracy,
            weights: *weights,
            max_iterations: *max_iterations,
        },
    )?;
    Ok(TuneSolverReport {
        solver: solver.clone(),
        parameters: parameters.clone(),
        steps,
        weights: *weights,
        accuracy: *accuracy,
        result,
    })
}
