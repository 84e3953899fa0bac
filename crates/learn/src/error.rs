//! What can go wrong while learning: one error type for the experiment workflows, wrapping
//! the typed errors of the steps they run.

use std::path::PathBuf;

use deform_integrator::{SceneError, StepError};
use thiserror::Error;

use crate::dataset::DatasetError;

/// Why an experiment (or one of its stages) failed.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum LearnError {
    /// A configuration value is invalid; names the file and the field.
    #[error("{}: {field}: {reason}", path.display())]
    Config {
        /// The configuration file.
        path: PathBuf,
        /// The field, dotted from the top (`dataset.split`).
        field: String,
        /// Why.
        reason: String,
    },
    /// A configuration file that does not parse (the message has line and column).
    #[error("{}: {reason}", path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// The parser's message.
        reason: String,
    },
    /// Reading or writing a file.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// A scene.
    #[error(transparent)]
    Scene(#[from] SceneError),
    /// Another run is writing into the results folder, or it cannot be created.
    #[error(transparent)]
    Locked(#[from] deform_fs::LockError),
    /// A dataset.
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    /// A fit.
    #[error(transparent)]
    Fit(#[from] FitError),
    /// A material.
    #[error(transparent)]
    Material(#[from] deform_materials::MaterialError),
    /// Building an integrator.
    #[error(transparent)]
    Integrator(#[from] deform_integrator::IntegratorError),
    /// A solver configuration.
    #[error(transparent)]
    Solver(#[from] deform_solvers::SolverError),
    /// A solver-policy configuration.
    #[error("policy: {0}")]
    Policy(#[from] deform_integrator::PolicyError),
    /// A step of a simulation failed: which simulation (`test trajectory 2`, a scene's
    /// name), which step, and why.
    #[error("{what}, step {step}: {source}")]
    Step {
        /// The simulation.
        what: String,
        /// The failed step (0-based).
        step: usize,
        /// Why.
        source: Box<StepError>,
    },
    /// The task cannot run on this input (e.g. fitting a Lame pair to an ensemble).
    #[error("{0}")]
    Unsupported(String),
    /// A fit or rollout failed on one trajectory of a dataset: the error, its trajectory
    /// numbered as in the dataset, and that trajectory's name and source
    /// ([`crate::Dataset::blame`]).
    #[error("{source} ({name})")]
    InTrajectory {
        /// The trajectory's folder name, and the file it was read from when imported.
        name: String,
        /// The error.
        source: Box<LearnError>,
    },
}

impl LearnError {
    /// A failed run of the simulation `what`.
    pub fn step(what: impl Into<String>, e: deform_integrator::RunError) -> Self {
        Self::Step {
            what: what.into(),
            step: e.step,
            source: e.source,
        }
    }
}

impl FitError {
    /// The trajectory a failure is about: its index among the trajectories the fit was
    /// given.
    pub fn trajectory(&self) -> Option<usize> {
        match self {
            FitError::Data { index: k, .. }
            | FitError::Assembly { trajectory: k, .. }
            | FitError::Step { trajectory: k, .. }
            | FitError::Retried { trajectory: k, .. }
            | FitError::Solve { trajectory: k, .. } => Some(*k),
            _ => None,
        }
    }

    /// The same failure about trajectory `index` (e.g. its index in the whole dataset
    /// rather than in the split the fit was given).
    pub fn renumbered(mut self, index: usize) -> Self {
        match &mut self {
            FitError::Data { index: k, .. }
            | FitError::Assembly { trajectory: k, .. }
            | FitError::Step { trajectory: k, .. }
            | FitError::Retried { trajectory: k, .. }
            | FitError::Solve { trajectory: k, .. } => *k = index,
            _ => {}
        }
        self
    }

    /// Whether simulating the model failed (a step, a retried step, an adjoint solve):
    /// what a trial point of an optimiser may do, and be backed off from.
    pub fn is_failed_simulation(&self) -> bool {
        matches!(
            self,
            FitError::Step { .. } | FitError::Retried { .. } | FitError::Solve { .. }
        )
    }
}

/// Why a fit failed.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum FitError {
    /// No pair in the data.
    #[error("no data pairs to fit")]
    NoData,
    /// A trajectory does not match the mesh.
    #[error("trajectory {index}: {reason}")]
    Data {
        /// Trajectory index.
        index: usize,
        /// What is wrong.
        reason: String,
    },
    /// The assembly failed on a data state (e.g. an inverted element for Neo-Hookean).
    #[error("trajectory {trajectory}, step {step}: {source}")]
    Assembly {
        /// Trajectory index.
        trajectory: usize,
        /// Step of the state.
        step: usize,
        /// The cause.
        source: deform_assembly::AssemblyError,
    },
    /// The least-squares problem is singular (the data do not excite a parameter).
    #[error("the data do not determine the parameters (rank-deficient least squares)")]
    Singular,
    /// The fit's input or options cannot work (a non-uniform material for the output
    /// error, a parameter that does not apply to the solver, a simplex of the wrong size).
    #[error("{0}")]
    Invalid(String),
    /// Coefficients that make no valid material.
    #[error("coefficients {coefficients:?}: {reason}")]
    Coefficients {
        /// The coefficients.
        coefficients: Vec<f64>,
        /// Why.
        reason: String,
    },
    /// The budget of loss evaluations is spent.
    #[error("the budget of {evaluations} loss evaluations is spent")]
    Budget {
        /// The budget.
        evaluations: usize,
    },
    /// The best loss has not dropped by a relative
    /// [`crate::output::STALL_IMPROVEMENT`] in `patience` loss evaluations.
    #[error("no progress in the last {patience} loss evaluations")]
    Stalled {
        /// The evaluations without progress.
        patience: usize,
    },
    /// The optimiser asked for this many trial points without spending its budget of
    /// simulations (points it could not use: not finite, or whose projection onto the step
    /// bound was seen before).
    #[error("the optimiser asked for {calls} trial points, most of them not simulated")]
    Trials {
        /// Trial points asked for.
        calls: usize,
    },
    /// A step of a rollout from trajectory `trajectory` failed.
    #[error("trajectory {trajectory}, step {step}: {source}")]
    Step {
        /// Trajectory index.
        trajectory: usize,
        /// The failed step.
        step: usize,
        /// Why.
        source: Box<deform_integrator::StepError>,
    },
    /// A step of a rollout converged only in halved substeps: it is not the Backward-Euler
    /// step of `dt` the data and the adjoint assume, so the fit refuses it (at a trial point
    /// of the optimiser this counts as a failed simulation, which it backs off from).
    #[error(
        "trajectory {trajectory}, step {step}: converged only after {retries} halvings of dt, not the scheme being fitted"
    )]
    Retried {
        /// Trajectory index.
        trajectory: usize,
        /// The step.
        step: usize,
        /// Halvings of dt.
        retries: usize,
    },
    /// A step of the direct-solver reference simulation failed.
    #[error("reference simulation, step {step}: {source}")]
    Reference {
        /// The failed step.
        step: usize,
        /// Why.
        source: Box<deform_integrator::StepError>,
    },
    /// An adjoint solve failed.
    #[error("trajectory {trajectory}, adjoint solve at step {step}: {source}")]
    Solve {
        /// Trajectory index.
        trajectory: usize,
        /// The step.
        step: usize,
        /// Why.
        source: deform_solvers::SolverError,
    },
    /// A scene (a fit's model variant) does not build.
    #[error(transparent)]
    Scene(#[from] deform_integrator::SceneError),
    /// The model cannot be assembled on the mesh.
    #[error(transparent)]
    Model(#[from] deform_assembly::AssemblyError),
    /// The optimiser failed to start.
    #[error("optimiser: {0}")]
    Optimiser(String),
}
