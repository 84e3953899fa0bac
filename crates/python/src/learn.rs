//! Learning from Python: trajectories from numpy arrays (`deform.Trajectory`), the material
//! fit in both stages (`deform.fit_material`), and experiment files (`deform.Experiment`:
//! dataset, fit, model selection, solver learning, coarsening) run by deform's library, each
//! returning deform's typed report as Python data.

use std::path::PathBuf;

use deform_learn::dataset::generate;
use deform_learn::ensemble::Member;
use deform_learn::import::{ArrayVelocities, Source, from_trajectories, trajectory_from_arrays};
use deform_learn::npy::Array;
use deform_learn::{
    DatasetSpec, EquationErrorOptions, FitError, OutputErrorOptions, Variations,
    fit_equation_error, fit_output_error, term_coefficients,
};
use deform_studies::{Experiment as RustExperiment, NoProgress, run};
use numpy::PyArrayDyn;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::arrays::{array, values};
use crate::errors;
use crate::materials::member;
use crate::scene::Scene;

/// A trajectory: positions and velocities at every step.
#[pyclass(module = "deform._deform", name = "Trajectory", frozen)]
pub struct Trajectory {
    trajectory: deform_learn::Trajectory,
    /// numpy's dtype of the positions given (their precision).
    dtype: String,
}

/// An array argument as deform's array type.
fn as_array(name: &str, obj: &Bound<'_, PyAny>) -> PyResult<Array> {
    let (data, shape) = values::<f64>(name, obj)?;
    // The precision the values had before they became float64 (numpy's dtype name).
    let dtype = obj
        .getattr("dtype")
        .and_then(|d| d.str().map(|s| s.to_string()))
        .unwrap_or_else(|_| "float64".into());
    // `values` gives data of its shape.
    Ok(Array::new(shape, data).with_dtype(dtype))
}

#[pymethods]
impl Trajectory {
    /// From `positions` (steps + 1, V, 3) and `velocities` of the same shape, or only the
    /// initial velocity `v0` (V, 3) (the others follow from Backward Euler's relation
    /// `v^n+1 = (x^n+1 - x^n) / dt`), or neither (the first frame is then dropped).
    /// `conditions` (a dict: `gravity`, `motions` of the scene's constraints, `forces` of its
    /// loads as `loads`) are those it was made under where they differ from the scene's.
    #[new]
    #[pyo3(signature = (positions, dt, velocities = None, v0 = None, conditions = None))]
    fn new(
        positions: &Bound<'_, PyAny>,
        dt: f64,
        velocities: Option<&Bound<'_, PyAny>>,
        v0: Option<&Bound<'_, PyAny>>,
        conditions: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let conditions: deform_integrator::Conditions = match conditions {
            Some(c) => {
                pythonize::depythonize(c).map_err(|e| errors::learn(format!("conditions: {e}")))?
            }
            None => Default::default(),
        };
        let x = as_array("positions", positions)?;
        let (v, name) = match (velocities, v0) {
            (Some(v), None) => (Some(as_array("velocities", v)?), "velocities"),
            (None, Some(v)) => (Some(as_array("v0", v)?), "v0"),
            (None, None) => (None, "velocities"),
            (Some(_), Some(_)) => {
                return Err(errors::learn("give velocities or v0, not both"));
            }
        };
        let velocities = match (&v, velocities.is_some()) {
            (Some(a), true) => ArrayVelocities::All(a),
            (Some(a), false) => ArrayVelocities::Initial(a),
            (None, _) => ArrayVelocities::Derived,
        };
        let mut trajectory = trajectory_from_arrays(("positions", Some(name)), &x, velocities, dt)
            .map_err(errors::learn)?;
        trajectory.conditions = conditions;
        Ok(Self {
            trajectory,
            dtype: x.dtype,
        })
    }

