//! Experiments as library functions: [`run`] takes an [`Experiment`] (a RON file: a base
//! scene, how to make the dataset, what to learn) and an [`ExperimentObserver`], makes the
//! dataset, learns from it and returns an [`ExperimentReport`]: data (typed rows, series
//! for plots, the files written), which the runner renders as markdown, CSV and plots.
//!
//! One function per task: [`fit_material`](fit_material::run) (force-model optimisation),
//! [`select_model`](select_model::run) (ensembles), [`select_solver`](select_solver::run)
//! (a learned solver policy against fixed solvers and schedules, [`deform_learn::compare`]),
//! [`tune_solver`](tune_solver::run) (a solver's parameters) and
//! [`tune_backward_euler`](story::run) (all of them on one coarse model) and
//! [`coarsen`](coarsen::run) (a coarse mesh and step fitted to a fine model, field by field).
//!
//! ```no_run
//! use deform_studies::{Experiment, NoProgress, TaskReport, run};
//!
//! let experiment = Experiment::load("assets/experiments/fit_material.ron".as_ref())?;
//! let report = run(&experiment, None, &mut NoProgress)?;
//! if let TaskReport::FitMaterial(fit) = &report.task {
//!     if let Some(error) = fit.young_error() {
//!         println!("E off by {:.3} %", 100.0 * error);
//!     }
//! }
//! # Ok::<(), deform_learn::LearnError>(())
//! ```

pub mod coarsen;
mod config;
mod error;
pub mod fit_material;
pub mod html;
pub mod plot;
pub mod render;
mod report;
pub mod select_model;
pub mod select_solver;
mod series;
pub mod story;
mod tables;
pub mod tune_solver;

use std::path::{Path, PathBuf};
use std::time::Instant;

use deform_integrator::Scene;
use deform_integrator::scene::Built;

pub use config::{Data, Experiment, PolicyTune, SceneRun, Task};
pub use error::RenderError;
pub use render::{render, write_report};
pub use report::{ExperimentReport, Marks, Plot, TaskReport};
pub use series::Series;

pub use deform_learn::dataset::DatasetSpec;
pub use deform_learn::import::ImportSpec;

use deform_learn::LearnError;
use deform_learn::dataset::{self, Dataset};

/// A stage of an experiment, for progress displays.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Simulating the dataset (one unit per step).
    Dataset,
    /// Fitting parameters (one unit per iteration or loss evaluation).
    Fit,
    /// Fitting an ensemble (one unit per loss evaluation).
    Ensemble,
    /// Free rollouts on held-out data (one unit per model).
    Rollouts,
    /// Logging Newton systems for solver selection (one unit per step).
    SolverData,
    /// Tuning parameters (one unit per simulation of an evaluation).
    Tune,
    /// Measuring policies on whole simulations (one unit per run).
    Policies,
    /// Comparing models side by side (one unit per model).
    Compare,
}

impl Stage {
    /// Short name.
    pub fn name(self) -> &'static str {
        match self {
            Stage::Dataset => "dataset",
            Stage::Fit => "fit",
            Stage::Ensemble => "ensemble",
            Stage::Rollouts => "rollouts",
            Stage::SolverData => "logging",
            Stage::Tune => "tune",
            Stage::Policies => "policies",
            Stage::Compare => "compare",
        }
    }
}

/// Watches an experiment's progress; every method does nothing by default.
pub trait ExperimentObserver {
    /// A stage starts, with its amount of work in its units.
    fn start(&mut self, _stage: Stage, _total: u64) {}
    /// `by` more units of the current stage are done.
    fn advance(&mut self, _by: u64) {}
    /// A status line for the current stage (e.g. the current loss).
    fn message(&mut self, _text: &str) {}
    /// The current stage is done.
    fn finish(&mut self) {}
}

/// The observer that shows nothing.
#[derive(Debug, Default, Clone, Copy)]
pub struct NoProgress;

impl ExperimentObserver for NoProgress {}

/// What every task gets: the experiment, the (coarse) scene the learned model steps with,
/// the data subsampled to its step, and where to write files.
pub struct Context<'a> {
    /// The experiment.
    pub experiment: &'a Experiment,
    /// The learned model's scene: the base's with `subsample x dt`.
    pub scene: Scene,
    /// The base model's scene, at its own step.
    pub base: Scene,
    /// The learned model's scene built (mesh, integrator, initial state).
    pub built: Built,
    /// The data at the learned model's step.
    pub data: Dataset,
    /// Results folder, when files are written.
    pub out: Option<&'a Path>,
}

