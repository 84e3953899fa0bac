//! The contact potential of a body against obstacles, and the bound it puts on a step.

use std::path::PathBuf;

use nalgebra::{Isometry3, Matrix3, Point3, SymmetricEigen, Vector3};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::obstacle::{carried, relative_path};
use crate::surface_contact::SelfContact;
use crate::{Barrier, FrictionSpec, Obstacle, ObstacleMotion, Surface, SurfacePair};

/// Contact as a scene gives it: the obstacles and, optionally, the barrier's parameters.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct ContactSpec {
    /// The obstacles.
    pub obstacles: Vec<Obstacle>,
    /// The barrier's activation distance (m); by default 1e-3 of the rest shape's bounding
    /// box diagonal, as IPC does.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dhat: Option<f64>,
    /// The barrier's stiffness (N/m); by default the mean diagonal of the rest stiffness
    /// matrix, the stiffness with which the material holds one vertex in place.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kappa: Option<f64>,
    /// Whether the barrier stiffens itself when surfaces are squeezed deep into it: after a
    /// step whose least distance is below [`ADAPT_BELOW`] of `dhat`, `kappa` doubles (at most
    /// [`ADAPT_MAX`] times its start), as IPC adapts it. By default on when `kappa` is
    /// chosen automatically and off when given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adaptive_kappa: Option<bool>,
    /// Coulomb friction against the obstacles, analytic and mesh (none by default: they are
    /// frictionless).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub friction: Option<FrictionSpec>,
    /// Whether the body's boundary surface also stays apart from itself (point-triangle and
    /// edge-edge barriers; off by default: self-contact costs a broad phase per evaluation).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub self_contact: bool,
    /// Fixed triangle-mesh obstacles (point-triangle and edge-edge barriers against the
    /// body's surface; friction counts them after `obstacles`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub meshes: Vec<MeshObstacle>,
    /// Obstacles that move (by index into `obstacles`, then `meshes`; the others stay).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub motions: Vec<ObstacleMotion>,
}

deform_setters::setters!(ContactSpec { obstacles: Vec<Obstacle>, dhat: Option<f64>, kappa: Option<f64>, adaptive_kappa: Option<bool>, friction: Option<FrictionSpec>, self_contact: bool, meshes: Vec<MeshObstacle>, motions: Vec<ObstacleMotion> });

/// A triangle-mesh obstacle as a scene names it (fixed, or moved by a motion); the
/// integrator reads the file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct MeshObstacle {
    /// The surface: an `.obj` file, or a tet mesh (`.msh`, `.node`, `.ele`) whose boundary
    /// is the obstacle. A scene's relative path is relative to the scene file.
    pub file: PathBuf,
    /// Moved by this much from where the file puts it (m).
    #[serde(default)]
    pub offset: [f64; 3],
}

deform_setters::setters!(MeshObstacle {
    file: PathBuf,
    offset: [f64; 3]
});

impl MeshObstacle {
    /// The obstacle of the surface in `file`, where the file puts it.
    pub fn new(file: impl Into<PathBuf>) -> Self {
        let (file, offset) = (file.into(), [0.0; 3]);
        Self { file, offset }
    }
}

/// Why contact cannot be set up or evaluated.
#[derive(Debug, Clone, PartialEq, Error)]
#[non_exhaustive]
pub enum ContactError {
    /// An obstacle or parameter is malformed.
    #[error("contact.{field}: {reason}")]
    Invalid {
        /// The field (`obstacles[1]`, `dhat`, `kappa`).
        field: String,
        /// Why.
        reason: String,
    },
    /// A vertex is on or inside an obstacle: the barrier is not defined there.
    #[error("vertex {vertex} is inside obstacle {obstacle} (signed distance {distance:e} m)")]
    Penetration {
        /// The vertex.
        vertex: usize,
        /// The obstacle's index.
        obstacle: usize,
        /// Its signed distance.
        distance: f64,
    },
    /// Two primitives of the body's surface touch: self-contact's barrier is not defined.
    #[error("{pair} touch (distance {distance:e} m)")]
    SelfContact {
        /// The primitives.
        pair: SurfacePair,
        /// Their distance.
        distance: f64,
    },
    /// Obstacles that move would pass through the body during a step: no first iterate that
    /// moves the body's surface with them stays clear of everything (the obstacles move too
    /// far in one step for the body's mesh; a smaller step or a slower motion).
    #[error(
        "moving obstacles would pass through the body in this step: no start moves its surface clear of them (take a smaller dt or a slower motion)"
    )]
    Overrun,
    /// A primitive of the body's surface touches one of a triangle-mesh obstacle.
    #[error(
        "the surface meets mesh obstacle {mesh}: {pair} (the obstacle's vertices numbered within it; distance {distance:e} m)"
    )]
    MeshObstacle {
        /// The obstacle's index in the meshes.
        mesh: usize,
        /// The primitives: the body's with the body's vertex indices, the obstacle's with
        /// its mesh's.
        pair: SurfacePair,
        /// Their distance.
        distance: f64,
    },
}

