//! Trajectory datasets: pairs `((x^n, v^n), (x^n+1, v^n+1))` from a base model, on disk as
//! RON metadata plus `.npy` arrays that numpy loads directly.
//!
//! Layout of a dataset folder (docs/experiments.md):
//!
//! ```text
//! meta.ron                  DatasetMeta: the base scene, seed, versions, splits, noise
//! traj_000/x.npy            positions,  shape (steps + 1, vertices, 3), float64
//! traj_000/v.npy            velocities, same shape
//! traj_000/markers.npy      observed marker positions, shape (steps + 1, markers, 3), when
//!                           only markers were observed (meta.ron lists the markers)
//! traj_001/...
//! ```

use std::path::{Path, PathBuf};

use deform_fs::write_atomic;
use deform_integrator::scene::{Built, Initial};
use deform_integrator::{
    Conditions, Integrator, IntegratorError, OnStep, RunOptions, Scene, State, StepError,
    StepReport, Termination,
};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::markers::{Marker, Observed};
use crate::rng::Rng;
use deform_fs::npy::{self, NpyError};

/// Which part of the data a trajectory belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Split {
    /// Fitting.
    Train,
    /// Model selection and early stopping.
    Validation,
    /// Held out for the final figures.
    Test,
}

/// One trajectory: states at `start_time + n dt`, `n = 0..=steps`. Outside this crate,
/// build it from `Default` and its setters (`Trajectory::default().x(x).v(v)`).
#[derive(Debug, Clone, PartialEq, Default)]
#[non_exhaustive]
pub struct Trajectory {
    /// The time of its first frame (s): 0, or `dt` for positions whose first frame was
    /// dropped for want of a velocity ([`crate::import::Velocities::Derived`]). Moving
    /// constraints and loads are evaluated at `start_time + n dt`.
    pub start_time: f64,
    /// Positions per step, flat `3N` each.
    pub x: Vec<Vec<f64>>,
    /// Velocities per step.
    pub v: Vec<Vec<f64>>,
    /// The first state is known exactly (e.g. a release from a known shape at rest): fits
    /// that estimate rollout starts keep it ([`crate::output::OutputErrorOptions::starts`]).
    pub exact_start: bool,
    /// The conditions it was made under where they differ from the model's (gravity,
    /// constraint motions, loads): every fit, rollout and solver log steps it under them.
    pub conditions: Conditions,
    /// What was observed, when not the whole state ([`crate::observe`]: markers at vertices
    /// or inside elements, what a capture gives): the output error and the rollout error
    /// compare only the markers, and the frames after the first are not read. The first
    /// frame holds the first state, known or estimated ([`crate::observe::estimate_start`]).
    pub observed: Option<Observed>,
}

deform_setters::setters!(Trajectory {
    start_time: f64,
    x: Vec<Vec<f64>>,
    v: Vec<Vec<f64>>,
    exact_start: bool,
    conditions: Conditions,
    observed: Option<Observed>,
});

impl Trajectory {
    /// Number of steps (pairs).
    pub fn steps(&self) -> usize {
        self.x.len().saturating_sub(1)
    }

    /// Runs `f` with `sim` under this trajectory's conditions, then puts back those `sim`
    /// had: every loop over a dataset's trajectories with one model goes through here.
    ///
    /// # Errors
    /// [`IntegratorError::Invalid`] when the conditions do not fit the model (another
    /// number of constraints or loads).
    pub fn under<R>(
        &self,
        sim: &mut Integrator,
        f: impl FnOnce(&mut Integrator) -> R,
    ) -> Result<R, IntegratorError> {
        if self.conditions == *sim.conditions() {
            return Ok(f(sim));
        }
        let previous = sim.conditions().clone();
        sim.set_conditions(&self.conditions)?;
        let out = f(sim);
        sim.set_conditions(&previous)
            .expect("the conditions in force were valid");
        Ok(out)
    }
}

/// What a trajectory started from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct TrajectoryMeta {
    /// Folder name inside the dataset.
    pub name: String,
    /// Its split.
    pub split: Split,
    /// Number of steps.
    pub steps: usize,
    /// The initial conditions used (the scene's own for imported data).
    pub initial: Initial,
    /// The positions file an imported trajectory came from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<PathBuf>,
    /// Its first state is known exactly ([`Trajectory::exact_start`]).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub exact_start: bool,
    /// The conditions it was made under where they differ from the scene's
    /// ([`Trajectory::conditions`]).
    #[serde(default, skip_serializing_if = "Conditions::is_default")]
    pub conditions: Conditions,
    /// The time of its first frame ([`Trajectory::start_time`]).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub start_time: f64,
    /// The markers, when only they were observed ([`Trajectory::observed`]); their positions
    /// are in `markers.npy`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub observed: Option<Vec<Marker>>,
}

