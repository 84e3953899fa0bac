//! Scenes: a mesh, its material, boundary conditions, the integrator's options and solver
//! policy, initial conditions and outputs, as one RON document with unknown fields rejected.
//!
//! The scene lives here rather than in xtask because the learning crate generates data from
//! scenes too; it only composes the specs of the crates below it.

use std::path::{Path, PathBuf};

use deform_assembly::MaterialField;
use deform_materials::{MaterialSpec, Model};
use deform_mesh::generate::BoxGrid;
use deform_mesh::memory;
use deform_mesh::select::Selector;
use deform_mesh::{MeshOptions, TetMesh};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::{
    Conditions, Constraint, ContactSpec, Integrator, IntegratorError, IntegratorOptions, Load,
    LoadSpec, Motion, PolicySpec, State,
};

/// Where the mesh comes from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub enum MeshSource {
    /// A `.msh`, `.node` or `.ele` file, relative to the scene file's directory.
    File(PathBuf),
    /// A generated box grid.
    Generate(BoxGrid),
    /// The beam of size `n` of `BENCHMARKS.md`.
    Beam(usize),
    /// Two `.npy` arrays, relative to the scene file: rest vertices (V, 3) and tets (T, 4) of
    /// any integer dtype, 0-based.
    Arrays {
        /// The rest vertices.
        vertices: PathBuf,
        /// The tets.
        tets: PathBuf,
    },
}

impl MeshSource {
    /// Makes relative file paths relative to `dir` (the folder of the file naming them).
    pub fn resolve_paths(&mut self, dir: &Path) {
        let files = match self {
            MeshSource::File(file) => vec![file],
            MeshSource::Arrays { vertices, tets } => vec![vertices, tets],
            MeshSource::Generate(_) | MeshSource::Beam(_) => vec![],
        };
        for file in files {
            if file.is_relative() {
                *file = deform_fs::join_clean(dir, file);
            }
        }
    }

    /// Whether the mesh comes from files (rather than a generator).
    pub fn is_file(&self) -> bool {
        matches!(self, MeshSource::File(_) | MeshSource::Arrays { .. })
    }
}

/// A set of vertices with a prescribed motion.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct ConstraintSpec {
    /// Which vertices.
    pub select: Selector,
    /// How they move.
    #[serde(default = "fixed")]
    pub motion: Motion,
}

crate::setters!(ConstraintSpec {
    select: Selector,
    motion: Motion
});

impl ConstraintSpec {
    /// The vertices `select` held fixed ([`ConstraintSpec::motion`] moves them).
    pub fn new(select: Selector) -> Self {
        let motion = Motion::Fixed;
        Self { select, motion }
    }
}

fn fixed() -> Motion {
    Motion::Fixed
}

/// Initial conditions beyond rest.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
#[non_exhaustive]
pub struct Initial {
    /// Uniform initial velocity (m/s).
    pub velocity: [f64; 3],
    /// Initial angular velocity (rad/s) about the rest centroid.
    pub angular_velocity: [f64; 3],
    /// Start from the static equilibrium under gravity instead of rest.
    pub equilibrium: bool,
    /// Uniform scaling of the initial positions about the rest centroid (1 = rest): a
    /// stretched or squeezed start that is then released.
    pub scale: Option<[f64; 3]>,
    /// A state in memory to start from instead (e.g. the first frame of a recorded
    /// trajectory); it overrides the fields above. Set from code, never read from a file.
    #[serde(skip)]
    pub state: Option<State>,
}

crate::setters!(Initial { velocity: [f64; 3], angular_velocity: [f64; 3], equilibrium: bool, scale: Option<[f64; 3]>, state: Option<State> });

/// What the runner writes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
#[non_exhaustive]
pub struct Output {
    /// Write a `.vtu` frame every this many steps (0: none).
    pub every: usize,
    /// A rest position; the CSV tracks the vertex nearest to it. `None` tracks the vertex
    /// with the largest rest x (then z): the tip of a cantilever.
    pub track: Option<[f64; 3]>,
}

crate::setters!(Output { every: usize, track: Option<[f64; 3]> });

impl Default for Output {
    fn default() -> Self {
        Self {
            every: 1,
            track: None,
        }
    }
}

