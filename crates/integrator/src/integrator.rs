//! The Backward-Euler Newton loop (seed Eq. 7-9) and the quasi-static solve.

use std::time::Instant;

use deform_assembly::{
    Assembly, AssemblyError, DofMap, Mass, MaterialField, Outputs, ReducedMatrix, StiffnessMatrix,
    StiffnessShift, Tangent,
};
use deform_mesh::TetMesh;
use deform_solvers::{
    Indefinite, LinearOperator, LinearSolver, Ordering, SetupStats, SolveStats, SolverError,
    SolverSpec,
    vector::{dot, for_each_entry, norm},
};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use sprs::CsMat;
use thiserror::Error;

use crate::conditions::{Conditions, Load};
use crate::contact::Contact;
use crate::matrix_free::{MatrixFreeNewton, Restricted};
use crate::observer::{NoObserver, Observer};
use crate::policy::{Decision, PolicyContext, SolverPolicy};
use crate::report::{CandidateOutcome, IterationReport, StageSeconds, StepError, StepReport};
use crate::secant::{self, Secant};
use crate::state::{Constraint, Motion, State};
use deform_contact::{ContactError, ContactModel, ContactSpec, ContactSummary};

/// Lumped or consistent mass.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum MassKind {
    /// Diagonal, `rho W / 4` per element corner.
    #[default]
    Lumped,
    /// Consistent linear-tetrahedron mass.
    Consistent,
}

/// Which element tangent Newton's matrix is built from.
///
/// In RON: `project: Never`, `Always` or `WhenNeeded`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum Projection {
    /// The exact tangent: Newton converges quadratically, but the matrix can be indefinite
    /// in compressed or inverted states.
    #[default]
    Never,
    /// Every element tangent projected to SPD: always a descent direction, but Newton
    /// converges only linearly far from the rest shape.
    Always,
    /// The exact tangent until it fails in a step (a solver reports the matrix is not
    /// positive definite, or the direction is not a descent direction); that iteration and
    /// the rest of the step then use the projected one. The failed solve's work is charged
    /// (`IterationReport::discarded`).
    WhenNeeded,
}

impl Projection {
    /// The tangent a step's Newton solve starts with.
    fn first_tangent(self) -> Tangent {
        match self {
            Projection::Always => Tangent::Projected,
            Projection::Never | Projection::WhenNeeded => Tangent::Exact,
        }
    }
}

/// Newton's stopping rules and globalisation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NewtonOptions {
    /// Converged when `||r|| <= abs`: the residual's 2-norm over the free DOFs, in N for
    /// the static solve and N s (momentum, `M (v - v^n) - dt f`) for a dynamic step.
    pub abs: f64,
    /// ... or when `||r|| <= rel ||r_0||` (first iterate of the step).
    pub rel: f64,
    /// ... or when the max-norm of a position update is below this (m); 0 disables.
    pub update: f64,
    /// Iteration cap.
    pub max_iterations: usize,
    /// With contact, solve each Newton system this many more times, each with the
    /// barrier's curvature replaced by its secant slope to the distances the last solution
    /// predicts (0: plain Newton). The barrier's curvature changes by a factor of several
    /// within a fraction of `dhat`, where Newton's linear model lands contacts a fiftieth
    /// of `dhat` off; the rounds reuse the preconditioner (a direct solver's factor, for
    /// at most 4 conjugate-gradient iterations a round) and start from the last solution,
    /// and all but the last stop at 1e-2 of the right-hand side, so they cost a few
    /// iterations each.
    pub barrier_secant: usize,
    /// Iterative linear solves stop once their residual is at most this fraction of
    /// Newton's own tolerance `max(abs, rel ||r_0||)`, whatever their relative tolerance
    /// asks (0: only theirs). The linear residual is the residual the Newton update
    /// predicts, so solving far below what Newton accepts buys nothing: at 0.1 the last
    /// update leaves at most a tenth of the tolerance to rounding of the solve.
    pub linear_floor: f64,
    /// Backtracking (Armijo) line search on the incremental potential.
    pub line_search: bool,
    /// Project element tangents to SPD: never, always (robust for inverting and compressed
    /// states), or only when the exact tangent fails ([`Projection`]).
    pub project: Projection,
}

impl Default for NewtonOptions {
    fn default() -> Self {
        Self {
            abs: 1e-10,
            rel: 1e-6,
            update: 0.0,
            max_iterations: 30,
            barrier_secant: 3,
            linear_floor: 0.1,
            line_search: true,
            project: Projection::Never,
        }
    }
}

/// Time-stepping options. Unknown fields are rejected in RON.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IntegratorOptions {
    /// Time step (s).
    pub dt: f64,
    /// Rayleigh mass damping `alpha` (1/s).
    pub alpha: f64,
    /// Rayleigh stiffness damping `gamma` (s). It may be negative, down to (not including)
    /// `-dt / 2`: Backward Euler's own numerical dissipation takes a low mode of frequency
    /// `omega` down by `1 / (1 + dt (dt + gamma) omega^2)` per step, so a coarse step can give
    /// some of it back (a model stepping `k` times coarser than its data dissipates like them at
    /// `gamma = -(k - 1) dt / k`); below `-dt / 2` the highest modes grow. A negative gamma is a
    /// fraction of the step: halved substeps scale it ([`IntegratorOptions::stiffness_damping`]).
    pub gamma: f64,
    /// Gravity (m/s^2).
    pub gravity: [f64; 3],
    /// Mass matrix.
    pub mass: MassKind,
    /// Newton options.
    pub newton: NewtonOptions,
    /// On failure, retry with the substep halved and go on, up to this many failed solves
    /// in a step (at most 20: dt / 2^20).
    pub max_retries: usize,
    /// When the chosen linear solver fails, solve with the direct solver instead of failing.
    pub fallback_to_direct: bool,
}

impl Default for IntegratorOptions {
    fn default() -> Self {
        Self {
            dt: 0.01,
            alpha: 0.0,
            gamma: 0.0,
            gravity: [0.0, 0.0, -9.81],
            mass: MassKind::Lumped,
            newton: NewtonOptions::default(),
            max_retries: 3,
            fallback_to_direct: true,
        }
    }
}

impl IntegratorOptions {
    /// Rayleigh stiffness damping at a (sub)step of `h`: `gamma`, or a negative `gamma`
    /// scaled by `h / dt` (it corrects the step's own dissipation, see
    /// [`IntegratorOptions::gamma`]).
    pub fn stiffness_damping(&self, h: f64) -> f64 {
        if self.gamma < 0.0 {
            self.gamma * h / self.dt
        } else {
            self.gamma
        }
    }

    /// Checks every value; the error names the field.
    ///
    /// # Errors
    /// [`IntegratorError::Invalid`].
    pub fn validate(&self) -> Result<(), IntegratorError> {
        let bad =
            |field: &'static str, reason: String| Err(IntegratorError::Invalid { field, reason });
        if !(self.dt.is_finite() && self.dt > 0.0) {
            return bad("dt", format!("{} must be finite and > 0", self.dt));
        }
        if !(self.alpha.is_finite() && self.alpha >= 0.0) {
            return bad("alpha", format!("{} must be finite and >= 0", self.alpha));
        }
        if !(self.gamma.is_finite() && self.gamma > -0.5 * self.dt) {
            let reason = format!(
                "{} must be finite and > -dt / 2 = {}",
                self.gamma,
                -0.5 * self.dt
            );
            return bad("gamma", reason);
        }
        if !self.gravity.iter().all(|g| g.is_finite()) {
            return bad("gravity", "must be finite".into());
        }
        let n = &self.newton;
        if !(n.abs.is_finite() && n.abs >= 0.0) {
            return bad("newton.abs", format!("{} must be finite and >= 0", n.abs));
        }
        if !(n.rel.is_finite() && n.rel >= 0.0 && n.rel < 1.0) {
            return bad("newton.rel", format!("{} must be in [0, 1)", n.rel));
        }
        if n.abs == 0.0 && n.rel == 0.0 && n.update == 0.0 {
            return bad("newton.abs", "abs, rel and update cannot all be 0".into());
        }
        if !(n.update.is_finite() && n.update >= 0.0) {
            return bad(
                "newton.update",
                format!("{} must be finite and >= 0", n.update),
            );
        }
        if !(n.linear_floor.is_finite() && (0.0..1.0).contains(&n.linear_floor)) {
            return bad(
                "newton.linear_floor",
                format!("{} must be in [0, 1)", n.linear_floor),
            );
        }
        if n.max_iterations == 0 {
            return bad("newton.max_iterations", "must be at least 1".into());
        }
        if self.max_retries > 20 {
            return bad(
                "max_retries",
                format!("{} is more than 20 halvings of dt", self.max_retries),
            );
        }
        Ok(())
    }
}