impl Context<'_> {
    /// The folder scene paths are relative to.
    pub fn origin(&self) -> &Path {
        &self.experiment.scene
    }

    /// `out/name`, when files are written.
    pub fn path(&self, name: &str) -> Option<PathBuf> {
        self.out.map(|o| o.join(name))
    }
}

/// The list of what a run wrote in its results folder (top-level names, one per line),
/// which the next run into the folder removes first. Listing, rather than matching names,
/// leaves a user's own files alone even in a folder like `.`.
const MANIFEST: &str = ".deform-run";

/// The data folders a run may leave half-written: listed before the run starts, so a killed
/// run's are cleared too.
const DATA_FOLDERS: [&str; 3] = ["dataset", "solver_data", "frames"];

/// Removes what the previous run listed, then lists the data folders this one may write.
fn clear_previous(out: &Path) -> Result<(), LearnError> {
    let listed = std::fs::read_to_string(out.join(MANIFEST)).unwrap_or_default();
    let listed: Vec<&str> = listed.lines().collect();
    deform_fs::clear_previous_run(out, |name, _| listed.contains(&name)).map_err(io_error)?;
    deform_fs::write_text(&out.join(MANIFEST), &DATA_FOLDERS.join("\n")).map_err(io_error)
}

/// Lists what `report`'s run wrote and what its renderer writes (`report.md`, the plots).
fn write_manifest(out: &Path, report: &ExperimentReport) -> Result<(), LearnError> {
    let mut names: std::collections::BTreeSet<String> = DATA_FOLDERS.map(String::from).into();
    let top = report.files.iter().filter_map(|f| f.components().next());
    names.extend(top.map(|c| c.as_os_str().to_string_lossy().into_owned()));
    names.insert("report.md".into());
    for p in report.plots() {
        names.extend(["svg", "png"].map(|x| format!("{}.{x}", p.stem)));
    }
    let text: Vec<String> = names.into_iter().collect();
    deform_fs::write_text(&out.join(MANIFEST), &text.join("\n")).map_err(io_error)
}

fn io_error(e: deform_fs::WriteError) -> LearnError {
    LearnError::Io {
        path: e.path,
        source: e.error,
    }
}

/// Runs an experiment: makes its dataset (saved in `out/dataset` when `out` is given),
/// runs its task and returns the report. The folder is locked for the run and, once the
/// data are made or imported, cleared of what an earlier run listed in it (other files
/// stay); data refused before that leave the folder as it was (and no folder at all when
/// the run made it). Files the task writes (datasets, solver data,
/// ParaView frames) go to `out` and are listed in [`ExperimentReport::files`]; with `out`
/// `None` nothing is written.
///
/// # Errors
/// [`LearnError`] naming the file, field, trajectory or step.
pub fn run(
    experiment: &Experiment,
    out: Option<&Path>,
    observer: &mut dyn ExperimentObserver,
) -> Result<ExperimentReport, LearnError> {
    let started = Instant::now();
    let scene = Scene::load(&experiment.scene)?;
    // One run at a time per results folder, which then holds only this run's files.
    let created = out.is_some_and(|o| !o.exists());
    let lock = out.map(deform_fs::lock_folder).transpose()?;
    let (base, data, built) = match make_data(experiment, &scene, observer) {
        Ok(made) => made,
        Err(e) => {
            drop(lock);
            if let Some(out) = out.filter(|_| created) {
                // Nothing of this run is in it but the lock: best effort.
                let _ = std::fs::remove_dir_all(out);
            }
            return Err(e);
        }
    };
    let _lock = lock;
    if let Some(out) = out {
        clear_previous(out)?;
    }
    let mut files = Vec::new();
    if let Some(out) = out {
        data.save(&out.join("dataset"))?;
        files.push(PathBuf::from("dataset"));
    }
    // The learned model may step coarser than the base (seed: cheap model, accurate data).
    let k = experiment.data.subsample();
    if data.trajectories.iter().any(|t| t.steps() < 2 * k) {
        return Err(LearnError::Unsupported(format!(
            "subsample {k} leaves a trajectory with less than two coarse steps"
        )));
    }
    let data = if k > 1 { data.subsample(k) } else { data };
    let mut scene = base.clone();
    scene.integrator.dt *= k as f64;
    let built = if k > 1 {
        scene.build(&experiment.scene)?
    } else {
        built
    };
    let (vertices, tets) = (built.mesh.num_vertices(), built.mesh.num_tets());
    let learned_dt = scene.integrator.dt;
    let cx_material = scene.material.clone();
    let cx = Context {
        experiment,
        scene,
        base,
        built,
        data,
        out,
    };
    let task = match &experiment.task {
        Task::FitMaterial { .. } => TaskReport::FitMaterial(fit_material::run(cx, observer)?),
        Task::SelectModel { .. } => TaskReport::SelectModel(select_model::run(cx, observer)?),
        Task::SelectSolver { .. } => {
            TaskReport::SelectSolver(select_solver::run(cx, observer, &mut files)?)
        }
        Task::TuneBackwardEuler { .. } => {
            TaskReport::TuneBackwardEuler(story::run(cx, observer, &mut files)?)
        }
        Task::TuneSolver { .. } => TaskReport::TuneSolver(tune_solver::run(cx)?),
        Task::Coarsen { .. } => TaskReport::Coarsen(coarsen::run(cx, observer, &mut files)?),
    };
    let mut report = ExperimentReport {
        name: experiment.name.clone(),
        scene: experiment.scene.clone(),
        vertices,
        tets,
        material: cx_material,
        data: experiment.data.clone(),
        learned_dt,
        task,
        files,
        seconds: 0.0,
    };
    if let Some(out) = out {
        for (name, text) in report.csv_files() {
            deform_fs::write_text(&out.join(&name), &text).map_err(io_error)?;
            report.files.push(name.into());
        }
        write_manifest(out, &report)?;
    }
    report.seconds = started.elapsed().as_secs_f64();
    Ok(report)
}