/// A simulation scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct Scene {
    /// Human-readable name (output folder name).
    pub name: String,
    /// The mesh.
    pub mesh: MeshSource,
    /// The material.
    pub material: MaterialSpec,
    /// A learned coefficient field over `material`: an `.npy` of shape (tets, terms),
    /// relative to the scene file, whose row `e` holds element `e`'s term coefficients
    /// (`Model::term_coefficients`: `mu, lambda` for a single model).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coefficients: Option<PathBuf>,
    /// Learned per-vertex scales of the lumped mass: an `.npy` of shape (vertices,),
    /// relative to the scene file (see [`Integrator::set_mass_scale`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mass_scale: Option<PathBuf>,
    /// Mass density (kg/m^3).
    pub density: f64,
    /// Boundary conditions.
    #[serde(default)]
    pub constraints: Vec<ConstraintSpec>,
    /// External loads: total forces on vertex sets ([`LoadSpec`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub loads: Vec<LoadSpec>,
    /// Barrier contact of the body's surface against obstacles (IPC's log barrier, with
    /// continuous collision detection in the line search).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub contact: Option<ContactSpec>,
    /// Time stepping.
    #[serde(default)]
    pub integrator: IntegratorOptions,
    /// The linear-solver policy.
    #[serde(default)]
    pub policy: PolicySpec,
    /// Initial conditions.
    #[serde(default)]
    pub initial: Initial,
    /// Number of steps.
    pub steps: usize,
    /// Outputs.
    #[serde(default)]
    pub output: Output,
}

crate::setters!(Scene { name: String, mesh: MeshSource, material: MaterialSpec, coefficients: Option<PathBuf>, mass_scale: Option<PathBuf>, density: f64, constraints: Vec<ConstraintSpec>, loads: Vec<LoadSpec>, contact: Option<ContactSpec>, integrator: IntegratorOptions, policy: PolicySpec, initial: Initial, steps: usize, output: Output });

impl Scene {
    /// A scene of `mesh` and `material` at `density` (kg/m^3) running `steps` steps, with
    /// everything else as a scene file leaves it out: no constraints, loads or contact,
    /// the default integrator options, solver policy, initial state and output. The
    /// setters named like the fields change the rest: `Scene::new(...).constraints(...)`.
    pub fn new(
        name: impl Into<String>,
        mesh: MeshSource,
        material: MaterialSpec,
        density: f64,
        steps: usize,
    ) -> Self {
        Self {
            name: name.into(),
            mesh,
            material,
            coefficients: None,
            mass_scale: None,
            density,
            constraints: Vec::new(),
            loads: Vec::new(),
            contact: None,
            integrator: IntegratorOptions::default(),
            policy: PolicySpec::default(),
            initial: Initial::default(),
            steps,
            output: Output::default(),
        }
    }
}

/// Why a scene cannot be loaded or built; messages name the file and field.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum SceneError {
    /// The file could not be read.
    #[error("{path}: {error}")]
    Io {
        /// The scene file.
        path: PathBuf,
        /// The cause.
        error: std::io::Error,
    },
    /// RON syntax or an unknown / missing field.
    #[error("{path}: {error}")]
    Parse {
        /// The scene file.
        path: PathBuf,
        /// The parser's message (with line and column).
        error: String,
    },
    /// A value is out of range.
    #[error("{path}: {field}: {reason}")]
    Invalid {
        /// The scene file.
        path: PathBuf,
        /// The field.
        field: String,
        /// Why.
        reason: String,
    },
}

/// The per-element field of `file` over `model`: one model per element.
fn coefficient_field(model: &Model, file: &Path, tets: usize) -> Result<MaterialField, String> {
    let a = deform_fs::npy::read(file).map_err(|e| e.to_string())?;
    let terms = model.term_coefficients().len();
    if a.shape != [tets, terms] {
        let shape = &a.shape;
        return Err(format!(
            "{}: shape {shape:?}, expected [{tets}, {terms}] (tets, terms)",
            file.display()
        ));
    }
    // One group per element.
    let index = (0..tets as u32).collect();
    MaterialField::from_term_coefficients(model, index, &a.data)
        .map_err(|e| format!("{} (one group per element): {e}", file.display()))
}

/// The per-vertex mass scales of `file`, one per vertex.
fn read_mass_scale(file: &Path, vertices: usize) -> Result<Vec<f64>, String> {
    let a = deform_fs::npy::read(file).map_err(|e| e.to_string())?;
    if a.shape != [vertices] {
        let shape = &a.shape;
        return Err(format!(
            "{}: shape {shape:?}, expected [{vertices}] (one scale per vertex)",
            file.display()
        ));
    }
    Ok(a.data)
}

