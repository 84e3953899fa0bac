//! The demo's story ([`Task::TuneBackwardEuler`]): a Backward-Euler model that steps
//! `subsample` times coarser than the base model is tuned with the base's data and compared
//! with the same coarse model untuned on the test trajectories, accuracy and cost side by
//! side. Tuned means all four of the seed's ideas that apply to one model: the material's
//! Lame pair fitted (equation error, then output error through the coarse steps; Rayleigh
//! damping by stage 1), an ensemble of energies kept when it predicts the validation
//! trajectories better, a solver policy learned on the tuned model's own Newton systems, and
//! that policy's largest Eisenstat-Walker forcing term tuned for the least work within the
//! accuracy bound.

use deform_solvers::WorkWeights;
use std::path::{Path, PathBuf};

use deform_integrator::{Integrator, IntegratorOptions, Scene, SolverPolicy};
use deform_materials::Lame;
use deform_mesh::TetMesh;
use deform_mesh::io::{Pvd, Vtu};
use serde::{Deserialize, Serialize};

use crate::{Context, ExperimentObserver, Stage, Task, with_lame};
use deform_learn::LearnError;
use deform_learn::dataset::{Split, Trajectory};
use deform_learn::ensemble::{FittedMember, Member, fit_ensemble, refine_ensemble};
use deform_learn::fit::fit_equation_error;
use deform_learn::output::{OutputErrorFit, fit_output_error};
use deform_learn::policy::{DEFAULT_FORCING, LearnedPolicy, PolicyOptions};
use deform_learn::rollout::{
    free_rollout_failure, mean_error, mean_rollout_errors, rollout, stable_or,
};
use deform_learn::solver_data::{Run, collect_runs};
use deform_learn::tuning::{Tuning, TuningResult, tune_policy};

/// Runs of each model whose whole-step times are reduced to their median (tiny problems:
/// one run's time varies by tens of percent here).
pub const TIME_REPEATS: usize = 3;

/// The three models side by side.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum StoryModel {
    /// The base model at its own step (the data).
    Base,
    /// The coarse model as configured.
    Untuned,
    /// The coarse model tuned.
    Tuned,
}

/// One model on the test trajectories.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct StoryRow {
    /// Which model.
    pub model: StoryModel,
    /// Its time step (s).
    pub dt: f64,
    /// Young's modulus (Pa) and Poisson's ratio of its (single-model) material.
    pub young: f64,
    /// Poisson's ratio.
    pub poisson: f64,
    /// Its solver policy.
    pub solver: String,
    /// RMS position error against the data per coarse step, averaged over trajectories.
    pub errors: Vec<f64>,
    /// Deterministic work.
    pub work: f64,
    /// Deterministic flops.
    pub flops: f64,
    /// Whole-step time, median of [`TIME_REPEATS`] runs.
    pub seconds: f64,
    /// Newton iterations.
    pub newton: usize,
    /// Direct fallbacks.
    pub fallbacks: usize,
}

impl StoryRow {
    /// Mean error over the predicted states.
    pub fn mean_error(&self) -> f64 {
        mean_error(&self.errors)
    }

    /// Error at the last state.
    pub fn final_error(&self) -> f64 {
        self.errors.last().copied().unwrap_or(0.0)
    }
}

/// Model selection inside the story.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct Selection {
    /// The ensemble's members after both stages.
    pub members: Vec<FittedMember>,
    /// Mean validation rollout error of the ensemble (m).
    pub ensemble_error: f64,
    /// The same for the single tuned model.
    pub single_error: f64,
    /// The ensemble replaced the single model.
    pub ensemble_kept: bool,
    /// Why the ensemble was not kept although its validation error was lower: its free
    /// rollout of a training trajectory failed (naming it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ensemble_unstable: Option<String>,
}