    /// What a capture gives: `positions` (steps + 1, M, 3) of M markers only, each a vertex
    /// (`vertices`, M ids) or a point inside an element (`elements`, M ids, and barycentric
    /// `weights`, (M, 4), used as given). The first state is estimated from the first frames
    /// with the scene's material: the least-strain shape through the markers, moving with the
    /// least-stiffness velocities through theirs. `fit_material` fits such trajectories by
    /// output error only (stage 1 needs whole states), refining their first states.
    #[staticmethod]
    #[pyo3(signature = (scene, positions, dt, *, vertices = None, elements = None, weights = None, conditions = None))]
    #[allow(clippy::too_many_arguments)]
    fn from_markers(
        py: Python<'_>,
        scene: &Scene,
        positions: &Bound<'_, PyAny>,
        dt: f64,
        vertices: Option<&Bound<'_, PyAny>>,
        elements: Option<&Bound<'_, PyAny>>,
        weights: Option<&Bound<'_, PyAny>>,
        conditions: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        use deform_learn::observe::{Marker, Observed};
        let conditions: deform_integrator::Conditions = match conditions {
            Some(c) => {
                pythonize::depythonize(c).map_err(|e| errors::learn(format!("conditions: {e}")))?
            }
            None => Default::default(),
        };
        let x = as_array("positions", positions)?;
        let [frames, count, 3] = x.shape[..] else {
            return Err(errors::learn(format!(
                "positions: shape {:?}, expected (steps + 1, markers, 3)",
                x.shape
            )));
        };
        let ids = |name: &str, a: &Bound<'_, PyAny>| -> PyResult<Vec<usize>> {
            let a = as_array(name, a)?;
            if a.shape != [count] {
                let reason = format!("{name}: shape {:?}, expected [{count}] (markers)", a.shape);
                return Err(errors::learn(reason));
            }
            a.indices()
                .map_err(|r| errors::learn(format!("{name}: {r}")))
        };
        let mut scene_copy = scene.scene.clone();
        scene_copy.integrator.dt = dt;
        let mut built = scene_copy.build(&scene.origin).map_err(errors::scene)?;
        let markers: Vec<Marker> = match (vertices, elements, weights) {
            (Some(v), None, None) => ids("vertices", v)?
                .into_iter()
                .map(Marker::Vertex)
                .collect(),
            (None, Some(e), Some(w)) => {
                let e = ids("elements", e)?;
                let w = as_array("weights", w)?;
                if w.shape != [count, 4] {
                    let reason = format!("weights: shape {:?}, expected [{count}, 4]", w.shape);
                    return Err(errors::learn(reason));
                }
                Marker::in_elements(&built.mesh, &e, &w.data).map_err(errors::learn)?
            }
            _ => return Err(errors::learn("give vertices, or elements and weights")),
        };
        let observed = Observed::from_flat(markers, &x.data);
        observed
            .check(built.mesh.num_vertices(), frames)
            .map_err(errors::learn)?;
        let trajectory = py
            .detach(|| {
                deform_learn::Trajectory::from_markers(&mut built.integrator, observed, conditions)
            })
            .map_err(errors::learn)?;
        Ok(Self {
            trajectory,
            dtype: x.dtype,
        })
    }

    /// The markers' positions (steps + 1, M, 3) of a trajectory made by `from_markers`, else
    /// None.
    #[getter]
    fn markers<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyArrayDyn<f64>>>> {
        self.trajectory
            .observed
            .as_ref()
            .map(|o| stack(py, &o.positions))
            .transpose()
    }

    /// The conditions it was made under where they differ from the scene's (a dict).
    #[getter]
    fn conditions<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_python(py, &self.trajectory.conditions)
    }

    /// Number of steps (pairs of consecutive states).
    #[getter]
    fn steps(&self) -> usize {
        self.trajectory.steps()
    }

    /// Positions (steps + 1, V, 3).
    #[getter]
    fn x<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        stack(py, &self.trajectory.x)
    }

    /// Velocities (steps + 1, V, 3).
    #[getter]
    fn v<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        stack(py, &self.trajectory.v)
    }
}

/// Frames of `3V` values as a (frames, V, 3) array.
fn stack<'py>(py: Python<'py>, frames: &[Vec<f64>]) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
    let v = frames.first().map_or(0, |f| f.len() / 3);
    array(py, frames.concat(), &[frames.len(), v, 3])
}