/// Why an integrator could not be built.
#[derive(Debug, Clone, Error)]
#[non_exhaustive]
pub enum IntegratorError {
    /// An option or boundary condition is out of range.
    #[error("invalid {field}: {reason}")]
    Invalid {
        /// The field.
        field: &'static str,
        /// Why.
        reason: String,
    },
    /// The assembly rejected the mesh, materials or constraints.
    #[error(transparent)]
    Assembly(#[from] AssemblyError),
}

/// Dynamic (Backward Euler, unknown `v`) or static (equilibrium, unknown `x`).
#[derive(Debug, Clone, Copy)]
enum Mode {
    Dynamic { dt: f64 },
    Static,
}

/// Steps a mesh in time.
pub struct Integrator {
    asm: Assembly,
    mass: Mass,
    rest: Vec<Vector3<f64>>,
    constraints: Vec<Constraint>,
    dofs: DofMap,
    options: IntegratorOptions,
    /// `M g` of the active gravity (the conditions', else the options').
    gravity_forces: Vec<f64>,
    /// External loads, each with its vertices' shares of the total force (mass-weighted).
    loads: Vec<(Load, Vec<f64>)>,
    /// Overrides of the model's own gravity, motions and loads (see [`Conditions`]).
    conditions: Conditions,
    /// `M g` plus the loads acting at Newton's end time (used only when there are loads).
    external: Vec<f64>,
    /// Per-vertex lumped-mass scales and the mesh's own masses they multiply, when set.
    mass_scale: Option<(Vec<f64>, Vec<f64>)>,
    /// K at Newton's iterate; with positive stiffness damping and the exact tangent,
    /// `K + s D_u K` (see [`Integrator::newton_matrix`]).
    k: StiffnessMatrix,
    /// The largest displacement of [`Integrator::stiffness_derivative`]'s forward difference:
    /// 1e-7 of the rest shape's bounding-box diagonal (truncation about 1e-6 relative,
    /// rounding about 1e-9).
    difference_step: f64,
    /// The Newton matrix on the free DOFs (no full copy is kept).
    a_free: ReducedMatrix,
    solvers: KeptSolvers,
    /// Counterfactual candidates, each with its own kept instance.
    candidates: KeptSolvers,
    policy: Box<dyn SolverPolicy>,
    /// Barrier contact against obstacles, when the body has any.
    contact: Option<Contact>,
    steps_taken: usize,
    work: Work,
}

impl std::fmt::Debug for Integrator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Integrator")
            .field("vertices", &self.asm.num_vertices())
            .field("elements", &self.asm.num_elements())
            .field("free_dofs", &self.dofs.num_free())
            .field("options", &self.options)
            .field("policy", &self.policy.name())
            .finish_non_exhaustive()
    }
}

/// Configures an [`Integrator`] ([`Integrator::builder`]); every setting has a default.
///
/// ```
/// use deform_integrator::{Constraint, Integrator, IntegratorOptions, MaterialField, Motion};
/// use deform_integrator::{MaterialSpec, TetMesh};
/// use deform_mesh::generate::BoxGrid;
///
/// let mesh: TetMesh = BoxGrid::beam(1).build().unwrap();
/// let model = ron::from_str::<MaterialSpec>("NeoHookean(Young(e: 1e6, nu: 0.4))").unwrap();
/// let clamp: Vec<usize> = (0..mesh.num_vertices())
///     .filter(|&v| mesh.rest_positions()[v].x == 0.0)
///     .collect();
/// let sim = Integrator::builder(&mesh, MaterialField::Uniform(model.build().unwrap()))
///     .density(1200.0)
///     .constraints(vec![Constraint { vertices: clamp, motion: Motion::Fixed }])
///     .options(IntegratorOptions { dt: 0.005, ..Default::default() })
///     .build()
///     .unwrap();
/// assert_eq!(sim.options().dt, 0.005);
/// ```
pub struct IntegratorBuilder<'a> {
    mesh: &'a TetMesh,
    materials: MaterialField,
    density: f64,
    constraints: Vec<Constraint>,
    loads: Vec<Load>,
    options: IntegratorOptions,
    policy: Option<Box<dyn SolverPolicy>>,
    contact: Option<ContactSpec>,
}

impl IntegratorBuilder<'_> {
    /// Barrier contact of the body's surface against obstacles (none by default).
    pub fn contact(mut self, contact: ContactSpec) -> Self {
        self.contact = Some(contact);
        self
    }

    /// Mass density (kg/m^3).
    pub fn density(mut self, density: f64) -> Self {
        self.density = density;
        self
    }

    /// Constrained vertex sets and their motions.
    pub fn constraints(mut self, constraints: Vec<Constraint>) -> Self {
        self.constraints = constraints;
        self
    }

    /// External loads (total forces on vertex sets, see [`crate::LoadForce`]).
    pub fn loads(mut self, loads: Vec<Load>) -> Self {
        self.loads = loads;
        self
    }

    /// Time-stepping options.
    pub fn options(mut self, options: IntegratorOptions) -> Self {
        self.options = options;
        self
    }

    /// The linear-solver policy.
    pub fn policy(mut self, policy: Box<dyn SolverPolicy>) -> Self {
        self.policy = Some(policy);
        self
    }

    /// Validates everything and builds the integrator.
    ///
    /// # Errors
    /// [`IntegratorError`] naming the bad field, vertex or element.
    pub fn build(self) -> Result<Integrator, IntegratorError> {
        Integrator::from_builder(self)
    }
}

/// Solver instances kept across solves (factorisations, stale preconditioners), one per
/// configuration.
type KeptSolvers = Vec<(SolverSpec, Box<dyn LinearSolver>)>;

/// The direct solver used as the fallback.
fn fallback_spec() -> SolverSpec {
    SolverSpec::Direct {
        ordering: Ordering::Auto,
        indefinite: Indefinite::Ldlt,
        parallel: true,
        precision: Default::default(),
    }
}