/// Refuses a simulation of `vertices` and `tets` that cannot fit in memory.
fn fits(origin: &Path, vertices: usize, tets: usize) -> Result<(), SceneError> {
    let needed = memory::simulation_lower_bound(vertices, tets);
    memory::check_fits(needed).map_err(|reason| SceneError::Invalid {
        path: origin.to_owned(),
        field: "mesh".into(),
        reason: format!("{vertices} vertices and {tets} tets: the simulation {reason}"),
    })
}

/// A scene turned into an integrator, its mesh and initial state.
pub struct Built {
    /// The mesh.
    pub mesh: TetMesh,
    /// The integrator.
    pub integrator: Integrator,
    /// The initial state.
    pub state: State,
}

impl Scene {
    /// Parses scene text and validates its values ([`Scene::validate`]); `path` names it in
    /// errors. Relative mesh paths stay as written.
    ///
    /// # Errors
    /// [`SceneError::Parse`] (with line and column) or [`SceneError::Invalid`].
    pub fn parse(text: &str, path: &Path) -> Result<Self, SceneError> {
        let scene: Scene = ron::from_str(text).map_err(|e| SceneError::Parse {
            path: path.to_owned(),
            error: e.to_string(),
        })?;
        scene.validate(path)?;
        Ok(scene)
    }

    /// Reads a scene file and validates its values ([`Scene::validate`]).
    ///
    /// # Errors
    /// [`SceneError`] naming the file (and line, column or field).
    pub fn load(path: &Path) -> Result<Self, SceneError> {
        let text = std::fs::read_to_string(path).map_err(|error| SceneError::Io {
            path: path.to_owned(),
            error,
        })?;
        let mut scene = Self::parse(&text, path)?;
        let dir = path.parent().unwrap_or(Path::new("."));
        scene.mesh.resolve_paths(dir);
        for file in [&mut scene.coefficients, &mut scene.mass_scale]
            .into_iter()
            .flatten()
        {
            if file.is_relative() {
                *file = deform_fs::join_clean(dir, file);
            }
        }
        for c in &mut scene.constraints {
            c.select.resolve_paths(dir);
        }
        for l in &mut scene.loads {
            l.select.resolve_paths(dir);
        }
        for m in scene.contact.iter_mut().flat_map(|c| &mut c.meshes) {
            if m.file.is_relative() {
                m.file = deform_fs::join_clean(dir, &m.file);
            }
        }
        scene.validate(path)?;
        Ok(scene)
    }

    /// Checks every value that does not need the mesh, naming the field: material,
    /// density, time stepping, policy, the constraints' motions, initial conditions, steps,
    /// name and output. [`Scene::load`] and [`Scene::build`] call it, so a bad value is
    /// refused before anything is allocated. `origin` names the scene in errors.
    ///
    /// # Errors
    /// [`SceneError::Invalid`] naming the field.
    pub fn validate(&self, origin: &Path) -> Result<(), SceneError> {
        let invalid = |field: &str, reason: String| {
            let (path, field) = (origin.to_owned(), field.to_owned());
            Err(SceneError::Invalid {
                path,
                field,
                reason,
            })
        };
        if let Err(e) = self.material.build() {
            return invalid("material", e.to_string());
        }
        if !(self.density.is_finite() && self.density > 0.0) {
            return invalid(
                "density",
                format!("{} must be finite and > 0", self.density),
            );
        }
        if let Err(e) = self.integrator.validate() {
            return invalid("integrator", e.to_string());
        }
        if let Err(e) = self.policy.build() {
            return invalid("policy", e.to_string());
        }
        for (i, c) in self.constraints.iter().enumerate() {
            if let Err(reason) = c.motion.validate() {
                return invalid(&format!("constraints[{i}].motion"), reason);
            }
        }
        for (i, l) in self.loads.iter().enumerate() {
            if let Err(reason) = l.load_force().validate() {
                return invalid(&format!("loads[{i}]"), reason);
            }
        }
        let finite = |v: &[f64; 3]| v.iter().all(|x| x.is_finite());
        let init = &self.initial;
        if !finite(&init.velocity) || !finite(&init.angular_velocity) {
            return invalid("initial", "velocities must be finite".into());
        }
        if let Some(s) = init.scale
            && !s.iter().all(|x| x.is_finite() && *x > 0.0)
        {
            return invalid("initial.scale", format!("{s:?} must be finite and > 0"));
        }
        if self.steps == 0 {
            return invalid("steps", "must be at least 1".into());
        }
        // The name becomes a results folder: a plain file name only.
        let plain = Path::new(&self.name).file_name() == Some(std::ffi::OsStr::new(&self.name));
        if !plain || self.name.contains(['/', '\\']) {
            let name = &self.name;
            return invalid(
                "name",
                format!("{name:?} must be a plain file name (it names the results folder)"),
            );
        }
        if self.output.track.is_some_and(|t| !finite(&t)) {
            return invalid("output.track", "must be finite".into());
        }
        // Refuse a generated mesh that cannot fit before allocating it.
        match &self.mesh {
            MeshSource::File(_) | MeshSource::Arrays { .. } => Ok(()),
            MeshSource::Generate(grid) => fits(origin, grid.num_vertices(), grid.num_tets()),
            MeshSource::Beam(n) => {
                let grid = BoxGrid::beam(*n);
                fits(origin, grid.num_vertices(), grid.num_tets())
            }
        }
    }