/// Gaussian noise added after generation.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct Noise {
    /// Standard deviation of position noise, relative to the RMS displacement from rest
    /// over the trajectory (0.01 = "1 % position noise").
    pub position: f64,
    /// Standard deviation of velocity noise, relative to the RMS velocity.
    pub velocity: f64,
    /// Seed of the noise.
    pub seed: u64,
}

deform_setters::setters!(Noise {
    position: f64,
    velocity: f64,
    seed: u64,
});

/// Everything needed to reproduce or reinterpret a dataset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct DatasetMeta {
    /// Format version of this layout.
    pub format: u32,
    /// deform's version that wrote it.
    pub deform_version: String,
    /// The base model's full scene (mesh, material, constraints, integrator, policy).
    pub scene: Scene,
    /// Seed of the initial-condition variations.
    pub seed: u64,
    /// Time step.
    pub dt: f64,
    /// Number of vertices.
    pub vertices: usize,
    /// The trajectories.
    pub trajectories: Vec<TrajectoryMeta>,
    /// Noise added, if any.
    pub noise: Option<Noise>,
}

/// A dataset in memory.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct Dataset {
    /// Metadata.
    pub meta: DatasetMeta,
    /// Trajectories, in the order of `meta.trajectories`.
    pub trajectories: Vec<Trajectory>,
}

impl Dataset {
    /// The dataset of `trajectories` described by `meta` (one entry per trajectory, in their
    /// order).
    pub fn new(meta: DatasetMeta, trajectories: Vec<Trajectory>) -> Self {
        Self { meta, trajectories }
    }
}

/// How to vary the initial conditions between trajectories.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
#[non_exhaustive]
pub struct Variations {
    /// Largest uniform initial speed (m/s), random direction.
    pub speed: f64,
    /// Largest initial angular speed (rad/s), random axis.
    pub spin: f64,
    /// Largest relative stretch or squeeze per axis of the released initial shape.
    pub stretch: f64,
    /// Start every trajectory from rest (no variation); overrides the above.
    pub rest: bool,
}

deform_setters::setters!(Variations {
    speed: f64,
    spin: f64,
    stretch: f64,
    rest: bool,
});

impl Default for Variations {
    fn default() -> Self {
        Self {
            speed: 1.0,
            spin: 2.0,
            stretch: 0.1,
            rest: false,
        }
    }
}

