//! `deform.Assembly`: energy, forces and the stiffness matrix of a mesh and material at given
//! positions, and its mass matrices; sparse matrices leave as CSR triplets.

use std::sync::Mutex;

use deform_assembly::{Mass, MaterialField, Tangent};
use numpy::PyArrayDyn;
use pyo3::prelude::*;

use crate::arrays::{array, values};
use crate::errors;
use crate::materials::Material;
use crate::mesh::Mesh;

/// K's CSR pattern as scipy takes it (32-bit indices where they fit), kept so that each
/// matrix costs one copy of the pattern and none of the values.
enum Pattern {
    I32(Vec<i32>, Vec<i32>),
    I64(Vec<i64>, Vec<i64>),
}

impl Pattern {
    fn of(asm: &deform_assembly::Assembly) -> Self {
        let (indptr, indices) = asm.stiffness_pattern();
        if indices.len() < i32::MAX as usize {
            let small = |v: &[usize]| v.iter().map(|&i| i as i32).collect();
            Pattern::I32(small(&indptr), small(&indices))
        } else {
            let wide = |v: &[usize]| v.iter().map(|&i| i as i64).collect();
            Pattern::I64(wide(&indptr), wide(&indices))
        }
    }

    /// A `scipy.sparse.csr_matrix` of `values` on this pattern (`values` moved, not copied).
    fn matrix<'py>(
        &self,
        py: Python<'py>,
        values: Vec<f64>,
        n: usize,
    ) -> PyResult<Bound<'py, PyAny>> {
        let nnz = values.len();
        let data = array(py, values, &[nnz])?.into_any();
        let (indices, indptr) = match self {
            Pattern::I32(p, i) => (
                array(py, i.clone(), &[nnz])?.into_any(),
                array(py, p.clone(), &[n + 1])?.into_any(),
            ),
            Pattern::I64(p, i) => (
                array(py, i.clone(), &[nnz])?.into_any(),
                array(py, p.clone(), &[n + 1])?.into_any(),
            ),
        };
        let kwargs = pyo3::types::PyDict::new(py);
        kwargs.set_item("shape", (n, n))?;
        py.import("scipy.sparse")?
            .getattr("csr_matrix")?
            .call(((data, indices, indptr),), Some(&kwargs))
    }
}

/// Energy, forces and stiffness of a mesh with one material.
#[pyclass(module = "deform._deform", name = "Assembly", frozen)]
pub struct Assembly {
    inner: Mutex<deform_assembly::Assembly>,
    mesh: deform_mesh::TetMesh,
    pattern: Pattern,
}

/// Positions from an (V, 3) or (3V,) array, flattened, and their shape.
fn positions(x: &Bound<'_, PyAny>) -> PyResult<(Vec<f64>, Vec<usize>)> {
    values("x", x)
}

/// The exact tangent, or each element's projected to positive semi-definite.
fn tangent(project: bool) -> Tangent {
    if project {
        Tangent::Projected
    } else {
        Tangent::Exact
    }
}

impl Assembly {
    /// The assembly, locked. Taken only with the GIL released (inside `detach`) or for
    /// quick work, so that a Python thread waiting for it never holds the GIL that the
    /// holder needs back.
    fn lock(&self) -> std::sync::MutexGuard<'_, deform_assembly::Assembly> {
        self.inner.lock().expect("not poisoned")
    }
}

#[pymethods]
impl Assembly {
    /// The assembly of `mesh` with `material` on every element.
    #[new]
    fn new(mesh: &Mesh, material: &Material) -> PyResult<Self> {
        let field = MaterialField::Uniform(material.model.clone());
        let asm = deform_assembly::Assembly::new(&mesh.mesh, field).map_err(errors::assembly)?;
        Ok(Self {
            pattern: Pattern::of(&asm),
            inner: Mutex::new(asm),
            mesh: mesh.mesh.clone(),
        })
    }

    /// The elastic energy at positions `x` ((V, 3) or (3V,)).
    fn energy(&self, py: Python<'_>, x: Bound<'_, PyAny>) -> PyResult<f64> {
        let (x, _) = positions(&x)?;
        py.detach(|| self.lock().energy(&x))
            .map_err(errors::assembly)
    }

