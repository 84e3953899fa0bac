//! Experiment files: RON documents (unknown fields rejected) naming a base scene, how to
//! make the dataset, and what to learn from it.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use deform_learn::LearnError;
use deform_learn::dataset::{DatasetSpec, Noise};
use deform_learn::fit::EquationErrorOptions;
use deform_learn::import::ImportSpec;
use deform_learn::output::OutputErrorOptions;

/// What to learn.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(clippy::large_enum_variant)] // one per experiment, parsed once: its size is immaterial
pub enum Task {
    /// Force-model optimisation: the scene's material family, its Lame pair by equation
    /// error, then (optionally) by output error.
    FitMaterial {
        /// Stage 1 options.
        #[serde(default)]
        equation_error: EquationErrorOptions,
        /// Stage 2 options; `None` stops after stage 1.
        #[serde(default)]
        output_error: Option<OutputErrorOptions>,
        /// A prior guess for stage 2, used when it explains the data better than the stage-1
        /// estimate (equation error degrades with noise on fine meshes).
        #[serde(default)]
        start: Option<deform_materials::Moduli>,
    },
    /// Model selection: an ensemble of these models ([`deform_learn::ensemble::Member`]).
    SelectModel {
        /// The candidate models.
        members: Vec<deform_learn::ensemble::Member>,
        /// Stage 2 for the ensemble and each single model; `None` stops after stage 1.
        #[serde(default)]
        output_error: Option<OutputErrorOptions>,
    },
    /// Solver selection: log every candidate at every Newton iteration of the training
    /// trajectories, learn a policy, and compare it with each fixed candidate and the
    /// Eisenstat-Walker rule on the test trajectories (work, time, accuracy).
    SelectSolver {
        /// The candidate configurations.
        candidates: Vec<deform_solvers::SolverSpec>,
        /// Neighbours of the learned model.
        #[serde(default = "five")]
        neighbours: usize,
        /// Minimum predicted success rate of a chosen candidate.
        #[serde(default = "success")]
        min_success: f64,
        /// Work of a factorisation flop relative to a solve flop (see `policy`); 1 counts
        /// plain flops.
        #[serde(default = "unit")]
        factor_weight: f64,
        /// Work of a flop of a sequential sweep (IC(0)'s triangular solves, SSOR) relative to
        /// a solve flop (see `deform_solvers::WorkWeights`); 1 counts plain flops.
        #[serde(default = "unit")]
        sweep_weight: f64,
        /// Scenes the policy never saw (other mesh, stiffness, dt, motion), each measured
        /// like the test trajectories.
        #[serde(default)]
        held_out: Vec<SceneRun>,
        /// More scenes to log for training (other sizes and stiffnesses, so the work and
        /// iteration models see how they scale), besides the training trajectories.
        #[serde(default)]
        also_train: Vec<SceneRun>,
        /// Runs per policy and case; wall times are medians over them.
        #[serde(default = "one")]
        repeats: usize,
        /// Inexact Newton for the learned policy: Eisenstat-Walker forcing terms
        /// `(eta_max, gamma)` for its iterative solves; `None` keeps their tolerances.
        #[serde(default)]
        forcing: Option<(f64, f64)>,
        /// Also run the learned policy with its Newton tolerance tuned (on the first training
        /// trajectory, for the least work within the accuracy bound).
        #[serde(default)]
        tune: Option<PolicyTune>,
        /// Refactorisation threshold of the hand schedule baseline (`StaleFactor`).
        #[serde(default = "twenty_usize")]
        refactor_above: usize,
    },
    /// The whole idea on one model (the demo's story): the model stepping
    /// `dataset.subsample` times coarser than the base is tuned (Lame pair by both stages, a
    /// learned solver policy over `candidates`, its largest forcing term tuned) and compared
    /// with the untuned coarse model on the test trajectories: error against the base's data,
    /// work and time, side by side, with ParaView frames of base, untuned and tuned.
    TuneBackwardEuler {
        /// Stage-1 options (with `damping: true`, Rayleigh alpha and gamma are fitted too
        /// and kept for stage 2: the coarse model's own damping can offset Backward Euler's
        /// numerical dissipation).
        #[serde(default)]
        equation_error: EquationErrorOptions,
        /// Stage-2 options of the material fit.
        output_error: OutputErrorOptions,
        /// Model selection: an ensemble of these models ([`deform_learn::ensemble::Member`]),
        /// fitted by both stages with the fitted damping, replaces the single model when its
        /// validation rollout error is lower. Empty: no selection.
        #[serde(default)]
        members: Vec<deform_learn::ensemble::Member>,
        /// Solver candidates of the learned policy.
        candidates: Vec<deform_solvers::SolverSpec>,
        /// Work of a factorisation flop relative to a solve flop.
        #[serde(default = "unit")]
        factor_weight: f64,
        /// Work of a flop of a sequential sweep (IC(0)'s triangular solves, SSOR) relative to
        /// a solve flop (see `deform_solvers::WorkWeights`); 1 counts plain flops.
        #[serde(default = "unit")]
        sweep_weight: f64,
        /// Relative position accuracy the tuned forcing term must keep.
        #[serde(default = "accuracy")]
        accuracy: f64,
        /// Nelder-Mead iterations for the forcing term.
        #[serde(default = "twenty")]
        max_iterations: u64,
    },
    /// Coarse models that learn from fine ones: the dataset (the base model's trajectories)
    /// is carried onto `mesh` at each of `dt_factors` times the base's step, where an
    /// untuned coarse model (the base's material and damping), a homogeneous fit, a fit per
    /// region and a fit per element are compared on the held-out motions `test` (simulated
    /// by the base model: the truth), with their cost per simulated second.
    Coarsen {
        /// The coarse mesh: a generator or a file (relative to the experiment file).
        mesh: deform_integrator::scene::MeshSource,
        /// The held-out motions, simulated by the base model (all of its trajectories are
        /// test; its split is ignored): best of another kind than the dataset's. `None`: the
        /// data's own test split (the only choice for imported data, which no base model
        /// of deform's made).
        #[serde(default)]
        test: Option<DatasetSpec>,
        /// Where each coarse rest vertex sits in the fine mesh, as the data's maker knows it:
        /// `.npy` files of the fine element of each coarse vertex (vertices,) and its
        /// barycentric weights there (vertices, 4), used as given (weights may be slightly
        /// negative for a vertex just outside a faceted fine surface). `None`: located.
        #[serde(default)]
        embedding: Option<EmbeddingFiles>,
        /// Region tags of the coarse elements for the per-region fit: an `.npy` of one
        /// integer per coarse element. `None`: `regions` slabs along the longest axis.
        #[serde(default)]
        region_tags: Option<PathBuf>,
        /// Coarse time steps as multiples of the base's: one case each.
        #[serde(default = "one_factor")]
        dt_factors: Vec<usize>,
        /// Regions of the per-region fit: slabs of equal length along the rest shape's
        /// longest axis.
        #[serde(default = "eight")]
        regions: u32,
        /// Weights of the per-element field's regularisation (towards the homogeneous fit
        /// and across shared faces alike) tried; the one with the least validation error is
        /// kept.
        #[serde(default = "weights")]
        regularisation: Vec<f64>,
        /// Fit Rayleigh alpha and gamma with every field (a coarser step's numerical
        /// dissipation is not a stiffness; gamma may go negative down to `-dt / 2`).
        #[serde(default = "yes")]
        damping: bool,
        /// Also fit a scale of each vertex's lumped mass with the per-element field (the
        /// total mass is not held; the report gives it).
        #[serde(default)]
        mass_scale: bool,
        /// Also fit a smooth field: trilinear hat functions with these node counts along
        /// x, y and z over the rest shape (see [`deform_learn::basis`]), a row of its own.
        #[serde(default)]
        smooth: Option<[usize; 3]>,
        /// The fitted coarse models' material, whose term coefficients every field fits
        /// (e.g. an `Ensemble` of linear, corotated, StVK and Neo-Hookean members: a Lame
        /// pair per member and element); `None`: the base's. The untuned row keeps the
        /// base's material.
        #[serde(default)]
        material: Option<deform_materials::MaterialSpec>,
        /// Relative Newton tolerances tried for every fitted model after its fit, besides
        /// the scene's (solver optimisation): the loosest whose mean validation rollout error
        /// is within 2 % of the one at the scene's tolerance is kept. A coarse model's error
        /// is its discretisation's, far above what a tight tolerance buys. Empty: the scene's.
        #[serde(default)]
        newton_rel: Vec<f64>,
        /// Newton's iteration cap in the fits' rollouts (`None`: the scene's); the fitted
        /// models then run with the scene's cap, under which their Newton tolerance is
        /// chosen. Under negative stiffness damping Newton converges slowly on fast states,
        /// or not at all (see [`deform_integrator::IntegratorOptions::gamma`]); a step that
        /// reaches the cap is retried in halves, whose gradient the fit only approximates.
        #[serde(default)]
        fit_newton_iterations: Option<usize>,
        /// Options of every output-error fit.
        output_error: OutputErrorOptions,
    },
    /// Solver optimisation: tune an iterative solver's relative tolerance for least work
    /// with the trajectory within `accuracy` of the direct solver's.
    TuneSolver {
        /// The iterative configuration.
        solver: deform_solvers::SolverSpec,
        /// What to tune, jointly (default: the relative tolerance).
        #[serde(default = "relative_tolerance")]
        parameters: Vec<deform_learn::tuning::SolverParameter>,
        /// Work of a factorisation flop relative to a solve flop.
        #[serde(default = "unit")]
        factor_weight: f64,
        /// Work of a flop of a sequential sweep (IC(0)'s triangular solves, SSOR) relative to
        /// a solve flop (see `deform_solvers::WorkWeights`); 1 counts plain flops.
        #[serde(default = "unit")]
        sweep_weight: f64,
        /// Relative max-norm position accuracy to keep.
        #[serde(default = "accuracy")]
        accuracy: f64,
        /// Nelder-Mead iterations.
        #[serde(default = "twenty")]
        max_iterations: u64,
    },
}