/// Fits the scene's material (its Lame pair, and Rayleigh damping with `damping`) to
/// `trajectories`: stage 1 by equation error, then (with `rollout > 0`) stage 2 by output
/// error on `rollout`-step rollouts with adjoint gradients (L-BFGS, `max_iterations`, at
/// most `max_evaluations` loss evaluations, 200 by default), from stage 1's estimate when it
/// is a material, else from the scene's. `starts` estimates the rollouts' first free
/// positions with the material (noisy data; by default only for markers, which need it).
/// Returns a dict: `stage1` and `stage2` (deform's fit reports), `termination` (how stage 2
/// stopped), `warnings`, and the fitted `E`, `nu`, `mu`, `lam`. A `UserWarning` is raised
/// when stage 1 is unusable or stage 2 stops on its iteration cap or evaluation budget.
#[pyfunction]
#[pyo3(signature = (scene, trajectories, *, damping = false, rollout = 10, max_iterations = 40, max_evaluations = None, starts = None))]
#[allow(clippy::too_many_arguments)]
fn fit_material<'py>(
    py: Python<'py>,
    scene: &Scene,
    trajectories: Vec<PyRef<'py, Trajectory>>,
    damping: bool,
    rollout: usize,
    max_iterations: u64,
    max_evaluations: Option<usize>,
    starts: Option<bool>,
) -> PyResult<Bound<'py, PyAny>> {
    let data: Vec<&deform_learn::Trajectory> = trajectories.iter().map(|t| &t.trajectory).collect();
    let markers = data.iter().any(|t| t.observed.is_some());
    if markers && starts == Some(false) {
        return Err(pyo3::exceptions::PyValueError::new_err(
            "starts=False with marker trajectories: their first states are estimates, which stage 2 must refine",
        ));
    }
    let starts = starts.unwrap_or(markers);
    let built = scene.scene.build(&scene.origin).map_err(errors::scene)?;
    let mut sim = built.integrator;
    let (stage1, stage2) = py
        .detach(|| {
            let options = EquationErrorOptions::default().damping(damping);
            // Markers only: no stage 1 (it needs whole states); stage 2 over whole
            // trajectories, refining their estimated first states.
            let stage1 = match markers {
                false => Some(fit_equation_error(&sim, &data, options)?),
                true => None,
            };
            if rollout == 0 {
                return Ok((stage1, None));
            }
            let start = match stage1.as_ref().filter(|s| s.unusable().is_none()) {
                Some(s) => s.coefficients.clone(),
                // The scene's own moduli (stage 2 refuses a scene with a coefficient field).
                None => {
                    let model = scene.scene.material.build();
                    term_coefficients(&model.map_err(|e| FitError::Invalid(e.to_string()))?)
                }
            };
            let whole = data.iter().map(|t| t.steps()).max().unwrap_or(0);
            let options = OutputErrorOptions::default()
                .rollout(if markers { rollout.max(whole) } else { rollout })
                .max_iterations(max_iterations)
                .max_evaluations(max_evaluations.unwrap_or(if markers {
                    200.max(max_iterations as usize)
                } else {
                    200
                }))
                .starts(starts.then(Default::default));
            let fit = fit_output_error(&mut sim, &data, &start, options, |_, _| {})?;
            Ok((stage1, Some(fit)))
        })
        .map_err(|e: FitError| errors::learn(e))?;
    let out = PyDict::new(py);
    let c = match (&stage2, &stage1) {
        (Some(f), _) => f.coefficients.clone(),
        (None, Some(s)) => s.coefficients.clone(),
        (None, None) => Vec::new(),
    };
    if let [mu, lam] = c[..] {
        out.set_item("mu", mu)?;
        out.set_item("lam", lam)?;
        if let Ok(l) = deform_materials::Lame::try_new(mu, lam) {
            let (e, nu) = l.to_young();
            out.set_item("E", e)?;
            out.set_item("nu", nu)?;
        }
    }
    match &stage1 {
        Some(s) => out.set_item("stage1", to_python(py, s)?)?,
        None => out.set_item("stage1", py.None())?,
    }
    match &stage2 {
        Some(f) => out.set_item("stage2", to_python(py, f)?)?,
        None => out.set_item("stage2", py.None())?,
    }
    let termination = stage2.as_ref().map(|f| f.termination.describe());
    out.set_item("termination", termination)?;
    let warnings = fit_warnings(stage1.as_ref(), stage2.as_ref());
    warn_all(py, &warnings)?;
    out.set_item("warnings", warnings)?;
    Ok(out.into_any())
}