    /// Validates the scene and builds its mesh only (read or generated, refused when the
    /// simulation cannot fit in memory): what needs the mesh without an integrator.
    ///
    /// # Errors
    /// [`SceneError::Invalid`] naming the field.
    pub fn build_mesh(&self, origin: &Path) -> Result<TetMesh, SceneError> {
        self.validate(origin)?;
        let invalid = |e: &dyn std::fmt::Display| SceneError::Invalid {
            path: origin.to_owned(),
            field: "mesh".to_owned(),
            reason: e.to_string(),
        };
        let mesh = match &self.mesh {
            MeshSource::File(file) => {
                deform_mesh::io::read(file, &MeshOptions::default()).map_err(|e| invalid(&e))?
            }
            MeshSource::Generate(grid) => grid.build().map_err(|e| invalid(&e))?,
            MeshSource::Beam(n) => BoxGrid::beam(*n).build().map_err(|e| invalid(&e))?,
            MeshSource::Arrays { vertices, tets } => {
                deform_mesh::io::read_arrays(vertices, tets, &MeshOptions::default())
                    .map_err(|e| invalid(&e))?
            }
        };
        // A file's size is known only now; generated meshes were measured by `validate`.
        fits(origin, mesh.num_vertices(), mesh.num_tets())?;
        Ok(mesh)
    }

    /// Builds the mesh, integrator and initial state. `origin` names the scene in errors.
    ///
    /// # Errors
    /// [`SceneError::Invalid`] naming the field.
    pub fn build(&self, origin: &Path) -> Result<Built, SceneError> {
        let mesh = self.build_mesh(origin)?;
        let invalid = |field: &str, reason: String| SceneError::Invalid {
            path: origin.to_owned(),
            field: field.to_owned(),
            reason,
        };
        let model = self
            .material
            .build()
            .map_err(|e| invalid("material", e.to_string()))?;
        let materials = match &self.coefficients {
            None => MaterialField::Uniform(model),
            Some(file) => coefficient_field(&model, file, mesh.num_tets())
                .map_err(|reason| invalid("coefficients", reason))?,
        };
        let mut constraints = Vec::new();
        for (i, c) in self.constraints.iter().enumerate() {
            let vertices = c
                .select
                .select(&mesh)
                .map_err(|e| invalid(&format!("constraints[{i}].select"), e.to_string()))?;
            if vertices.is_empty() {
                return Err(invalid(
                    &format!("constraints[{i}].select"),
                    "selects no vertex".into(),
                ));
            }
            constraints.push(Constraint {
                vertices,
                motion: c.motion.clone(),
            });
        }
        let mut loads = Vec::new();
        for (i, l) in self.loads.iter().enumerate() {
            let field = format!("loads[{i}].select");
            let vertices = l
                .select
                .select(&mesh)
                .map_err(|e| invalid(&field, e.to_string()))?;
            if vertices.is_empty() {
                return Err(invalid(&field, "selects no vertex".into()));
            }
            let force = l.load_force();
            loads.push(Load { vertices, force });
        }
        let policy = self
            .policy
            .build()
            .map_err(|e| invalid("policy", e.to_string()))?;
        let mut builder = Integrator::builder(&mesh, materials)
            .density(self.density)
            .constraints(constraints)
            .loads(loads)
            .options(self.integrator.clone())
            .policy(policy);
        if let Some(contact) = &self.contact {
            builder = builder.contact(contact.clone());
        }
        let mut integrator = builder.build().map_err(|e| match e {
            IntegratorError::Invalid {
                field: "contact",
                reason,
            } => invalid("contact", reason),
            e => invalid("integrator", e.to_string()),
        })?;
        if let Some(file) = &self.mass_scale {
            let scale = read_mass_scale(file, mesh.num_vertices())
                .map_err(|reason| invalid("mass_scale", reason))?;
            integrator
                .set_mass_scale(Some(&scale))
                .map_err(|e| invalid("mass_scale", format!("{}: {e}", file.display())))?;
        }
        if let Some(Err(e)) = integrator.contact_at(&integrator.rest_state().x) {
            return Err(invalid("contact", format!("at rest, {e}")));
        }
        let state = self
            .initial_state(&mesh, &mut integrator)
            .map_err(|e| invalid("initial", e))?;
        if let Some(Err(e)) = integrator.contact_at(&state.x) {
            return Err(invalid("initial", format!("{e}")));
        }
        Ok(Built {
            mesh,
            integrator,
            state,
        })
    }

