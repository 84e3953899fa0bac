//! `deform.Experiment`: experiment files (dataset, fit, model selection, solver learning,
//! coarsening) run by deform's library, returning the typed report as Python data.

use std::path::PathBuf;

use deform_learn::experiment::{Experiment as RustExperiment, NoProgress, run};
use pyo3::prelude::*;

use crate::errors;

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
        pythonize::pythonize(py, &report).map_err(errors::learn)
    }

    /// Its name.
    #[getter]
    fn name(&self) -> String {
        self.experiment.name.clone()
    }
}

/// Adds the experiment class to the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Experiment>()
}