/// What the potential found at a configuration.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct ContactSummary {
    /// The barrier energy (J).
    pub energy: f64,
    /// Vertex-obstacle pairs, and with self-contact surface pairs, closer than `dhat`.
    pub active: usize,
    /// The least signed distance of a surface vertex to an obstacle, or of two surface
    /// primitives closer than `dhat` (m; infinite with neither).
    pub min_distance: f64,
}

/// A 3x3 block of the contact Hessian on a vertex's diagonal.
pub type VertexBlock = (usize, Matrix3<f64>);

/// A 3x3 block of the contact Hessian coupling two different vertices: rows of the first,
/// columns of the second.
pub type CouplingBlock = (usize, usize, Matrix3<f64>);

/// The contact Hessian as blocks; a vertex or a pair of vertices may appear more than once
/// (the blocks add up). Each pair's Hessian is projected to positive semidefinite, so their
/// sum is too.
#[derive(Debug, Clone, Default, PartialEq)]
#[non_exhaustive]
pub struct ContactHessian {
    /// Blocks on vertices' diagonals (obstacles, friction, self-contact).
    pub vertex: Vec<VertexBlock>,
    /// Blocks between two different vertices (self-contact), each with its transpose as
    /// `(j, i, B^T)`.
    pub coupling: Vec<CouplingBlock>,
}

impl ContactHessian {
    /// Forgets every block.
    pub fn clear(&mut self) {
        self.vertex.clear();
        self.coupling.clear();
    }

    /// Whether there is no block.
    pub fn is_empty(&self) -> bool {
        self.vertex.is_empty() && self.coupling.is_empty()
    }

    /// `y += scale H x`, over the vertex blocks and the blocks between vertices.
    pub fn add_product(&self, scale: f64, x: &[f64], y: &mut [f64]) {
        let coupled = self.coupling.iter().map(|(i, j, b)| (i, j, b));
        for (i, j, b) in self.vertex.iter().map(|(v, b)| (v, v, b)).chain(coupled) {
            let bx = b * nalgebra::Vector3::new(x[3 * j], x[3 * j + 1], x[3 * j + 2]) * scale;
            for k in 0..3 {
                y[3 * i + k] += bx[k];
            }
        }
    }

    /// Adds the 12x12 Hessian `h` of a pair of primitives on `vertices`, block by block
    /// (blocks that are zero, and those of vertices from `movable` on, fixed obstacles', are
    /// left out).
    pub(crate) fn add_pair(
        &mut self,
        vertices: &[usize; 4],
        h: &nalgebra::SMatrix<f64, 12, 12>,
        movable: usize,
    ) {
        for (a, &va) in vertices.iter().enumerate() {
            for (b, &vb) in vertices.iter().enumerate() {
                let block: Matrix3<f64> = h.fixed_view::<3, 3>(3 * a, 3 * b).into_owned();
                if block == Matrix3::zeros() || va >= movable || vb >= movable {
                    continue;
                }
                if va == vb {
                    self.vertex.push((va, block));
                } else {
                    self.coupling.push((va, vb, block));
                }
            }
        }
    }
}

/// The barrier potential `B(x) = sum_v sum_o b(phi_o(x_v))` of a body's surface vertices
/// against analytic obstacles, with IPC's log barrier `b`; with the same barrier on the
/// distances of surface primitives, against fixed triangle meshes and the surface itself.
#[derive(Debug, Clone, PartialEq)]
pub struct ContactModel {
    obstacles: Vec<Obstacle>,
    barrier: Barrier,
    vertices: Vec<usize>,
    /// Each obstacle's coefficient of friction and the smoothing speed `eps_v` (m/s).
    friction: Option<(Vec<f64>, f64)>,
    /// The surface's self-contact and its contact with `meshes`, when modelled.
    surface: Option<SelfContact>,
    /// Triangle-mesh obstacles where they rest (flat positions, triangles).
    meshes: Vec<Surface>,
    /// The obstacles where they rest (`obstacles` is where they are at the current step's
    /// end, `before` where they were at its start), and how those that move do, each with
    /// the pivot it turns about by default.
    rest_obstacles: Vec<Obstacle>,
    before: Vec<Obstacle>,
    motions: Vec<ObstacleMotion>,
    pivots: Vec<Vector3<f64>>,
    /// Each analytic obstacle's rigid motion over the current step (from where it was at
    /// the step's start to where it is at its end); `None` while it rests.
    steps: Vec<Option<Isometry3<f64>>>,
}