    /// The elastic forces `-dE/dx` at `x`, in `x`'s shape.
    fn forces<'py>(
        &self,
        py: Python<'py>,
        x: Bound<'_, PyAny>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        let (x, shape) = positions(&x)?;
        let mut f = vec![0.0; x.len()];
        py.detach(|| self.lock().forces(&x, &mut f))
            .map_err(errors::assembly)?;
        array(py, f, &shape)
    }

    /// The stiffness matrix `K = d2E/dx2` at `x` (3V x 3V, symmetric) as a
    /// `scipy.sparse.csr_matrix`; `project=True` projects each element's `dP/dF` to positive
    /// semi-definite.
    #[pyo3(signature = (x, project = false))]
    fn stiffness<'py>(
        &self,
        py: Python<'py>,
        x: Bound<'_, PyAny>,
        project: bool,
    ) -> PyResult<Bound<'py, PyAny>> {
        let (x, _) = positions(&x)?;
        let tangent = tangent(project);
        let values = py
            .detach(|| {
                let mut asm = self.lock();
                let mut values = vec![0.0; 9 * asm.pattern().num_blocks()];
                asm.evaluate_values(&x, None, None, &mut values, tangent)
                    .map(|()| values)
            })
            .map_err(errors::assembly)?;
        self.pattern.matrix(py, values, x.len())
    }

    /// Energy, forces and the stiffness matrix at `x` in one pass over the elements (the
    /// fast way to get all three): `(energy, forces in x's shape, scipy CSR K)`.
    #[pyo3(signature = (x, project = false))]
    fn evaluate<'py>(
        &self,
        py: Python<'py>,
        x: Bound<'_, PyAny>,
        project: bool,
    ) -> PyResult<(f64, Bound<'py, PyArrayDyn<f64>>, Bound<'py, PyAny>)> {
        let (x, shape) = positions(&x)?;
        let tangent = tangent(project);
        let (energy, f, values) = py
            .detach(|| {
                let mut asm = self.lock();
                let (mut energy, mut f) = (0.0, vec![0.0; x.len()]);
                let mut values = vec![0.0; 9 * asm.pattern().num_blocks()];
                asm.evaluate_values(&x, Some(&mut energy), Some(&mut f), &mut values, tangent)
                    .map(|()| (energy, f, values))
            })
            .map_err(errors::assembly)?;
        let k = self.pattern.matrix(py, values, x.len())?;
        Ok((energy, array(py, f, &shape)?, k))
    }

    /// Lumped vertex masses `rho W / 4` per element corner: (V,).
    fn lumped_mass<'py>(
        &self,
        py: Python<'py>,
        density: f64,
    ) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        check_density(density)?;
        let m = self.mesh.lumped_mass(density);
        let n = m.len();
        array(py, m, &[n])
    }

    /// The mass matrix (3V x 3V) as a `scipy.sparse.csr_matrix`: lumped (diagonal) or
    /// consistent.
    #[pyo3(signature = (density, lumped = true))]
    fn mass_matrix<'py>(
        &self,
        py: Python<'py>,
        density: f64,
        lumped: bool,
    ) -> PyResult<Bound<'py, PyAny>> {
        check_density(density)?;
        let asm = self.lock();
        let mass = if lumped {
            Mass::lumped(&self.mesh, density)
        } else {
            Mass::consistent(&self.mesh, density, asm.pattern())
        };
        // 1 M + 0 K on K's pattern.
        let k = asm.stiffness_matrix();
        let mut m = asm.stiffness_matrix();
        asm.combine(1.0, &mass, 0.0, &k, &mut m)
            .map_err(errors::assembly)?;
        let (_, _, values) = m.into_csr().into_raw_storage();
        self.pattern.matrix(py, values, asm.num_dofs())
    }
}

fn check_density(density: f64) -> PyResult<()> {
    if density.is_finite() && density > 0.0 {
        Ok(())
    } else {
        Err(errors::assembly(format!(
            "density {density} must be finite and > 0"
        )))
    }
}

/// Adds the assembly class to the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Assembly>()
}