/// Warns of a coarse model whose fit stopped on its cap or budget, or failed a free rollout.
fn coarse_fit_warnings(
    py: Python<'_>,
    m: &deform_studies::coarsen::CoarseModelFit,
    unstable: Option<&str>,
) -> PyResult<()> {
    let name = m.model.name();
    let mut warnings = Vec::new();
    if let Some(why) = unstable {
        warnings.push(format!(
            "{name}: the fitted model failed a free rollout ({why}); its start stands"
        ));
    }
    if let Some(t) = m.fit.as_ref().map(|f| &f.termination)
        && t.on_limit()
    {
        warnings.push(format!(
            "{name}: the fit stopped on its {} without converging",
            t.describe()
        ));
    }
    warn_all(py, &warnings)
}

/// Each of `warnings` as a Python `UserWarning`.
fn warn_all(py: Python<'_>, warnings: &[String]) -> PyResult<()> {
    let category = py.get_type::<pyo3::exceptions::PyUserWarning>();
    for w in warnings {
        let message = std::ffi::CString::new(w.as_str()).unwrap_or_default();
        PyErr::warn(py, &category, &message, 1)?;
    }
    Ok(())
}

/// What a user of a material fit must know: stage 1's estimate unusable, stage 2 stopped by
/// its iteration cap or evaluation budget rather than converged.
fn fit_warnings(
    stage1: Option<&deform_learn::EquationErrorFit>,
    stage2: Option<&deform_learn::OutputErrorFit>,
) -> Vec<String> {
    let mut warnings = Vec::new();
    if let Some(why) = stage1.and_then(|s| s.unusable()) {
        warnings.push(format!("stage 1 (equation error) is unusable: {why}"));
    }
    if let Some(f) = stage2
        && f.termination.on_limit()
    {
        warnings.push(format!(
            "stage 2 (output error) stopped on its {} without converging: raise max_iterations or max_evaluations",
            f.termination.describe()
        ));
    }
    warnings
}

/// Model selection: a non-negative weighted ensemble of `models` (names as `Material`
/// takes them; default all six) fitted to `train` by equation error, each member's share
/// of the elastic energy measured on `evaluate` (default `train`); with `rollout > 0` the
/// kept members are then refined by output error. Returns deform's ensemble report as a
/// dict (members with their effective Lame pairs and energy shares, models the data leave
/// undefined listed as excluded), with `refined` when refined.
#[pyfunction]
#[pyo3(signature = (scene, train, *, models = None, evaluate = None, rollout = 0, max_iterations = 40))]
#[allow(clippy::too_many_arguments)]
fn fit_ensemble<'py>(
    py: Python<'py>,
    scene: &Scene,
    train: Vec<PyRef<'py, Trajectory>>,
    models: Option<Vec<String>>,
    evaluate: Option<Vec<PyRef<'py, Trajectory>>>,
    rollout: usize,
    max_iterations: u64,
) -> PyResult<Bound<'py, PyAny>> {
    let names: Vec<Member> = match models {
        Some(m) => m.iter().map(|n| member(n)).collect::<PyResult<_>>()?,
        None => Member::ALL.to_vec(),
    };
    let train: Vec<&deform_learn::Trajectory> = train.iter().map(|t| &t.trajectory).collect();
    let evaluate: Vec<&deform_learn::Trajectory> = match &evaluate {
        Some(e) => e.iter().map(|t| &t.trajectory).collect(),
        None => train.clone(),
    };
    let (fit, refined) = py
        .detach(|| {
            let fit =
                deform_learn::fit_ensemble(&scene.scene, &scene.origin, &names, &train, &evaluate)?;
            if rollout == 0 {
                return Ok((fit, None));
            }
            let options = OutputErrorOptions::default()
                .rollout(rollout)
                .max_iterations(max_iterations);
            let (refined, _) = deform_learn::refine_ensemble(
                &fit,
                &scene.scene,
                &scene.origin,
                &train,
                &evaluate,
                options,
                |_, _| {},
            )?;
            Ok((fit, Some(refined)))
        })
        .map_err(|e: deform_learn::FitError| errors::learn(e))?;
    let out = to_python(py, &fit)?;
    if let Some(r) = refined {
        out.set_item("refined", to_python(py, &r)?)?;
    }
    Ok(out)
}

