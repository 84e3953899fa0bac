//! `deform.Simulation`: a scene ([`crate::scene`]) stepped by Backward Euler with Newton and
//! the scene's solver policy; the state is numpy arrays, reports are plain Python data.

use std::sync::Mutex;

use deform_integrator::{Integrator, State, StepReport};
use numpy::PyArrayDyn;
use pyo3::prelude::*;

use crate::arrays::{array, values};
use crate::errors;
use crate::mesh::Mesh;
use crate::scene::Scene;

/// The integrator and its state.
struct Running {
    integrator: Integrator,
    state: State,
    mesh: deform_mesh::TetMesh,
}

/// A running simulation of a scene.
#[pyclass(module = "deform._deform", name = "Simulation", frozen)]
pub struct Simulation {
    inner: Mutex<Running>,
}

impl Simulation {
    /// The integrator and state, locked: for long work only with the GIL released, and
    /// never across a Python callback (which may read the state).
    fn lock(&self) -> std::sync::MutexGuard<'_, Running> {
        self.inner.lock().expect("not poisoned")
    }

    /// One step with the GIL released.
    fn step_detached(&self, py: Python<'_>) -> PyResult<(StepReport, f64)> {
        py.detach(|| {
            let mut running = self.lock();
            let Running {
                integrator, state, ..
            } = &mut *running;
            integrator.step(state).map(|r| (r, state.t))
        })
        .map_err(errors::simulation)
    }
}

/// A state vector from a (V, 3) or (3V,) array of `n` values.
fn state_values(name: &str, a: &Bound<'_, PyAny>, n: usize) -> PyResult<Vec<f64>> {
    let (data, shape) = values::<f64>(name, a)?;
    if data.len() != n {
        return Err(errors::simulation(format!(
            "{name}: shape {shape:?}, expected ({}, 3) or ({n},)",
            n / 3
        )));
    }
    if let Some(i) = data.iter().position(|v| !v.is_finite()) {
        return Err(pyo3::exceptions::PyValueError::new_err(format!(
            "{name}: non-finite value at vertex {}, component {}",
            i / 3,
            i % 3
        )));
    }
    Ok(data)
}

/// A state vector as a (V, 3) array.
fn frame<'py>(py: Python<'py>, values: &[f64]) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
    array(py, values.to_vec(), &[values.len() / 3, 3])
}

#[pymethods]
impl Simulation {
    /// Builds the scene's mesh, materials, constraints and initial state.
    #[new]
    fn new(py: Python<'_>, scene: &Scene) -> PyResult<Self> {
        let built = py
            .detach(|| scene.scene.build(&scene.origin))
            .map_err(errors::scene)?;
        Ok(Self {
            inner: Mutex::new(Running {
                integrator: built.integrator,
                state: built.state,
                mesh: built.mesh,
            }),
        })
    }

    /// One Backward-Euler step; returns its report (Newton iterations, solver choices,
    /// residuals, energy, time) as a dict. Raises `SimulationError` when the step fails,
    /// leaving the state as it was.
    fn step<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let (report, _) = self.step_detached(py)?;
        report_dict(py, &report)
    }

    /// `steps` steps; `callback(report)` after each (return `False` to stop early). Returns
    /// a summary dict: steps, newton_iterations, linear_iterations, seconds, t.
    #[pyo3(signature = (steps, callback = None))]
    fn run<'py>(
        &self,
        py: Python<'py>,
        steps: usize,
        callback: Option<Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let (mut done, mut newton, mut linear, mut seconds) = (0usize, 0usize, 0usize, 0.0);
        let mut t = self.lock().state.t;
        for _ in 0..steps {
            let (report, now) = self.step_detached(py)?;
            t = now;
            done += 1;
            newton += report.newton_iterations();
            linear += report.linear_iterations();
            seconds += report.seconds;
            if let Some(cb) = &callback {
                let go_on = cb.call1((report_dict(py, &report)?,))?;
                if go_on.is(pyo3::types::PyBool::new(py, false)) {
                    break;
                }
            }
        }
        let summary = pyo3::types::PyDict::new(py);
        summary.set_item("steps", done)?;
        summary.set_item("newton_iterations", newton)?;
        summary.set_item("linear_iterations", linear)?;
        summary.set_item("seconds", seconds)?;
        summary.set_item("t", t)?;
        Ok(summary.into_any())
    }

    /// Runs the next steps with a learned linear-solver policy (kept solvers stay, so
    /// factorisations are reused).
    fn set_policy(&self, policy: &crate::policy::LearnedPolicy) {
        self.lock()
            .integrator
            .set_policy(Box::new(policy.policy.clone()));
    }

    /// Positions (V, 3); settable (a (V, 3) or (3V,) array).
    #[getter]
    fn x<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        frame(py, &self.lock().state.x)
    }

    #[setter]
    fn set_x(&self, x: Bound<'_, PyAny>) -> PyResult<()> {
        // Converted (Python code) before the state is locked.
        let n = self.lock().state.x.len();
        let x = state_values("x", &x, n)?;
        self.lock().state.x = x;
        Ok(())
    }

    /// Velocities (V, 3); settable.
    #[getter]
    fn v<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        frame(py, &self.lock().state.v)
    }

    #[setter]
    fn set_v(&self, v: Bound<'_, PyAny>) -> PyResult<()> {
        let n = self.lock().state.v.len();
        let v = state_values("v", &v, n)?;
        self.lock().state.v = v;
        Ok(())
    }

    /// Simulated time (s).
    #[getter]
    fn t(&self) -> f64 {
        self.lock().state.t
    }

    /// The time step (s).
    #[getter]
    fn dt(&self) -> f64 {
        self.lock().integrator.options().dt
    }

    /// The mesh.
    #[getter]
    fn mesh(&self) -> Mesh {
        Mesh {
            mesh: self.lock().mesh.clone(),
        }
    }

    /// Vertex indices held by constraints, (C,) int64.
    #[getter]
    fn constrained<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<i64>>> {
        let c: Vec<i64> = self
            .lock()
            .integrator
            .dofs()
            .constrained_vertices()
            .into_iter()
            .map(|v| v as i64)
            .collect();
        let n = c.len();
        array(py, c, &[n])
    }
}

/// A step report as a dict.
fn report_dict<'py>(py: Python<'py>, report: &StepReport) -> PyResult<Bound<'py, PyAny>> {
    pythonize::pythonize(py, report).map_err(errors::simulation)
}

/// Adds the simulation class to the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Simulation>()?;
    Ok(())
}