/// Why a dataset could not be made, read or written.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum DatasetError {
    /// An array file.
    #[error(transparent)]
    Npy(#[from] NpyError),
    /// The metadata file.
    #[error("{path}: {reason}")]
    Meta {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// Building the scene.
    #[error(transparent)]
    Scene(#[from] deform_integrator::SceneError),
    /// A step of the base model failed.
    #[error("trajectory {trajectory}, step {step}: {source}")]
    Step {
        /// Trajectory index.
        trajectory: usize,
        /// Step index.
        step: usize,
        /// The failure.
        source: Box<StepError>,
    },
    /// Arrays disagree with the metadata or each other.
    #[error("{0}")]
    Inconsistent(String),
}

/// Current layout version.
pub(crate) const FORMAT: u32 = 1;

/// Split `count` trajectories by the fractions `(train, validation)`, the rest test; at least
/// one trajectory in each non-empty split when there are three or more.
pub(crate) fn split_of(k: usize, count: usize, fractions: (f64, f64)) -> Split {
    let (train, val, _) = split_counts(count, fractions);
    if k < train {
        Split::Train
    } else if k < train + val {
        Split::Validation
    } else {
        Split::Test
    }
}

/// Trajectories in the train, validation and test splits of `count` by `fractions`.
pub fn split_counts(count: usize, fractions: (f64, f64)) -> (usize, usize, usize) {
    let train = ((fractions.0 * count as f64).round() as usize).clamp(1, count.max(1));
    let val = ((fractions.1 * count as f64).round() as usize).min(count.saturating_sub(train));
    (train, val, count.saturating_sub(train + val))
}

/// How to make the dataset: [`DatasetSpec::new`] and setters for the rest, which keep
/// working when a field is added.
///
/// ```
/// use deform_learn::DatasetSpec;
///
/// let spec = DatasetSpec::new(6, 40, 1).split((0.5, 0.25));
/// assert_eq!((spec.trajectories, spec.split), (6, (0.5, 0.25)));
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct DatasetSpec {
    /// Number of trajectories.
    pub trajectories: usize,
    /// Steps per trajectory.
    pub steps: usize,
    /// Seed of the initial-condition variations.
    pub seed: u64,
    /// Initial-condition variations.
    #[serde(default)]
    pub variations: Variations,
    /// Train and validation fractions (the rest is test).
    #[serde(default = "default_split")]
    pub split: (f64, f64),
    /// Noise added to the data.
    #[serde(default)]
    pub noise: Option<Noise>,
    /// Learn a model that steps `subsample` times coarser than the base: the data keep every
    /// `subsample`-th state and the learned scene uses `subsample x dt` (the seed's accuracy
    /// claim: a cheap model fitted to an accurate one). 1 learns at the base's own step.
    #[serde(default = "one")]
    pub subsample: usize,
    /// Conditions to cycle through: trajectory `k` is made under `conditions[k % len]`
    /// (gravity, constraint motions, loads overriding the scene's); empty: the scene's own.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub conditions: Vec<Conditions>,
}

deform_setters::setters!(DatasetSpec {
    trajectories: usize,
    steps: usize,
    seed: u64,
    variations: Variations,
    split: (f64, f64),
    noise: Option<Noise>,
    subsample: usize,
    conditions: Vec<Conditions>,
});

pub(crate) fn one() -> usize {
    1
}

pub(crate) fn default_split() -> (f64, f64) {
    (0.6, 0.2)
}

impl DatasetSpec {
    /// `trajectories` trajectories of `steps` steps from `seed`, no variations beyond the
    /// defaults, split 0.6 / 0.2, no noise, the base's own step.
    pub fn new(trajectories: usize, steps: usize, seed: u64) -> Self {
        Self {
            trajectories,
            steps,
            seed,
            variations: Variations::default(),
            split: default_split(),
            noise: None,
            subsample: 1,
            conditions: Vec::new(),
        }
    }
}

/// Generates `spec.trajectories` trajectories of `spec.steps` steps from `scene` (its
/// `initial` is replaced by random variations drawn from `spec.seed`), split
/// `(train, validation)` by `spec.split`, the rest test. `progress(trajectory, step)` is
/// called after every step. Noise and subsampling are the caller's ([`Dataset::add_noise`],
/// [`Dataset::subsample`]).
///
/// # Errors
/// [`DatasetError`] naming the trajectory and step that failed.
pub fn generate(
    scene: &Scene,
    origin: &Path,
    spec: &DatasetSpec,
    mut progress: impl FnMut(usize, usize),
) -> Result<Dataset, DatasetError> {
    let (count, steps, seed) = (spec.trajectories, spec.steps, spec.seed);
    let (variations, fractions) = (&spec.variations, spec.split);
    // Every draw first, in trajectory order: the data do not depend on how they are run.
    let mut rng = Rng::new(seed);
    let starts: Vec<(Initial, Conditions)> = (0..count)
        .map(|k| {
            let initial = draw_initial(scene, variations, &mut rng);
            let conditions = match spec.conditions.as_slice() {
                [] => Conditions::default(),
                all => all[k % all.len()].clone(),
            };
            (initial, conditions)
        })
        .collect();
    let trajectories = simulate_all(scene, origin, &starts, steps, &mut progress)?;
    let metas = (starts.into_iter().enumerate())
        .map(|(k, (initial, conditions))| TrajectoryMeta {
            name: format!("traj_{k:03}"),
            split: split_of(k, count, fractions),
            steps,
            initial,
            source: None,
            start_time: 0.0,
            exact_start: false,
            conditions,
            observed: None,
        })
        .collect();
    let vertices = trajectories
        .first()
        .map_or(0, |t: &Trajectory| t.x[0].len() / 3);
    Ok(Dataset {
        meta: DatasetMeta {
            format: FORMAT,
            deform_version: env!("CARGO_PKG_VERSION").to_owned(),
            scene: scene.clone(),
            seed,
            dt: scene.integrator.dt,
            vertices,
            trajectories: metas,
            noise: None,
        },
        trajectories,
    })
}

/// A random initial state of `scene` (the scene's own when `variations.rest`).
fn draw_initial(scene: &Scene, variations: &Variations, rng: &mut Rng) -> Initial {
    if variations.rest {
        return scene.initial.clone();
    }
    let dir = |rng: &mut Rng| {
        let v = Vector3::new(rng.normal(), rng.normal(), rng.normal());
        v / v.norm().max(1e-12)
    };
    let speed = rng.range(0.0, variations.speed);
    let spin = rng.range(0.0, variations.spin);
    let (d1, d2) = (dir(rng), dir(rng));
    let s = variations.stretch;
    Initial::default()
        .velocity((d1 * speed).into())
        .angular_velocity((d2 * spin).into())
        .equilibrium(false)
        .scale(Some([
            rng.range(1.0 - s, 1.0 + s),
            rng.range(1.0 - s, 1.0 + s),
            rng.range(1.0 - s, 1.0 + s),
        ]))
        .state(None)
}

/// Trajectory `k`: `steps` steps of `scene` from `initial` under `conditions`, by an
/// integrator of its own; `progress(step)` after each step.
fn simulate_one(
    scene: &Scene,
    origin: &Path,
    (k, (initial, conditions)): (usize, &(Initial, Conditions)),
    steps: usize,
    progress: &mut dyn FnMut(usize),
) -> Result<Trajectory, DatasetError> {
    let mut variant = scene.with_conditions(conditions, origin)?;
    variant.initial = initial.clone();
    let Built {
        mut integrator,
        mut state,
        ..
    } = variant.build(origin)?;
    let mut traj = Trajectory {
        x: vec![state.x.clone()],
        v: vec![state.v.clone()],
        start_time: 0.0,
        exact_start: false,
        conditions: conditions.clone(),
        observed: None,
    };
    let summary = integrator.run(
        &mut state,
        &RunOptions::steps(steps),
        &mut OnStep(|report: &StepReport, state: &State| {
            traj.x.push(state.x.clone());
            traj.v.push(state.v.clone());
            progress(report.step);
        }),
    );
    if let Termination::Failed { step, error } = summary.termination {
        return Err(DatasetError::Step {
            trajectory: k,
            step,
            source: error,
        });
    }
    Ok(traj)
}

/// Every trajectory of `starts`, in order. Below
/// `lanes::SIDE_BY_SIDE_MAX_DOFS` (20,000) free DOFs they run side by side
/// (`lanes::side_by_side`; each has its own integrator, so the bits do not depend
/// on the thread count); `progress` is called on this thread.
fn simulate_all(
    scene: &Scene,
    origin: &Path,
    starts: &[(Initial, Conditions)],
    steps: usize,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<Vec<Trajectory>, DatasetError> {
    let small = || -> Result<bool, DatasetError> {
        let free = scene.build(origin)?.integrator.dofs().num_free();
        Ok(crate::lanes::worth_it(starts.len(), free))
    };
    if starts.len() < 2 || !small()? {
        return (starts.iter().enumerate())
            .map(|job| simulate_one(scene, origin, job, steps, &mut |s| progress(job.0, s)))
            .collect();
    }
    let mut lanes = vec![(); rayon::current_num_threads().min(starts.len())];
    let run = |_: &mut (), k: usize, step: &mut dyn FnMut(usize)| {
        simulate_one(scene, origin, (k, &starts[k]), steps, step)
    };
    crate::lanes::side_by_side(&mut lanes, starts.len(), &run, progress)
}

impl Dataset {
    /// The trajectories of one split.
    pub fn split(&self, split: Split) -> Vec<&Trajectory> {
        self.meta
            .trajectories
            .iter()
            .zip(&self.trajectories)
            .filter(|(m, _)| m.split == split)
            .map(|(_, t)| t)
            .collect()
    }

    /// Names a failure on the trajectories of `splits` (as a fit was given them: split after
    /// split, each in dataset order) by the dataset's numbering, the trajectory's name and the
    /// file it was read from; failures about no trajectory pass unchanged. A fit numbers
    /// trajectories within what it was given, which is not what a user reads in the dataset.
    pub fn blame<E: Into<crate::LearnError>>(
        &self,
        splits: &[Split],
    ) -> impl Fn(E) -> crate::LearnError + '_ {
        let order: Vec<usize> = splits.iter().flat_map(|&s| self.indices(s)).collect();
        move |e| {
            let fit = match e.into() {
                crate::LearnError::Fit(fit) => fit,
                other => return other,
            };
            match fit.trajectory().and_then(|k| order.get(k)) {
                Some(&k) => crate::LearnError::InTrajectory {
                    name: self.describe(k),
                    source: Box::new(fit.renumbered(k).into()),
                },
                None => fit.into(),
            }
        }
    }

    /// Trajectory `k`'s name, and the file it was read from when it was imported.
    pub fn describe(&self, k: usize) -> String {
        let meta = &self.meta.trajectories[k];
        match &meta.source {
            Some(path) => format!("{}, read from {}", meta.name, path.display()),
            None => meta.name.clone(),
        }
    }

    /// The dataset of one split's trajectories only (e.g. the held-out ones).
    pub fn only(&self, split: Split) -> Dataset {
        let keep: Vec<usize> = self.indices(split).collect();
        let mut meta = self.meta.clone();
        meta.trajectories = keep
            .iter()
            .map(|&k| self.meta.trajectories[k].clone())
            .collect();
        Dataset {
            meta,
            trajectories: keep.iter().map(|&k| self.trajectories[k].clone()).collect(),
        }
    }

    /// The indices of the trajectories of one split.
    pub fn indices(&self, split: Split) -> impl Iterator<Item = usize> + Clone + '_ {
        let metas = self.meta.trajectories.iter().enumerate();
        metas.filter(move |(_, m)| m.split == split).map(|(k, _)| k)
    }

    /// `scene` as trajectory `k` was made: under its conditions, starting where it starts
    /// (the initial conditions that generated it, or, for an imported trajectory, which has
    /// none, its first state).
    ///
    /// # Errors
    /// [`DatasetError::Scene`] when the trajectory's conditions do not fit `scene` (another
    /// number of constraints or loads).
    pub fn scene_of(&self, k: usize, scene: &Scene) -> Result<Scene, DatasetError> {
        let meta = &self.meta.trajectories[k];
        let origin = Path::new(&meta.name);
        let mut s = scene.with_conditions(&self.trajectories[k].conditions, origin)?;
        s.initial = meta.initial.clone();
        if meta.source.is_some() {
            s.initial.state = Some(state_at(&self.trajectories[k], 0, self.meta.dt));
        }
        Ok(s)
    }

    /// One dataset of several made by the same base model (the parts of a sweep over seeds,
    /// or motions made under other gravity, constraint motions or loads): their trajectories
    /// in order, renamed `traj_000`, `traj_001`, ...; the first part's scene and seed. A
    /// part whose scene differs from the first's only in its conditions keeps them: its
    /// trajectories carry them ([`Trajectory::conditions`]).
    ///
    /// # Errors
    /// [`DatasetError::Inconsistent`] naming the first part that differs from the first in
    /// anything else of the scene, time step, vertex count or noise, or for no parts.
    pub fn merge(parts: Vec<Dataset>) -> Result<Dataset, DatasetError> {
        let mut parts = parts.into_iter();
        let Some(mut out) = parts.next() else {
            return Err(DatasetError::Inconsistent("no datasets to merge".into()));
        };
        let own = out.meta.scene.conditions();
        for (k, mut part) in parts.enumerate() {
            let origin = Path::new("merge");
            let (a, b) = (&out.meta, &part.meta);
            // The part's scene with the first's conditions: equal when only they differ.
            let other_scene = match b.scene.with_conditions(&own, origin) {
                Ok(s) => s != a.scene,
                Err(_) => true,
            };
            let differs = [
                (
                    other_scene,
                    "scene (beyond gravity, constraint motions and loads)",
                ),
                (a.dt != b.dt, "time step"),
                (a.vertices != b.vertices, "vertex count"),
                (a.noise != b.noise, "noise"),
            ];
            if let Some((_, what)) = differs.iter().find(|(d, _)| *d) {
                return Err(DatasetError::Inconsistent(format!(
                    "dataset {} of the merge has another {what} than the first",
                    k + 1
                )));
            }
            if part.meta.scene != out.meta.scene {
                for (t, m) in part
                    .trajectories
                    .iter_mut()
                    .zip(&mut part.meta.trajectories)
                {
                    let made = part.meta.scene.with_conditions(&t.conditions, origin)?;
                    let full = made.conditions();
                    t.conditions = if full == own {
                        Conditions::default()
                    } else {
                        full
                    };
                    m.conditions = t.conditions.clone();
                }
            }
            out.meta.trajectories.extend(part.meta.trajectories);
            out.trajectories.extend(part.trajectories);
        }
        for (i, m) in out.meta.trajectories.iter_mut().enumerate() {
            m.name = format!("traj_{i:03}");
        }
        Ok(out)
    }

    /// Keeps every `k`-th state of every trajectory: data of a fine time step seen at the
    /// coarse step `k dt` (the setting where a cheap model learns from an accurate one).
    ///
    /// # Panics
    /// If `k == 0`.
    pub fn subsample(&self, k: usize) -> Dataset {
        assert!(k > 0, "the subsampling factor must be at least 1");
        let mut out = self.clone();
        for (t, m) in out.trajectories.iter_mut().zip(&mut out.meta.trajectories) {
            t.x = t.x.iter().step_by(k).cloned().collect();
            t.v = t.v.iter().step_by(k).cloned().collect();
            if let Some(o) = &mut t.observed {
                o.positions = o.positions.iter().step_by(k).cloned().collect();
            }
            m.steps = t.steps();
        }
        out.meta.dt *= k as f64;
        out
    }

    /// Adds Gaussian noise to positions and velocities (not to constrained vertices, whose
    /// motion is known), scaled per trajectory by the RMS displacement and RMS velocity.
    pub fn add_noise(&mut self, noise: Noise, constrained: &[usize]) {
        let mut rng = Rng::new(noise.seed);
        let rest = self
            .trajectories
            .first()
            .map(|t| t.x[0].clone())
            .unwrap_or_default();
        let mut skip = vec![false; self.meta.vertices];
        for &c in constrained {
            if c < skip.len() {
                skip[c] = true;
            }
        }
        for t in &mut self.trajectories {
            let rms = |frames: &[Vec<f64>], reference: Option<&[f64]>| {
                let (mut sum, mut count) = (0.0, 0usize);
                for f in frames {
                    for (i, v) in f.iter().enumerate() {
                        let d = v - reference.map_or(0.0, |r| r[i]);
                        sum += d * d;
                        count += 1;
                    }
                }
                (sum / count.max(1) as f64).sqrt()
            };
            let (sx, sv) = (
                noise.position * rms(&t.x, Some(&rest)),
                noise.velocity * rms(&t.v, None),
            );
            for (frames, sigma) in [(&mut t.x, sx), (&mut t.v, sv)] {
                for f in frames.iter_mut() {
                    for (i, v) in f.iter_mut().enumerate() {
                        if !skip[i / 3] {
                            *v += sigma * rng.normal();
                        }
                    }
                }
            }
        }
        self.meta.noise = Some(noise);
    }

    /// Writes the dataset folder (see the module docs); every file atomically.
    ///
    /// # Errors
    /// [`DatasetError`] naming the file.
    pub fn save(&self, dir: &Path) -> Result<(), DatasetError> {
        let meta_path = dir.join("meta.ron");
        std::fs::create_dir_all(dir).map_err(|e| DatasetError::Meta {
            path: dir.to_owned(),
            reason: e.to_string(),
        })?;
        for (m, t) in self.meta.trajectories.iter().zip(&self.trajectories) {
            let sub = dir.join(&m.name);
            std::fs::create_dir_all(&sub).map_err(|e| DatasetError::Meta {
                path: sub.clone(),
                reason: e.to_string(),
            })?;
            let shape = [t.x.len(), self.meta.vertices, 3];
            npy::write(&sub.join("x.npy"), &shape, &t.x.concat())?;
            npy::write(&sub.join("v.npy"), &shape, &t.v.concat())?;
            if let Some(o) = &t.observed {
                let shape = [o.positions.len(), o.markers.len(), 3];
                npy::write(&sub.join("markers.npy"), &shape, &o.positions.concat())?;
            }
        }
        // The markers are the trajectories' own (set on them, not on the meta).
        let mut meta = self.meta.clone();
        for (m, t) in meta.trajectories.iter_mut().zip(&self.trajectories) {
            m.observed = t.observed.as_ref().map(|o| o.markers.clone());
            m.start_time = t.start_time;
        }
        let text =
            ron::ser::to_string_pretty(&meta, ron::ser::PrettyConfig::default()).map_err(|e| {
                DatasetError::Meta {
                    path: meta_path.clone(),
                    reason: e.to_string(),
                }
            })?;
        write_atomic(&meta_path, |w| w.write_all(text.as_bytes())).map_err(|e| DatasetError::Meta {
            path: meta_path.clone(),
            reason: e.to_string(),
        })
    }

    /// Reads a dataset folder written by [`Dataset::save`] (or by hand in that layout).
    ///
    /// # Errors
    /// [`DatasetError`] naming the file and what does not match.
    pub fn load(dir: &Path) -> Result<Self, DatasetError> {
        let meta_path = dir.join("meta.ron");
        let text = std::fs::read_to_string(&meta_path).map_err(|e| DatasetError::Meta {
            path: meta_path.clone(),
            reason: e.to_string(),
        })?;
        let meta: DatasetMeta = ron::from_str(&text).map_err(|e| DatasetError::Meta {
            path: meta_path.clone(),
            reason: e.to_string(),
        })?;
        if meta.format != FORMAT {
            return Err(DatasetError::Meta {
                path: meta_path,
                reason: format!("format {} is not the supported {FORMAT}", meta.format),
            });
        }
        if meta.vertices == 0 {
            return Err(DatasetError::Meta {
                path: meta_path,
                reason: "vertices must be at least 1".into(),
            });
        }
        let mut trajectories = Vec::with_capacity(meta.trajectories.len());
        for m in &meta.trajectories {
            let read = |file: &str| -> Result<Vec<Vec<f64>>, DatasetError> {
                let path = dir.join(&m.name).join(file);
                let a = npy::read(&path)?;
                if a.shape != [m.steps + 1, meta.vertices, 3] {
                    return Err(DatasetError::Inconsistent(format!(
                        "{}: shape {:?}, meta.ron says ({}, {}, 3)",
                        path.display(),
                        a.shape,
                        m.steps + 1,
                        meta.vertices
                    )));
                }
                if let Some(i) = a.data.iter().position(|v| !v.is_finite()) {
                    return Err(DatasetError::Inconsistent(format!(
                        "{}: non-finite value at step {}, vertex {}",
                        path.display(),
                        i / (3 * meta.vertices),
                        (i / 3) % meta.vertices
                    )));
                }
                Ok(a.data
                    .chunks(3 * meta.vertices)
                    .map(<[f64]>::to_vec)
                    .collect())
            };
            let origin = dir.join(&m.name);
            meta.scene.with_conditions(&m.conditions, &origin)?;
            trajectories.push(Trajectory {
                x: read("x.npy")?,
                v: read("v.npy")?,
                start_time: m.start_time,
                exact_start: m.exact_start,
                conditions: m.conditions.clone(),
                observed: read_observed(&dir.join(&m.name), m, meta.vertices)?,
            });
        }
        Ok(Self { meta, trajectories })
    }
}

/// The observations of trajectory `m` in folder `sub`: its markers and `markers.npy`.
fn read_observed(
    sub: &Path,
    m: &TrajectoryMeta,
    vertices: usize,
) -> Result<Option<Observed>, DatasetError> {
    let Some(markers) = &m.observed else {
        return Ok(None);
    };
    let path = sub.join("markers.npy");
    if markers.is_empty() {
        let reason = "lists no observed marker".to_owned();
        return Err(DatasetError::Inconsistent(format!("{}: {reason}", m.name)));
    }
    let a = npy::read(&path)?;
    if a.shape != [m.steps + 1, markers.len(), 3] {
        return Err(DatasetError::Inconsistent(format!(
            "{}: shape {:?}, meta.ron says ({}, {}, 3)",
            path.display(),
            a.shape,
            m.steps + 1,
            markers.len()
        )));
    }
    let observed = Observed {
        markers: markers.clone(),
        positions: a
            .data
            .chunks(3 * markers.len())
            .map(<[f64]>::to_vec)
            .collect(),
    };
    observed
        .check(vertices, m.steps + 1)
        .map_err(|e| DatasetError::Inconsistent(format!("{}: {e}", path.display())))?;
    Ok(Some(observed))
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

/// The state at step `n` of a trajectory.
pub fn state_at(t: &Trajectory, n: usize, dt: f64) -> State {
    State::new(t.x[n].clone(), t.v[n].clone(), t.start_time + n as f64 * dt)
}
