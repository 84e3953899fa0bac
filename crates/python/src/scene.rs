//! `deform.Scene`: a simulation scene from a RON file or text (mesh, material, constraints,
//! time stepping, solver policy), shared by simulations and learned policies.

use std::path::{Path, PathBuf};

use deform_integrator::Scene as RustScene;
use pyo3::prelude::*;

use crate::errors;
use crate::mesh::Mesh;

/// A simulation scene: mesh, material, constraints, time stepping, solver policy.
#[pyclass(module = "deform._deform", name = "Scene", frozen)]
pub struct Scene {
    pub scene: RustScene,
    /// Where relative paths of the scene are resolved from (its file).
    pub origin: PathBuf,
}

#[pymethods]
impl Scene {
    /// Loads a scene file (RON; unknown fields are refused).
    #[staticmethod]
    fn load(path: PathBuf) -> PyResult<Self> {
        let scene = RustScene::load(&path).map_err(errors::scene)?;
        Ok(Self {
            scene,
            origin: path,
        })
    }

    /// A scene from RON text; relative paths in it are resolved from `origin` (a file path
    /// whose folder holds them; default: the current folder).
    #[staticmethod]
    #[pyo3(signature = (text, origin = PathBuf::from("scene.ron")))]
    fn from_ron(text: &str, origin: PathBuf) -> PyResult<Self> {
        let mut scene = RustScene::parse(text, &origin).map_err(errors::scene)?;
        let dir = origin.parent().unwrap_or(Path::new(".")).to_path_buf();
        scene.mesh.resolve_paths(&dir);
        scene.validate(&origin).map_err(errors::scene)?;
        Ok(Self { scene, origin })
    }

    /// The scene as RON text.
    fn to_ron(&self) -> PyResult<String> {
        let pretty = ron::ser::PrettyConfig::default().struct_names(true);
        ron::ser::to_string_pretty(&self.scene, pretty).map_err(errors::scene)
    }

    /// Its name.
    #[getter]
    fn name(&self) -> String {
        self.scene.name.clone()
    }

    /// The number of steps it asks for.
    #[getter]
    fn steps(&self) -> usize {
        self.scene.steps
    }

    /// The time step (s).
    #[getter]
    fn dt(&self) -> f64 {
        self.scene.integrator.dt
    }

    /// Builds its mesh.
    fn mesh(&self) -> PyResult<Mesh> {
        let mesh = self.scene.build_mesh(&self.origin).map_err(errors::scene)?;
        Ok(Mesh { mesh })
    }
}

/// Adds the scene class to the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Scene>()?;
    Ok(())
}