/// A step whose least contact distance falls below this fraction of `dhat` doubles an
/// adaptive barrier's stiffness ([`ContactSpec::adaptive_kappa`]): a barrier too soft for
/// the loads lets surfaces come within a millionth of `dhat`, where its curvature makes
/// Newton crawl (the soft tube of `assets/scenes/tube_squash.ron`).
pub const ADAPT_BELOW: f64 = 1e-2;

/// The most an adaptive barrier's stiffness grows over its start.
pub const ADAPT_MAX: f64 = 1024.0;

/// The fraction of a vertex's distance to an obstacle that a step may close: a step is
/// bounded so that no distance falls below a tenth of what it was (IPC's CCD keeps the same
/// margin), so that it stays positive and the barrier finite.
pub const STEP_MARGIN: f64 = 0.1;

impl ContactModel {
    /// The potential of `vertices` (the ones that can touch: the body's surface) against
    /// `obstacles`, with `barrier`.
    ///
    /// # Errors
    /// [`ContactError::Invalid`] naming a malformed obstacle or barrier parameter.
    pub fn new(
        obstacles: Vec<Obstacle>,
        barrier: Barrier,
        vertices: Vec<usize>,
    ) -> Result<Self, ContactError> {
        for (i, o) in obstacles.iter().enumerate() {
            o.check().map_err(|reason| ContactError::Invalid {
                field: format!("obstacles[{i}]"),
                reason,
            })?;
        }
        for (field, value) in [("dhat", barrier.dhat), ("kappa", barrier.kappa)] {
            if !(value > 0.0 && value.is_finite()) {
                return Err(ContactError::Invalid {
                    field: field.into(),
                    reason: format!("must be positive and finite, got {value}"),
                });
            }
        }
        Ok(Self {
            barrier,
            vertices,
            friction: None,
            surface: None,
            meshes: Vec::new(),
            rest_obstacles: obstacles.clone(),
            before: obstacles.clone(),
            motions: Vec::new(),
            pivots: Vec::new(),
            steps: vec![None; obstacles.len()],
            obstacles,
        })
    }

    /// The same potential with self-contact of the surface `triangles` (vertex indices into
    /// `rest`, the rest positions, flat `3N`): point-triangle and edge-edge barriers, the
    /// edge pairs' mollifier from their rest lengths.
    ///
    /// # Errors
    /// [`ContactError::Invalid`] naming a malformed triangle, or two primitives closer than
    /// `dhat` at rest (`dhat`).
    pub fn with_self_contact(
        mut self,
        triangles: Vec<[usize; 3]>,
        rest: &[f64],
    ) -> Result<Self, ContactError> {
        if self.friction.is_some() {
            return Err(ContactError::Invalid {
                field: "self_contact".into(),
                reason: "give self-contact before friction (its coefficients count it)".into(),
            });
        }
        let surface = SelfContact::with_meshes(triangles, rest, true, &self.meshes)?;
        surface.check_separated(rest, self.barrier.dhat)?;
        self.surface = Some(surface);
        // The surface was built with the meshes at rest: place those that move.
        self.set_step(0.0, 0.0);
        Ok(self)
    }

    /// The same potential with fixed triangle-mesh obstacles `meshes` (each flat positions
    /// and triangles) that the body's surface `triangles` (vertex indices into `rest`, flat
    /// `3N`) stays apart from: point-triangle and edge-edge barriers between the body's
    /// primitives and the meshes', the same as self-contact's (which stays as it was).
    /// Friction against them, as against the analytic obstacles, comes after
    /// ([`ContactModel::with_friction`]).
    ///
    /// # Errors
    /// [`ContactError::Invalid`] naming a malformed triangle or a non-finite position
    /// (`meshes[1][4]`).
    pub fn with_mesh_obstacles(
        mut self,
        triangles: Vec<[usize; 3]>,
        rest: &[f64],
        meshes: Vec<Surface>,
    ) -> Result<Self, ContactError> {
        if self.friction.is_some() {
            return Err(ContactError::Invalid {
                field: "meshes".into(),
                reason: "give mesh obstacles before friction (its coefficients count them)".into(),
            });
        }
        let self_pairs = self.surface.as_ref().is_some_and(SelfContact::self_pairs);
        self.surface = Some(SelfContact::with_meshes(
            triangles, rest, self_pairs, &meshes,
        )?);
        self.meshes = meshes;
        self.set_step(0.0, 0.0);
        Ok(self)
    }

