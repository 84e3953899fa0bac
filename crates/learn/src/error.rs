//! What can go wrong while learning: one error type for the experiment workflows, wrapping
//! the typed errors of the steps they run.

use std::path::PathBuf;

use deform_integrator::{SceneError, StepError};
use thiserror::Error;

use crate::dataset::DatasetError;
use crate::fit::FitError;

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