/// What the story found.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct StoryReport {
    /// Base steps per coarse step.
    pub subsample: usize,
    /// Rayleigh `(alpha, gamma)` as configured.
    pub damping_before: (f64, f64),
    /// Rayleigh `(alpha, gamma)` fitted by stage 1.
    pub damping_after: (f64, f64),
    /// Stage 2 of the material fit.
    pub fit: OutputErrorFit,
    /// Why stage 2's Lame pair was rejected, when it was: its free rollout of a training
    /// or validation trajectory failed (naming it), and stage 1's pair stands instead.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub unstable: Option<String>,
    /// Model selection, when members were given.
    pub selection: Option<Selection>,
    /// Logged Newton systems of the tuned model.
    pub logged: usize,
    /// Solver candidates of the learned policy.
    pub candidates: usize,
    /// The forcing-term tuning.
    pub tuning: TuningResult,
    /// The tuned largest forcing term.
    pub eta_max: f64,
    /// The accuracy bound.
    pub accuracy: f64,
    /// Factorisation and sweep flops' weights in work.
    pub weights: WorkWeights,
    /// Test trajectories.
    pub tests: usize,
    /// Coarse steps per test trajectory.
    pub steps: usize,
    /// Base, untuned, tuned.
    pub rows: Vec<StoryRow>,
}

impl StoryReport {
    fn row(&self, model: StoryModel) -> &StoryRow {
        self.rows
            .iter()
            .find(|r| r.model == model)
            .expect("every model has a row")
    }

    /// Tuned over untuned: mean error, work, time.
    pub fn ratios(&self) -> (f64, f64, f64) {
        let (u, t) = (self.row(StoryModel::Untuned), self.row(StoryModel::Tuned));
        (
            t.mean_error() / u.mean_error().max(f64::MIN_POSITIVE),
            t.work / u.work.max(f64::MIN_POSITIVE),
            t.seconds / u.seconds.max(f64::MIN_POSITIVE),
        )
    }

    /// Tuned time over the base's.
    pub fn time_against_base(&self) -> f64 {
        self.row(StoryModel::Tuned).seconds
            / self.row(StoryModel::Base).seconds.max(f64::MIN_POSITIVE)
    }
}

/// Runs [`Task::TuneBackwardEuler`]; frames of the first test trajectory go to
/// `out/frames/{base,untuned,tuned}`, the solver logs to `out/solver_data`.
///
/// # Errors
/// [`LearnError`].
pub fn run(
    mut cx: Context<'_>,
    observer: &mut dyn ExperimentObserver,
    files: &mut Vec<PathBuf>,
) -> Result<StoryReport, LearnError> {
    let Task::TuneBackwardEuler {
        equation_error,
        output_error,
        members,
        candidates,
        factor_weight,
        sweep_weight,
        accuracy,
        max_iterations,
    } = &cx.experiment.task
    else {
        unreachable!("dispatched on the task")
    };
    let weights = &WorkWeights::factor(*factor_weight).sweep(*sweep_weight);
    let origin = cx.experiment.scene.as_path();
    let (solver_data, frames) = (cx.path("solver_data"), cx.path("frames"));
    let train = cx.data.split(Split::Train);
    let tests = cx.data.split(Split::Test);
    let truth = cx.scene.material.build()?.lame().ok_or_else(|| {
        LearnError::Unsupported("the scene's model has no single Lame pair".into())
    })?;

    // 1. Force-model optimisation through the coarse steps; stage 2 refines the Lame pair
    // with stage 1's damping.
    observer.start(Stage::Fit, output_error.max_evaluations as u64);
    let blame = cx.data.blame(&[Split::Train]);
    let stage1 =
        fit_equation_error(&cx.built.integrator, &train, *equation_error).map_err(&blame)?;
    let sim = &mut cx.built.integrator;
    let mut options = sim.options().clone();
    (options.alpha, options.gamma) = (stage1.alpha, stage1.gamma);
    sim.set_options(options)?;
    let fit = fit_output_error(
        sim,
        &train,
        &stage1.coefficients,
        *output_error,
        |_, loss| {
            observer.advance(1);
            observer.message(&format!("loss {loss:.3e}"));
        },
    )
    .map_err(&blame)?;
    observer.finish();
    // The fitted pair must run freely over the data it was fitted and validated on, or stage
    // 1's stands.
    let validation = cx.data.split(Split::Validation);
    let sets = [train.as_slice(), validation.as_slice()];
    let (c, unstable) = stable_or(sim, &sets, &fit.coefficients, &stage1.coefficients);
    let fitted = Lame::try_new(c[0], c[1])?;
    let mut tuned_scene = with_lame(&cx.scene, fitted.mu, fitted.lambda)?;
    tuned_scene.integrator.alpha = stage1.alpha;
    tuned_scene.integrator.gamma = stage1.gamma;

    // 2. Model selection.
    let selection = if members.is_empty() {
        None
    } else {
        let (selection, scene) = select(
            &tuned_scene,
            origin,
            members,
            &train,
            &validation,
            *output_error,
            observer,
        )
        .map_err(cx.data.blame(&[Split::Train, Split::Validation]))?;
        tuned_scene = scene;
        Some(selection)
    };

    // 3. Solver selection on the tuned model's own Newton systems.
    let steps = train.first().map_or(0, |t| t.steps());
    let train_index = cx.data.indices(Split::Train);
    let runs: Vec<Run<'_>> = train_index
        .clone()
        .map(|k| Ok((cx.data.scene_of(k, &tuned_scene)?, origin, steps)))
        .collect::<Result<_, LearnError>>()?;
    let (policy, logged) = learn_policy(&runs, candidates, *weights, fitted, observer)?;
    if let Some(path) = solver_data {
        logged.save(&path)?;
        files.push("solver_data".into());
    }

    // 4. Solver optimisation: the largest forcing term, on the first training trajectory.
    let mut tune_scene = tuned_scene.clone();
    if let Some(k) = train_index.clone().next() {
        tune_scene = cx.data.scene_of(k, &tuned_scene)?;
    }
    let tuning = tune_forcing(
        &policy,
        &(tune_scene, origin, steps),
        *weights,
        *accuracy,
        *max_iterations,
        observer,
    )?;
    let gamma = DEFAULT_FORCING.1;
    let eta_max = 10f64.powf(tuning.log10_values[0]);
    let tuned_policy = policy.with_forcing(Some((eta_max, gamma)));

    // 5. Side by side on the test trajectories; frames of the first.
    let tuned = Tuned {
        scene: &tuned_scene,
        policy: &tuned_policy,
        lame: fitted,
        solver: format!(
            "learned over {} candidates, eta_max {eta_max:.2e}",
            candidates.len()
        ),
    };
    let on = Comparison {
        tests: &tests,
        weights: *weights,
        frames,
    };
    let rows = side_by_side(&cx, &tuned, truth, &on, files, observer)?;
    Ok(StoryReport {
        subsample: cx.experiment.data.subsample(),
        damping_before: (cx.scene.integrator.alpha, cx.scene.integrator.gamma),
        damping_after: (stage1.alpha, stage1.gamma),
        fit,
        unstable,
        selection,
        logged: logged.len(),
        candidates: candidates.len(),
        tuning,
        eta_max,
        accuracy: *accuracy,
        weights: *weights,
        tests: tests.len(),
        steps,
        rows,
    })
}