fn one() -> usize {
    1
}

fn one_factor() -> Vec<usize> {
    vec![1]
}

fn eight() -> u32 {
    8
}

fn weights() -> Vec<f64> {
    vec![0.0, 1e-3, 1e-2]
}

fn yes() -> bool {
    true
}

fn relative_tolerance() -> Vec<deform_learn::tuning::SolverParameter> {
    vec![deform_learn::tuning::SolverParameter::RelativeTolerance]
}

fn five() -> usize {
    deform_learn::policy::DEFAULT_NEIGHBOURS
}

fn twenty_usize() -> usize {
    20
}

/// How the learned policy's parameters are tuned in a solver-selection experiment: Newton's
/// relative tolerance, the largest forcing term (when the task has `forcing`), and Newton's
/// tangent projection (the scenes' own or one of `projections`), for the least work on the
/// first training trajectory and `scenes` within `accuracy`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct PolicyTune {
    /// Relative max-norm position error allowed against the direct reference.
    #[serde(default = "accuracy")]
    pub accuracy: f64,
    /// Nelder-Mead iterations (per projection tried).
    #[serde(default = "twelve")]
    pub max_iterations: u64,
    /// More training scenes simulated by every evaluation (paths relative to the
    /// experiment file).
    #[serde(default)]
    pub scenes: Vec<SceneRun>,
    /// Tangent projections tried besides the scenes' own; the chosen one then replaces
    /// every scene's.
    #[serde(default)]
    pub projections: Vec<deform_integrator::Projection>,
}