impl Integrator {
    /// An integrator for `mesh` with `materials`, to be configured: density 1000 kg/m^3,
    /// no constrained vertices, default options, the direct solver at every iteration
    /// unless the [`IntegratorBuilder`] says otherwise.
    pub fn builder(mesh: &TetMesh, materials: MaterialField) -> IntegratorBuilder<'_> {
        IntegratorBuilder {
            mesh,
            materials,
            density: 1000.0,
            constraints: Vec::new(),
            loads: Vec::new(),
            options: IntegratorOptions::default(),
            policy: None,
            contact: None,
        }
    }

    fn from_builder(b: IntegratorBuilder<'_>) -> Result<Self, IntegratorError> {
        let IntegratorBuilder {
            mesh,
            materials,
            density,
            constraints,
            loads,
            options,
            policy,
            contact,
        } = b;
        let policy: Box<dyn SolverPolicy> = match policy {
            Some(p) => p,
            None => Box::new(crate::policy::BySize::default()),
        };
        options.validate()?;
        if !(density.is_finite() && density > 0.0) {
            return Err(IntegratorError::Invalid {
                field: "density",
                reason: format!("{density} must be finite and > 0"),
            });
        }
        for c in &constraints {
            c.motion
                .validate()
                .map_err(|reason| IntegratorError::Invalid {
                    field: "motion",
                    reason,
                })?;
        }
        let mut asm = Assembly::new(mesh, materials)?;
        let mass = match options.mass {
            MassKind::Lumped => Mass::lumped(mesh, density),
            MassKind::Consistent => Mass::consistent(mesh, density, asm.pattern()),
        };
        let constrained: Vec<usize> = constraints
            .iter()
            .flat_map(|c| c.vertices.iter().copied())
            .collect();
        let dofs = DofMap::new(mesh.num_vertices(), &constrained)?;
        let gravity_forces = gravity_forces(&asm, &mass, options.gravity)?;
        let loads = load_shares(&asm, &mass, loads)?;
        let k = asm.stiffness_matrix();
        let a_free = dofs.reduced_matrix(&k)?;
        let (lo, hi) = mesh.bounding_box();
        let contact = contact
            .map(|spec| Contact::build(&spec, mesh, &mut asm))
            .transpose()?;
        Ok(Self {
            asm,
            mass,
            rest: mesh.rest_positions().to_vec(),
            constraints,
            dofs,
            options,
            gravity_forces,
            loads,
            conditions: Conditions::default(),
            external: Vec::new(),
            mass_scale: None,
            k,
            difference_step: 1e-7 * (hi - lo).norm(),
            a_free,
            solvers: Vec::new(),
            candidates: Vec::new(),
            policy,
            contact,
            steps_taken: 0,
            work: Work::default(),
        })
    }

    /// The assembly (energy, forces, K of this mesh).
    pub fn assembly(&self) -> &Assembly {
        &self.asm
    }

    /// Mutable assembly, e.g. to change material parameters between steps.
    pub fn assembly_mut(&mut self) -> &mut Assembly {
        &mut self.asm
    }

    /// The mass matrix.
    pub fn mass(&self) -> &Mass {
        &self.mass
    }

    /// The free / constrained DOF map.
    pub fn dofs(&self) -> &DofMap {
        &self.dofs
    }

    /// The options.
    pub fn options(&self) -> &IntegratorOptions {
        &self.options
    }

    /// Replaces the options (e.g. a tuned Newton tolerance).
    ///
    /// # Errors
    /// As [`IntegratorOptions::validate`].
    pub fn set_options(&mut self, options: IntegratorOptions) -> Result<(), IntegratorError> {
        options.validate()?;
        if options.mass != self.options.mass {
            return Err(IntegratorError::Invalid {
                field: "mass",
                reason: "the kind of mass matrix is fixed when the integrator is built".into(),
            });
        }
        let gravity_changed = options.gravity != self.options.gravity;
        self.options = options;
        if gravity_changed && self.conditions.gravity.is_none() {
            self.update_gravity_forces()?;
        }
        Ok(())
    }

    /// Scales each vertex's lumped mass by `scale[v]` (finite, > 0; one per vertex), or
    /// restores the mesh's masses with `None`: a learned coarse model's mass distribution.
    /// Gravity forces follow the masses. The total mass is whatever the scales make it.
    ///
    /// # Errors
    /// [`IntegratorError::Invalid`] for a consistent mass matrix, a wrong length or a scale
    /// that is not finite and positive (naming the vertex).
    pub fn set_mass_scale(&mut self, scale: Option<&[f64]>) -> Result<(), IntegratorError> {
        let invalid = |reason: String| IntegratorError::Invalid {
            field: "mass_scale",
            reason,
        };
        let Mass::Lumped(current) = &self.mass else {
            return Err(invalid("needs the lumped mass".into()));
        };
        if let Some(scale) = scale {
            check_mass_scale(scale, current.len()).map_err(invalid)?;
        }
        let own = match self.mass_scale.take() {
            Some((_, own)) => own,
            None => current.clone(),
        };
        match scale {
            Some(scale) => {
                self.mass = Mass::Lumped(own.iter().zip(scale).map(|(m, s)| m * s).collect());
                self.mass_scale = Some((scale.to_vec(), own));
            }
            None => self.mass = Mass::Lumped(own),
        }
        self.update_gravity_forces()
    }

    /// The per-vertex mass scales set by [`Integrator::set_mass_scale`].
    pub fn mass_scale(&self) -> Option<&[f64]> {
        self.mass_scale.as_ref().map(|(s, _)| s.as_slice())
    }

    /// The mesh's own (unscaled) lumped vertex masses, or the row sums of the consistent
    /// mass.
    pub fn unscaled_vertex_masses(&self) -> Vec<f64> {
        match &self.mass_scale {
            Some((_, own)) => own.clone(),
            None => self.asm.vertex_masses(&self.mass),
        }
    }

    /// `M g` for the current mass and active gravity.
    fn update_gravity_forces(&mut self) -> Result<(), IntegratorError> {
        self.gravity_forces = gravity_forces(&self.asm, &self.mass, self.gravity())?;
        Ok(())
    }

    /// The active gravity: the conditions', else the options' (the model's own).
    pub fn gravity(&self) -> [f64; 3] {
        self.conditions.gravity.unwrap_or(self.options.gravity)
    }

    /// The overrides of the model's gravity, constraint motions and loads in force.
    pub fn conditions(&self) -> &Conditions {
        &self.conditions
    }

    /// Steps from now on under `conditions` (the model's own where they say `None`;
    /// `Conditions::default()` restores the model's own): one model, motions made under
    /// different forcing.
    ///
    /// # Errors
    /// [`IntegratorError::Invalid`] naming the field when a value is not finite or there is
    /// not one motion per constraint or one force per load.
    pub fn set_conditions(&mut self, conditions: &Conditions) -> Result<(), IntegratorError> {
        self.check(conditions)?;
        let gravity_changed = conditions.gravity != self.conditions.gravity;
        self.conditions = conditions.clone();
        if gravity_changed {
            self.update_gravity_forces()?;
        }
        Ok(())
    }

    /// Refuses conditions that do not fit this model (see [`Conditions::validate`]).
    fn check(&self, conditions: &Conditions) -> Result<(), IntegratorError> {
        conditions
            .validate(self.constraints.len(), self.loads.len())
            .map_err(|(field, reason)| IntegratorError::Invalid {
                field: "conditions",
                reason: format!("{field}: {reason}"),
            })
    }

    /// The motion of constraint `i` under the conditions in force.
    fn motion(&self, i: usize) -> &Motion {
        match &self.conditions.motions {
            Some(m) => &m[i],
            None => &self.constraints[i].motion,
        }
    }

    /// Number of external loads.
    pub fn num_loads(&self) -> usize {
        self.loads.len()
    }

    /// The external forces at time `t`: gravity's `M g` and the loads acting at `t`.
    pub fn external_forces(&self, t: f64) -> Vec<f64> {
        let mut f = self.gravity_forces.clone();
        self.add_loads(&self.conditions, t, 1e-9 * self.options.dt, &mut f);
        f
    }

    /// [`Integrator::external_forces`] under other conditions than those in force (e.g. a
    /// trajectory's, for a fit that reads forces off data without stepping).
    ///
    /// # Errors
    /// As [`Integrator::set_conditions`].
    pub fn external_forces_under(
        &self,
        conditions: &Conditions,
        t: f64,
    ) -> Result<Vec<f64>, IntegratorError> {
        self.check(conditions)?;
        let g = conditions.gravity.unwrap_or(self.options.gravity);
        let mut f = if g == self.gravity() {
            self.gravity_forces.clone()
        } else {
            gravity_forces(&self.asm, &self.mass, g)?
        };
        self.add_loads(conditions, t, 1e-9 * self.options.dt, &mut f);
        Ok(f)
    }

    /// Adds the loads acting at `t` under `conditions` to `f`.
    fn add_loads(&self, conditions: &Conditions, t: f64, slack: f64, f: &mut [f64]) {
        for (i, (load, shares)) in self.loads.iter().enumerate() {
            let force = match &conditions.loads {
                Some(l) => l[i],
                None => load.force,
            };
            if !force.active(t, slack) {
                continue;
            }
            for (&v, s) in load.vertices.iter().zip(shares) {
                for d in 0..3 {
                    f[3 * v + d] += s * force.force[d];
                }
            }
        }
    }

    /// The external forces Newton uses: `M g`, or with loads those acting at `t` (refreshed
    /// into the `external` buffer).
    fn refresh_external(&mut self, t: f64, slack: f64) {
        if self.loads.is_empty() {
            return;
        }
        let mut f = std::mem::take(&mut self.external);
        f.clear();
        f.extend_from_slice(&self.gravity_forces);
        self.add_loads(&self.conditions, t, slack, &mut f);
        self.external = f;
    }

    /// The external forces of the current Newton solve.
    fn external(&self) -> &[f64] {
        if self.loads.is_empty() {
            &self.gravity_forces
        } else {
            &self.external
        }
    }

    /// Replaces the solver policy (kept solvers stay, so factorisations are reused).
    pub fn set_policy(&mut self, policy: Box<dyn SolverPolicy>) {
        self.policy = policy;
    }

    /// The policy.
    pub fn policy(&self) -> &dyn SolverPolicy {
        self.policy.as_ref()
    }

    /// A copy for an independent run beside this one (rollouts of a fit on other threads):
    /// the same mesh, materials, masses, constraints, loads, conditions and options, the
    /// policy's fork and no kept solver instances, as after [`Integrator::restart`]. A run
    /// on the copy gives the bits a run on this integrator gives after `restart`. `None` when
    /// the policy cannot be forked ([`SolverPolicy::fork`]).
    pub fn fork(&self) -> Option<Integrator> {
        let policy = self.policy.fork()?;
        let candidates: Vec<SolverSpec> = self.candidates.iter().map(|(s, _)| s.clone()).collect();
        let mut copy = Integrator {
            asm: self.asm.clone(),
            mass: self.mass.clone(),
            rest: self.rest.clone(),
            constraints: self.constraints.clone(),
            dofs: self.dofs.clone(),
            options: self.options.clone(),
            gravity_forces: self.gravity_forces.clone(),
            loads: self.loads.clone(),
            conditions: self.conditions.clone(),
            external: self.external.clone(),
            mass_scale: self.mass_scale.clone(),
            k: self.k.clone(),
            difference_step: self.difference_step,
            a_free: self.a_free.clone(),
            solvers: Vec::new(),
            candidates: Vec::new(),
            policy,
            contact: self.contact.clone(),
            steps_taken: 0,
            work: Work::default(),
        };
        copy.set_candidates(&candidates).ok()?;
        Some(copy)
    }

    /// Forgets earlier runs, so that the next run's results depend on its start alone (not
    /// on which runs this integrator made before): the step count restarts at 0, the policy
    /// is replaced by its fork, and every kept solver instance but the direct ones (which
    /// keep only their symbolic analysis: the factor is recomputed at every solve) is
    /// dropped, with their stale preconditioners and tolerances. Returns `false`, changing
    /// nothing, when the policy cannot be forked.
    pub fn restart(&mut self) -> bool {
        let Some(policy) = self.policy.fork() else {
            return false;
        };
        self.policy = policy;
        self.steps_taken = 0;
        if let Some(c) = self.contact.as_mut() {
            c.reset();
        }
        let direct = |s: &SolverSpec| matches!(s, SolverSpec::Direct { .. });
        self.solvers.retain(|(s, _)| direct(s));
        for (spec, solver) in &mut self.candidates {
            // A configuration that built once builds again.
            if let Some(fresh) = spec.build().ok().filter(|_| !direct(spec)) {
                *solver = fresh;
            }
        }
        true
    }

    /// The contact potential, when the body has obstacles to touch.
    pub fn contact(&self) -> Option<&ContactModel> {
        self.contact.as_ref().map(|c| &c.model)
    }

    /// Sets contact's coefficients of friction, one per frictional obstacle
    /// ([`ContactModel::frictional`]'s order); the next step lags friction with them.
    ///
    /// # Errors
    /// [`IntegratorError::Invalid`] (`contact`) without contact or friction, for another
    /// count, or a coefficient that is negative or not finite.
    pub fn set_friction_coefficients(&mut self, mu: &[f64]) -> Result<(), IntegratorError> {
        let invalid = |reason: String| IntegratorError::Invalid {
            field: "contact",
            reason,
        };
        let c = self
            .contact
            .as_mut()
            .ok_or_else(|| invalid("the scene has no contact".into()))?;
        c.model
            .set_friction_coefficients(mu)
            .map_err(|e| invalid(e.to_string()))
    }

    /// The contact potential at positions `x` (flat `3N`): energy, active pairs, least
    /// distance. `None` without contact. A state to start from is checked with it: it also
    /// refuses surfaces that pass through each other ([`ContactModel::check_crossings`]).
    ///
    /// # Errors
    /// [`ContactError::Penetration`] naming the first vertex inside an obstacle; the pair of
    /// surface primitives that touch or cross.
    pub fn contact_at(&self, x: &[f64]) -> Option<Result<ContactSummary, ContactError>> {
        self.contact.as_ref().map(|c| {
            c.model.check_crossings(x)?;
            c.model.evaluate(x, None, None)
        })
    }

    /// Solver configurations to run, besides the policy's choice, on the same linear system
    /// at every Newton iteration (counterfactual logging for learning solver policies). Each
    /// keeps its own instance, so stale factors age as if it were in use; their outcomes go
    /// to [`IterationReport::candidates`] and never change the trajectory.
    ///
    /// # Errors
    /// The first configuration that does not build.
    pub fn set_candidates(&mut self, specs: &[SolverSpec]) -> Result<(), SolverError> {
        self.candidates = specs
            .iter()
            .map(|s| s.build().map(|b| (s.clone(), b)))
            .collect::<Result<_, _>>()?;
        Ok(())
    }

    /// Gravity forces `M g` (of the active gravity; the loads are in
    /// [`Integrator::external_forces`]).
    pub fn gravity_forces(&self) -> &[f64] {
        &self.gravity_forces
    }

    /// Number of steps taken.
    pub fn steps_taken(&self) -> usize {
        self.steps_taken
    }

    /// The initial state: rest positions with constrained vertices at their time-0 targets.
    pub fn rest_state(&self) -> State {
        let mut s = State::at_rest(self.rest.iter().flat_map(|p| [p.x, p.y, p.z]).collect());
        self.apply_constraints(&mut s.x, None, 0.0, 0.0);
        s
    }

    /// Every constrained vertex with its prescribed position at `t`, in constraint order.
    pub fn constrained_targets(&self, t: f64) -> Vec<(usize, [f64; 3])> {
        let each = |(k, c): (usize, &Constraint)| {
            let motion = self.motion(k);
            let at = move |&i: &usize| (i, motion.position(&self.rest[i], t).into());
            c.vertices.iter().map(at).collect::<Vec<_>>()
        };
        self.constraints.iter().enumerate().flat_map(each).collect()
    }

    /// Sets constrained positions to their targets at `t` and, when `v` is given, the
    /// velocities that reach them from `x_prev` in `dt`.
    fn apply_constraints(&self, x: &mut [f64], v: Option<(&mut [f64], &[f64])>, t: f64, dt: f64) {
        let mut v = v;
        for (k, c) in self.constraints.iter().enumerate() {
            for &i in &c.vertices {
                let target = self.motion(k).position(&self.rest[i], t);
                if let Some((v, x_prev)) = v.as_mut() {
                    for d in 0..3 {
                        v[3 * i + d] = (target[d] - x_prev[3 * i + d]) / dt;
                    }
                }
                x[3 * i..3 * i + 3].copy_from_slice(target.as_slice());
            }
        }
    }

    /// Advances `state` by one step of `options.dt` (Backward Euler), retrying with halved
    /// substeps on failure when `max_retries > 0`. On error `state` is unchanged.
    ///
    /// # Errors
    /// [`StepError`] with the report up to the failure.
    pub fn step(&mut self, state: &mut State) -> Result<StepReport, StepError> {
        self.step_observed(state, &mut NoObserver)
    }

    /// [`step`](Self::step), with every Newton iteration going to `observer` (its `step`
    /// method is the run executor's to call, [`Integrator::run`]).
    ///
    /// # Errors
    /// [`StepError`] with the report up to the failure.
    pub fn step_observed(
        &mut self,
        state: &mut State,
        observer: &mut dyn Observer,
    ) -> Result<StepReport, StepError> {
        let start = Instant::now();
        let dt = self.options.dt;
        let mut report = self.advance(state, dt, observer)?;
        report.step = self.steps_taken;
        report.seconds = start.elapsed().as_secs_f64();
        self.steps_taken += 1;
        Ok(report)
    }

    /// `dt` in one Newton solve or, when that fails, in substeps: each failure halves the
    /// substep and the step goes on from where it got, so at most `max_retries` solves fail
    /// and the cost of retrying is linear in `max_retries`.
    fn advance(
        &mut self,
        state: &mut State,
        dt: f64,
        observer: &mut dyn Observer,
    ) -> Result<StepReport, StepError> {
        let (mut current, mut h, mut remaining) = (state.clone(), dt, dt);
        let (mut retries, mut smallest) = (0, dt);
        let mut iterations: Vec<IterationReport> = Vec::new();
        loop {
            let sub = h.min(remaining);
            let solved = self.newton(&current, Mode::Dynamic { dt: sub }, observer);
            // Surfaces squeezed deep into the barrier stiffen it for what follows.
            if let Some(c) = self.contact.as_mut() {
                c.adapt();
            }
            match solved {
                Ok((next, mut report)) => {
                    current = next;
                    remaining -= sub;
                    smallest = smallest.min(sub);
                    iterations.append(&mut report.iterations);
                    if remaining <= 1e-12 * dt {
                        *state = current;
                        return Ok(StepReport {
                            iterations,
                            retries,
                            dt: smallest,
                            ..report
                        });
                    }
                }
                Err(e) if retries < self.options.max_retries && retryable(&e) => {
                    iterations.extend(e.report().iterations.iter().cloned());
                    retries += 1;
                    h = sub / 2.0;
                }
                Err(e) => return Err(e.with_earlier(&iterations, retries)),
            }
        }
    }

    /// Static equilibrium under gravity and the constraints at `state.t`: `f_e(x) + M g = 0`
    /// on the free DOFs, by the same Newton machinery (with the potential `E - (M g) . x`
    /// for the line search). Velocities are set to zero.
    ///
    /// # Errors
    /// [`StepError`] with the report.
    pub fn solve_static(&mut self, state: &mut State) -> Result<StepReport, StepError> {
        let start = Instant::now();
        let (next, mut report) = self.newton(state, Mode::Static, &mut NoObserver)?;
        *state = next;
        report.seconds = start.elapsed().as_secs_f64();
        Ok(report)
    }

    /// Newton on the unknown `u` (`v` when dynamic, `x` when static), in named stages:
    /// [`residual`](Self::residual), the convergence test, the
    /// [`Newton matrix`](Self::newton_matrix), the [`direction`](Self::direction) (solve,
    /// fallback, projection switch), the [`line search`](Self::line_search), the record.
    /// Its vectors live in the integrator's [`Work`], allocated once.
    fn newton(
        &mut self,
        state: &State,
        mode: Mode,
        observer: &mut dyn Observer,
    ) -> Result<(State, StepReport), StepError> {
        let mut work = std::mem::take(&mut self.work);
        work.resize(self.asm.num_dofs(), self.dofs.num_free());
        let result = self.newton_in(state, mode, observer, &mut work);
        self.work = work;
        result
    }

    fn newton_in(
        &mut self,
        state: &State,
        mode: Mode,
        observer: &mut dyn Observer,
        w: &mut Work,
    ) -> Result<(State, StepReport), StepError> {
        let newton = self.options.newton;
        let (t1, dt) = match mode {
            Mode::Dynamic { dt } => (state.t + dt, dt),
            Mode::Static => (state.t, 0.0),
        };
        self.refresh_external(t1, 1e-9 * self.options.dt);
        self.lag_friction(state, mode);
        let mut report = StepReport {
            t: t1,
            dt,
            policy: self.policy.name(),
            ..StepReport::default()
        };
        let (mut x, mut u) = self
            .initial_iterate(state, mode, t1)
            .map_err(|e| e.into_step_error(&report))?;
        let mut tangent = newton.project.first_tangent();
        // Solves whose result was not used (a failed choice before the fallback, an
        // exact-tangent attempt before projection), charged to the next iteration's report.
        let mut discarded: Vec<CandidateOutcome> = Vec::new();
        // The energy at `x` when the line search's accepted trial left it, with the forces,
        // in `w.f`: the residual is then formed without assembling again, and K is assembled
        // only if Newton goes on (a converged check needs no K).
        let mut evaluated: Option<f64> = None;
        let mut iteration = 0;
        while iteration <= newton.max_iterations {
            let started = Instant::now();
            let mut stages = StageSeconds::default();
            let k_at_x = evaluated.is_none();
            let (energy, rn) = match evaluated.take() {
                Some(energy) => self
                    .form_residual(mode, state, &u, w)
                    .map(|rn| (energy, rn)),
                None => self.residual(mode, state, &x, &u, tangent, w),
            }
            .map_err(|e| e.into_step_error(&report))?;
            stages.residual = started.elapsed().as_secs_f64();
            if iteration == 0 {
                report.initial_residual = rn;
            }
            report.final_residual = rn;
            report.energy = energy;
            let converged = self.converged(iteration, rn, &report);
            if converged || self.at_rounding_floor(iteration, rn, &report) {
                (report.converged, report.rounding_floor) = (true, !converged);
                report.contact = self.contact.as_ref().and_then(|c| c.last);
                let v = match mode {
                    Mode::Dynamic { .. } => u,
                    Mode::Static => vec![0.0; x.len()],
                };
                return Ok((State { x, v, t: t1 }, report));
            }
            if iteration == newton.max_iterations {
                break;
            }
            let clock = Instant::now();
            if !k_at_x {
                self.newton_stiffness(mode, &x, &u, tangent)
                    .map_err(|e| e.into_step_error(&report))?;
            }
            let (c_m, c_k) = self
                .newton_matrix(mode)
                .map_err(|e| fail_assembly(e, &report))?;
            stages.matrix = clock.elapsed().as_secs_f64();
            let clock = Instant::now();
            let point = NewtonPoint::new(&x, tangent, (c_m, c_k), mode, &newton, &report);
            let context = IterationContext {
                step: self.steps_taken,
                iteration,
                dt,
                residual: rn,
                initial_residual: report.initial_residual,
            };
            let found = self.direction(point, &context, &report, &mut discarded, w)?;
            stages.direction = clock.elapsed().as_secs_f64();
            let Some(found) = found else {
                // The exact tangent failed; this iteration again with the projected one.
                tangent = Tangent::Projected;
                continue;
            };
            let clock = Instant::now();
            w.du.iter_mut().for_each(|v| *v = 0.0);
            self.dofs
                .scatter(&w.du_free, &mut w.du)
                .expect("sizes match");
            let bound = self.step_bound(mode, state, &u, w);
            let step_length = if newton.line_search && found.slope < 0.0 {
                let (step_length, at_trial) = self
                    .line_search(mode, state, &u, (energy, found.slope, tangent), bound, w)
                    .map_err(|e| fail_assembly(e, &report))?;
                evaluated = at_trial;
                step_length
            } else {
                bound
            };
            stages.line_search = clock.elapsed().as_secs_f64();
            for (ui, di) in u.iter_mut().zip(&w.du) {
                *ui += step_length * di;
            }
            self.positions_into(mode, state, &u, &mut x);
            let update = position_update(mode, &w.du, step_length);
            if !update.is_finite() {
                return Err(StepError::NonFinite {
                    what: "update",
                    report: Box::new(report),
                });
            }
            // Record: the iteration's report goes to the observer, the policy and the step.
            let it = IterationReport {
                iteration,
                residual: rn,
                energy,
                solver: found.solver,
                setup: found.setup,
                solve: found.solve,
                fallback: found.fallback,
                step_length,
                step_bound: bound,
                update,
                seconds: started.elapsed().as_secs_f64(),
                stages,
                candidates: found.candidates,
                discarded: std::mem::take(&mut discarded),
            };
            observer.iteration(&it);
            self.policy.observe(
                &context.policy(self.dofs.num_free(), &report.iterations),
                &it,
            );
            report.iterations.push(it);
            iteration += 1;
        }
        Err(StepError::NotConverged {
            report: Box::new(report),
        })
    }

    /// Newton's first iterate `(x, u)` for a step ending at `t1`: `v^n` (dynamic) or `x^n`
    /// (static), constrained DOFs at their targets.
    ///
    /// # Errors
    /// [`ContactError::Overrun`] when obstacles that move pass through the body whatever
    /// its first iterate.
    fn initial_iterate(
        &self,
        state: &State,
        mode: Mode,
        t1: f64,
    ) -> Result<(Vec<f64>, Vec<f64>), StageError> {
        let mut x = state.x.clone();
        let mut u = match mode {
            Mode::Dynamic { .. } => state.v.clone(),
            Mode::Static => state.x.clone(),
        };
        match mode {
            Mode::Dynamic { dt } => {
                self.apply_constraints(&mut x, Some((&mut u, &state.x)), t1, dt);
                self.feasible_velocity(state, dt, &mut u)?;
                for i in 0..x.len() {
                    x[i] = state.x[i] + dt * u[i];
                }
            }
            Mode::Static => {
                self.apply_constraints(&mut x, None, t1, 0.0);
                u.copy_from_slice(&x);
            }
        }
        Ok((x, u))
    }

    /// With contact, scales the free DOFs of the first iterate's velocity `u` so that the
    /// first iterate `x^n + dt u` is reached from `x^n` without touching an obstacle (the
    /// barrier must be finite there); the constrained ones follow their motions.
    fn feasible_velocity(&self, state: &State, dt: f64, u: &mut [f64]) -> Result<(), ContactError> {
        let Some(c) = &self.contact else {
            return Ok(());
        };
        if c.model.moving() {
            return self.carried_velocity(&c.model, state, dt, u);
        }
        let dx: Vec<f64> = u.iter().map(|v| dt * v).collect();
        let bound = c.model.step_bound(&state.x, &dx);
        if bound < 1.0 {
            for &i in self.dofs.free_dofs() {
                u[i] *= bound;
            }
        }
        Ok(())
    }

    /// [`Integrator::feasible_velocity`] while obstacles move: vertices they would come too
    /// close to move with them ([`ContactModel::carry`]); if the rest of the path still
    /// comes too close to something, the free velocities are scaled down and carried
    /// again, and at worst the free vertices only move with the obstacles; if even that
    /// comes too close, the step is refused rather than let an obstacle pass through.
    fn carried_velocity(
        &self,
        model: &ContactModel,
        state: &State,
        dt: f64,
        u: &mut [f64],
    ) -> Result<(), ContactError> {
        let v0: Vec<f64> = u.to_vec();
        for scale in [1.0, 0.5, 0.0] {
            let mut dx: Vec<f64> = v0.iter().map(|v| dt * v).collect();
            for &i in self.dofs.free_dofs() {
                dx[i] *= scale;
            }
            model.carry(&state.x, &mut dx, |v| !self.dofs.is_constrained(v));
            if model.first_step_bound(&state.x, &dx) >= 1.0 {
                for &i in self.dofs.free_dofs() {
                    u[i] = dx[i] / dt;
                }
                return Ok(());
            }
        }
        Err(ContactError::Overrun)
    }

    /// Stage 1: assembles energy, forces, K (Newton's, see [`Integrator::newton_matrix`]) and,
    /// with stiffness damping, `K u` at `x`, and [forms the residual](Self::form_residual);
    /// returns the energy and the residual's 2-norm.
    fn residual(
        &mut self,
        mode: Mode,
        state: &State,
        x: &[f64],
        u: &[f64],
        tangent: Tangent,
        w: &mut Work,
    ) -> Result<(f64, f64), StageError> {
        let mut energy = 0.0;
        let shift = self.damping_shift(mode, u, tangent);
        let damped = self.stiffness_damping(mode) != 0.0;
        self.asm.evaluate(
            x,
            Outputs {
                energy: Some(&mut energy),
                forces: Some(&mut w.f),
                stiffness: Some(&mut self.k),
                tangent,
                stiffness_product: damped.then_some((u, &mut w.ku[..])),
                stiffness_shift: shift,
            },
        )?;
        energy += self.add_contact(x, Some(&mut w.f), true)?;
        Ok((energy, self.form_residual(mode, state, u, w)?))
    }

    /// The residual (the gradient of the merit function in `u`) on the free DOFs, into
    /// `w.r_free`, from the elastic forces in `w.f` (and `K u` in `w.ku`, for stiffness
    /// damping); returns its 2-norm.
    fn form_residual(
        &self,
        mode: Mode,
        state: &State,
        u: &[f64],
        w: &mut Work,
    ) -> Result<f64, StageError> {
        let external = self.external();
        match mode {
            Mode::Dynamic { dt } => {
                let gamma = self.options.stiffness_damping(dt);
                let alpha = self.options.alpha;
                self.asm.mass_apply(&self.mass, u, &mut w.fd)?;
                let ku = &w.ku;
                for_each_entry(&mut w.fd, |i, d| {
                    *d = -(alpha * *d + if gamma == 0.0 { 0.0 } else { gamma * ku[i] });
                });
                for_each_entry(&mut w.dv, |i, d| *d = u[i] - state.v[i]);
                self.asm.mass_apply(&self.mass, &w.dv, &mut w.r)?;
                let (f, fd) = (&w.f, &w.fd);
                for_each_entry(&mut w.r, |i, r| *r -= dt * (f[i] + fd[i] + external[i]));
            }
            Mode::Static => {
                let f = &w.f;
                for_each_entry(&mut w.r, |i, r| *r = -(f[i] + external[i]));
            }
        }
        self.dofs
            .restrict(&w.r, &mut w.r_free)
            .expect("sizes match");
        let rn = norm(&w.r_free);
        if !rn.is_finite() {
            return Err(StageError::NonFinite("residual"));
        }
        Ok(rn)
    }

    /// Newton's K at the iterate `(x, u)` alone (see [`Integrator::newton_matrix`]), when
    /// the residual came from the line search's trial.
    fn newton_stiffness(
        &mut self,
        mode: Mode,
        x: &[f64],
        u: &[f64],
        tangent: Tangent,
    ) -> Result<(), StageError> {
        let shift = self.damping_shift(mode, u, tangent);
        let outputs = Outputs {
            stiffness: Some(&mut self.k),
            tangent,
            stiffness_shift: shift,
            ..Outputs::default()
        };
        self.asm.evaluate(x, outputs)?;
        self.add_contact(x, None, true)?;
        Ok(())
    }

    /// The contact potential at `x`: adds its forces to `forces`, keeps its Hessian's
    /// blocks for Newton's matrix when asked, and returns its energy (0 without contact).
    fn add_contact(
        &mut self,
        x: &[f64],
        forces: Option<&mut [f64]>,
        hessian: bool,
    ) -> Result<f64, ContactError> {
        match self.contact.as_mut() {
            Some(c) => c.evaluate(x, forces, hessian),
            None => Ok(0.0),
        }
    }

    /// Places contact's moving obstacles for a solve from `state` (where they are at its
    /// end) and lags its friction at `state` (none when static).
    fn lag_friction(&mut self, state: &State, mode: Mode) {
        if let Some(c) = self.contact.as_mut() {
            let t1 = match mode {
                Mode::Dynamic { dt } => state.t + dt,
                Mode::Static => state.t,
            };
            c.model.set_step(state.t, t1);
            c.set_lag(match mode {
                Mode::Dynamic { dt } => c.model.lag_friction(&state.x, dt),
                Mode::Static => Default::default(),
            });
        }
    }

    /// How far along `w.du` from the iterate `u` the line search may go: the contact's
    /// continuous collision bound (1 without contact). Flags the friction pairs the full
    /// step carries past their sticking position (see [`Contact::flag_reversals`]). Uses
    /// `w.xt` as scratch.
    fn step_bound(&mut self, mode: Mode, state: &State, u: &[f64], w: &mut Work) -> f64 {
        if self.contact.is_none() {
            return 1.0;
        }
        self.positions_into(mode, state, u, &mut w.xt);
        let scale = match mode {
            Mode::Dynamic { dt } => dt,
            Mode::Static => 1.0,
        };
        let dx: Vec<f64> = w.du.iter().map(|d| scale * d).collect();
        let c = self.contact.as_mut().expect("checked above");
        c.flag_reversals(&w.xt, &dx);
        c.model.step_bound(&w.xt, &dx)
    }

    /// Rayleigh stiffness damping of this solve: `gamma` at the step (0 when static).
    fn stiffness_damping(&self, mode: Mode) -> f64 {
        match mode {
            Mode::Dynamic { dt } => self.options.stiffness_damping(dt),
            Mode::Static => 0.0,
        }
    }

    /// With positive stiffness damping and the exact tangent, the shift that makes the
    /// assembled K Newton's `K + s D_u K` (see [`Integrator::newton_matrix`]); `None`
    /// otherwise, or when `u` is 0 (no derivative along it).
    fn damping_shift<'a>(
        &self,
        mode: Mode,
        u: &'a [f64],
        tangent: Tangent,
    ) -> Option<StiffnessShift<'a>> {
        let Mode::Dynamic { dt } = mode else {
            return None;
        };
        let gamma = self.options.stiffness_damping(dt);
        let speed = u.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        (gamma > 0.0 && tangent == Tangent::Exact && speed > 0.0).then(|| StiffnessShift {
            direction: u,
            step: self.difference_step / speed,
            scale: dt * gamma / (dt + gamma),
        })
    }

    /// Stage 2: `||r|| <= max(abs, rel ||r_0||)` (at iteration 0 only `abs`), or the last
    /// position update below `update`.
    fn converged(&self, iteration: usize, rn: f64, report: &StepReport) -> bool {
        let n = &self.options.newton;
        let last_update = report
            .iterations
            .last()
            .map_or(f64::INFINITY, |it| it.update);
        rn <= n.abs.max(n.rel * report.initial_residual) && (iteration > 0 || rn <= n.abs)
            || (iteration > 0 && last_update <= n.update)
    }

    /// Stage 2, when the tolerance is out of reach: well past the start (`rn <= 1e-8 r_0`),
    /// two full Newton iterations that did not halve the residual mean it is at its rounding
    /// floor, where Newton converges quadratically otherwise; more iterations would only
    /// end at the cap.
    fn at_rounding_floor(&self, iteration: usize, rn: f64, report: &StepReport) -> bool {
        let its = &report.iterations;
        iteration >= 2
            && its.len() >= 2
            && rn <= 1e-8 * report.initial_residual
            && rn >= 0.5 * its[its.len() - 2].residual
            && its[its.len() - 2..].iter().all(|it| it.step_length == 1.0)
    }

    /// Stage 3: the Newton matrix `c_m M + c_k K` on the free DOFs, refilled in place;
    /// returns `(c_m, c_k)`.
    ///
    /// It is the residual's Jacobian in `u`. Dynamic: `c_m = 1 + dt alpha`,
    /// `c_k = dt (dt + gamma)`, and with positive stiffness damping and the exact tangent the K
    /// assembled at the iterate is `K + s D_u K` with `s = dt gamma / (dt + gamma)`: `D_u K`
    /// (by a forward difference in the same element pass, [`StiffnessShift`]) is the
    /// derivative of the damping force `-gamma K(x) u` in `x`. Without it Newton converges
    /// only linearly when `gamma != 0` (a fitted coarse model took 1.6x the iterations). It
    /// is left out with the projected tangent (whose derivative is not the energy's), in
    /// matrix-free solves, which apply the element tangents' `c_m M + c_k K`, and for
    /// negative gamma: that damping gives energy back (Backward Euler's own dissipation, at
    /// a coarse step), `s` is negative (`-dt` at `gamma = -dt/2`), and on fast states the
    /// exact matrix sent Newton into inverted elements (a 4x-step coarse fit failed at its
    /// first rollout, also with a line search on the residual's norm) where `c_m M + c_k K`,
    /// positive definite, converges slowly, or on the fastest states not at all: there the
    /// residual wanders, and the step's equation may have no solution near the start.
    fn newton_matrix(&mut self, mode: Mode) -> Result<(f64, f64), AssemblyError> {
        let o = &self.options;
        let (c_m, c_k) = match mode {
            Mode::Dynamic { dt } => (1.0 + dt * o.alpha, dt * o.stiffness_damping(dt) + dt * dt),
            Mode::Static => (0.0, 1.0),
        };
        self.asm
            .combine_reduced(c_m, &self.mass, c_k, &self.k, &self.dofs, &mut self.a_free)?;
        if let Some(c) = &mut self.contact {
            let scale = contact_scale(mode);
            self.a_free
                .add_vertex_blocks(&self.dofs, &c.hessian.vertex, scale)?;
            c.coupled = if c.hessian.coupling.is_empty() {
                None
            } else {
                Some(
                    self.a_free
                        .with_couplings(&self.dofs, &c.hessian.coupling, scale)?,
                )
            };
        }
        Ok((c_m, c_k))
    }

    /// `D_v K = d/de K(x + e v)` at `e = 0` into `out`, from `k`, the exact-tangent K at `x`:
    /// the derivative of `K(x) w` in `x` along `v` is `D_v K w` (symmetric: a third derivative
    /// of the energy). A forward difference whose largest displacement is 1e-7 of the rest
    /// shape's size, the one Newton's matrix uses ([`StiffnessShift`]): one assembly.
    ///
    /// # Errors
    /// As [`Assembly::evaluate`] at `x`.
    pub fn stiffness_derivative(
        &mut self,
        x: &[f64],
        v: &[f64],
        k: &StiffnessMatrix,
        out: &mut StiffnessMatrix,
    ) -> Result<(), AssemblyError> {
        if k.nnz() != out.nnz() {
            return Err(AssemblyError::PatternMismatch);
        }
        let speed = v.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        if speed == 0.0 {
            out.values_mut().fill(0.0);
            return Ok(());
        }
        let shift = StiffnessShift {
            direction: v,
            step: self.difference_step / speed,
            scale: 1.0,
        };
        let outputs = Outputs {
            stiffness: Some(out),
            stiffness_shift: Some(shift),
            ..Outputs::default()
        };
        self.asm.evaluate(x, outputs)?;
        // `K + D_v K` less K: rounding of about 1e-16 |K| against |D_v K|.
        for (d, k) in out.values_mut().iter_mut().zip(k.csr().data()) {
            *d -= k;
        }
        Ok(())
    }

    /// Stage 4: the policy's solver on `-r` into `w.du_free`, the direct fallback when it
    /// fails, the candidates' counterfactual solves. `None` when the exact tangent failed
    /// (indefinite, or not a descent direction) and `Projection::WhenNeeded` switches to the
    /// projected one; the failed work goes to `discarded`.
    fn direction(
        &mut self,
        point: NewtonPoint<'_>,
        context: &IterationContext,
        report: &StepReport,
        discarded: &mut Vec<CandidateOutcome>,
        w: &mut Work,
    ) -> Result<Option<Direction>, StepError> {
        // `WhenNeeded` switches to the projected tangent once per step at most.
        let can_project = self.options.newton.project == Projection::WhenNeeded
            && point.tangent == Tangent::Exact;
        for (b, r) in w.rhs.iter_mut().zip(&w.r_free) {
            *b = -r;
        }
        let decision = self
            .policy
            .choose(&context.policy(self.dofs.num_free(), &report.iterations));
        w.du_free.iter_mut().for_each(|v| *v = 0.0);
        let attempt = self.linear_solve(point, &decision, &w.rhs, &mut w.du_free);
        let attempt = match attempt {
            Err(failed)
                if self.options.fallback_to_direct
                    && decision.solver != fallback_spec()
                    && !(can_project && failed.error.is_indefinite()) =>
            {
                discarded.push(failed.outcome(&decision.solver));
                w.du_free.iter_mut().for_each(|v| *v = 0.0);
                self.linear_solve(
                    point,
                    &Decision::solver(fallback_spec()),
                    &w.rhs,
                    &mut w.du_free,
                )
                .map(|(setup, solve)| (setup, solve, true))
            }
            other => other.map(|(setup, solve)| (setup, solve, false)),
        };
        let (setup, solve, fallback) = match attempt {
            Ok(done) => done,
            Err(failed) if can_project && failed.error.is_indefinite() => {
                discarded.push(failed.outcome(&decision.solver));
                return Ok(None);
            }
            Err(failed) => {
                return Err(StepError::Solver {
                    source: failed.error,
                    report: Box::new(report.clone()),
                });
            }
        };
        // An indefinite exact tangent can also give an ascent direction without failing.
        let slope: f64 = w.r_free.iter().zip(&w.du_free).map(|(a, b)| a * b).sum();
        if can_project && slope >= 0.0 {
            discarded.push(CandidateOutcome {
                solver: decision.solver.clone(),
                setup: Some(setup),
                solve: Some(solve),
                error: Some(format!("not a descent direction (r . du = {slope:e})")),
                distance: f64::INFINITY,
            });
            return Ok(None);
        }
        let candidates = if self.candidates.is_empty() {
            Vec::new()
        } else {
            self.run_candidates(point, &w.rhs, &w.du_free)
        };
        Ok(Some(Direction {
            solver: if fallback {
                fallback_spec()
            } else {
                decision.solver
            },
            setup,
            solve,
            fallback,
            slope,
            candidates,
        }))
    }

    /// Stage 5: backtracking (Armijo) on the merit function along `w.du` from `u`, from the
    /// step length `bound` (contact's collision bound, else 1); returns the step length and
    /// the energy at the accepted trial, whose forces (and `K u`, with
    /// stiffness damping) it leaves in `w.f` (and `w.ku`): each trial assembles them, so the
    /// next residual is formed without another pass (with the iterate's `tangent`, which the
    /// damping's `K u` is of). `None` when no trial was assembled.
    fn line_search(
        &mut self,
        mode: Mode,
        state: &State,
        u: &[f64],
        (energy, slope, tangent): (f64, f64, Tangent),
        bound: f64,
        w: &mut Work,
    ) -> Result<(f64, Option<f64>), AssemblyError> {
        let gamma = self.stiffness_damping(mode);
        let damping = self.damping_model(mode, w)?;
        let phi0 = self.merit(mode, state, u, energy, 0.0, w);
        // Near the solution the predicted decrease falls below the rounding noise of the
        // merit function; Armijo's test is then meaningless, so take the step.
        let noise = 1e-12 * phi0.abs();
        let mut step_length = bound;
        loop {
            // The trial is assembled even then: its energy and forces are the next residual's.
            let untestable = -slope * step_length <= noise;
            let mut trial = std::mem::take(&mut w.trial);
            let mut xt = std::mem::take(&mut w.xt);
            let du = &w.du;
            for_each_entry(&mut trial, |i, t| *t = u[i] + step_length * du[i]);
            self.positions_into(mode, state, &trial, &mut xt);
            let mut e = 0.0;
            let outputs = Outputs {
                energy: Some(&mut e),
                forces: Some(&mut w.f[..]),
                tangent,
                stiffness_product: (gamma != 0.0).then_some((&trial[..], &mut w.ku[..])),
                ..Outputs::default()
            };
            let assembled = match self.asm.evaluate(&xt, outputs) {
                Ok(()) => true,
                Err(AssemblyError::Inadmissible { .. }) => false,
                Err(e) => return Err(e),
            };
            // Within the bound no vertex reaches an obstacle; the barrier is finite.
            let contact = match assembled {
                true => self.add_contact(&xt, Some(&mut w.f[..]), false).ok(),
                false => None,
            };
            let (phi, evaluated) = match contact {
                Some(c) => {
                    e += c;
                    let (l, q) = damping;
                    let quadratic = step_length * (l + 0.5 * step_length * q);
                    (self.merit(mode, state, &trial, e, quadratic, w), true)
                }
                None => (f64::INFINITY, false),
            };
            (w.trial, w.xt) = (trial, xt);
            if untestable
                || phi <= phi0 + 1e-4 * step_length * slope + noise
                || step_length < 1e-4 * bound
            {
                return Ok((step_length, evaluated.then_some(e)));
            }
            step_length *= 0.5;
        }
    }

    /// The stiffness-damping part of the merit function along `w.du` from the iterate, as
    /// `(l, q)` of `s l + s^2 q / 2` at step length `s`: `l = dt gamma du . K_0 u_0`, its slope
    /// (`K_0 u_0` from the residual's pass, in `w.ku`), and `q = dt gamma du . K du` with
    /// Newton's K (with its `D_u K` term, a model of the curvature like any in a line search).
    /// Zero without stiffness damping; uses `w.fd` as scratch.
    fn damping_model(&self, mode: Mode, w: &mut Work) -> Result<(f64, f64), AssemblyError> {
        let (Mode::Dynamic { dt }, gamma) = (mode, self.stiffness_damping(mode)) else {
            return Ok((0.0, 0.0));
        };
        if gamma == 0.0 {
            return Ok((0.0, 0.0));
        }
        // `damping_forces` with alpha 0 and gamma 1: `-K du`.
        self.asm
            .damping_forces(0.0, 1.0, &self.mass, &self.k, &w.du, &mut w.fd)?;
        let (l, q) = (dot(&w.du, &w.ku), -dot(&w.du, &w.fd));
        Ok((dt * gamma * l, dt * gamma * q))
    }

    /// Positions of the iterate `u`, into `x`.
    fn positions_into(&self, mode: Mode, state: &State, u: &[f64], x: &mut [f64]) {
        match mode {
            Mode::Dynamic { dt } => for_each_entry(x, |i, xi| *xi = state.x[i] + dt * u[i]),
            Mode::Static => x.copy_from_slice(u),
        }
    }

    /// The merit function, whose gradient in `u` at the iterate is the residual: the
    /// incremental potential, with the stiffness-damping part given as `damping` (see
    /// [`Integrator::damping_model`]; 0 at the iterate). Uses `w.dv` and `w.mdv` as scratch.
    fn merit(
        &self,
        mode: Mode,
        state: &State,
        u: &[f64],
        energy: f64,
        damping: f64,
        w: &mut Work,
    ) -> f64 {
        let gravity = dot(u, self.external());
        match mode {
            Mode::Dynamic { dt } => {
                for_each_entry(&mut w.dv, |i, d| *d = u[i] - state.v[i]);
                self.asm
                    .mass_apply(&self.mass, &w.dv, &mut w.mdv)
                    .expect("sizes match");
                let kinetic = 0.5 * dot(&w.dv, &w.mdv);
                self.asm
                    .mass_apply(&self.mass, u, &mut w.mdv)
                    .expect("sizes match");
                let mass_damping = 0.5 * dt * self.options.alpha * dot(u, &w.mdv);
                kinetic + energy + mass_damping + damping - dt * gravity
            }
            Mode::Static => energy - gravity,
        }
    }

    /// Factorises (or sets up) and solves with the kept solver of `spec`.
    fn linear_solve(
        &mut self,
        point: NewtonPoint<'_>,
        decision: &Decision,
        rhs: &[f64],
        x: &mut [f64],
    ) -> Result<(SetupStats, SolveStats), FailedSolve> {
        let (system, solvers, _) = self.system(point);
        system.solve(solvers, decision, rhs, x)
    }

    /// The Newton system at `point`, and the kept solver instances (the policy's and the
    /// counterfactual candidates'), borrowed apart.
    fn system<'a>(
        &'a mut self,
        point: NewtonPoint<'a>,
    ) -> (System<'a>, &'a mut KeptSolvers, &'a mut KeptSolvers) {
        (
            System {
                asm: &self.asm,
                mass: &self.mass,
                dofs: &self.dofs,
                rest: &self.rest,
                options: &self.options,
                a_free: self
                    .contact
                    .as_ref()
                    .and_then(|c| c.coupled.as_ref())
                    .unwrap_or(&self.a_free.matrix),
                contact: self.contact.as_ref().map(|c| &c.hessian),
                secant: self.contact.as_ref().map(|c| Secant {
                    model: &c.model,
                    dofs: &self.dofs,
                    x: point.x,
                    scale: point.position_scale,
                    c_contact: point.c_contact,
                    rounds: self.options.newton.barrier_secant,
                }),
                point,
            },
            &mut self.solvers,
            &mut self.candidates,
        )
    }

    /// Runs every counterfactual candidate on the current system.
    fn run_candidates(
        &mut self,
        point: NewtonPoint<'_>,
        rhs: &[f64],
        chosen: &[f64],
    ) -> Vec<CandidateOutcome> {
        let specs: Vec<SolverSpec> = self.candidates.iter().map(|(s, _)| s.clone()).collect();
        let chosen_norm = chosen.iter().map(|v| v * v).sum::<f64>().sqrt();
        let (system, _, candidates) = self.system(point);
        specs
            .iter()
            .map(|spec| {
                let mut x = vec![0.0; rhs.len()];
                let outcome =
                    system.solve(candidates, &Decision::solver(spec.clone()), rhs, &mut x);
                match outcome {
                    Ok((setup, solve)) => {
                        let diff = x
                            .iter()
                            .zip(chosen)
                            .map(|(a, b)| (a - b).powi(2))
                            .sum::<f64>()
                            .sqrt();
                        CandidateOutcome {
                            solver: spec.clone(),
                            setup: Some(setup),
                            solve: Some(solve),
                            error: None,
                            distance: diff / chosen_norm.max(f64::MIN_POSITIVE),
                        }
                    }
                    Err(failed) => failed.outcome(spec),
                }
            })
            .collect()
    }
}