    /// The triangles of the surface in self-contact, when modelled.
    pub fn self_contact_surface(&self) -> Option<&[[usize; 3]]> {
        self.surface
            .as_ref()
            .filter(|s| s.self_pairs())
            .map(SelfContact::triangles)
    }

    /// Refuses positions `x` where the body's surface passes through a mesh obstacle's (or,
    /// with self-contact, its own): an edge of one through a triangle of the other. Starting
    /// states are checked with it; Newton's steps never make such a crossing (the collision
    /// bound keeps every pair apart), so it is not repeated per evaluation. A body wholly
    /// inside a closed obstacle, with no crossing, is not seen.
    ///
    /// # Errors
    /// [`ContactError::MeshObstacle`] or [`ContactError::SelfContact`] naming the edge and
    /// triangle ([`SurfacePair::EdgeTriangle`]).
    pub fn check_crossings(&self, x: &[f64]) -> Result<(), ContactError> {
        match &self.surface {
            Some(s) => s.check_crossings(x),
            None => Ok(()),
        }
    }

    /// The fixed triangle-mesh obstacles (flat positions, triangles).
    pub fn mesh_obstacles(&self) -> &[Surface] {
        &self.meshes
    }

    /// The same potential with friction as `spec` says ([`ContactModel::lag_friction`]):
    /// one coefficient for every obstacle, or one for each, the analytic obstacles first
    /// and then the mesh obstacles; with self-contact, the body's own surface gets
    /// [`FrictionSpec::self_coefficient`] (give the meshes and self-contact first).
    ///
    /// # Errors
    /// [`ContactError::Invalid`] naming a bad coefficient or threshold.
    pub fn with_friction(mut self, spec: &FrictionSpec) -> Result<Self, ContactError> {
        let obstacles = self.obstacles.len() + self.meshes.len();
        let mut mu = spec.coefficients(obstacles)?;
        match self.surface.as_ref().is_some_and(SelfContact::self_pairs) {
            true => mu.push(spec.self_coefficient()),
            false if spec.self_mu.is_some() => {
                return Err(ContactError::Invalid {
                    field: "friction.self_mu".into(),
                    reason: "given without self_contact".into(),
                });
            }
            false => {}
        }
        self.friction = Some((mu, spec.velocity_threshold));
        Ok(self)
    }

    /// How many obstacles friction acts against: the analytic ones, then the meshes, then
    /// the body's own surface when it is in self-contact.
    pub fn frictional(&self) -> usize {
        let own = self.surface.as_ref().is_some_and(SelfContact::self_pairs);
        self.obstacles.len() + self.meshes.len() + usize::from(own)
    }

    /// The body's surface in contact with itself or with meshes, when modelled.
    pub(crate) fn surface(&self) -> Option<&SelfContact> {
        self.surface.as_ref()
    }

    /// The same potential with obstacles that move as `motions` say (at most one motion per
    /// obstacle; a mesh obstacle `m` is obstacle `obstacles().len() + m`, so give the meshes
    /// first), placed where they are at time 0.
    ///
    /// # Errors
    /// [`ContactError::Invalid`] naming a malformed motion (`motions[1]`).
    pub fn with_motions(mut self, motions: Vec<ObstacleMotion>) -> Result<Self, ContactError> {
        let analytic = self.obstacles.len();
        let mut pivots = Vec::with_capacity(motions.len());
        for (i, m) in motions.iter().enumerate() {
            let invalid = |reason| ContactError::Invalid {
                field: format!("motions[{i}]"),
                reason,
            };
            m.check(analytic + self.meshes.len()).map_err(invalid)?;
            if motions[..i].iter().any(|o| o.obstacle == m.obstacle) {
                return Err(invalid(format!("obstacle {} moves twice", m.obstacle)));
            }
            let centre = match m.obstacle.checked_sub(analytic) {
                None => self.rest_obstacles[m.obstacle].centre(),
                Some(mesh) => bounding_centre(&self.meshes[mesh].0),
            };
            pivots.push(centre);
        }
        self.motions = motions;
        self.pivots = pivots;
        self.set_step(0.0, 0.0);
        Ok(self)
    }