deform_setters::setters!(PolicyTune { accuracy: f64, max_iterations: u64, scenes: Vec<SceneRun>, projections: Vec<deform_integrator::Projection> });

impl Default for PolicyTune {
    /// The defaults of an experiment file's `tune: Some(())`.
    fn default() -> Self {
        Self {
            accuracy: accuracy(),
            max_iterations: twelve(),
            scenes: Vec::new(),
            projections: Vec::new(),
        }
    }
}

fn twelve() -> u64 {
    12
}

/// A scene file and how many steps to simulate it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct SceneRun {
    /// Scene file, relative to the experiment file.
    pub scene: PathBuf,
    /// Steps to simulate.
    pub steps: usize,
}

deform_setters::setters!(SceneRun {
    scene: PathBuf,
    steps: usize
});

impl SceneRun {
    /// `steps` steps of the scene file `scene`.
    pub fn new(scene: impl Into<PathBuf>, steps: usize) -> Self {
        let scene = scene.into();
        Self { scene, steps }
    }
}

fn unit() -> f64 {
    1.0
}

fn success() -> f64 {
    deform_learn::policy::DEFAULT_MIN_SUCCESS
}

fn accuracy() -> f64 {
    1e-6
}

fn twenty() -> u64 {
    20
}

/// Where an experiment's data come from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Data {
    /// Simulated by the base scene (the file's `dataset`).
    Generate(DatasetSpec),
    /// Made elsewhere (the file's `import`); the scene is the model to learn.
    Import(ImportSpec),
}

