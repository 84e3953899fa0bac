//! numpy at the boundary: contiguous float64 / int64 arrays in (the Python layer converts
//! what users pass), new arrays out.

use numpy::{PyArray1, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

/// Anything numpy takes (arrays of any dtype and layout, nested lists) as a C-contiguous
/// array of `T`'s dtype, converted by `numpy.ascontiguousarray`. Values that do not convert
/// (strings, NaN to integers) raise numpy's `ValueError` / `TypeError`.
pub fn convert<'py, T: numpy::Element>(
    name: &str,
    obj: &Bound<'py, PyAny>,
) -> PyResult<PyReadonlyArrayDyn<'py, T>> {
    let py = obj.py();
    let dtype = numpy::dtype::<T>(py);
    let np = py.import("numpy")?;
    let a = np
        .getattr("ascontiguousarray")?
        .call1((obj, dtype))
        .map_err(|e| PyValueError::new_err(format!("{name}: {e}")))?;
    let a = a
        .cast_into::<numpy::PyArrayDyn<T>>()
        .map_err(|e| PyValueError::new_err(format!("{name}: not an array of numbers ({e})")))?;
    Ok(a.readonly())
}

/// The values of anything numpy takes (see [`convert`]) and its shape.
pub fn values<T: numpy::Element + Copy>(
    name: &str,
    obj: &Bound<'_, PyAny>,
) -> PyResult<(Vec<T>, Vec<usize>)> {
    let a = convert::<T>(name, obj)?;
    let shape = a.shape().to_vec();
    let data = a
        .as_slice()
        .map_err(|_| PyValueError::new_err(format!("{name}: the array must be C-contiguous")))?;
    Ok((data.to_vec(), shape))
}

/// `data` as a new array of `shape`.
pub fn array<'py, T: numpy::Element>(
    py: Python<'py>,
    data: Vec<T>,
    shape: &[usize],
) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
    PyArray1::from_vec(py, data).reshape(shape.to_vec())
}

/// Checks that `shape` is `expected` (`None`: any length), naming the array.
pub fn check_shape(name: &str, shape: &[usize], expected: &[Option<usize>]) -> PyResult<()> {
    let fits = shape.len() == expected.len()
        && shape
            .iter()
            .zip(expected)
            .all(|(s, e)| e.is_none_or(|e| *s == e));
    if fits {
        return Ok(());
    }
    let want: Vec<String> = expected
        .iter()
        .map(|e| e.map_or("n".to_owned(), |e| e.to_string()))
        .collect();
    Err(PyValueError::new_err(format!(
        "{name}: shape {shape:?}, expected ({})",
        want.join(", ")
    )))
}
