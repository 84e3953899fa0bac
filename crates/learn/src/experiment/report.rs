//! What an experiment found, as data: one report type per task, tables as typed rows,
//! series for plots, the files written. Rendering (markdown, CSV, plots) is the caller's.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use super::fit_material::FitMaterialReport;
use super::select_model::SelectModelReport;
use super::select_solver::Key;
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

impl ExperimentReport {
    /// The one-line summary of an experiment's headline figure.
    pub fn headline(&self) -> String {
        match &self.task {
            TaskReport::FitMaterial(r) => format!(
                "E off by {:.3} %, nu by {:.3} %; rollout error fitted / true {:.3}",
                100.0 * r.young_error(),
                100.0 * r.poisson_error(),
                r.rollout_ratio()
            ),
            TaskReport::SelectModel(r) => {
                let top = r
                    .ensemble
                    .members
                    .iter()
                    .max_by(|a, b| a.energy_share.total_cmp(&b.energy_share));
                format!(
                    "{} carries {:.1} % of the energy; best single model {}",
                    top.map_or("-".to_owned(), |m| m.model.to_string()),
                    100.0 * top.map_or(0.0, |m| m.energy_share),
                    r.best_single()
                        .and_then(|m| m.member)
                        .map_or("-".to_owned(), |m| m.to_string())
                )
            }
            TaskReport::SelectSolver(r) => r
                .cases
                .last()
                .and_then(|c| {
                    let (l, bw, bs) = (
                        c.learned()?,
                        c.best_fixed(true, Key::Work)?,
                        c.best_fixed(true, Key::SolverSeconds)?,
                    );
                    Some(format!(
                        "{}: {} / best fixed without reuse {:.2}x work, {:.2}x solver time",
                        c.label,
                        l.contender.name(),
                        l.measured.work / bw.measured.work,
                        l.measured.seconds / bs.measured.seconds.max(f64::MIN_POSITIVE)
                    ))
                })
                .unwrap_or_default(),
            TaskReport::TuneBackwardEuler(r) => {
                let (e, w, t) = r.ratios();
                format!("tuned / untuned: error {e:.2}x, work {w:.2}x, time {t:.2}x")
            }
            TaskReport::TuneSolver(r) => format!(
                "{}: {:.2}x the work as configured",
                r.tuned_values(),
                r.work_ratio()
            ),
        }
    }
}