impl Data {
    /// Number of trajectories.
    pub fn trajectories(&self) -> usize {
        match self {
            Data::Generate(d) => d.trajectories,
            Data::Import(i) => i.trajectories.len(),
        }
    }

    /// Train and validation fractions (the rest is test).
    pub fn split(&self) -> (f64, f64) {
        match self {
            Data::Generate(d) => d.split,
            Data::Import(i) => i.split,
        }
    }

    /// How many times coarser than the data the learned model steps.
    pub fn subsample(&self) -> usize {
        match self {
            Data::Generate(d) => d.subsample,
            Data::Import(i) => i.subsample,
        }
    }

    /// Noise added to the data.
    pub fn noise(&self) -> Option<Noise> {
        match self {
            Data::Generate(d) => d.noise,
            Data::Import(i) => i.noise,
        }
    }
}

/// An experiment.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "ExperimentFile", into = "ExperimentFile")]
#[non_exhaustive]
pub struct Experiment {
    /// Name (results folder).
    pub name: String,
    /// The base model's scene file, relative to the experiment file: it makes the data, or,
    /// for imported data, it is the model to learn.
    pub scene: PathBuf,
    /// The data.
    pub data: Data,
    /// What to learn.
    pub task: Task,
}

deform_setters::setters!(Experiment {
    name: String,
    scene: PathBuf,
    data: Data,
    task: Task
});

impl Experiment {
    /// The experiment `name` running `task` on `data` for the scene file `scene` (what an
    /// experiment file holds; [`Experiment::load`] reads one).
    pub fn new(name: impl Into<String>, scene: impl Into<PathBuf>, data: Data, task: Task) -> Self {
        Self {
            name: name.into(),
            scene: scene.into(),
            data,
            task,
        }
    }
}

/// An experiment as its file states it: `dataset` (generate) or `import`, exactly one.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, rename = "Experiment")]
struct ExperimentFile {
    name: String,
    scene: PathBuf,
    #[serde(
        default,
        deserialize_with = "present",
        skip_serializing_if = "Option::is_none"
    )]
    dataset: Option<DatasetSpec>,
    #[serde(
        default,
        deserialize_with = "present",
        skip_serializing_if = "Option::is_none"
    )]
    import: Option<ImportSpec>,
    task: Task,
}

/// A field that is either absent (`None`, by `default`) or written plainly, without RON's
/// `Some(...)`.
fn present<'de, D, T>(d: D) -> Result<Option<T>, D::Error>
where
    D: serde::Deserializer<'de>,
    T: Deserialize<'de>,
{
    T::deserialize(d).map(Some)
}

impl TryFrom<ExperimentFile> for Experiment {
    type Error = String;