/// The integrator's vectors for Newton, allocated once and resized when the mesh changes.
#[derive(Debug, Default)]
struct Work {
    /// Elastic forces, damping forces, residual, `v - v^n`, `M (v - v^n)`, and `K u` for
    /// stiffness damping (full `3N`).
    f: Vec<f64>,
    ku: Vec<f64>,
    fd: Vec<f64>,
    r: Vec<f64>,
    dv: Vec<f64>,
    mdv: Vec<f64>,
    /// The direction, the line search's trial iterate and its positions (full `3N`).
    du: Vec<f64>,
    trial: Vec<f64>,
    xt: Vec<f64>,
    /// Residual, right-hand side and direction on the free DOFs.
    r_free: Vec<f64>,
    rhs: Vec<f64>,
    du_free: Vec<f64>,
}

impl Work {
    fn resize(&mut self, n: usize, free: usize) {
        for v in [
            &mut self.f,
            &mut self.ku,
            &mut self.fd,
            &mut self.r,
            &mut self.dv,
            &mut self.mdv,
            &mut self.du,
            &mut self.trial,
            &mut self.xt,
        ] {
            v.resize(n, 0.0);
        }
        for v in [&mut self.r_free, &mut self.rhs, &mut self.du_free] {
            v.resize(free, 0.0);
        }
    }
}