/// A report as Python data.
fn to_python<'py, T: serde::Serialize>(py: Python<'py>, v: &T) -> PyResult<Bound<'py, PyAny>> {
    pythonize::pythonize(py, v).map_err(errors::learn)
}

/// A dataset: trajectories of one base model (scene) with their metadata, saved as RON plus
/// `.npy` (see docs/experiments.md). Picklable, so sweeps can make parts on other processes
/// or machines (e.g. Dask) and merge them.
#[pyclass(module = "deform._deform", name = "Dataset", frozen)]
pub struct Dataset {
    dataset: deform_learn::Dataset,
}

#[pymethods]
impl Dataset {
    /// `trajectories` simulations of `scene` of `steps` steps from initial conditions varied
    /// by `seed` (uniform speed up to `speed` m/s, spin up to `spin` rad/s, stretch up to
    /// `stretch` per axis), split into train / validation / test by `split`.
    #[staticmethod]
    #[pyo3(signature = (scene, trajectories, steps, seed, *, speed = 1.0, spin = 2.0, stretch = 0.1, split = (0.6, 0.2)))]
    #[allow(clippy::too_many_arguments)]
    fn generate(
        py: Python<'_>,
        scene: &Scene,
        trajectories: usize,
        steps: usize,
        seed: u64,
        speed: f64,
        spin: f64,
        stretch: f64,
        split: (f64, f64),
    ) -> PyResult<Self> {
        let spec = DatasetSpec::new(trajectories, steps, seed)
            .variations(
                Variations::default()
                    .speed(speed)
                    .spin(spin)
                    .stretch(stretch)
                    .rest(false),
            )
            .split(split);
        let dataset = py
            .detach(|| generate(&scene.scene, &scene.origin, &spec, |_, _| {}))
            .map_err(errors::learn)?;
        Ok(Self { dataset })
    }

    /// A dataset of trajectories made elsewhere (each with its conditions) for the model
    /// `scene`, at the scene's time step, split in this order into train / validation /
    /// test by `split`. Refused, naming the trajectory, step and vertex, when a constrained
    /// vertex is not where the scene's constraints put it.
    #[staticmethod]
    #[pyo3(signature = (scene, trajectories, *, split = (0.6, 0.2)))]
    fn from_trajectories(
        py: Python<'_>,
        scene: &Scene,
        trajectories: Vec<PyRef<'_, Trajectory>>,
        split: (f64, f64),
    ) -> PyResult<Self> {
        let given: Vec<_> = trajectories
            .iter()
            .enumerate()
            .map(|(k, t)| {
                let source = Source {
                    name: format!("trajectory {k}").into(),
                    dtype: t.dtype.clone(),
                    rounding: deform_learn::npy::rounding_of(&t.dtype),
                };
                (t.trajectory.clone(), source)
            })
            .collect();
        let dataset = py
            .detach(|| from_trajectories(&scene.scene, &scene.origin, given, split))
            .map_err(errors::learn)?;
        Ok(Self { dataset })
    }

