//! `deform.Material`: every energy model by name with Young's modulus and Poisson's ratio or
//! the Lame pair, evaluated over arrays of deformation gradients.

use deform_learn::ensemble::Member;
use deform_materials::{Material as _, MaterialSpec, Model, Moduli};
use nalgebra::Matrix3;
use numpy::PyArrayDyn;
use pyo3::prelude::*;

use crate::arrays::{array, check_shape, values};
use crate::errors;

/// A hyperelastic energy density `Psi(F)` (one model or a weighted ensemble).
#[pyclass(module = "deform._deform", name = "Material", frozen)]
pub struct Material {
    pub spec: MaterialSpec,
    pub model: Model,
}

/// The model names Python uses, and the models they are.
const MODELS: [(&str, Member); 6] = [
    ("linear", Member::LinearElastic),
    ("corotated", Member::CorotatedLinear),
    ("fixed_corotated", Member::FixedCorotated),
    ("stvk", Member::StVenantKirchhoff),
    ("neo_hookean", Member::NeoHookean),
    ("stable_neo_hookean", Member::StableNeoHookean),
];

/// The model of a Python name (`Material`, `fit_ensemble`).
pub fn member(name: &str) -> PyResult<Member> {
    match MODELS.iter().find(|(n, _)| *n == name) {
        Some((_, m)) => Ok(*m),
        None => {
            let names: Vec<&str> = MODELS.iter().map(|(n, _)| *n).collect();
            Err(errors::material(format!(
                "unknown model {name:?}; one of {}",
                names.join(", ")
            )))
        }
    }
}

impl Material {
    fn from_spec(spec: MaterialSpec) -> PyResult<Self> {
        let model = spec.build().map_err(errors::material)?;
        Ok(Self { spec, model })
    }
}

impl Material {
    /// `per(model, F)` of each `F` of a (N, 3, 3) array (row-major, `F[n, i, j]`), with the
    /// GIL released, as an array of shape (N, *tail).
    fn per_gradient<'py, const W: usize>(
        &self,
        py: Python<'py>,
        f: &Bound<'_, PyAny>,
        tail: &[usize],
        per: impl Fn(&Model, &Matrix3<f64>) -> [f64; W] + Send + Sync,
    ) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        let (data, shape) = values::<f64>("F", f)?;
        check_shape("F", &shape, &[None, Some(3), Some(3)])?;
        let model = &self.model;
        let out: Vec<f64> = py.detach(|| {
            data.chunks(9)
                .flat_map(|f| per(model, &Matrix3::from_row_slice(f)))
                .collect()
        });
        array(py, out, &[&[shape[0]], tail].concat())
    }
}

#[pymethods]
impl Material {
    /// `Material(model, E=..., nu=...)` or `Material(model, mu=..., lam=...)`; `model` is
    /// one of linear, corotated, fixed_corotated, stvk, neo_hookean, stable_neo_hookean.
    #[new]
    #[pyo3(signature = (model, *, E = None, nu = None, mu = None, lam = None))]
    #[allow(non_snake_case)]
    fn new(
        model: &str,
        E: Option<f64>,
        nu: Option<f64>,
        mu: Option<f64>,
        lam: Option<f64>,
    ) -> PyResult<Self> {
        let moduli = match (E, nu, mu, lam) {
            (Some(e), Some(nu), None, None) => Moduli::Young { e, nu },
            (None, None, Some(mu), Some(lambda)) => Moduli::Lame { mu, lambda },
            _ => {
                return Err(errors::material(
                    "give either E and nu, or mu and lam".to_owned(),
                ));
            }
        };
        Self::from_spec(member(model)?.spec(moduli))
    }

    /// A material from its RON text as scene files state it, e.g.
    /// `NeoHookean(Young(e: 1e5, nu: 0.4))` or an `Ensemble([...])`.
    #[staticmethod]
    fn from_ron(text: &str) -> PyResult<Self> {
        let spec: MaterialSpec = ron::from_str(text).map_err(errors::material)?;
        Self::from_spec(spec)
    }

    /// The RON text of this material (as scene files state it).
    fn to_ron(&self) -> PyResult<String> {
        ron::to_string(&self.spec).map_err(errors::material)
    }

    /// The Lame pair `(mu, lam)` of a single model (`None` for an ensemble).
    #[getter]
    fn lame(&self) -> Option<(f64, f64)> {
        self.model.lame().map(|l| (l.mu, l.lambda))
    }

    /// The energy density of each `F` of a (N, 3, 3) array: (N,).
    fn psi<'py>(
        &self,
        py: Python<'py>,
        f: Bound<'_, PyAny>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        self.per_gradient::<1>(py, &f, &[], |m, f| [m.psi(f)])
    }

    /// The first Piola-Kirchhoff stress `dPsi/dF` of each `F`: (N, 3, 3).
    fn first_piola<'py>(
        &self,
        py: Python<'py>,
        f: Bound<'_, PyAny>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        self.per_gradient::<9>(py, &f, &[3, 3], |m, f| {
            let p = m.first_piola(f);
            // Row-major, as numpy stores it.
            std::array::from_fn(|k| p[(k / 3, k % 3)])
        })
    }

    /// The tangent `dP/dF` of each `F`: (N, 9, 9) with `T[n, 3i+j, 3k+l] = dP_ij / dF_kl`
    /// (row-major flattening, as `F.reshape(9)`); `project=True` clamps it to positive
    /// semi-definite.
    #[pyo3(signature = (f, project = false))]
    fn tangent<'py>(
        &self,
        py: Python<'py>,
        f: Bound<'_, PyAny>,
        project: bool,
    ) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        self.per_gradient::<81>(py, &f, &[9, 9], |m, f| {
            let t = if project {
                m.dp_df_projected(f)
            } else {
                m.dp_df(f)
            };
            // deform orders vec(F) column-major (3j + i); numpy row-major (3i + j).
            let col = |r: usize| 3 * (r % 3) + r / 3;
            std::array::from_fn(|k| t[(col(k / 9), col(k % 9))])
        })
    }

    fn __repr__(&self) -> PyResult<String> {
        Ok(format!("Material.from_ron({:?})", self.to_ron()?))
    }
}

/// Adds the material class to the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Material>()
}