/// What the policy sees of an iteration.
struct IterationContext {
    step: usize,
    iteration: usize,
    dt: f64,
    residual: f64,
    initial_residual: f64,
}

impl IterationContext {
    fn policy<'a>(&self, num_free: usize, history: &'a [IterationReport]) -> PolicyContext<'a> {
        PolicyContext {
            step: self.step,
            iteration: self.iteration,
            dt: self.dt,
            num_free,
            residual: self.residual,
            initial_residual: self.initial_residual,
            history,
        }
    }
}

/// A Newton direction found (in `Work::du_free`) and what finding it cost.
struct Direction {
    solver: SolverSpec,
    setup: SetupStats,
    solve: SolveStats,
    fallback: bool,
    /// `r . du`: negative for a descent direction.
    slope: f64,
    candidates: Vec<CandidateOutcome>,
}

/// Why the residual stage failed.
enum StageError {
    Assembly(AssemblyError),
    Contact(ContactError),
    NonFinite(&'static str),
}

impl From<ContactError> for StageError {
    fn from(e: ContactError) -> Self {
        Self::Contact(e)
    }
}

impl From<AssemblyError> for StageError {
    fn from(e: AssemblyError) -> Self {
        Self::Assembly(e)
    }
}

impl StageError {
    fn into_step_error(self, report: &StepReport) -> StepError {
        match self {
            StageError::Assembly(e) => fail_assembly(e, report),
            StageError::Contact(source) => StepError::Contact {
                source,
                report: Box::new(report.clone()),
            },
            StageError::NonFinite(what) => StepError::NonFinite {
                what,
                report: Box::new(report.clone()),
            },
        }
    }
}

/// The factor of the contact Hessian in Newton's matrix: contact is a force on positions,
/// which move `dt` times the unknown velocity when dynamic (`dt^2`, as for K without
/// damping: Rayleigh damping is of the elastic forces only).
fn contact_scale(mode: Mode) -> f64 {
    match mode {
        Mode::Dynamic { dt } => dt * dt,
        Mode::Static => 1.0,
    }
}

/// The max-norm of the position update of a Newton step `du` taken with `step_length`
/// (`du` is a velocity update when dynamic: positions move `dt` times it).
fn position_update(mode: Mode, du: &[f64], step_length: f64) -> f64 {
    let scale = match mode {
        Mode::Dynamic { dt } => dt,
        Mode::Static => 1.0,
    };
    du.iter()
        .fold(0.0f64, |m, v| m.max((scale * step_length * v).abs()))
}

fn fail_assembly(source: AssemblyError, report: &StepReport) -> StepError {
    StepError::Assembly {
        source,
        report: Box::new(report.clone()),
    }
}

/// Where the Newton matrix `c_m M + c_k K` is linearised, for matrix-free solves.
#[derive(Clone, Copy)]
struct NewtonPoint<'a> {
    x: &'a [f64],
    tangent: Tangent,
    c_m: f64,
    c_k: f64,
    /// The factor of contact's Hessian blocks ([`contact_scale`]).
    c_contact: f64,
    /// Iterative solves stop at this residual norm ([`NewtonOptions::linear_floor`]).
    floor: f64,
    /// Positions move this times the unknown's update (`dt` dynamic, 1 static).
    position_scale: f64,
}

