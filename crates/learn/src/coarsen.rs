//! Coarse-from-fine data: a fine model's trajectories carried onto a coarse mesh of the same
//! body, so that a cheap model can learn from an accurate one. Each coarse rest vertex is
//! located once in the fine rest mesh ([`Embedding`]); the coarse positions and velocities
//! of every step are the fine state interpolated there. The result is an ordinary
//! [`Dataset`] of the coarse scene, which every fit in this crate takes.
//!
//! ```
//! use std::path::Path;
//! use deform_integrator::Scene;
//! use deform_learn::coarsen::{Constraints, coarsen};
//! use deform_learn::dataset::{DatasetSpec, generate};
//!
//! let text = r#"Scene(name: "fine", mesh: Beam(2), material: NeoHookean(Young(e: 1e5, nu: 0.4)),
//!     density: 1000.0, constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
//!     integrator: (dt: 0.01), steps: 3)"#;
//! let fine = Scene::parse(text, Path::new("fine.ron")).unwrap();
//! let coarse = fine.clone().mesh(deform_integrator::scene::MeshSource::Beam(1));
//! let data = generate(&fine, Path::new("fine.ron"), &DatasetSpec::new(1, 3, 7), |_, _| ()).unwrap();
//! let (coarse_data, report) = coarsen(&data, &coarse, Path::new("coarse.ron"), Constraints::FromFine).unwrap();
//! assert_eq!((report.vertices, report.outside), (20, 0));
//! assert_eq!(coarse_data.trajectories[0].x[3].len(), 3 * 20);
//! ```

use std::path::{Path, PathBuf};

use deform_fs::npy;
use deform_integrator::scene::{ConstraintSpec, MeshSource};
use deform_integrator::{Scene, SceneError};
use deform_mesh::embed::Embedding;
use deform_mesh::io::{MshFormat, MshVersion};
use deform_mesh::select::Selector;
use serde::{Deserialize, Serialize};

use crate::LearnError;
use crate::dataset::{Dataset, Trajectory};

/// Where the coarse model's constraints come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum Constraints {
    /// Each fine constraint (and load) becomes a coarse one on the coarse vertices that lie
    /// on its vertex set (all their interpolation weight on its fine vertices), with the
    /// same motion (force).
    #[default]
    FromFine,
    /// The coarse scene's own selectors.
    OwnSelectors,
}

/// What the mapping did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct Mapping {
    /// Coarse vertices.
    pub vertices: usize,
    /// Coarse tets.
    pub tets: usize,
    /// Fine tets over coarse tets.
    pub ratio: f64,
    /// Coarse vertices outside the fine mesh (placed on the nearest fine element).
    pub outside: usize,
    /// Their largest distance from the fine mesh (m).
    pub max_distance: f64,
    /// Coarse vertices constrained per constraint.
    pub constrained: Vec<usize>,
}

/// Carries `fine`'s trajectories onto `coarse`'s mesh. The returned dataset has `coarse` as
/// its scene (with its constraints replaced per `constraints`), the fine data's time step,
/// splits and initial conditions. `origin` names the coarse scene in errors.
///
/// # Errors
/// [`LearnError::Scene`] when either scene does not build or a mapped constraint selects
/// no coarse vertex.
pub fn coarsen(
    fine: &Dataset,
    coarse: &Scene,
    origin: &Path,
    constraints: Constraints,
) -> Result<(Dataset, Mapping), LearnError> {
    coarsen_embedded(fine, coarse, origin, constraints, None)
}

