//! What an experiment found, as data: one report type per task, tables as typed rows,
//! series for plots, the files written. Rendering (markdown, CSV, plots) is the caller's.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::coarsen::{CoarseModel, CoarsenReport};
use crate::fit_material::FitMaterialReport;
use crate::select_model::SelectModelReport;
use crate::select_solver::{CaseReport, PolicyRow, SelectSolverReport};
use crate::series::Series;
use crate::story::StoryReport;
use crate::tune_solver::TuneSolverReport;
use deform_learn::compare::Choice;

/// A line plot of a report: what to draw (values against their index), not how.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct Plot {
    /// File stem in the results folder (`rollout_error`: `rollout_error.svg` and `.png`).
    pub stem: String,
    /// The title.
    pub title: String,
    /// The x axis' label.
    pub x_label: &'static str,
    /// The y axis' label (of the values, also with `log`).
    pub y_label: &'static str,
    /// Plot the values' base-10 logarithms (non-positive values left out).
    pub log: bool,
    /// The lines.
    pub series: Vec<Series>,
    /// A categorical y axis: the name of each whole value `0, 1, ...` (drawn as points,
    /// not lines).
    pub categories: Option<Vec<String>>,
    /// Dashed vertical lines at these x (region boundaries).
    pub x_marks: Vec<f64>,
    /// How the values are drawn.
    pub marks: Marks,
}

/// How a plot draws its values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[non_exhaustive]
pub enum Marks {
    /// Lines through consecutive values (a quantity along steps or iterations).
    #[default]
    Lines,
    /// A dot per value (a category per iteration, a value per element).
    Points,
}

impl Plot {
    pub(crate) fn new(
        stem: impl Into<String>,
        title: impl Into<String>,
        axes: [&'static str; 2],
    ) -> Self {
        let [x_label, y_label] = axes;
        let (stem, title) = (stem.into(), title.into());
        let (log, series) = (false, Vec::new());
        let (categories, x_marks, marks) = (None, Vec::new(), Marks::Lines);
        Self {
            stem,
            title,
            x_label,
            y_label,
            log,
            series,
            categories,
            x_marks,
            marks,
        }
    }

    fn log(mut self) -> Self {
        self.log = true;
        self
    }

    fn categories(mut self, names: Vec<String>) -> Self {
        self.categories = Some(names);
        self.marks = Marks::Points;
        self
    }

    fn points(mut self) -> Self {
        self.marks = Marks::Points;
        self
    }

    fn x_marks(mut self, at: Vec<f64>) -> Self {
        self.x_marks = at;
        self
    }

    pub(crate) fn with(mut self, series: Vec<Series>) -> Self {
        self.series = series;
        self
    }

    /// `rollout_error`: RMS position error per step of each series.
    fn rollouts(series: Vec<Series>) -> Self {
        Self::new(
            "rollout_error",
            "test rollout RMS position error",
            ["step", "m"],
        )
        .with(series)
    }
}

/// An experiment's results.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[non_exhaustive]
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
    /// Where the data came from.
    pub data: crate::Data,
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
    /// Coarse models fitted to a fine one.
    Coarsen(CoarsenReport),
}