    /// The fine dataset carried onto `coarse`'s mesh (a scene of the same body): every state
    /// interpolated at the coarse rest vertices, located in the fine mesh or, with
    /// `elements` (V_coarse,) and `weights` (V_coarse, 4), placed as given (their fine
    /// element and barycentric weights, used as is). Constraints and loads are carried from
    /// the fine scene. Returns the coarse dataset and the mapping's report (a dict).
    #[pyo3(signature = (coarse, *, elements = None, weights = None))]
    fn coarsen<'py>(
        &self,
        py: Python<'py>,
        coarse: &Scene,
        elements: Option<&Bound<'py, PyAny>>,
        weights: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<(Self, Bound<'py, PyAny>)> {
        let embedding = match (elements, weights) {
            (Some(e), Some(w)) => {
                let e = as_array("elements", e)?;
                let w = as_array("weights", w)?;
                if w.shape.len() != 2 || w.shape[1] != 4 {
                    let shape = &w.shape;
                    return Err(errors::learn(format!(
                        "weights: shape {shape:?}, expected (V, 4)"
                    )));
                }
                let fine = self
                    .dataset
                    .meta
                    .scene
                    .build_mesh(&coarse.origin)
                    .map_err(errors::scene)?;
                let element = e
                    .indices()
                    .map_err(|r| errors::learn(format!("elements: {r}")))?;
                let rows = w.data.chunks(4).map(|c| [c[0], c[1], c[2], c[3]]).collect();
                let given = deform_mesh::embed::Embedding::given(&fine, element, rows)
                    .map_err(|r| errors::learn(format!("embedding: {r}")))?;
                Some(given)
            }
            (None, None) => None,
            _ => return Err(errors::learn("give elements and weights together")),
        };
        let (dataset, mapping) = py
            .detach(|| {
                deform_learn::coarsen::coarsen_embedded(
                    &self.dataset,
                    &coarse.scene,
                    &coarse.origin,
                    deform_learn::coarsen::Constraints::FromFine,
                    embedding.as_ref(),
                )
            })
            .map_err(errors::learn)?;
        Ok((Self { dataset }, to_python(py, &mapping)?))
    }