/// [`coarsen`] with the coarse rest vertices' places in the fine mesh given (see
/// [`Embedding::given`], e.g. from [`read_embedding`]) instead of located; `None` locates
/// them.
///
/// # Errors
/// As [`coarsen`]; [`LearnError::Scene`] when the embedding has not one entry per coarse
/// vertex.
pub fn coarsen_embedded(
    fine: &Dataset,
    coarse: &Scene,
    origin: &Path,
    constraints: Constraints,
    embedding: Option<&Embedding>,
) -> Result<(Dataset, Mapping), LearnError> {
    if let Some(k) = fine.trajectories.iter().position(|t| t.observed.is_some()) {
        return Err(LearnError::Unsupported(format!(
            "trajectory {k} observes only some vertices: coarsening interpolates whole states"
        )));
    }
    let fine_scene = &fine.meta.scene;
    let fine_mesh = fine_scene.build_mesh(origin)?;
    let mut coarse = coarse.clone();
    let coarse_mesh = coarse.build_mesh(origin)?;
    let embedding = match embedding {
        Some(e) if e.len() != coarse_mesh.num_vertices() => {
            let reason = format!(
                "{} embedded points for {} coarse vertices",
                e.len(),
                coarse_mesh.num_vertices()
            );
            return Err(invalid(origin, "embedding", reason));
        }
        Some(e) => e.clone(),
        None => Embedding::locate(&fine_mesh, coarse_mesh.rest_positions()),
    };
    if constraints == Constraints::FromFine {
        // The coarse vertices that lie on a fine vertex set.
        let carry = |select: &Selector, field: String| -> Result<Selector, LearnError> {
            let on = select
                .select(&fine_mesh)
                .map_err(|e| invalid(origin, &field, e.to_string()))?;
            let mut set = vec![false; fine_mesh.num_vertices()];
            on.iter().for_each(|&v| set[v] = true);
            let vertices = supported_by(&embedding, &fine_mesh, &set);
            if vertices.is_empty() {
                let reason = "no coarse vertex lies on this fine vertex set".to_owned();
                return Err(invalid(origin, &field, reason));
            }
            Ok(Selector::Indices(vertices))
        };
        let mut mapped = Vec::new();
        for (i, c) in fine_scene.constraints.iter().enumerate() {
            mapped.push(
                ConstraintSpec::new(carry(&c.select, format!("constraints[{i}].select"))?)
                    .motion(c.motion.clone()),
            );
        }
        coarse.constraints = mapped;
        let mut loads = Vec::new();
        for (i, l) in fine_scene.loads.iter().enumerate() {
            loads.push(
                l.clone()
                    .select(carry(&l.select, format!("loads[{i}].select"))?),
            );
        }
        coarse.loads = loads;
    }
    let constrained = coarse
        .constraints
        .iter()
        .map(|c| c.select.select(&coarse_mesh).map_or(0, |v| v.len()))
        .collect();
    let map = |states: &[Vec<f64>]| -> Vec<Vec<f64>> {
        states
            .iter()
            .map(|s| embedding.interpolate(&fine_mesh, s))
            .collect()
    };
    let trajectories = fine
        .trajectories
        .iter()
        .map(|t| Trajectory {
            x: map(&t.x),
            v: map(&t.v),
            start_time: t.start_time,
            exact_start: t.exact_start,
            conditions: t.conditions.clone(),
            observed: None,
        })
        .collect();
    let mut meta = fine.meta.clone();
    meta.scene = coarse;
    meta.vertices = coarse_mesh.num_vertices();
    let report = Mapping {
        vertices: coarse_mesh.num_vertices(),
        tets: coarse_mesh.num_tets(),
        ratio: fine_mesh.num_tets() as f64 / coarse_mesh.num_tets() as f64,
        outside: embedding.outside.len(),
        max_distance: embedding.max_distance,
        constrained,
    };
    Ok((Dataset { meta, trajectories }, report))
}