    /// Places the moving obstacles for a step from time `t0` to `t1`: where they are at
    /// `t1` (Newton solves for the state there), remembering where they were at `t0` (for
    /// [`ContactModel::carry`], [`ContactModel::first_step_bound`] and friction).
    pub fn set_step(&mut self, t0: f64, t1: f64) {
        let analytic = self.obstacles.len();
        for (m, centre) in self.motions.iter().zip(&self.pivots) {
            let (from, to) = (m.placement(t0, centre), m.placement(t1, centre));
            let step = (from != to).then(|| to * from.inverse());
            match m.obstacle.checked_sub(analytic) {
                None => {
                    let rest = &self.rest_obstacles[m.obstacle];
                    self.obstacles[m.obstacle] = rest.moved(&to);
                    self.before[m.obstacle] = rest.moved(&from);
                    self.steps[m.obstacle] = step;
                }
                Some(mesh) => {
                    if let Some(surface) = self.surface.as_mut() {
                        surface.place_mesh(mesh, &from, &to);
                    }
                }
            }
        }
    }

    /// How the obstacles move.
    pub fn motions(&self) -> &[ObstacleMotion] {
        &self.motions
    }

    /// The analytic obstacles and the mesh obstacles (flat positions, triangles) where they
    /// are at time `t`: for viewing them beside the body.
    pub fn placed_at(&self, t: f64) -> (Vec<Obstacle>, Vec<Surface>) {
        let (mut obstacles, mut meshes) = (self.rest_obstacles.clone(), self.meshes.clone());
        let analytic = obstacles.len();
        for (m, centre) in self.motions.iter().zip(&self.pivots) {
            let place = m.placement(t, centre);
            match m.obstacle.checked_sub(analytic) {
                None => obstacles[m.obstacle] = obstacles[m.obstacle].moved(&place),
                Some(mesh) => {
                    for p in meshes[mesh].0.chunks_exact_mut(3) {
                        let q = place * Point3::new(p[0], p[1], p[2]);
                        p.copy_from_slice(q.coords.as_slice());
                    }
                }
            }
        }
        (obstacles, meshes)
    }

    /// Analytic obstacle `i` where it was at the current step's start.
    pub(crate) fn before(&self, i: usize) -> &Obstacle {
        &self.before[i]
    }

    /// Analytic obstacle `i`'s rigid motion over the current step, if it moves.
    pub(crate) fn step_motion(&self, i: usize) -> Option<&Isometry3<f64>> {
        self.steps[i].as_ref()
    }

    /// Whether an obstacle moves during the current step.
    pub fn moving(&self) -> bool {
        self.steps.iter().any(Option::is_some)
            || self.surface.as_ref().is_some_and(SelfContact::moving)
    }

    /// Makes the step's first displacement `dx` (from `x` at the step's start) clear of the
    /// obstacles that move: a surface vertex of `movable` that an obstacle would come too
    /// close to on the path relative to it (in the obstacle's frame at the step's start, a
    /// straight path from the vertex to where `dx` takes it) goes along that path only as
    /// far as is safe and moves with the obstacle from there. Its gap then stays above a
    /// fifth of what it was (for a mesh obstacle, of the least of it and `dhat`).
    pub fn carry(&self, x: &[f64], dx: &mut [f64], movable: impl Fn(usize) -> bool) {
        for &v in self.vertices.iter().filter(|&&v| movable(v)) {
            let p = Vector3::new(x[3 * v], x[3 * v + 1], x[3 * v + 2]);
            for (before, step) in self.before.iter().zip(&self.steps) {
                let Some(step) = step else {
                    continue;
                };
                let d = before.distance(&p);
                if !(d > 0.0) {
                    continue;
                }
                let dp = Vector3::new(dx[3 * v], dx[3 * v + 1], dx[3 * v + 2]);
                let relative = relative_path(step, &p, &dp);
                let s = before.time_of_approach(&p, &relative, 2.0 * STEP_MARGIN * d);
                if s < 1.0 {
                    let dp = carried(step, &p, &relative, s);
                    dx[3 * v..3 * v + 3].copy_from_slice(dp.as_slice());
                }
            }
        }
        if let Some(surface) = &self.surface {
            surface.carry(x, dx, &movable, self.barrier.dhat);
        }
    }