    fn try_from(f: ExperimentFile) -> Result<Self, String> {
        let data = match (f.dataset, f.import) {
            (Some(d), None) => Data::Generate(d),
            (None, Some(i)) => Data::Import(i),
            (Some(_), Some(_)) => {
                return Err("give `dataset` (generate) or `import`, not both".into());
            }
            (None, None) => return Err("missing field `dataset` (or `import`)".into()),
        };
        Ok(Self {
            name: f.name,
            scene: f.scene,
            data,
            task: f.task,
        })
    }
}

impl From<Experiment> for ExperimentFile {
    fn from(e: Experiment) -> Self {
        let (dataset, import) = match e.data {
            Data::Generate(d) => (Some(d), None),
            Data::Import(i) => (None, Some(i)),
        };
        Self {
            name: e.name,
            scene: e.scene,
            dataset,
            import,
            task: e.task,
        }
    }
}

/// A given embedding of a coarse mesh's vertices in a fine mesh ([`Task::Coarsen`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct EmbeddingFiles {
    /// The fine element of each coarse vertex, an `.npy` of integers (vertices,).
    pub elements: PathBuf,
    /// Its barycentric weights in that element's vertex order, (vertices, 4).
    pub weights: PathBuf,
}

deform_setters::setters!(EmbeddingFiles {
    elements: PathBuf,
    weights: PathBuf
});

impl EmbeddingFiles {
    /// The embedding's element and weight files.
    pub fn new(elements: impl Into<PathBuf>, weights: impl Into<PathBuf>) -> Self {
        let (elements, weights) = (elements.into(), weights.into());
        Self { elements, weights }
    }
}

impl Experiment {
    /// Parses experiment text and validates it; `path` names it in errors. Scene paths
    /// stay as written. An optional field may be written bare (`test: (...)` for
    /// `test: Some((...))`).
    ///
    /// # Errors
    /// [`LearnError::Parse`] (with line and column) or [`LearnError::Config`] naming the
    /// field.
    pub fn parse(text: &str, path: &Path) -> Result<Self, LearnError> {
        let options = ron::Options::default()
            .with_default_extension(ron::extensions::Extensions::IMPLICIT_SOME);
        let e: Experiment = options.from_str(text).map_err(|e| LearnError::Parse {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })?;
        e.validate().map_err(|(field, reason)| LearnError::Config {
            path: path.to_path_buf(),
            field: field.to_owned(),
            reason,
        })?;
        Ok(e)
    }

    /// The generated dataset's conditions against the scene's constraints and loads, named
    /// in the experiment file `path` (they were reported against the scene when the data were
    /// made).
    fn check_conditions(&self, path: &Path) -> Result<(), LearnError> {
        let Data::Generate(d) = &self.data else {
            return Ok(());
        };
        if d.conditions.is_empty() {
            return Ok(());
        }
        let scene = deform_integrator::Scene::load(&self.scene)?;
        for (k, c) in d.conditions.iter().enumerate() {
            c.validate(scene.constraints.len(), scene.loads.len())
                .map_err(|(field, reason)| LearnError::Config {
                    path: path.to_path_buf(),
                    field: format!("dataset.conditions[{k}].{field}"),
                    reason,
                })?;
        }
        Ok(())
    }

