//! Data deform did not make: trajectories from `.npy` files, as an experiment's dataset
//! ([`ImportSpec`], the `import` of an experiment file) or one by one
//! ([`import_trajectory`]).
//!
//! The experiment's scene is the model to learn: its mesh (a file or `.npy` arrays), material
//! family and starting guess, density, constraints (selectors or an `.npy` of vertex ids) and
//! Newton options. The import states the facts of how the data were made that a scene would
//! otherwise default: the time step, gravity and the mass matrix; they replace the scene's.

use std::path::{Path, PathBuf};

use deform_fs::npy::{self, Array};
use deform_integrator::{Conditions, MassKind, Scene};
use serde::{Deserialize, Serialize};

use crate::dataset::{
    self, Dataset, DatasetError, DatasetMeta, Noise, Trajectory, TrajectoryMeta, split_of,
};

/// Where an imported trajectory's velocities come from.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub enum VelocitySource {
    /// Every step's, an `.npy` of the positions' shape.
    File(PathBuf),
    /// Only the initial velocity `v0`, an `.npy` of shape (vertices, 3) ([`Velocities::Initial`]).
    Initial(PathBuf),
    /// None: derived from the positions ([`Velocities::Derived`]; the first frame is dropped).
    Derived,
}

/// The markers a capture followed ([`crate::observe::Marker`]), as `.npy` files.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub enum MarkerFiles {
    /// Vertices: their ids, an integer `.npy` of shape (markers,).
    Vertices(PathBuf),
    /// Points inside elements: the element ids, shape (markers,), and the barycentric weights
    /// of their corners, shape (markers, 4), used as given.
    Inside {
        /// The element ids.
        elements: PathBuf,
        /// The weights.
        weights: PathBuf,
    },
}

impl MarkerFiles {
    fn paths(&mut self) -> Vec<&mut PathBuf> {
        match self {
            Self::Vertices(p) => vec![p],
            Self::Inside { elements, weights } => vec![elements, weights],
        }
    }
}

/// One imported trajectory.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct ImportedTrajectory {
    /// Positions, an `.npy` of shape (steps + 1, vertices, 3), relative to the experiment file.
    pub positions: PathBuf,
    /// Its velocities.
    pub velocities: VelocitySource,
    /// The first frame (positions and velocities) is exact, e.g. a release from a known
    /// shape: fits that estimate rollout starts keep it (not with `Derived` velocities,
    /// which drop it). `Initial` velocities imply it.
    #[serde(default)]
    pub exact_start: bool,
    /// The conditions this trajectory was made under where they differ from the import's
    /// and the scene's: its gravity, the motions of the scene's constraints, the forces of
    /// its loads (e.g. `(gravity: Some((0.0, 0.0, 0.0)))` for a motion made without gravity).
    #[serde(default, skip_serializing_if = "Conditions::is_default")]
    pub conditions: Conditions,
    /// Only these markers were observed (what a capture gives): `positions` then holds their
    /// positions, shape (steps + 1, markers, 3), `velocities` must be `Derived` and the first
    /// state is estimated from the first frames with the scene's material
    /// ([`Trajectory::from_markers`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub markers: Option<MarkerFiles>,
}

deform_setters::setters!(ImportedTrajectory { positions: PathBuf, velocities: VelocitySource, exact_start: bool, conditions: Conditions, markers: Option<MarkerFiles> });

impl ImportedTrajectory {
    /// The positions in `positions` with velocities from `velocities`, made under the
    /// import's conditions.
    pub fn new(positions: impl Into<PathBuf>, velocities: VelocitySource) -> Self {
        Self {
            positions: positions.into(),
            velocities,
            exact_start: false,
            conditions: Conditions::default(),
            markers: None,
        }
    }
}

/// A dataset made elsewhere. Nothing about how the data were made is assumed: `dt`,
/// `gravity` (`(0, 0, 0)` for none) and `mass` are required and replace the scene's; each
/// trajectory may have been made under other conditions
/// ([`ImportedTrajectory::conditions`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct ImportSpec {
    /// The data's time step (s).
    pub dt: f64,
    /// The gravity the data were made under (m/s^2).
    pub gravity: [f64; 3],
    /// The mass matrix the data were made with.
    pub mass: MassKind,
    /// The trajectories, split in this order by `split`.
    pub trajectories: Vec<ImportedTrajectory>,
    /// Train and validation fractions (the rest is test).
    #[serde(default = "dataset::default_split")]
    pub split: (f64, f64),
    /// Noise added after import (e.g. to test a fit's robustness on clean outside data).
    #[serde(default)]
    pub noise: Option<Noise>,
    /// Learn a model that steps `subsample` times coarser than the data.
    #[serde(default = "dataset::one")]
    pub subsample: usize,
}