    /// The same potential with the barrier's stiffness `kappa` (everything else, surfaces
    /// and friction included, as it was).
    ///
    /// # Errors
    /// [`ContactError::Invalid`] for a `kappa` that is not positive and finite.
    pub fn with_stiffness(mut self, kappa: f64) -> Result<Self, ContactError> {
        self.set_stiffness(kappa)?;
        Ok(self)
    }

    /// Sets the coefficients of friction, one per frictional obstacle in
    /// [`ContactModel::frictional`]'s order (the smoothing speed stays).
    ///
    /// # Errors
    /// [`ContactError::Invalid`] (`friction.mu`) without friction, for another count, or a
    /// coefficient that is negative or not finite.
    pub fn set_friction_coefficients(&mut self, mu: &[f64]) -> Result<(), ContactError> {
        let invalid = |reason: String| ContactError::Invalid {
            field: "friction.mu".into(),
            reason,
        };
        let expected = self.frictional();
        let Some((own, _)) = self.friction.as_mut() else {
            return Err(invalid("the contact has no friction to set".into()));
        };
        if mu.len() != expected {
            return Err(invalid(format!(
                "{} coefficients for {expected} frictional obstacles",
                mu.len()
            )));
        }
        if let Some(m) = mu.iter().find(|m| !(m.is_finite() && **m >= 0.0)) {
            return Err(invalid(format!("{m} must be finite and >= 0")));
        }
        own.copy_from_slice(mu);
        Ok(())
    }

    /// Sets the barrier's stiffness `kappa` in place (see [`ContactModel::with_stiffness`]).
    ///
    /// # Errors
    /// [`ContactError::Invalid`] for a `kappa` that is not positive and finite.
    pub fn set_stiffness(&mut self, kappa: f64) -> Result<(), ContactError> {
        if !(kappa > 0.0 && kappa.is_finite()) {
            return Err(ContactError::Invalid {
                field: "kappa".into(),
                reason: format!("must be positive and finite, got {kappa}"),
            });
        }
        self.barrier.kappa = kappa;
        Ok(())
    }

    /// The same potential without friction.
    pub fn without_friction(mut self) -> Self {
        self.friction = None;
        self
    }

    /// Each obstacle's coefficient of friction and the smoothing speed, with friction.
    pub fn friction(&self) -> Option<(&[f64], f64)> {
        self.friction.as_ref().map(|(mu, eps)| (&mu[..], *eps))
    }

    /// The obstacles.
    pub fn obstacles(&self) -> &[Obstacle] {
        &self.obstacles
    }

    /// The barrier.
    pub fn barrier(&self) -> Barrier {
        self.barrier
    }

    /// The vertices that can touch.
    pub fn vertices(&self) -> &[usize] {
        &self.vertices
    }

    /// [`ContactError::Penetration`] at the first vertex of the whole body, interior ones
    /// included, on or inside an analytic obstacle. The barrier acts on surface vertices
    /// only, so an obstacle wholly inside the body (a small sphere in a beam) touches none
    /// of them: a starting state is checked with this too.
    ///
    /// # Errors
    /// The first vertex (in order) on or inside an obstacle.
    pub fn check_body_outside(&self, x: &[f64]) -> Result<(), ContactError> {
        for (v, p) in x.chunks_exact(3).enumerate() {
            let p = Vector3::new(p[0], p[1], p[2]);
            for (i, o) in self.obstacles.iter().enumerate() {
                outside(v, i, o.distance(&p))?;
            }
        }
        Ok(())
    }

    /// The potential at positions `x` (flat `3N`): its energy and summary; adds its forces
    /// `-grad B` to `forces` and, with `hessian`, replaces its content with the Hessian's
    /// nonzero blocks, each vertex's and each surface pair's projected to positive
    /// semidefinite.
    ///
    /// # Errors
    /// [`ContactError::Penetration`] at the first vertex (in order) on or inside an obstacle;
    /// [`ContactError::SelfContact`] for two surface primitives that touch.
    pub fn evaluate(
        &self,
        x: &[f64],
        forces: Option<&mut [f64]>,
        hessian: Option<&mut ContactHessian>,
    ) -> Result<ContactSummary, ContactError> {
        self.evaluate_projected(x, forces, hessian, true)
    }