impl ExperimentReport {
    /// The report's plots.
    pub fn plots(&self) -> Vec<Plot> {
        match &self.task {
            TaskReport::FitMaterial(r) => {
                let losses = r.output_error.iter().flat_map(|f| &f.iterations);
                let loss = Series::new("loss", losses.map(|it| it.loss).collect());
                vec![
                    Plot::new(
                        "loss",
                        "output-error loss per iteration",
                        ["iteration", "loss"],
                    )
                    .log()
                    .with(vec![loss]),
                    Plot::rollouts(r.rollouts.clone()),
                ]
            }
            TaskReport::SelectModel(r) => vec![Plot::rollouts(r.rollouts.clone())],
            TaskReport::SelectSolver(r) => r
                .cases
                .iter()
                .enumerate()
                .flat_map(|(i, c)| r.plots(i, c))
                .collect(),
            TaskReport::TuneBackwardEuler(r) => {
                let errors = |i: usize, name: &str| Series::new(name, r.rows[i].errors.clone());
                vec![Plot::rollouts(vec![
                    errors(1, "untuned"),
                    errors(2, "tuned"),
                ])]
            }
            TaskReport::TuneSolver(_) => Vec::new(),
            TaskReport::Coarsen(r) => r
                .cases
                .iter()
                .flat_map(|c| {
                    let rows = c.rows.iter().filter(|row| row.model != CoarseModel::Fine);
                    let series = rows.map(|row| Series::new(row.model.name(), row.errors.clone()));
                    let k = c.dt_factor;
                    let errors = Plot::new(
                        format!("rollout_error_{k}x_dt"),
                        format!("held-out RMS position error against the fine model, coarse step {k}x"),
                        ["coarse step", "m"],
                    )
                    .with(series.collect());
                    let field = Plot::new(
                        format!("field_{k}x_dt"),
                        format!("per-element field, coarse step {k}x (ParaView: coarse_{k}x_dt_field.vtu)"),
                        ["element centroid along the body's longest axis (fraction of its length)", "Pa"],
                    )
                    .log()
                    .x_marks(c.region_bounds.clone())
                    .points()
                    .with(c.field.clone());
                    [errors, field]
                })
                .collect(),
        }
    }

    /// The one-line summary of an experiment's headline figure.
    pub fn headline(&self) -> String {
        match &self.task {
            TaskReport::FitMaterial(r) => r.headline(),
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
                        .map_or("none (no single model fitted)".to_owned(), |m| m
                            .to_string())
                )
            }
            TaskReport::SelectSolver(r) => r
                .cases
                .last()
                .and_then(CaseReport::headline)
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
            TaskReport::Coarsen(r) => r.headline(),
        }
    }
}

impl SelectSolverReport {
    /// Case `ci`'s plots: work and Newton iterations per step of every policy, and the
    /// learned policy's solver at every Newton iteration (its index among the candidates,
    /// -1 for a fallback).
    fn plots(&self, ci: usize, case: &CaseReport) -> Vec<Plot> {
        let stem = |what: &str| format!("case{ci}_{what}");
        let per_step = |f: fn(&(f64, usize)) -> f64| -> Vec<Series> {
            let series = |row: &PolicyRow| {
                Series::new(
                    row.contender.name(),
                    row.measured.per_step.iter().map(f).collect(),
                )
            };
            case.rows.iter().map(series).collect()
        };
        let label = &case.label;
        let mut plots = vec![
            Plot::new(
                stem("work"),
                format!("work per step: {label}"),
                ["step", "work"],
            )
            .log()
            .with(per_step(|p| p.0)),
            Plot::new(
                stem("newton"),
                format!("Newton iterations per step: {label}"),
                ["step", "iterations"],
            )
            .with(per_step(|p| p.1 as f64)),
        ];
        if let Some(learned) = case.learned() {
            // A categorical axis of the candidates' names, the fallback after them.
            let mut names: Vec<String> = self.candidates.iter().map(|s| s.to_string()).collect();
            names.push("fallback".into());
            let fallback = self.candidates.len() as f64;
            let index = |c: &Choice| {
                let found = self
                    .candidates
                    .iter()
                    .position(|s| !c.fallback && *s == c.solver);
                found.map_or(fallback, |i| i as f64)
            };
            let choices = Series::new(
                "learned",
                learned.measured.choices.iter().map(index).collect(),
            );
            let title = format!("learned policy's solver per Newton iteration: {label}");
            let axes = ["Newton iteration (all steps)", "solver"];
            let plot = Plot::new(stem("choices"), title, axes).categories(names);
            plots.push(plot.with(vec![choices]));
        }
        plots
    }
}