deform_setters::setters!(ImportSpec { dt: f64, gravity: [f64; 3], mass: MassKind, trajectories: Vec<ImportedTrajectory>, split: (f64, f64), noise: Option<Noise>, subsample: usize });

impl ImportSpec {
    /// Trajectories made at step `dt` (s) under `gravity` with `mass`, split (0.6, 0.2),
    /// without added noise or subsampling.
    pub fn new(
        dt: f64,
        gravity: [f64; 3],
        mass: MassKind,
        trajectories: Vec<ImportedTrajectory>,
    ) -> Self {
        Self {
            dt,
            gravity,
            mass,
            trajectories,
            split: dataset::default_split(),
            noise: None,
            subsample: 1,
        }
    }
}

impl ImportSpec {
    /// `scene` with the data's time step, gravity and mass matrix.
    pub fn scene(&self, scene: &Scene) -> Scene {
        let mut s = scene.clone();
        s.integrator.dt = self.dt;
        s.integrator.gravity = self.gravity;
        s.integrator.mass = self.mass;
        s
    }

    /// Makes relative file paths relative to `dir` (the experiment file's folder).
    pub fn resolve_paths(&mut self, dir: &Path) {
        for t in &mut self.trajectories {
            let velocities = match &mut t.velocities {
                VelocitySource::File(p) | VelocitySource::Initial(p) => Some(p),
                VelocitySource::Derived => None,
            };
            let markers = t
                .markers
                .as_mut()
                .map(MarkerFiles::paths)
                .unwrap_or_default();
            for p in std::iter::once(&mut t.positions)
                .chain(velocities)
                .chain(markers)
            {
                if p.is_relative() {
                    *p = dir.join(&*p);
                }
            }
        }
    }
}

/// Reads the trajectories of `spec` for the model `scene` (whose data's facts `spec` sets:
/// [`ImportSpec::scene`]), split by `spec.split`, each with its own conditions, and checks
/// them as [`from_trajectories`] does. Noise and subsampling are the caller's, as for
/// generated data.
///
/// # Errors
/// [`DatasetError`] naming the file, or the scene's error.
pub fn import(spec: &ImportSpec, scene: &Scene, origin: &Path) -> Result<Dataset, DatasetError> {
    let scene = spec.scene(scene);
    // Positions are checked against the mesh before their velocities are read, so that
    // transposed positions are blamed on the positions file, not on velocities that do
    // not match them.
    let vertices = scene.build_mesh(origin)?.num_vertices();
    let mut read = Vec::with_capacity(spec.trajectories.len());
    for t in &spec.trajectories {
        if let Some(files) = &t.markers {
            read.push(read_markers(t, files, &scene, origin)?);
            continue;
        }
        let velocities = match &t.velocities {
            VelocitySource::File(p) => Velocities::File(p),
            VelocitySource::Initial(p) => Velocities::Initial(p),
            VelocitySource::Derived => Velocities::Derived,
        };
        if t.exact_start && t.velocities == VelocitySource::Derived {
            return Err(DatasetError::Inconsistent(format!(
                "{}: exact_start with Derived velocities: the first frame, which has no velocity, is dropped",
                t.positions.display()
            )));
        }
        let (mut trajectory, stored) =
            read_trajectory(&t.positions, velocities, spec.dt, Some(vertices))?;
        trajectory.exact_start |= t.exact_start;
        trajectory.conditions = t.conditions.clone();
        let source = Source {
            name: t.positions.clone(),
            dtype: stored.dtype.clone(),
            rounding: stored.rounding(),
        };
        read.push((trajectory, source));
    }
    from_trajectories(&scene, origin, read, spec.split)
}