    /// The barrier's exact Hessian at `x` into `hessian` (its blocks as
    /// [`ContactModel::evaluate`] gives them, none projected): where a pair's distance
    /// curves (spheres, boxes' edges, surface pairs whose triangle or edges move), the
    /// exact Hessian is indefinite. An adjoint needs it exact; Newton takes the projected
    /// one.
    ///
    /// # Errors
    /// As [`ContactModel::evaluate`].
    pub fn exact_hessian(
        &self,
        x: &[f64],
        hessian: &mut ContactHessian,
    ) -> Result<ContactSummary, ContactError> {
        self.evaluate_projected(x, None, Some(hessian), false)
    }

    fn evaluate_projected(
        &self,
        x: &[f64],
        mut forces: Option<&mut [f64]>,
        mut hessian: Option<&mut ContactHessian>,
        project: bool,
    ) -> Result<ContactSummary, ContactError> {
        if let Some(h) = hessian.as_deref_mut() {
            h.clear();
        }
        let b = self.barrier;
        let mut summary = ContactSummary {
            energy: 0.0,
            active: 0,
            min_distance: f64::INFINITY,
        };
        for &v in &self.vertices {
            let p = Vector3::new(x[3 * v], x[3 * v + 1], x[3 * v + 2]);
            let mut block = Matrix3::zeros();
            for (i, o) in self.obstacles.iter().enumerate() {
                let distance = o.distance(&p);
                summary.min_distance = summary.min_distance.min(distance);
                outside(v, i, distance)?;
                if distance >= b.dhat {
                    continue;
                }
                let jet = o.jet(&p);
                summary.active += 1;
                summary.energy += b.value(distance);
                let (d1, d2) = (b.first(distance), b.second(distance));
                if let Some(f) = forces.as_deref_mut() {
                    for k in 0..3 {
                        f[3 * v + k] -= d1 * jet.gradient[k];
                    }
                }
                if hessian.is_some() {
                    let n = jet.gradient;
                    let exact = n * n.transpose() * d2 + jet.hessian * d1;
                    block += if project { project_psd(exact) } else { exact };
                }
            }
            if let Some(h) = hessian.as_deref_mut()
                && block != Matrix3::zeros()
            {
                h.vertex.push((v, block));
            }
        }
        if let Some(surface) = &self.surface {
            surface.evaluate(x, (b, project), &mut summary, forces, hessian)?;
        }
        Ok(summary)
    }

    /// The change to Newton's barrier Hessian at `x` (as [`ContactModel::evaluate`] gives
    /// it, each pair projected) when each pair's `b''(d)` is replaced by the secant slope of
    /// `b'` from `d` to `d + grad d . dx`, the distance the linearised step `dx` predicts
    /// ([`Barrier::secant`]), into `out`; returns how many pairs it changed. Pairs beyond
    /// `dhat` that the step is predicted to bring within it count too (their Newton model
    /// has no barrier at all).
    ///
    /// The barrier's curvature changes by a factor of several over a fraction of `dhat`
    /// (`b''' / b''` is about `-4.4 / dhat` at `d = dhat / 2`), so a Newton step that moves a
    /// contact by a tenth of `dhat` lands a fiftieth of `dhat` off. Solving again with the
    /// corrected matrix (the same right-hand side) makes the linear model's barrier forces
    /// exact at the distances it predicts; repeated, it converges to the step whose
    /// elasticity is linearised and whose barrier is not. Friction is left as it is.
    ///
    /// Only the vertex-obstacle pairs of analytic obstacles are corrected; surface pairs
    /// (self-contact, mesh obstacles) keep `b''`. Their distances are not linear in the
    /// positions (the closest points move, edges turn), and on the self-contacting tube
    /// (`tube_squash.ron`) Newton took 1366 iterations and 850 s with them corrected,
    /// against 1139 and 300 s with no rounds (each pair costs two 12x12 eigendecompositions
    /// a direction); with the ground's pairs alone, as many iterations as with no rounds.
    pub fn secant_correction(&self, x: &[f64], dx: &[f64], out: &mut ContactHessian) -> usize {
        out.clear();
        let b = self.barrier;
        let mut changed = 0;
        for &v in &self.vertices {
            let p = Vector3::new(x[3 * v], x[3 * v + 1], x[3 * v + 2]);
            let dp = Vector3::new(dx[3 * v], dx[3 * v + 1], dx[3 * v + 2]);
            let mut block = Matrix3::zeros();
            for o in &self.obstacles {
                let distance = o.distance(&p);
                if !(distance > 0.0) {
                    continue;
                }
                let jet = o.jet(&p);
                let n = jet.gradient;
                let to = distance + n.dot(&dp);
                if distance >= b.dhat && to >= b.dhat {
                    continue;
                }
                let (d1, d2) = (b.first(distance), b.second(distance));
                let secant = b.secant(distance, to);
                if secant == d2 {
                    continue;
                }
                let nn = n * n.transpose();
                block += project_psd(nn * secant + jet.hessian * d1)
                    - project_psd(nn * d2 + jet.hessian * d1);
                changed += 1;
            }
            if block != Matrix3::zeros() {
                out.vertex.push((v, block));
            }
        }
        changed
    }

