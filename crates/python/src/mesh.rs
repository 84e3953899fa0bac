//! `deform.Mesh`: linear tetrahedral meshes from files (every format deform reads), from
//! numpy arrays or from the box generator, and written to every format deform writes.

use std::path::PathBuf;

use deform_mesh::generate::BoxGrid;
use deform_mesh::io::ReadError;
use deform_mesh::{MeshOptions, TetMesh};
use nalgebra::Vector3;
use numpy::PyArrayDyn;
use pyo3::prelude::*;

use crate::arrays::{array, check_shape, values};
use crate::errors;

/// A linear tetrahedral mesh (rest positions and elements).
#[pyclass(module = "deform._deform", name = "Mesh", frozen)]
pub struct Mesh {
    pub mesh: TetMesh,
}

/// A read error: `OSError` when the file cannot be opened, else `MeshError`.
fn read_error(e: ReadError) -> PyErr {
    match e {
        ReadError::Io { .. } => errors::os(e),
        other => errors::mesh(other),
    }
}

#[pymethods]
impl Mesh {
    /// A mesh from `vertices` (V, 3) float64 and `tets` (T, 4) int64 (vertex indices);
    /// validated (indices in range, finite positions, no degenerate element; an inverted
    /// element is reoriented).
    #[new]
    fn new(vertices: Bound<'_, PyAny>, tets: Bound<'_, PyAny>) -> PyResult<Self> {
        let (v, vs) = values::<f64>("vertices", &vertices)?;
        check_shape("vertices", &vs, &[None, Some(3)])?;
        let (t, ts) = values::<i64>("tets", &tets)?;
        check_shape("tets", &ts, &[None, Some(4)])?;
        let rest: Vec<Vector3<f64>> = v.chunks(3).map(Vector3::from_column_slice).collect();
        let mut elements = Vec::with_capacity(ts[0]);
        for (e, c) in t.chunks(4).enumerate() {
            let mut tet = [0usize; 4];
            for (k, &i) in c.iter().enumerate() {
                tet[k] = usize::try_from(i).map_err(|_| {
                    errors::mesh(format!("tets: element {e}: negative vertex index {i}"))
                })?;
            }
            elements.push(tet);
        }
        let mesh = TetMesh::try_new(rest, elements).map_err(errors::mesh)?;
        Ok(Self { mesh })
    }

    /// Rest positions, (V, 3).
    #[getter]
    fn vertices<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        let n = self.mesh.num_vertices();
        array(py, self.mesh.rest_positions_flat(), &[n, 3])
    }

    /// Elements, (T, 4) int64.
    #[getter]
    fn tets<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<i64>>> {
        let t: Vec<i64> = self
            .mesh
            .tets()
            .iter()
            .flatten()
            .map(|&i| i as i64)
            .collect();
        array(py, t, &[self.mesh.num_tets(), 4])
    }

    /// Rest volumes, (T,).
    #[getter]
    fn volumes<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        array(py, self.mesh.volumes().to_vec(), &[self.mesh.num_tets()])
    }

    /// Region tag of each element, (T,) int64.
    #[getter]
    fn regions<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<i64>>> {
        let r: Vec<i64> = self.mesh.regions().iter().map(|&r| r as i64).collect();
        array(py, r, &[self.mesh.num_tets()])
    }

    /// Boundary triangles oriented outward, (F, 3) int64.
    #[getter]
    fn boundary_faces<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<i64>>> {
        let faces = deform_mesh::topology::faces(&self.mesh).boundary;
        let n = faces.len();
        let f: Vec<i64> = faces.into_iter().flatten().map(|i| i as i64).collect();
        array(py, f, &[n, 3])
    }

    /// Number of vertices.
    #[getter]
    fn num_vertices(&self) -> usize {
        self.mesh.num_vertices()
    }

    /// Number of elements.
    #[getter]
    fn num_tets(&self) -> usize {
        self.mesh.num_tets()
    }

    /// Writes the mesh; the format follows the extension (`.msh`, `.vtu`, `.node`/`.ele`
    /// stem, `.obj` boundary), written atomically.
    fn write(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        let mesh = &self.mesh;
        py.detach(|| deform_mesh::io::write(&path, mesh))
            .map_err(errors::mesh)
    }

    fn __repr__(&self) -> String {
        format!(
            "Mesh(vertices={}, tets={})",
            self.mesh.num_vertices(),
            self.mesh.num_tets()
        )
    }
}

/// Reads a mesh: Gmsh `.msh` (2.2 and 4.1, ASCII and binary) or TetGen `.node`/`.ele`; the
/// format follows the extension.
#[pyfunction]
fn read_mesh(py: Python<'_>, path: PathBuf) -> PyResult<Mesh> {
    let mesh = py
        .detach(|| deform_mesh::io::read(&path, &MeshOptions::default()))
        .map_err(read_error)?;
    Ok(Mesh { mesh })
}

/// The beam of `BENCHMARKS.md`: `4n x n x n` cubes on `[0, 1] x [0, 0.25] x [0, 0.25]`,
/// six tets each (`6 * 4 n^3` tets).
#[pyfunction]
fn beam(n: usize) -> PyResult<Mesh> {
    let mesh = BoxGrid::beam(n).build().map_err(errors::mesh)?;
    Ok(Mesh { mesh })
}

/// A box of `cells` (nx, ny, nz) cubes of total `size` with lower corner `origin`, six tets
/// per cube.
#[pyfunction]
#[pyo3(signature = (cells, size, origin = [0.0, 0.0, 0.0]))]
fn box_mesh(cells: [usize; 3], size: [f64; 3], origin: [f64; 3]) -> PyResult<Mesh> {
    let grid = BoxGrid::new(cells, size).origin(origin);
    let mesh = grid.build().map_err(errors::mesh)?;
    Ok(Mesh { mesh })
}

/// Adds the mesh class and functions to the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Mesh>()?;
    m.add_function(wrap_pyfunction!(read_mesh, m)?)?;
    m.add_function(wrap_pyfunction!(beam, m)?)?;
    m.add_function(wrap_pyfunction!(box_mesh, m)?)?;
    Ok(())
}