    /// Fits coarse models to this dataset of a coarse model (e.g. from
    /// [`Dataset.coarsen`]) on its training trajectories, choosing on its validation ones:
    /// the untuned scene, a homogeneous fit, a fit per region (`tags`, one per coarse
    /// element, or `regions` slabs), and a fit per element at each of `regularisation`
    /// (the least validation error kept), each with Rayleigh damping when `damping`; every
    /// fitted model must run freely over every training and validation trajectory, or it
    /// is replaced by the model its fit started from. With `save` (a folder), the
    /// per-element model is written there as the scene `name.ron` with its field. Returns
    /// a dict: `models` (name, fit, alpha, gamma, unstable, and `validation_error` and
    /// `test_error`: the mean free-rollout position error in m on the validation and the
    /// held-out test trajectories, `None` for an empty split), `regularisation`, `chosen`,
    /// `files`. A `UserWarning` is raised for each fit that stopped on its iteration cap or
    /// evaluation budget, or whose model failed a free rollout.
    #[pyo3(signature = (*, regions = 8, tags = None, regularisation = vec![0.0, 1e-3, 1e-2], damping = true, rollout = 10, max_iterations = 50, save = None, name = "coarse".to_owned()))]
    #[allow(clippy::too_many_arguments)]
    fn fit_coarse<'py>(
        &self,
        py: Python<'py>,
        regions: u32,
        tags: Option<Vec<u32>>,
        regularisation: Vec<f64>,
        damping: bool,
        rollout: usize,
        max_iterations: u64,
        save: Option<PathBuf>,
        name: String,
    ) -> PyResult<Bound<'py, PyAny>> {
        use deform_studies::coarsen::{CoarseSettings, fit_coarse_models};
        let scene = &self.dataset.meta.scene;
        let options = OutputErrorOptions::default()
            .rollout(rollout)
            .max_iterations(max_iterations);
        let settings = CoarseSettings::new(scene.integrator.newton.max_iterations, options)
            .regions(regions)
            .tags(tags)
            .regularisation(regularisation)
            .damping(damping);
        let origin = save.clone().unwrap_or_default().join(format!("{name}.ron"));
        let (fits, files, errors) = py
            .detach(|| {
                let fits = fit_coarse_models(&self.dataset, &origin, &settings, &mut NoProgress)?;
                let files = match &save {
                    Some(dir) => fits.save(scene, &name, dir)?,
                    None => Vec::new(),
                };
                let errors = fits.split_errors(&self.dataset, &origin)?;
                Ok::<_, deform_learn::LearnError>((fits, files, errors))
            })
            .map_err(errors::learn)?;
        let out = PyDict::new(py);
        let models = pyo3::types::PyList::empty(py);
        for (m, e) in fits.models.iter().zip(errors) {
            let row = PyDict::new(py);
            row.set_item("name", m.model.name())?;
            match &m.fit {
                Some(f) => row.set_item("fit", to_python(py, f)?)?,
                None => row.set_item("fit", py.None())?,
            }
            row.set_item("alpha", m.options.alpha)?;
            row.set_item("gamma", m.options.gamma)?;
            let unstable = m.fit.as_ref().and_then(|f| f.unstable.clone());
            row.set_item("unstable", unstable.clone())?;
            row.set_item("validation_error", e.validation)?;
            row.set_item("test_error", e.test)?;
            models.append(row)?;
            coarse_fit_warnings(py, m, unstable.as_deref())?;
        }
        out.set_item("models", models)?;
        out.set_item("regularisation", fits.regularisation.clone())?;
        out.set_item("chosen", fits.chosen)?;
        out.set_item("files", files)?;
        Ok(out.into_any())
    }

    /// Loads a saved dataset folder.
    #[staticmethod]
    fn load(py: Python<'_>, dir: PathBuf) -> PyResult<Self> {
        let dataset = py
            .detach(|| deform_learn::Dataset::load(&dir))
            .map_err(errors::learn)?;
        Ok(Self { dataset })
    }

    /// Saves it in folder `dir` (written atomically, file by file).
    fn save(&self, py: Python<'_>, dir: PathBuf) -> PyResult<()> {
        py.detach(|| self.dataset.save(&dir)).map_err(errors::learn)
    }

    /// One dataset of parts made by the same scene (a sweep over seeds): their trajectories
    /// in order.
    #[staticmethod]
    fn merge(parts: Vec<PyRef<'_, Dataset>>) -> PyResult<Self> {
        let parts = parts.iter().map(|p| p.dataset.clone()).collect();
        let dataset = deform_learn::Dataset::merge(parts).map_err(errors::learn)?;
        Ok(Self { dataset })
    }

    /// The trajectories (copies), in order.
    #[getter]
    fn trajectories(&self) -> Vec<Trajectory> {
        let t = self.dataset.trajectories.iter().cloned();
        t.map(|trajectory| Trajectory {
            trajectory,
            dtype: "float64".into(),
        })
        .collect()
    }

    /// The metadata (scene, seed, dt, each trajectory's split and initial conditions).
    #[getter]
    fn meta<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_python(py, &self.dataset.meta)
    }

    fn __len__(&self) -> usize {
        self.dataset.trajectories.len()
    }

    /// Pickling: the metadata's RON and the arrays' bytes.
    fn __reduce__<'py>(&self, py: Python<'py>) -> PyResult<(Bound<'py, PyAny>, (Vec<u8>,))> {
        let from_bytes = py
            .import("deform._deform")?
            .getattr("Dataset")?
            .getattr("_from_bytes")?;
        Ok((from_bytes, (to_bytes(&self.dataset)?,)))
    }

    /// The inverse of pickling.
    #[staticmethod]
    fn _from_bytes(bytes: Vec<u8>) -> PyResult<Self> {
        let dataset = from_bytes(&bytes).map_err(errors::learn)?;
        Ok(Self { dataset })
    }
}