    /// The largest step length `s` in `[0, 1]` (conservatively) such that moving every
    /// vertex from `x` along `dx` by `t dx`, `t <= s`, keeps each vertex-obstacle distance
    /// above [`STEP_MARGIN`] of its value at `x` (with self-contact, each surface pair's
    /// above [`STEP_MARGIN`] of the least of its value and `dhat`): continuous collision
    /// detection for a linear path (positions linear in the step length, as in Newton's line
    /// search).
    pub fn step_bound(&self, x: &[f64], dx: &[f64]) -> f64 {
        self.bound(x, dx, false)
    }

    /// [`ContactModel::step_bound`] for a step's first displacement `dx` from `x`, the state
    /// at the step's start: an obstacle that moves during the step is taken where it was,
    /// and each vertex's path relative to it (its displacement less the obstacle's).
    pub fn first_step_bound(&self, x: &[f64], dx: &[f64]) -> f64 {
        self.bound(x, dx, true)
    }

    fn bound(&self, x: &[f64], dx: &[f64], relative: bool) -> f64 {
        let mut bound = 1.0f64;
        for &v in &self.vertices {
            let p = Vector3::new(x[3 * v], x[3 * v + 1], x[3 * v + 2]);
            let dp = Vector3::new(dx[3 * v], dx[3 * v + 1], dx[3 * v + 2]);
            for (i, o) in self.obstacles.iter().enumerate() {
                let (o, dp) = match (relative, &self.steps[i]) {
                    (true, Some(step)) => (&self.before[i], relative_path(step, &p, &dp)),
                    _ => (o, dp),
                };
                if dp == Vector3::zeros() {
                    continue;
                }
                let d = o.distance(&p);
                if d > 0.0 {
                    bound = bound.min(o.time_of_approach(&p, &dp, STEP_MARGIN * d));
                } else {
                    return 0.0;
                }
            }
        }
        if let Some(surface) = &self.surface {
            bound = bound.min(surface.step_bound(x, dx, self.barrier.dhat, relative));
        }
        bound
    }
}

/// [`ContactError::Penetration`] unless `vertex` is at a positive `distance` (NaN is not)
/// from `obstacle`.
fn outside(vertex: usize, obstacle: usize, distance: f64) -> Result<(), ContactError> {
    if distance > 0.0 {
        Ok(())
    } else {
        Err(ContactError::Penetration {
            vertex,
            obstacle,
            distance,
        })
    }
}

/// The centre of the bounding box of flat positions.
fn bounding_centre(x: &[f64]) -> Vector3<f64> {
    let points = x.chunks_exact(3).map(Vector3::from_column_slice);
    let lo = points
        .clone()
        .fold(Vector3::repeat(f64::INFINITY), |a, p| a.inf(&p));
    let hi = points.fold(Vector3::repeat(f64::NEG_INFINITY), |a, p| a.sup(&p));
    (lo + hi) * 0.5
}

/// `m` with its negative eigenvalues set to zero.
fn project_psd(m: Matrix3<f64>) -> Matrix3<f64> {
    let eig = SymmetricEigen::new(m);
    if eig.eigenvalues.min() >= 0.0 {
        return m;
    }
    let clamped = eig.eigenvalues.map(|l| l.max(0.0));
    eig.eigenvectors * Matrix3::from_diagonal(&clamped) * eig.eigenvectors.transpose()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn projection_keeps_psd_and_drops_negative_parts() {
        let n = Vector3::new(0.0, 0.6, 0.8);
        let m = n * n.transpose() * 3.0 - (Matrix3::identity() - n * n.transpose()) * 2.0;
        let p = project_psd(m);
        assert!((p - n * n.transpose() * 3.0).norm() < 1e-12);
        let psd = Matrix3::new(2.0, 1.0, 0.0, 1.0, 2.0, 0.0, 0.0, 0.0, 1.0);
        assert_eq!(project_psd(psd), psd);
    }
}
