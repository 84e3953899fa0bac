//! The Backward-Euler Newton loop (seed Eq. 7-9) and the quasi-static solve.

mod contact_step;
mod direction;
mod external;
mod line_search;
mod newton;

use self::contact_step::*;
use self::direction::*;
use self::external::*;
use self::newton::*;
use crate::conditions::{Conditions, Load};
use crate::contact::Contact;
use crate::matrix_free::{MatrixFreeNewton, Restricted};
use crate::observer::{NoObserver, Observer};
use crate::policy::{Decision, PolicyContext, SolverPolicy};
use crate::report::{CandidateOutcome, IterationReport, StageSeconds, StepError, StepReport};
use crate::secant::{self, Secant};
use crate::state::{Constraint, Motion, State};
use deform_assembly::{
    Assembly, AssemblyError, DofMap, Mass, MaterialField, Outputs, ReducedMatrix, StiffnessMatrix,
    StiffnessShift, Tangent,
};
use deform_contact::{ContactError, ContactModel, ContactSpec, ContactSummary};
use deform_mesh::TetMesh;
use deform_solvers::{
    Indefinite, LinearOperator, LinearSolver, Ordering, SetupStats, SolveStats, SolverError,
    SolverSpec,
    vector::{dot, norm, update_from, update_from2, update_from3},
};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use sprs::CsMat;
use std::time::Instant;
use thiserror::Error;

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

/// Newton's stopping rules and globalisation. Build it from `Default` and its setters: it
/// may gain fields, which breaks no code built this way (a struct literal cannot be
/// written outside this crate).
///
/// ```
/// use deform_integrator::{IntegratorOptions, NewtonOptions, Projection};
///
/// let newton = NewtonOptions::default().rel(1e-8).max_iterations(50).project(Projection::Always);
/// let options = IntegratorOptions::default().dt(1e-3).alpha(0.1).newton(newton);
/// assert_eq!((options.dt, options.newton.rel), (1e-3, 1e-8));
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
#[non_exhaustive]
pub struct NewtonOptions {
    /// Converged when `||r|| <= abs`: the residual's 2-norm over the free DOFs, in N for
    /// the static solve and N s (momentum, `M (v - v^n) - dt f`) for a dynamic step.
    pub abs: f64,
    /// ... or when `||r|| <= rel ||r_0||` (first iterate of the step).
    pub rel: f64,
    /// ... or when the max-norm of a position update is below this (m) and the residual is
    /// below the step's first; 0 disables.
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

crate::setters!(NewtonOptions {
    abs: f64,
    rel: f64,
    update: f64,
    max_iterations: usize,
    barrier_secant: usize,
    linear_floor: f64,
    line_search: bool,
    project: Projection,
});

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

/// Time-stepping options. Unknown fields are rejected in RON. Build it from `Default` and
/// its setters (`IntegratorOptions::default().dt(1e-3).alpha(0.1)`; see [`NewtonOptions`]):
/// it may gain fields.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
#[non_exhaustive]
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

crate::setters!(IntegratorOptions {
    dt: f64,
    alpha: f64,
    gamma: f64,
    gravity: [f64; 3],
    mass: MassKind,
    newton: NewtonOptions,
    max_retries: usize,
    fallback_to_direct: bool,
});

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
///     .options(IntegratorOptions::default().dt(0.005))
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
    /// [`ContactError::Penetration`] naming the first vertex (interior ones included) inside
    /// an obstacle; the pair of surface primitives that touch or cross.
    pub fn contact_at(&self, x: &[f64]) -> Option<Result<ContactSummary, ContactError>> {
        self.contact.as_ref().map(|c| {
            c.model.check_body_outside(x)?;
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

impl From<SolverError> for FailedSolve {
    fn from(error: SolverError) -> Self {
        Self { setup: None, error }
    }
}