/// The metadata's RON (its length first, 8 bytes) and every frame's positions, then
/// velocities (then observed markers' positions), as little-endian f64.
fn to_bytes(d: &deform_learn::Dataset) -> PyResult<Vec<u8>> {
    let mut meta = d.meta.clone();
    for (m, t) in meta.trajectories.iter_mut().zip(&d.trajectories) {
        m.observed = t.observed.as_ref().map(|o| o.markers.clone());
        m.start_time = t.start_time;
    }
    let meta = ron::to_string(&meta).map_err(errors::learn)?;
    let mut out = (meta.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(meta.as_bytes());
    for t in &d.trajectories {
        let markers = t.observed.iter().flat_map(|o| &o.positions);
        for frame in t.x.iter().chain(&t.v).chain(markers) {
            out.extend(frame.iter().flat_map(|v| v.to_le_bytes()));
        }
    }
    Ok(out)
}

/// The inverse of [`to_bytes`].
fn from_bytes(bytes: &[u8]) -> Result<deform_learn::Dataset, String> {
    let short = || "truncated dataset bytes".to_owned();
    let len = u64::from_le_bytes(bytes.get(..8).ok_or_else(short)?.try_into().expect("8"));
    let text = bytes.get(8..8 + len as usize).ok_or_else(short)?;
    let text = std::str::from_utf8(text).map_err(|e| e.to_string())?;
    let meta: deform_learn::DatasetMeta = ron::from_str(text).map_err(|e| e.to_string())?;
    let mut values = bytes[8 + len as usize..]
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().expect("8")));
    let mut frames = |count: usize, n: usize| -> Result<Vec<Vec<f64>>, String> {
        (0..count)
            .map(|_| {
                let f: Vec<f64> = values.by_ref().take(n).collect();
                if f.len() == n { Ok(f) } else { Err(short()) }
            })
            .collect()
    };
    let mut trajectories = Vec::new();
    for m in &meta.trajectories {
        let x = frames(m.steps + 1, 3 * meta.vertices)?;
        let v = frames(m.steps + 1, 3 * meta.vertices)?;
        let observed = match &m.observed {
            Some(markers) => Some(deform_learn::observe::Observed {
                markers: markers.clone(),
                positions: frames(m.steps + 1, 3 * markers.len())?,
            }),
            None => None,
        };
        trajectories.push(
            deform_learn::Trajectory::default()
                .x(x)
                .v(v)
                .start_time(m.start_time)
                .exact_start(m.exact_start)
                .conditions(m.conditions.clone())
                .observed(observed),
        );
    }
    Ok(deform_learn::Dataset::new(meta, trajectories))
}

/// An experiment file.
#[pyclass(module = "deform._deform", name = "Experiment", frozen)]
pub struct Experiment {
    experiment: RustExperiment,
}

#[pymethods]
impl Experiment {
    /// Loads an experiment file (RON; unknown fields are refused).
    #[staticmethod]
    fn load(path: PathBuf) -> PyResult<Self> {
        let experiment = RustExperiment::load(&path).map_err(errors::learn)?;
        Ok(Self { experiment })
    }

    /// Runs it (the GIL is released meanwhile); writes the results under `out` when given
    /// (report.md, CSV, plots' data, the dataset). Returns the report as a dict.
    #[pyo3(signature = (out = None))]
    fn run<'py>(&self, py: Python<'py>, out: Option<PathBuf>) -> PyResult<Bound<'py, PyAny>> {
        let e = &self.experiment;
        let report = py
            .detach(|| run(e, out.as_deref(), &mut NoProgress))
            .map_err(errors::learn)?;
        if let Some(out) = &out {
            py.detach(|| deform_studies::write_report(&report, out))
                .map_err(errors::os)?;
        }
        to_python(py, &report)
    }

    /// Its name.
    #[getter]
    fn name(&self) -> String {
        self.experiment.name.clone()
    }
}

/// Adds the experiment class to the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Experiment>()?;
    m.add_class::<Trajectory>()?;
    m.add_class::<Dataset>()?;
    m.add_function(wrap_pyfunction!(fit_material, m)?)?;
    m.add_function(wrap_pyfunction!(fit_ensemble, m)?)?;
    Ok(())
}