    fn initial_state(&self, mesh: &TetMesh, integrator: &mut Integrator) -> Result<State, String> {
        let init = &self.initial;
        if let Some(state) = &init.state {
            let n = 3 * mesh.num_vertices();
            if state.x.len() != n || state.v.len() != n {
                let (x, v) = (state.x.len(), state.v.len());
                return Err(format!(
                    "the given state has {x} positions and {v} velocities, the mesh {n} DOFs"
                ));
            }
            if !state.x.iter().chain(&state.v).all(|v| v.is_finite()) {
                return Err("non-finite initial state".into());
            }
            return Ok(state.clone());
        }
        let mut state = integrator.rest_state();
        if init.equilibrium {
            integrator
                .solve_static(&mut state)
                .map_err(|e| format!("static equilibrium: {e}"))?;
        }
        let n = mesh.num_vertices() as f64;
        let centroid = mesh
            .rest_positions()
            .iter()
            .fold(nalgebra::Vector3::zeros(), |a, p| a + p)
            / n;
        let omega = nalgebra::Vector3::from(init.angular_velocity);
        for (v, p) in mesh.rest_positions().iter().enumerate() {
            if integrator.dofs().is_constrained(v) {
                continue;
            }
            let w = omega.cross(&(p - centroid));
            for d in 0..3 {
                state.v[3 * v + d] = init.velocity[d] + w[d];
                if let Some(s) = init.scale {
                    state.x[3 * v + d] = centroid[d] + s[d] * (state.x[3 * v + d] - centroid[d]);
                }
            }
        }
        if !state.x.iter().chain(&state.v).all(|v| v.is_finite()) {
            return Err("non-finite initial state".into());
        }
        Ok(state)
    }

    /// The scene's own conditions, every field given (what [`Conditions`] override).
    pub fn conditions(&self) -> Conditions {
        Conditions {
            gravity: Some(self.integrator.gravity),
            motions: Some(self.constraints.iter().map(|c| c.motion.clone()).collect()),
            loads: Some(self.loads.iter().map(LoadSpec::load_force).collect()),
        }
    }

    /// The scene under `conditions`: their gravity, constraint motions and load forces where
    /// they give them. `origin` names the scene in errors.
    ///
    /// # Errors
    /// [`SceneError::Invalid`] naming the field of `conditions` that does not fit the scene.
    pub fn with_conditions(
        &self,
        conditions: &Conditions,
        origin: &Path,
    ) -> Result<Scene, SceneError> {
        conditions
            .validate(self.constraints.len(), self.loads.len())
            .map_err(|(field, reason)| SceneError::Invalid {
                path: origin.to_owned(),
                field: format!("conditions.{field}"),
                reason,
            })?;
        let mut s = self.clone();
        if let Some(g) = conditions.gravity {
            s.integrator.gravity = g;
        }
        for (c, m) in s
            .constraints
            .iter_mut()
            .zip(conditions.motions.iter().flatten())
        {
            c.motion = m.clone();
        }
        for (l, f) in s.loads.iter_mut().zip(conditions.loads.iter().flatten()) {
            (l.force, l.until) = (f.force, f.until);
        }
        Ok(s)
    }

    /// The tracked vertex: the one nearest to `output.track`, or the one with the largest
    /// rest x (then largest z), e.g. the tip of a cantilever.
    pub fn tracked_vertex(&self, mesh: &TetMesh) -> usize {
        let p = mesh.rest_positions();
        let best = |key: &dyn Fn(usize) -> (f64, f64)| {
            (0..p.len())
                .min_by(|&a, &b| key(a).partial_cmp(&key(b)).expect("finite positions"))
                .unwrap_or(0)
        };
        match self.output.track {
            Some(t) => best(&|v| ((p[v] - nalgebra::Vector3::from(t)).norm(), 0.0)),
            None => best(&|v| (-p[v].x, -p[v].z)),
        }
    }
}