impl<'a> NewtonPoint<'a> {
    /// The point `x` of a Newton iteration of `report`'s step, with its matrix's factors.
    fn new(
        x: &'a [f64],
        tangent: Tangent,
        (c_m, c_k): (f64, f64),
        mode: Mode,
        newton: &NewtonOptions,
        report: &StepReport,
    ) -> Self {
        Self {
            x,
            tangent,
            c_m,
            c_k,
            c_contact: contact_scale(mode),
            floor: newton.linear_floor * newton.abs.max(newton.rel * report.initial_residual),
            position_scale: match mode {
                Mode::Dynamic { dt } => dt,
                Mode::Static => 1.0,
            },
        }
    }
}

/// The linear system of a Newton iteration: the assembled reduced matrix, or the same matrix
/// applied element by element at `point` for matrix-free configurations.
struct System<'a> {
    asm: &'a Assembly,
    mass: &'a Mass,
    dofs: &'a DofMap,
    /// Rest positions, for geometric orderings of new direct solvers.
    rest: &'a [Vector3<f64>],
    options: &'a IntegratorOptions,
    a_free: &'a CsMat<f64>,
    /// Contact's Hessian blocks at the point (for matrix-free solves).
    contact: Option<&'a deform_contact::ContactHessian>,
    /// The barrier's secant rounds, with contact.
    secant: Option<Secant<'a>>,
    point: NewtonPoint<'a>,
}

