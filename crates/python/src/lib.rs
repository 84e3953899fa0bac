//! deform from Python: the `deform._deform` extension module behind the `deform` package
//! (`crates/python/python/deform`). Rust does the work; numpy arrays cross the boundary as
//! contiguous float64 / int64 buffers (the Python layer converts what users pass), sparse
//! matrices as CSR triplets that the Python layer wraps in `scipy.sparse.csr_matrix`, and
//! reports as plain Python data (through serde). Every error becomes a Python exception
//! carrying deform's message; the GIL is released during assembly, steps and experiments.

use pyo3::prelude::*;

mod arrays;
mod assembly;
mod errors;
mod learn;
mod materials;
mod mesh;
mod policy;
mod scene;
mod simulation;

/// The extension module.
#[pymodule]
fn _deform(m: &Bound<'_, PyModule>) -> PyResult<()> {
    errors::register(m)?;
    mesh::register(m)?;
    materials::register(m)?;
    assembly::register(m)?;
    scene::register(m)?;
    simulation::register(m)?;
    learn::register(m)?;
    policy::register(m)?;
    Ok(())
}