/// A trajectory of markers only: their positions and the first state estimated with the
/// model `scene`.
fn read_markers(
    t: &ImportedTrajectory,
    files: &MarkerFiles,
    scene: &Scene,
    origin: &Path,
) -> Result<(Trajectory, Source), DatasetError> {
    let name = t.positions.display();
    let bad = |reason: String| DatasetError::Inconsistent(format!("{name}: {reason}"));
    if t.velocities != VelocitySource::Derived || t.exact_start {
        return Err(bad(
            "markers only: velocities must be Derived and exact_start false (the first state is estimated)".into(),
        ));
    }
    let mut built = scene.build(origin)?;
    let a = npy::read(&t.positions)?;
    let [frames, count, 3] = a.shape[..] else {
        return Err(bad(format!(
            "shape {:?}, expected (steps + 1, markers, 3)",
            a.shape
        )));
    };
    let in_file = |path: &Path, reason: String| {
        DatasetError::Inconsistent(format!("{}: {reason}", path.display()))
    };
    let markers = match files {
        MarkerFiles::Vertices(path) => {
            let ids = npy::read(path)?;
            if ids.shape != [count] {
                let reason = format!("shape {:?}, expected [{count}] (markers)", ids.shape);
                return Err(in_file(path, reason));
            }
            let ids = ids.indices().map_err(|r| in_file(path, r))?;
            let n = built.mesh.num_vertices();
            if let Some((k, v)) = ids.iter().enumerate().find(|&(_, &v)| v >= n) {
                let reason = format!("marker {k}: vertex {v} is out of range for {n} vertices");
                return Err(in_file(path, reason));
            }
            ids.into_iter()
                .map(crate::observe::Marker::Vertex)
                .collect()
        }
        MarkerFiles::Inside { elements, weights } => {
            let (e, w) = (npy::read(elements)?, npy::read(weights)?);
            // Each file's own faults are blamed on it.
            if e.shape != [count] {
                let reason = format!("shape {:?}, expected [{count}] (markers)", e.shape);
                return Err(in_file(elements, reason));
            }
            if w.shape != [count, 4] {
                let reason = format!("shape {:?}, expected [{count}, 4] (markers)", w.shape);
                return Err(in_file(weights, reason));
            }
            let ids = e.indices().map_err(|r| in_file(elements, r))?;
            let n = built.mesh.num_tets();
            if let Some((k, e)) = ids.iter().enumerate().find(|&(_, &e)| e >= n) {
                let reason = format!("marker {k}: element {e} is out of range for {n} elements");
                return Err(in_file(elements, reason));
            }
            crate::observe::Marker::in_elements(&built.mesh, &ids, &w.data)
                .map_err(|err| in_file(weights, err.to_string()))?
        }
    };
    let observed = crate::observe::Observed::from_flat(markers, &a.data);
    observed
        .check(built.mesh.num_vertices(), frames)
        .map_err(|e| bad(e.to_string()))?;
    let trajectory =
        Trajectory::from_markers(&mut built.integrator, observed, t.conditions.clone())
            .map_err(|e| bad(format!("the first state: {e}")))?;
    let source = Source {
        name: t.positions.clone(),
        dtype: a.dtype.clone(),
        rounding: a.rounding(),
    };
    Ok((trajectory, source))
}

/// Where a trajectory of [`from_trajectories`] came from: what names it in errors and
/// metadata, and how its positions were stored.
#[derive(Debug, Clone, PartialEq)]
pub struct Source {
    /// Its file (or what the caller calls it: `array 0`).
    pub name: PathBuf,
    /// numpy's dtype of the positions as stored (`float64`, `float32`).
    pub dtype: String,
    /// Their relative rounding ([`Array::rounding`]).
    pub rounding: f64,
}

impl Source {
    /// Float64 values called `name`.
    pub fn float64(name: impl Into<PathBuf>) -> Self {
        Self {
            name: name.into(),
            dtype: "float64".into(),
            rounding: f64::EPSILON,
        }
    }
}