/// The tuned coarse model.
struct Tuned<'a> {
    scene: &'a Scene,
    policy: &'a LearnedPolicy,
    lame: Lame,
    solver: String,
}

/// Where and how the models are compared.
struct Comparison<'a> {
    tests: &'a [&'a Trajectory],
    weights: WorkWeights,
    /// Folder of the frames, when files are written.
    frames: Option<PathBuf>,
}

/// Base, untuned and tuned on the test trajectories; frames of the first.
fn side_by_side(
    cx: &Context<'_>,
    tuned: &Tuned<'_>,
    truth: Lame,
    on: &Comparison<'_>,
    files: &mut Vec<PathBuf>,
    observer: &mut dyn ExperimentObserver,
) -> Result<Vec<StoryRow>, LearnError> {
    let (tests, weights, frames) = (on.tests, on.weights, &on.frames);
    let origin = cx.experiment.scene.as_path();
    observer.start(Stage::Compare, 3);
    let base_policy = cx.base.policy.build()?.name();
    let mut rows = Vec::new();
    for (model, scene, policy, refine) in [
        (
            StoryModel::Base,
            &cx.base,
            None,
            cx.experiment.data.subsample(),
        ),
        (StoryModel::Untuned, &cx.scene, None, 1),
        (StoryModel::Tuned, tuned.scene, Some(tuned.policy), 1),
    ] {
        let make = || -> Result<(Integrator, TetMesh), LearnError> {
            let built = scene.build(origin)?;
            let mut sim = built.integrator;
            if let Some(p) = policy {
                sim.set_policy(Box::new(p.clone()));
            }
            Ok((sim, built.mesh))
        };
        let dir = frames.as_ref().map(|f| f.join(model.name()));
        let mut row = run_model_timed(&make, tests, refine, weights, dir.as_deref())?;
        if dir.is_some() {
            files.push(PathBuf::from("frames").join(model.name()));
        }
        row.model = model;
        row.dt = scene.integrator.dt;
        let lame = if model == StoryModel::Tuned {
            tuned.lame
        } else {
            truth
        };
        (row.young, row.poisson) = lame.to_young();
        row.solver = match model {
            StoryModel::Tuned => tuned.solver.clone(),
            _ => base_policy.clone(),
        };
        rows.push(row);
        observer.advance(1);
    }
    observer.finish();
    Ok(rows)
}