impl System<'_> {
    /// Solves with the instance of the decision's solver kept in `list`, on the operator
    /// it asks for.
    fn solve(
        &self,
        list: &mut KeptSolvers,
        decision: &Decision,
        rhs: &[f64],
        x: &mut [f64],
    ) -> Result<(SetupStats, SolveStats), FailedSolve> {
        if !decision.solver.is_matrix_free() {
            return solve_with(list, self, self.a_free, decision, rhs, x);
        }
        // The operator adds a diagonal mass: lumped only.
        if self.options.mass != MassKind::Lumped {
            return Err(
                SolverError::Unsupported("matrix-free Newton solves need the lumped mass").into(),
            );
        }
        let p = self.point;
        let tangents = self.asm.tangents(p.x, p.tangent).map_err(|_| {
            FailedSolve::from(SolverError::Unsupported(
                "element tangents failed at this point",
            ))
        })?;
        let op = MatrixFreeNewton::new(self.asm, tangents, self.mass, p.c_m, p.c_k)
            .with_contact(self.contact, p.c_contact);
        let reduced = Restricted::new(&op, self.dofs);
        solve_with(list, self, &reduced, decision, rhs, x)
    }
}

/// Factorises (or sets up) and solves with the instance of the decision's solver kept in
/// `list` (built on first use), refreshed and with its tolerance set as the decision says.
fn solve_with(
    list: &mut KeptSolvers,
    system: &System<'_>,
    a: &dyn LinearOperator,
    decision: &Decision,
    rhs: &[f64],
    x: &mut [f64],
) -> Result<(SetupStats, SolveStats), FailedSolve> {
    let spec = &decision.solver;
    let index = match list.iter().position(|(s, _)| s == spec) {
        Some(i) => i,
        None => {
            let mut solver = spec.build()?;
            // The free vertices' rest positions, in row order: geometric nested dissection.
            let coordinates: Vec<[f64; 3]> = system
                .dofs
                .free_dofs()
                .iter()
                .step_by(3)
                .map(|&d| {
                    let p = system.rest[d / 3];
                    [p.x, p.y, p.z]
                })
                .collect();
            solver.set_coordinates(Some(&coordinates));
            list.push((spec.clone(), solver));
            list.len() - 1
        }
    };
    let solver = &mut list[index].1;
    if decision.refresh {
        solver.refresh();
    }
    if let Some(rel) = decision.rel_tolerance {
        solver.set_relative_tolerance(rel)?;
    }
    solver.set_residual_floor(system.point.floor);
    let setup = solver.factorize(a)?;
    // The barrier's secant rounds where there are contacts. A direct solver's factor is of
    // `a` alone: its rounds are a few conjugate-gradient iterations preconditioned by it
    // (docs/theory.md, "Contact").
    let solved = match &system.secant {
        Some(secant) if secant.rounds > 0 && system.contact.is_some_and(|h| !h.is_empty()) => {
            let direct = matches!(spec, SolverSpec::Direct { .. });
            secant::solve(
                secant,
                solver.as_mut(),
                a,
                rhs,
                x,
                system.point.floor,
                direct,
            )
        }
        _ => solver.solve(a, rhs, x),
    };
    match solved {
        Ok(stats) => Ok((setup, stats)),
        Err(error) => Err(FailedSolve {
            setup: Some(setup),
            error,
        }),
    }
}

