//! What an experiment found, as data: one report type per task, tables as typed rows,
//! series for plots, the files written. Rendering (markdown, CSV, plots) is the caller's.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use super::fit_material::FitMaterialReport;
use super::select_model::SelectModelReport;
use super::select_solver::SelectSolverReport;
use super::story::StoryReport;
use super::tune_solver::TuneSolverReport;
use crate::dataset::DatasetSpec;

/// A named sequence of values, one per step (or iteration): a line of a plot, a column of a
/// CSV file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Series {
    /// Its name in legends and headers.
    pub name: String,
    /// The values.
    pub values: Vec<f64>,
}

impl Series {
    /// A series.
    pub fn new(name: impl Into<String>, values: Vec<f64>) -> Self {
        Self {
            name: name.into(),
            values,
        }
    }
}

/// An experiment's results.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ExperimentReport {
    /// The experiment's name.
    pub name: String,
    /// The base scene's file.
    pub scene: PathBuf,
    /// Vertices of the mesh.
    pub vertices: usize,
    /// Tetrahedra of the mesh.
    pub tets: usize,
    /// The base scene's material.
    pub material: deform_materials::MaterialSpec,
    /// How the dataset was made.
    pub dataset: DatasetSpec,
    /// The learned model's time step (`subsample` x the base's).
    pub learned_dt: f64,
    /// The task's results.
    pub task: TaskReport,
    /// Files written, relative to the results folder.
    pub files: Vec<PathBuf>,
    /// Wall time, seconds.
    pub seconds: f64,
}

/// One task's results.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[allow(clippy::large_enum_variant)]
pub enum TaskReport {
    /// Force-model optimisation.
    FitMaterial(FitMaterialReport),
    /// Model selection.
    SelectModel(SelectModelReport),
    /// Solver selection.
    SelectSolver(SelectSolverReport),
    /// The demo's story: a coarse model tuned with the base's data.
    TuneBackwardEuler(StoryReport),
    /// Solver optimisation.
    TuneSolver(TuneSolverReport),
}