/// The base model's scene (the experiment's, with the data's facts for imported data), the
/// data (noise added) and the base scene built.
fn make_data(
    experiment: &Experiment,
    scene: &Scene,
    observer: &mut dyn ExperimentObserver,
) -> Result<(Scene, Dataset, Built), LearnError> {
    let origin = experiment.scene.as_path();
    let (base, mut data) = match &experiment.data {
        Data::Generate(spec) => {
            observer.start(Stage::Dataset, (spec.trajectories * spec.steps) as u64);
            let data = dataset::generate(scene, origin, spec, |_, _| observer.advance(1))?;
            observer.finish();
            (scene.clone(), data)
        }
        Data::Import(spec) => {
            observer.start(Stage::Dataset, spec.trajectories.len() as u64);
            let data = deform_learn::import::import(spec, scene, origin)?;
            observer.finish();
            (spec.scene(scene), data)
        }
    };
    let built = base.build(origin)?;
    if let Some(noise) = experiment.data.noise() {
        data.add_noise(noise, &built.integrator.dofs().constrained_vertices());
    }
    Ok((base, data, built))
}

/// The scene with its single material's moduli replaced by a Lame pair.
///
/// # Errors
/// [`LearnError::Unsupported`] for an ensemble.
pub(crate) fn with_lame(scene: &Scene, mu: f64, lambda: f64) -> Result<Scene, LearnError> {
    let material = scene
        .material
        .with_moduli(deform_materials::Moduli::Lame { mu, lambda })
        .ok_or_else(|| {
            LearnError::Unsupported(format!(
                "fitting a material needs a single model, the scene has {:?}",
                scene.material
            ))
        })?;
    let mut s = scene.clone();
    s.material = material;
    Ok(s)
}

/// The scene with each frictional obstacle's coefficient replaced, in
/// [`deform_integrator::ContactModel::frictional`]'s order (the analytic obstacles, the mesh
/// obstacles, then the body's own surface with self-contact).
///
/// # Errors
/// [`LearnError::Unsupported`] for a scene without friction or another count.
pub(crate) fn with_friction(scene: &Scene, mu: &[f64]) -> Result<Scene, LearnError> {
    let mut s = scene.clone();
    let unsupported = |why: String| Err(LearnError::Unsupported(why));
    let Some(contact) = s.contact.as_mut().filter(|c| c.friction.is_some()) else {
        return unsupported("the scene has no friction to set".into());
    };
    let external = contact.obstacles.len() + contact.meshes.len();
    let frictional = external + usize::from(contact.self_contact);
    if mu.len() != frictional {
        return unsupported(format!(
            "{} coefficients of friction for {frictional} frictional obstacles",
            mu.len()
        ));
    }
    let friction = contact.friction.as_mut().expect("checked above");
    friction.mu = mu[..external].to_vec();
    if contact.self_contact {
        friction.self_mu = Some(mu[external]);
    }
    Ok(s)
}

/// The mean over the trajectories of `split` of the rollout error of `scene` at each
/// recorded state.
///
/// # Errors
/// The scene's, or the rollout's naming the trajectory as in the dataset.
pub(crate) fn mean_rollout(
    scene: &Scene,
    origin: &Path,
    data: &deform_learn::Dataset,
    split: deform_learn::Split,
) -> Result<Vec<f64>, LearnError> {
    let mut sim = scene.build(origin)?.integrator;
    deform_learn::rollout::split_rollout_errors(&mut sim, data, split)
}