/// A linear solve that failed, with what it had spent: its set-up, when that succeeded, and
/// the solve's statistics inside the error (`SolverError::stats`).
#[derive(Debug)]
struct FailedSolve {
    setup: Option<SetupStats>,
    error: SolverError,
}

impl From<SolverError> for FailedSolve {
    fn from(error: SolverError) -> Self {
        Self { setup: None, error }
    }
}

impl FailedSolve {
    /// As a candidate outcome (its cost, why it failed).
    fn outcome(&self, spec: &SolverSpec) -> CandidateOutcome {
        CandidateOutcome {
            solver: spec.clone(),
            setup: self.setup.or_else(|| self.error.spent().copied()),
            solve: self.error.stats().cloned(),
            error: Some(self.error.to_string()),
            distance: f64::INFINITY,
        }
    }
}

/// Gravity forces `M g`.
fn gravity_forces(
    asm: &Assembly,
    mass: &Mass,
    gravity: [f64; 3],
) -> Result<Vec<f64>, AssemblyError> {
    let g: Vec<f64> = (0..asm.num_dofs()).map(|i| gravity[i % 3]).collect();
    let mut f = vec![0.0; g.len()];
    asm.mass_apply(mass, &g, &mut f)?;
    Ok(f)
}

/// Each load with its vertices' shares of its force, in proportion to their masses.
fn load_shares(
    asm: &Assembly,
    mass: &Mass,
    loads: Vec<Load>,
) -> Result<Vec<(Load, Vec<f64>)>, IntegratorError> {
    let masses = asm.vertex_masses(mass);
    let mut out = Vec::with_capacity(loads.len());
    for load in loads {
        let invalid = |reason: String| IntegratorError::Invalid {
            field: "loads",
            reason,
        };
        load.force.validate().map_err(invalid)?;
        if let Some(&v) = load.vertices.iter().find(|&&v| v >= masses.len()) {
            return Err(invalid(format!(
                "vertex {v} is out of range for {} vertices",
                masses.len()
            )));
        }
        let total: f64 = load.vertices.iter().map(|&v| masses[v]).sum();
        if !(total > 0.0) {
            return Err(invalid("a load on no vertex (or no mass)".into()));
        }
        let shares = load.vertices.iter().map(|&v| masses[v] / total).collect();
        out.push((load, shares));
    }
    Ok(out)
}

/// Why per-vertex mass scales cannot be used (see [`Integrator::set_mass_scale`]).
fn check_mass_scale(scale: &[f64], vertices: usize) -> Result<(), String> {
    if scale.len() != vertices {
        return Err(format!("{} scales for {vertices} vertices", scale.len()));
    }
    match scale.iter().position(|s| !(s.is_finite() && *s > 0.0)) {
        Some(v) => Err(format!("vertex {v}: {} must be finite and > 0", scale[v])),
        None => Ok(()),
    }
}

fn retryable(e: &StepError) -> bool {
    !matches!(
        e,
        StepError::Assembly {
            source: AssemblyError::NonFinite { .. },
            ..
        }
    )
}