/// Logs every candidate on the Newton systems of `runs` and learns a policy from the logs
/// (default options, forcing on, the fitted Young's modulus as a feature).
fn learn_policy(
    runs: &[Run<'_>],
    candidates: &[deform_solvers::SolverSpec],
    weights: WorkWeights,
    fitted: Lame,
    observer: &mut dyn ExperimentObserver,
) -> Result<(LearnedPolicy, deform_learn::solver_data::SolverDataset), LearnError> {
    let total: usize = runs.iter().map(|r| r.2).sum();
    observer.start(Stage::SolverData, total as u64);
    let logged = collect_runs(runs, candidates, |_| observer.advance(1))?;
    observer.finish();
    let policy = LearnedPolicy::train(
        &logged,
        PolicyOptions::new(fitted.to_young().0)
            .weights(weights)
            .forcing(Some(DEFAULT_FORCING)),
    );
    Ok((policy, logged))
}

/// Tunes the learned policy's largest forcing term for the least work within `accuracy`.
fn tune_forcing(
    policy: &LearnedPolicy,
    run: &Run<'_>,
    weights: WorkWeights,
    accuracy: f64,
    max_iterations: u64,
    observer: &mut dyn ExperimentObserver,
) -> Result<TuningResult, LearnError> {
    let tuning = Tuning {
        start: vec![vec![-1.0], vec![-3.0]],
        range: vec![(-8.0, -0.3)],
        weights,
        fallback: true,
        accuracy,
        max_iterations,
    };
    observer.start(Stage::Tune, tuning.max_evaluations());
    let gamma = DEFAULT_FORCING.1;
    let advance = std::cell::RefCell::new(&mut *observer);
    let make = |p: &[f64], _: &mut IntegratorOptions| -> Option<Box<dyn SolverPolicy>> {
        advance.borrow_mut().advance(1);
        Some(Box::new(
            policy.with_forcing(Some((10f64.powf(p[0]), gamma))),
        ))
    };
    let tuning = tune_policy(std::slice::from_ref(run), &make, &tuning)?;
    observer.finish();
    Ok(tuning)
}

impl StoryModel {
    /// Its key in tables and its frames' folder.
    pub fn name(self) -> &'static str {
        match self {
            StoryModel::Base => "base",
            StoryModel::Untuned => "untuned",
            StoryModel::Tuned => "tuned",
        }
    }
}

/// An ensemble fitted the same two ways (with the fitted damping) replaces the single
/// model when it predicts the validation trajectories better.
fn select(
    tuned: &Scene,
    origin: &Path,
    members: &[Member],
    train: &[&Trajectory],
    validation: &[&Trajectory],
    options: deform_learn::output::OutputErrorOptions,
    observer: &mut dyn ExperimentObserver,
) -> Result<(Selection, Scene), LearnError> {
    observer.start(Stage::Ensemble, options.max_evaluations as u64);
    let ensemble = fit_ensemble(tuned, origin, members, train, validation)?;
    let (ensemble, _) = refine_ensemble(
        &ensemble,
        tuned,
        origin,
        train,
        validation,
        options,
        |_, _| observer.advance(1),
    )?;
    observer.finish();
    let rollout = |scene: &Scene| -> Result<f64, LearnError> {
        let mut sim = scene.build(origin)?.integrator;
        let mut total = 0.0;
        for t in validation {
            total += mean_error(&mean_rollout_errors(&mut sim, &[t])?);
        }
        Ok(total / validation.len().max(1) as f64)
    };
    let single_error = rollout(tuned)?;
    let mut ensemble_scene = tuned.clone();
    let ensemble_error = match ensemble.spec() {
        Some(spec) => {
            ensemble_scene.material = spec;
            rollout(&ensemble_scene).unwrap_or(f64::INFINITY)
        }
        None => f64::INFINITY,
    };
    // The validation rollouts ran above; the ensemble must run freely on its training
    // trajectories too before it replaces the single model.
    let mut ensemble_unstable = None;
    if ensemble_error < single_error {
        let mut sim = ensemble_scene.build(origin)?.integrator;
        ensemble_unstable = free_rollout_failure(&mut sim, &[train]);
    }
    let ensemble_kept = ensemble_error < single_error && ensemble_unstable.is_none();
    let selection = Selection {
        members: ensemble.members,
        ensemble_error,
        single_error,
        ensemble_kept,
        ensemble_unstable,
    };
    Ok((
        selection,
        if ensemble_kept {
            ensemble_scene
        } else {
            tuned.clone()
        },
    ))
}