    /// Reads an experiment file; scene paths are made relative to its directory.
    ///
    /// # Errors
    /// [`LearnError::Io`], [`LearnError::Parse`] (with line and column) or
    /// [`LearnError::Config`] naming the file and the field.
    pub fn load(path: &Path) -> Result<Self, LearnError> {
        let text = std::fs::read_to_string(path).map_err(|source| LearnError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let mut e = Self::parse(&text, path)?;
        let dir = path.parent().unwrap_or(Path::new("."));
        if e.scene.is_relative() {
            e.scene = deform_fs::join_clean(dir, &e.scene);
        }
        e.check_conditions(path)?;
        if let Task::SelectSolver {
            held_out,
            also_train,
            tune,
            ..
        } = &mut e.task
        {
            let tuned = tune.iter_mut().flat_map(|t| t.scenes.iter_mut());
            for h in held_out.iter_mut().chain(also_train).chain(tuned) {
                if h.scene.is_relative() {
                    h.scene = deform_fs::join_clean(dir, &h.scene);
                }
            }
        }
        if let Task::Coarsen {
            mesh,
            embedding,
            region_tags,
            ..
        } = &mut e.task
        {
            mesh.resolve_paths(dir);
            let embedding = embedding
                .iter_mut()
                .flat_map(|e| [&mut e.elements, &mut e.weights]);
            for file in embedding.chain(region_tags) {
                if file.is_relative() {
                    *file = deform_fs::join_clean(dir, file);
                }
            }
        }
        if let Data::Import(import) = &mut e.data {
            import.resolve_paths(dir);
        }
        Ok(e)
    }

    /// Checks the values serde cannot, before any work starts: the field and why.
    fn validate(&self) -> Result<(), (&'static str, String)> {
        self.validate_dataset()?;
        let positive = |field: &'static str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err((field, format!("{v} must be finite and > 0")))
            }
        };
        let output = |field: &'static str, o: &OutputErrorOptions| {
            if o.rollout == 0 {
                return Err((field, "rollout must be at least 1".to_owned()));
            }
            if !(o.velocity_weight.is_finite() && o.velocity_weight >= 0.0) {
                return Err((
                    field,
                    format!("velocity_weight {} must be >= 0", o.velocity_weight),
                ));
            }
            Ok(())
        };
        let candidates = |c: &[deform_solvers::SolverSpec]| {
            if c.is_empty() {
                return Err(("task.candidates", "needs at least one solver".to_owned()));
            }
            for s in c {
                s.build().map_err(|e| ("task.candidates", e.to_string()))?;
            }
            Ok(())
        };
        match &self.task {
            Task::FitMaterial { output_error, .. } => {
                if let Some(o) = output_error {
                    output("task.output_error", o)?;
                }
            }
            Task::SelectModel {
                members,
                output_error,
            } => {
                if members.is_empty() {
                    return Err(("task.members", "needs at least one model".into()));
                }
                if let Some(o) = output_error {
                    output("task.output_error", o)?;
                }
            }
            Task::SelectSolver {
                candidates: c,
                neighbours,
                min_success,
                factor_weight,
                sweep_weight,
                repeats,
                forcing,
                tune,
                ..
            } => {
                candidates(c)?;
                if *neighbours == 0 {
                    return Err(("task.neighbours", "must be at least 1".into()));
                }
                if !(*min_success >= 0.0 && *min_success <= 1.0) {
                    return Err((
                        "task.min_success",
                        format!("{min_success} must be in [0, 1]"),
                    ));
                }
                positive("task.factor_weight", *factor_weight)?;
                positive("task.sweep_weight", *sweep_weight)?;
                if *repeats == 0 {
                    return Err(("task.repeats", "must be at least 1".into()));
                }
                if let Some((eta, gamma)) = forcing
                    && !(*eta > 0.0 && *eta < 1.0 && *gamma > 0.0 && *gamma <= 1.0)
                {
                    return Err((
                        "task.forcing",
                        format!("({eta}, {gamma}): eta_max must be in (0, 1), gamma in (0, 1]"),
                    ));
                }
                if let Some(t) = tune {
                    positive("task.tune.accuracy", t.accuracy)?;
                }
            }
            Task::TuneBackwardEuler {
                output_error,
                candidates: c,
                factor_weight,
                sweep_weight,
                accuracy,
                ..
            } => {
                output("task.output_error", output_error)?;
                candidates(c)?;
                positive("task.factor_weight", *factor_weight)?;
                positive("task.sweep_weight", *sweep_weight)?;
                positive("task.accuracy", *accuracy)?;
            }
            Task::Coarsen { output_error, .. } => {
                self.validate_coarsen()?;
                output("task.output_error", output_error)?;
            }
            Task::TuneSolver {
                solver,
                parameters,
                factor_weight,
                sweep_weight,
                accuracy,
                ..
            } => {
                solver.build().map_err(|e| ("task.solver", e.to_string()))?;
                if parameters.is_empty() {
                    return Err(("task.parameters", "needs at least one parameter".into()));
                }
                if (1..parameters.len()).any(|i| parameters[..i].contains(&parameters[i])) {
                    return Err(("task.parameters", format!("{parameters:?} repeats one")));
                }
                positive("task.factor_weight", *factor_weight)?;
                positive("task.sweep_weight", *sweep_weight)?;
                positive("task.accuracy", *accuracy)?;
            }
        }
        Ok(())
    }

    /// [`Task::Coarsen`]'s values.
    fn validate_coarsen(&self) -> Result<(), (&'static str, String)> {
        let Task::Coarsen {
            test,
            dt_factors,
            regions,
            regularisation,
            material,
            newton_rel,
            fit_newton_iterations,
            ..
        } = &self.task
        else {
            return Ok(());
        };
        if *fit_newton_iterations == Some(0) {
            return Err(("task.fit_newton_iterations", "must be at least 1".into()));
        }
        if let Some(m) = material {
            m.build().map_err(|e| ("task.material", e.to_string()))?;
        }
        if let Some(test) = test
            && (test.trajectories == 0 || test.steps == 0)
        {
            return Err((
                "task.test",
                "needs at least one step of one trajectory".into(),
            ));
        }
        if dt_factors.is_empty() || dt_factors.contains(&0) {
            return Err((
                "task.dt_factors",
                format!("{dt_factors:?}: needs factors >= 1"),
            ));
        }
        let data_steps = match (&self.data, test) {
            (Data::Import(_), Some(_)) => {
                return Err((
                    "task.test",
                    "imported data have no base model of deform's to simulate held-out motions: leave `test` out, and the data's test split is held out".into(),
                ));
            }
            (Data::Generate(d), Some(t)) => d.steps.min(t.steps),
            (Data::Generate(d), None) => d.steps,
            // Imported trajectories' lengths are known once read.
            (Data::Import(_), None) => usize::MAX,
        };
        if test.is_none() {
            let (a, b) = self.data.split();
            let count = self.data.trajectories();
            if deform_learn::dataset::split_counts(count, (a, b)).2 == 0 {
                return Err((
                    "task.test",
                    format!(
                        "without held-out motions the data's test split is held out, and ({a}, {b}) of {count} trajectories leaves none"
                    ),
                ));
            }
        }
        if let Some(k) = dt_factors.iter().find(|&&k| 2 * k > data_steps) {
            return Err((
                "task.dt_factors",
                format!("{k} leaves less than two coarse steps"),
            ));
        }
        if *regions == 0 {
            return Err(("task.regions", "must be at least 1".into()));
        }
        if regularisation.is_empty() || !regularisation.iter().all(|w| w.is_finite() && *w >= 0.0) {
            return Err((
                "task.regularisation",
                format!("{regularisation:?}: needs weights >= 0"),
            ));
        }
        if !newton_rel.iter().all(|r| *r > 0.0 && *r < 1.0) {
            return Err((
                "task.newton_rel",
                format!("{newton_rel:?}: needs tolerances in (0, 1)"),
            ));
        }
        Ok(())
    }

    fn validate_dataset(&self) -> Result<(), (&'static str, String)> {
        let (trajectories, subsample, split, noise) = match &self.data {
            Data::Generate(d) => {
                if d.steps == 0 {
                    return Err(("dataset.steps", "must be at least 1".into()));
                }
                if d.subsample == 0 || d.steps < 2 * d.subsample {
                    return Err((
                        "dataset.subsample",
                        "must be at least 1 and leave two coarse steps".into(),
                    ));
                }
                (
                    "dataset.trajectories",
                    "dataset.subsample",
                    "dataset.split",
                    "dataset.noise",
                )
            }
            Data::Import(i) => {
                if !(i.dt.is_finite() && i.dt > 0.0) {
                    return Err(("import.dt", format!("{} must be finite and > 0", i.dt)));
                }
                if !i.gravity.iter().all(|g| g.is_finite()) {
                    return Err(("import.gravity", format!("{:?} must be finite", i.gravity)));
                }
                if i.subsample == 0 {
                    return Err(("import.subsample", "must be at least 1".into()));
                }
                (
                    "import.trajectories",
                    "import.subsample",
                    "import.split",
                    "import.noise",
                )
            }
        };
        let count = self.data.trajectories();
        if count == 0 {
            return Err((trajectories, "must be at least 1".into()));
        }
        let (a, b) = self.data.split();
        // Every task but solver tuning and coarsening reports on the test trajectories.
        let needs_test = !matches!(self.task, Task::TuneSolver { .. } | Task::Coarsen { .. });
        let room = if needs_test {
            a + b < 1.0
        } else {
            a + b <= 1.0
        };
        if !(a > 0.0 && b >= 0.0 && room) {
            return Err((
                split,
                format!("({a}, {b}) must leave room for a test split"),
            ));
        }
        if let Task::Coarsen { .. } = self.task
            && self.data.subsample() != 1
        {
            return Err((subsample, "must be 1: coarsening has dt_factors".into()));
        }
        // Model selection and coarsening choose on validation trajectories.
        let needs_validation = match &self.task {
            Task::SelectModel { .. } | Task::Coarsen { .. } => true,
            Task::TuneBackwardEuler { members, .. } => !members.is_empty(),
            _ => false,
        };
        let (_, validation, test) = deform_learn::dataset::split_counts(count, (a, b));
        let missing = match (needs_validation && validation == 0, needs_test && test == 0) {
            (true, _) => Some("validation"),
            (false, true) => Some("test"),
            (false, false) => None,
        };
        if let Some(which) = missing {
            let advice = split_advice(count, needs_validation, needs_test);
            return Err((
                split,
                format!(
                    "({a}, {b}) of {count} trajectories leaves no {which} trajectory: {advice}"
                ),
            ));
        }
        if let Some(n) = self.data.noise()
            && !(n.position.is_finite()
                && n.position >= 0.0
                && n.velocity.is_finite()
                && n.velocity >= 0.0)
        {
            return Err((noise, format!("{n:?}: levels must be finite and >= 0")));
        }
        Ok(())
    }
}

