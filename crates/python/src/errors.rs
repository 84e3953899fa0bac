//! Python exceptions for deform's typed errors: each carries deform's message (file, line,
//! element, field), and subclasses `ValueError` (bad input) or `RuntimeError` (a simulation
//! that failed on good input); an unreadable file is an `OSError`.

use pyo3::create_exception;
use pyo3::exceptions::{PyOSError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;

create_exception!(
    deform,
    MeshError,
    PyValueError,
    "A mesh that cannot be read, built or written."
);
create_exception!(
    deform,
    MaterialError,
    PyValueError,
    "Invalid material parameters or a model name deform does not have."
);
create_exception!(
    deform,
    AssemblyError,
    PyValueError,
    "Positions or materials the assembly refuses (wrong shape, non-finite, inverted element)."
);
create_exception!(
    deform,
    SceneError,
    PyValueError,
    "A scene that cannot be parsed, validated or built."
);
create_exception!(
    deform,
    SimulationError,
    PyRuntimeError,
    "A step that failed (Newton did not converge, a solver failed)."
);
create_exception!(
    deform,
    LearnError,
    PyValueError,
    "A dataset, fit or experiment that failed."
);

/// Adds the exception types to the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("MeshError", py.get_type::<MeshError>())?;
    m.add("MaterialError", py.get_type::<MaterialError>())?;
    m.add("AssemblyError", py.get_type::<AssemblyError>())?;
    m.add("SceneError", py.get_type::<SceneError>())?;
    m.add("SimulationError", py.get_type::<SimulationError>())?;
    m.add("LearnError", py.get_type::<LearnError>())?;
    Ok(())
}

/// `MeshError` with `e`'s message.
pub fn mesh(e: impl std::fmt::Display) -> PyErr {
    MeshError::new_err(e.to_string())
}

/// `MaterialError` with `e`'s message.
pub fn material(e: impl std::fmt::Display) -> PyErr {
    MaterialError::new_err(e.to_string())
}

/// `AssemblyError` with `e`'s message.
pub fn assembly(e: impl std::fmt::Display) -> PyErr {
    AssemblyError::new_err(e.to_string())
}

/// `SceneError` with `e`'s message.
pub fn scene(e: impl std::fmt::Display) -> PyErr {
    SceneError::new_err(e.to_string())
}

/// `SimulationError` with `e`'s message.
pub fn simulation(e: impl std::fmt::Display) -> PyErr {
    SimulationError::new_err(e.to_string())
}

/// `LearnError` with `e`'s message.
pub fn learn(e: impl std::fmt::Display) -> PyErr {
    LearnError::new_err(e.to_string())
}

/// `OSError` with `e`'s message (a file that cannot be read or written).
pub fn os(e: impl std::fmt::Display) -> PyErr {
    PyOSError::new_err(e.to_string())
}
