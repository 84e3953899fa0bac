//! The solver-policy pipeline from Python: log every candidate linear solver on a scene's
//! Newton systems (`deform.SolverData.collect`), learn which to run when
//! (`deform.LearnedPolicy.train`), and simulate with it (`Simulation.set_policy`).

use std::path::PathBuf;

use deform_learn::policy::PolicyOptions;
use deform_learn::solver_data::{SolverDataset, collect};
use pyo3::prelude::*;

use crate::errors;
use crate::scene::Scene;

/// Every candidate's outcome on every Newton iteration's linear system of a scene (the
/// trajectory is the scene's own policy's).
#[pyclass(module = "deform._deform", name = "SolverData", frozen)]
pub struct SolverData {
    data: SolverDataset,
}

/// Solver configurations from their RON texts (`"Direct()"`, `"Pcg(preconditioner: Ic0)"`).
fn specs(texts: &[String]) -> PyResult<Vec<deform_solvers::SolverSpec>> {
    texts
        .iter()
        .map(|t| ron::from_str(t).map_err(|e| errors::learn(format!("candidate {t:?}: {e}"))))
        .collect()
}

#[pymethods]
impl SolverData {
    /// Simulates `steps` steps of `scene`, running every one of `candidates` (solver
    /// configurations as RON text) on every Newton system besides the scene's policy.
    #[staticmethod]
    fn collect(
        py: Python<'_>,
        scene: &Scene,
        candidates: Vec<String>,
        steps: usize,
    ) -> PyResult<Self> {
        let specs = specs(&candidates)?;
        let data = py
            .detach(|| collect(&scene.scene, &scene.origin, &specs, steps, |_| {}))
            .map_err(errors::learn)?;
        Ok(Self { data })
    }

    /// Loads a saved solver dataset folder.
    #[staticmethod]
    fn load(dir: PathBuf) -> PyResult<Self> {
        let data = SolverDataset::load(&dir).map_err(errors::learn)?;
        Ok(Self { data })
    }

    /// Saves it (RON metadata and `.npy` arrays).
    fn save(&self, dir: PathBuf) -> PyResult<()> {
        self.data.save(&dir).map_err(errors::learn)
    }

    /// Number of logged linear systems.
    fn __len__(&self) -> usize {
        self.data.features.len()
    }
}

/// A learned linear-solver policy: per Newton iteration, the candidate with the least
/// predicted work among those predicted to succeed.
#[pyclass(module = "deform._deform", name = "LearnedPolicy", frozen)]
pub struct LearnedPolicy {
    pub policy: deform_learn::policy::LearnedPolicy,
}

#[pymethods]
impl LearnedPolicy {
    /// Trains on `data`; `young` is the Young's modulus of the material it will run on (a
    /// feature), `factor_weight` the work of a factorisation flop relative to a solve
    /// flop, `sweep_weight` that of a flop of a sequential sweep (IC(0)'s triangular solves,
    /// SSOR), `forcing` Eisenstat-Walker's `(eta_max, gamma)` for inexact Newton.
    #[staticmethod]
    #[pyo3(signature = (data, *, young, neighbours = 5, min_success = 0.9, factor_weight = 1.0, sweep_weight = 1.0, forcing = None))]
    fn train(
        data: &SolverData,
        young: f64,
        neighbours: usize,
        min_success: f64,
        factor_weight: f64,
        sweep_weight: f64,
        forcing: Option<(f64, f64)>,
    ) -> PyResult<Self> {
        if !(young.is_finite() && young > 0.0) {
            return Err(errors::learn(format!(
                "young = {young} must be finite and > 0"
            )));
        }
        let options = PolicyOptions::new(young)
            .neighbours(neighbours)
            .min_success(min_success)
            .weights(deform_solvers::WorkWeights::factor(factor_weight).sweep(sweep_weight))
            .forcing(forcing);
        let policy = deform_learn::policy::LearnedPolicy::train(&data.data, options);
        Ok(Self { policy })
    }

    /// Its name, with its candidates.
    #[getter]
    fn name(&self) -> String {
        deform_integrator::SolverPolicy::name(&self.policy)
    }
}

/// Adds the classes to the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<SolverData>()?;
    m.add_class::<LearnedPolicy>()?;
    Ok(())
}