/// What to write instead of a split that leaves no validation or test trajectory: a split
/// of `count` trajectories with one of each that the task needs and the rest for training,
/// or how many trajectories it needs.
fn split_advice(count: usize, validation: bool, test: bool) -> String {
    let (v, t) = (usize::from(validation), usize::from(test));
    let needed = 1 + v + t;
    if count < needed {
        return format!(
            "this task needs at least {needed} trajectories (train, and one each for validation and test as it uses them)"
        );
    }
    let fraction = |k: usize| k as f64 / count as f64;
    format!(
        "use split: ({:.3}, {:.3}) ({} train, {v} validation, {t} test)",
        fraction(count - v - t),
        fraction(v),
        count - v - t
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The advised split, as printed, gives every count from 2 to 200 the trajectories the
    /// task needs (at least one to train on).
    #[test]
    fn the_advised_split_leaves_what_the_task_needs() {
        for count in 1..=200 {
            for (validation, test) in [(false, true), (true, false), (true, true)] {
                let advice = split_advice(count, validation, test);
                let Some(rest) = advice.strip_prefix("use split: (") else {
                    assert!(
                        count < 1 + usize::from(validation) + usize::from(test),
                        "{advice}"
                    );
                    continue;
                };
                let numbers: Vec<f64> = rest
                    .split(')')
                    .next()
                    .unwrap()
                    .split(", ")
                    .map(|x| x.parse().unwrap())
                    .collect();
                let (train, v, t) =
                    deform_learn::dataset::split_counts(count, (numbers[0], numbers[1]));
                assert!(train >= 1, "{count}: {advice}");
                assert!(!validation || v >= 1, "{count}: {advice}");
                assert!(!test || t >= 1, "{count}: {advice}");
            }
        }
    }
}