/// [`run_model`], with the step time the median of [`TIME_REPEATS`] runs (frames from the
/// first).
fn run_model_timed(
    make: &dyn Fn() -> Result<(Integrator, TetMesh), LearnError>,
    tests: &[&Trajectory],
    refine: usize,
    weights: WorkWeights,
    frames: Option<&Path>,
) -> Result<StoryRow, LearnError> {
    let mut row = run_model(make, tests, refine, weights, frames)?;
    let mut seconds = vec![row.seconds];
    for _ in 1..TIME_REPEATS {
        seconds.push(run_model(make, tests, refine, weights, None)?.seconds);
    }
    seconds.sort_by(f64::total_cmp);
    row.seconds = seconds[seconds.len() / 2];
    Ok(row)
}

/// Rolls a fresh model out from the first state of each trajectory for its length (`refine`
/// finer steps per recorded step), comparing with the data; writes frames of the first.
fn run_model(
    make: &dyn Fn() -> Result<(Integrator, TetMesh), LearnError>,
    tests: &[&Trajectory],
    refine: usize,
    weights: WorkWeights,
    frames: Option<&Path>,
) -> Result<StoryRow, LearnError> {
    let len = tests.first().map_or(0, |t| t.x.len());
    let mut row = StoryRow {
        model: StoryModel::Base,
        dt: 0.0,
        young: 0.0,
        poisson: 0.0,
        solver: String::new(),
        errors: vec![0.0; len],
        work: 0.0,
        flops: 0.0,
        seconds: 0.0,
        newton: 0,
        fallbacks: 0,
    };
    for (k, t) in tests.iter().enumerate() {
        let (mut sim, mesh) = make()?;
        let mut writer = match frames.filter(|_| k == 0) {
            Some(dir) => Some(Frames::new(dir, &mesh)?),
            None => None,
        };
        let mut failed = None;
        let r = rollout(
            &mut sim,
            t,
            refine,
            weights,
            &format!("test trajectory {k}"),
            &mut |n, state| {
                if let Some(w) = writer.as_mut()
                    && failed.is_none()
                {
                    failed = w.write(n, &state.x, state.t).err();
                }
            },
        )?;
        if let Some(e) = failed {
            return Err(e);
        }
        for (m, e) in row.errors.iter_mut().zip(&r.errors) {
            *m += e / tests.len() as f64;
        }
        let s = &r.summary;
        row.seconds += s.step_seconds;
        row.work += s.work;
        row.flops += s.flops as f64;
        row.newton += s.newton_iterations;
        row.fallbacks += s.fallbacks;
    }
    Ok(row)
}

/// ParaView frames of one rollout: a `.vtu` per recorded state and a `.pvd` series.
struct Frames<'m> {
    dir: PathBuf,
    mesh: &'m TetMesh,
    pvd: Pvd,
}

impl<'m> Frames<'m> {
    fn new(dir: &Path, mesh: &'m TetMesh) -> Result<Self, LearnError> {
        std::fs::create_dir_all(dir).map_err(|source| LearnError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
        Ok(Self {
            dir: dir.to_path_buf(),
            mesh,
            pvd: Pvd::new(dir.join("series.pvd")),
        })
    }

    fn write(&mut self, n: usize, x: &[f64], time: f64) -> Result<(), LearnError> {
        let file = self.dir.join(format!("frame_{n:05}.vtu"));
        let io = |e: deform_mesh::io::WriteError| LearnError::Io {
            path: file.clone(),
            source: std::io::Error::other(e.to_string()),
        };
        Vtu::deformed(self.mesh, x).write(&file).map_err(io)?;
        self.pvd.push(time, &file).map_err(io)
    }
}