/// A dataset of trajectories made elsewhere (each with its conditions) for the model `scene`
/// at its time step, split in this order by `split`. Each trajectory must have the mesh's
/// vertex count, and its constrained vertices must sit where the scene's constraints, moving
/// as its conditions say, put them (to 1e-9 of the mesh's size, or the positions' own
/// rounding when stored in single precision): data the model cannot reproduce are refused,
/// naming the source, step and vertex. Each trajectory starts from its own first state.
///
/// # Errors
/// [`DatasetError`] naming the source, or the scene's error.
pub fn from_trajectories(
    scene: &Scene,
    origin: &Path,
    trajectories: Vec<(Trajectory, Source)>,
    split: (f64, f64),
) -> Result<Dataset, DatasetError> {
    let mut built = scene.build(origin)?;
    let (dt, vertices) = (scene.integrator.dt, built.mesh.num_vertices());
    let (lo, hi) = built.mesh.bounding_box();
    let extent = lo.abs().max().max(hi.abs().max()) + (hi - lo).norm();
    let count = trajectories.len();
    let mut metas = Vec::with_capacity(count);
    let mut kept = Vec::with_capacity(count);
    for (k, (trajectory, source)) in trajectories.into_iter().enumerate() {
        let name = source.name.display();
        let tolerance = (1e-9 * (hi - lo).norm()).max(4.0 * source.rounding * extent);
        built
            .integrator
            .set_conditions(&trajectory.conditions)
            .map_err(|e| DatasetError::Inconsistent(format!("{name}: {e}")))?;
        let found = trajectory.x.first().map_or(0, |f| f.len() / 3);
        let ragged = trajectory.x.len() != trajectory.v.len()
            || trajectory
                .x
                .iter()
                .chain(&trajectory.v)
                .any(|f| f.len() != 3 * found);
        if found != vertices || ragged {
            return Err(DatasetError::Inconsistent(format!(
                "{name}: {found} vertices, the scene's mesh has {vertices}"
            )));
        }
        // Of a partially observed trajectory only the first frame is a whole state.
        let whole = match &trajectory.observed {
            Some(o) => {
                o.check(vertices, trajectory.x.len())
                    .map_err(|e| DatasetError::Inconsistent(format!("{name}: {e}")))?;
                1
            }
            None => trajectory.x.len(),
        };
        for (n, x) in trajectory.x.iter().take(whole).enumerate() {
            let time = trajectory.start_time + n as f64 * dt;
            let targets = built.integrator.constrained_targets(time);
            for (i, target) in targets {
                let off = (0..3)
                    .map(|d| (x[3 * i + d] - target[d]).powi(2))
                    .sum::<f64>();
                if off.sqrt() > tolerance {
                    return Err(DatasetError::Inconsistent(format!(
                        "{name}: step {n}: vertex {i} is constrained by the scene but lies {:.3e} m from where its constraint puts it (positions stored as {}, tolerance {tolerance:.1e} m)",
                        off.sqrt(),
                        source.dtype
                    )));
                }
            }
        }
        metas.push(TrajectoryMeta {
            name: format!("traj_{k:03}"),
            split: split_of(k, count, split),
            steps: trajectory.steps(),
            initial: scene.initial.clone(),
            source: Some(source.name.clone()),
            start_time: trajectory.start_time,
            exact_start: trajectory.exact_start,
            conditions: trajectory.conditions.clone(),
            observed: trajectory.observed.as_ref().map(|o| o.markers.clone()),
        });
        kept.push(trajectory);
    }
    Ok(Dataset {
        meta: DatasetMeta {
            format: dataset::FORMAT,
            deform_version: env!("CARGO_PKG_VERSION").to_owned(),
            scene: scene.clone(),
            seed: 0,
            dt,
            vertices,
            trajectories: metas,
            noise: None,
        },
        trajectories: kept,
    })
}

/// Rejects a non-finite value of an array of `frame` values per step, naming the array
/// (its file), step and vertex.
fn finite(name: &str, data: &[f64], frame: usize) -> Result<(), DatasetError> {
    match data.iter().position(|v| !v.is_finite()) {
        Some(i) => Err(DatasetError::Inconsistent(format!(
            "{name}: non-finite value at step {}, vertex {}",
            i / frame,
            (i % frame) / 3
        ))),
        None => Ok(()),
    }
}