/// Saves a learned model as a scene a user keeps and runs (`cargo xtask simulate`):
/// `dir/NAME.ron` is `scene` with its coefficient field in `dir/NAME.coefficients.npy`
/// (shape (tets, terms), see [`Scene::coefficients`]) and its per-vertex mass scales, when
/// given, in `dir/NAME.mass_scale.npy` ([`Scene::mass_scale`]); a mesh read from a file is
/// copied to
/// `dir/NAME.msh` (binary, so coordinates survive bit for bit), a generated one stays a
/// generator. Returns the files written, the scene file first.
///
/// # Errors
/// [`LearnError`] when the scene does not build, the field has the wrong length or a
/// file cannot be written.
pub fn save_model(
    scene: &Scene,
    coefficients: &[f64],
    mass_scale: Option<&[f64]>,
    dir: &Path,
) -> Result<Vec<PathBuf>, LearnError> {
    let origin = dir.join(format!("{}.ron", scene.name));
    let mut saved = scene.clone();
    saved.coefficients = None;
    saved.mass_scale = None;
    let mesh = saved.build_mesh(&origin)?;
    let model = saved.material.build()?;
    let (tets, terms) = (mesh.num_tets(), model.term_coefficients().len());
    if coefficients.len() != tets * terms {
        let reason = format!(
            "{} coefficients for {tets} tets x {terms} terms",
            coefficients.len()
        );
        return Err(LearnError::Scene(SceneError::Invalid {
            path: origin,
            field: "coefficients".into(),
            reason,
        }));
    }
    if let Some(scale) = mass_scale
        && scale.len() != mesh.num_vertices()
    {
        let reason = format!(
            "{} scales for {} vertices",
            scale.len(),
            mesh.num_vertices()
        );
        return Err(LearnError::Scene(SceneError::Invalid {
            path: origin,
            field: "mass_scale".into(),
            reason,
        }));
    }
    // Every write names its file.
    let io = |path: &Path, e: &dyn std::fmt::Display| LearnError::Io {
        path: path.to_owned(),
        source: std::io::Error::other(e.to_string()),
    };
    std::fs::create_dir_all(dir).map_err(|e| io(dir, &e))?;
    let mut written = vec![origin.clone()];
    if saved.mesh.is_file() {
        let name = format!("{}.msh", scene.name);
        let format = MshFormat {
            version: MshVersion::V4_1,
            binary: true,
        };
        let path = dir.join(&name);
        deform_mesh::io::write_msh(&path, &mesh, format).map_err(|e| io(&path, &e))?;
        written.push(path);
        saved.mesh = MeshSource::File(name.into());
    }
    let field = format!("{}.coefficients.npy", scene.name);
    let path = dir.join(&field);
    npy::write(&path, &[tets, terms], coefficients).map_err(|e| io(&path, &e))?;
    written.push(path);
    saved.coefficients = Some(field.into());
    if let Some(scale) = mass_scale {
        let name = format!("{}.mass_scale.npy", scene.name);
        let path = dir.join(&name);
        npy::write(&path, &[scale.len()], scale).map_err(|e| io(&path, &e))?;
        written.push(path);
        saved.mass_scale = Some(name.into());
    }
    let text =
        ron::ser::to_string_pretty(&saved, ron::ser::PrettyConfig::default().struct_names(true))
            .map_err(|e| io(&origin, &e))?;
    deform_fs::write_text(&origin, &text).map_err(|e| io(&origin, &e))?;
    Ok(written)
}

/// Reads a given embedding of `vertices` coarse vertices in `fine`: `.npy` files of their
/// fine elements (vertices,) and barycentric weights (vertices, 4) ([`Embedding::given`]).
///
/// # Errors
/// [`LearnError::Scene`] naming the file and what is wrong.
pub fn read_embedding(
    elements: &Path,
    weights: &Path,
    fine: &deform_mesh::TetMesh,
    vertices: usize,
) -> Result<Embedding, LearnError> {
    let bad = |file: &Path, reason: String| invalid(file, "embedding", reason);
    let e = npy::read(elements).map_err(|e| bad(elements, e.to_string()))?;
    let w = npy::read(weights).map_err(|e| bad(weights, e.to_string()))?;
    if e.shape != [vertices] {
        let reason = format!(
            "shape {:?}, expected [{vertices}] (coarse vertices)",
            e.shape
        );
        return Err(bad(elements, reason));
    }
    if w.shape != [vertices, 4] {
        let reason = format!("shape {:?}, expected [{vertices}, 4]", w.shape);
        return Err(bad(weights, reason));
    }
    let element = e.indices().map_err(|r| bad(elements, r))?;
    let rows = w.data.chunks(4).map(|c| [c[0], c[1], c[2], c[3]]).collect();
    Embedding::given(fine, element, rows).map_err(|r| bad(weights, r))
}

/// The located points whose interpolation weight lies entirely on vertices in `set`.
fn supported_by(e: &Embedding, mesh: &deform_mesh::TetMesh, set: &[bool]) -> Vec<usize> {
    let on = |(&t, w): (&usize, &[f64; 4])| {
        let tet = mesh.tets()[t];
        (0..4).all(|a| w[a].abs() <= 1e-12 || set[tet[a]])
    };
    let points = e.element.iter().zip(&e.weights).enumerate();
    points.filter(|(_, p)| on(*p)).map(|(i, _)| i).collect()
}

fn invalid(origin: &Path, field: &str, reason: String) -> LearnError {
    LearnError::Scene(SceneError::Invalid {
        path: origin.to_owned(),
        field: field.to_owned(),
        reason,
    })
}