/// The velocities of an imported trajectory.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Velocities<'a> {
    /// Every step's, an `.npy` of the positions' shape.
    File(&'a Path),
    /// Only the initial velocity `v0`, an `.npy` of shape (vertices, 3); the others follow
    /// from Backward Euler's own relation `v^n+1 = (x^n+1 - x^n) / dt`, and the first frame,
    /// the one state known exactly, is kept.
    Initial(&'a Path),
    /// None: every velocity from that relation; the first frame has none and is dropped, so
    /// the trajectory starts at step 1.
    Derived,
}

/// Velocities of a trajectory given as arrays (see [`trajectory_from_arrays`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ArrayVelocities<'a> {
    /// Every step's, of the positions' shape.
    All(&'a Array),
    /// Only the initial velocity, (vertices, 3); the others follow from Backward Euler's
    /// own relation and the first frame is kept.
    Initial(&'a Array),
    /// None: the first frame is dropped.
    Derived,
}

/// Trajectories made elsewhere: positions per step as `.npy` of shape (steps + 1, vertices,
/// 3) (any float or integer dtype numpy writes), with the velocities `velocities` says.
///
/// # Errors
/// [`DatasetError`] naming the file.
pub fn import_trajectory(
    positions: &Path,
    velocities: Velocities<'_>,
    dt: f64,
) -> Result<Trajectory, DatasetError> {
    read_trajectory(positions, velocities, dt, None).map(|(t, _)| t)
}

/// [`import_trajectory`], and how the positions were stored (their dtype, the values not
/// kept).
fn read_trajectory(
    positions: &Path,
    velocities: Velocities<'_>,
    dt: f64,
    vertices: Option<usize>,
) -> Result<(Trajectory, Array), DatasetError> {
    let a = npy::read(positions)?;
    if let (Some(n), [frames, found, 3]) = (vertices, &a.shape[..])
        && *found != n
    {
        let hint = match *frames == n {
            true => " (transposed? the first axis is the frames)",
            false => "",
        };
        return Err(DatasetError::Inconsistent(format!(
            "{}: shape {:?}, expected (frames, {n}, 3): the scene's mesh has {n} vertices{hint}",
            positions.display(),
            a.shape
        )));
    }
    let read_v;
    let v = match velocities {
        Velocities::File(path) => {
            read_v = (npy::read(path)?, path);
            (ArrayVelocities::All(&read_v.0), Some(read_v.1))
        }
        Velocities::Initial(path) => {
            read_v = (npy::read(path)?, path);
            (ArrayVelocities::Initial(&read_v.0), Some(read_v.1))
        }
        Velocities::Derived => (ArrayVelocities::Derived, None),
    };
    let names = (
        positions.display().to_string(),
        v.1.map(|p| p.display().to_string()),
    );
    let t = trajectory_from_arrays((&names.0, names.1.as_deref()), &a, v.0, dt)?;
    let mut stored = a;
    stored.data = Vec::new();
    Ok((t, stored))
}

/// [`import_trajectory`] of arrays in memory (positions (steps + 1, vertices, 3), flat C
/// order); `names` name the positions and velocities in errors (file paths, or what the
/// caller calls them).
///
/// # Errors
/// [`DatasetError::Inconsistent`] naming the array, step and vertex.
pub fn trajectory_from_arrays(
    names: (&str, Option<&str>),
    a: &Array,
    velocities: ArrayVelocities<'_>,
    dt: f64,
) -> Result<Trajectory, DatasetError> {
    let (positions, v_name) = (names.0, names.1.unwrap_or("velocities"));
    if a.shape.len() != 3 || a.shape[2] != 3 || a.shape[0] < 2 || a.shape[1] == 0 {
        return Err(DatasetError::Inconsistent(format!(
            "{positions}: shape {:?}, expected (steps + 1 >= 2, vertices >= 1, 3)",
            a.shape
        )));
    }
    if a.data.len() != a.shape.iter().product::<usize>() {
        return Err(DatasetError::Inconsistent(format!(
            "{positions}: {} values for shape {:?}",
            a.data.len(),
            a.shape
        )));
    }
    if !(dt.is_finite() && dt > 0.0) {
        return Err(DatasetError::Inconsistent(format!(
            "dt = {dt} must be finite and > 0"
        )));
    }
    let frame = 3 * a.shape[1];
    finite(positions, &a.data, frame)?;
    let x: Vec<Vec<f64>> = a.data.chunks(frame).map(<[f64]>::to_vec).collect();
    let checked = |b: &Array, shape: &[usize]| -> Result<Vec<f64>, DatasetError> {
        if b.shape != shape || b.data.len() != shape.iter().product::<usize>() {
            return Err(DatasetError::Inconsistent(format!(
                "{v_name}: shape {:?}, expected {shape:?} (as the positions {positions})",
                b.shape
            )));
        }
        finite(v_name, &b.data, frame)?;
        Ok(b.data.clone())
    };
    let derived = |n: usize| -> Vec<f64> {
        let (a, b) = (&x[n], &x[n - 1]);
        a.iter().zip(b).map(|(a, b)| (a - b) / dt).collect()
    };
    let v = match velocities {
        ArrayVelocities::All(b) => {
            let data = checked(b, &a.shape)?;
            data.chunks(frame).map(<[f64]>::to_vec).collect()
        }
        ArrayVelocities::Initial(b) => {
            let v0 = checked(b, &a.shape[1..])?;
            std::iter::once(v0)
                .chain((1..x.len()).map(derived))
                .collect()
        }
        ArrayVelocities::Derived => {
            let v = (1..x.len()).map(derived).collect();
            // Its first frame is the data's second.
            return Ok(Trajectory {
                start_time: dt,
                x: x[1..].to_vec(),
                v,
                ..Trajectory::default()
            });
        }
    };
    // Given initial velocities make the first frame the one state known exactly.
    let exact_start = matches!(velocities, ArrayVelocities::Initial(_));
    Ok(Trajectory {
        x,
        v,
        exact_start,
        ..Trajectory::default()
    })
}
