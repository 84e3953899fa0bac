//! The Backward-Euler Newton loop (seed Eq. 7-9) and the quasi-static solve.

use std::time::Instant;

use deform_assembly::{
    Assembly, AssemblyError, DofMap, Mass, MaterialField, Outputs, ReducedMatrix, Tangent,
};
use deform_mesh::TetMesh;
use deform_solvers::{
    Indefinite, LinearOperator, LinearSolver, Ordering, SetupStats, SolveStats, SolverError,
    SolverSpec,
};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use sprs::CsMat;
use thiserror::Error;

use crate::matrix_free::{MatrixFreeNewton, Restricted};
use crate::policy::{PolicyContext, SolverPolicy};
use crate::report::{CandidateOutcome, IterationReport, StepError, StepReport};
use crate::run::{NoObserver, Observer};
use crate::state::{Constraint, State};

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

/// Newton's stopping rules and globalisation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NewtonOptions {
    /// Converged when `||r|| <= abs`.
    pub abs: f64,
    /// ... or when `||r|| <= rel ||r_0||` (first iterate of the step).
    pub rel: f64,
    /// ... or when the max-norm of a position update is below this (m); 0 disables.
    pub update: f64,
    /// Iteration cap.
    pub max_iterations: usize,
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
    /// Rayleigh stiffness damping `gamma` (s).
    pub gamma: f64,
    /// Gravity (m/s^2).
    pub gravity: [f64; 3],
    /// Mass matrix.
    pub mass: MassKind,
    /// Newton options.
    pub newton: NewtonOptions,
    /// On failure, retry with dt halved (two half steps) up to this many times.
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
        if !(self.gamma.is_finite() && self.gamma >= 0.0) {
            return bad("gamma", format!("{} must be finite and >= 0", self.gamma));
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
        if n.max_iterations == 0 {
            return bad("newton.max_iterations", "must be at least 1".into());
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
    /// `M g`.
    gravity_forces: Vec<f64>,
    k: CsMat<f64>,
    a: CsMat<f64>,
    a_free: ReducedMatrix,
    solvers: KeptSolvers,
    /// Counterfactual candidates, each with its own kept instance.
    candidates: KeptSolvers,
    policy: Box<dyn SolverPolicy>,
    steps_taken: usize,
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
    /// An integrator for `mesh` with `materials`, mass density `density` (kg/m^3), constrained
    /// vertex sets, options and a solver policy.
    ///
    /// # Errors
    /// [`IntegratorError`] naming the bad field, vertex or element.
    pub fn new(
        mesh: &TetMesh,
        materials: MaterialField,
        density: f64,
        constraints: Vec<Constraint>,
        options: IntegratorOptions,
        policy: Box<dyn SolverPolicy>,
    ) -> Result<Self, IntegratorError> {
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
        let asm = Assembly::new(mesh, materials)?;
        let mass = match options.mass {
            MassKind::Lumped => Mass::lumped(mesh, density),
            MassKind::Consistent => Mass::consistent(mesh, density, asm.pattern()),
        };
        let constrained: Vec<usize> = constraints
            .iter()
            .flat_map(|c| c.vertices.iter().copied())
            .collect();
        let dofs = DofMap::new(mesh.num_vertices(), &constrained)?;
        let g: Vec<f64> = (0..asm.num_dofs())
            .map(|i| options.gravity[i % 3])
            .collect();
        let mut gravity_forces = vec![0.0; g.len()];
        asm.mass_apply(&mass, &g, &mut gravity_forces)?;
        let k = asm.stiffness_matrix();
        let a = asm.stiffness_matrix();
        let a_free = dofs.reduced_matrix(&a)?;
        Ok(Self {
            asm,
            mass,
            rest: mesh.rest_positions().to_vec(),
            constraints,
            dofs,
            options,
            gravity_forces,
            k,
            a,
            a_free,
            solvers: Vec::new(),
            candidates: Vec::new(),
            policy,
            steps_taken: 0,
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
        self.options = options;
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

    /// Gravity forces `M g`.
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

    /// Sets constrained positions to their targets at `t` and, when `v` is given, the
    /// velocities that reach them from `x_prev` in `dt`.
    fn apply_constraints(&self, x: &mut [f64], v: Option<(&mut [f64], &[f64])>, t: f64, dt: f64) {
        let mut v = v;
        for c in &self.constraints {
            for &i in &c.vertices {
                let target = c.motion.position(&self.rest[i], t);
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
        let mut report = self.advance(state, dt, 0, observer)?;
        report.step = self.steps_taken;
        report.seconds = start.elapsed().as_secs_f64();
        self.steps_taken += 1;
        Ok(report)
    }

    /// `dt` in one Newton solve, or in two halves (recursively) when it fails.
    fn advance(
        &mut self,
        state: &mut State,
        dt: f64,
        depth: usize,
        observer: &mut dyn Observer,
    ) -> Result<StepReport, StepError> {
        match self.newton(state, Mode::Dynamic { dt }, observer) {
            Ok((next, report)) => {
                *state = next;
                Ok(report)
            }
            Err(e) if depth < self.options.max_retries && retryable(&e) => {
                let earlier = e.report().iterations.clone();
                let mut half = state.clone();
                let first = self
                    .advance(&mut half, dt / 2.0, depth + 1, observer)
                    .map_err(|e2| e2.with_earlier(&earlier, depth + 1))?;
                let second = self
                    .advance(&mut half, dt / 2.0, depth + 1, observer)
                    .map_err(|e2| e2.with_earlier(&earlier, depth + 1))?;
                *state = half;
                let mut iterations = earlier;
                iterations.extend(first.iterations);
                iterations.extend(second.iterations);
                Ok(StepReport {
                    iterations,
                    retries: 1 + first.retries.max(second.retries),
                    dt: first.dt.min(second.dt),
                    ..second
                })
            }
            Err(e) => Err(e),
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

    /// Newton on the unknown `u` (`v` when dynamic, `x` when static).
    fn newton(
        &mut self,
        state: &State,
        mode: Mode,
        observer: &mut dyn Observer,
    ) -> Result<(State, StepReport), StepError> {
        let n = self.asm.num_dofs();
        let opts = self.options.clone();
        let (t1, dt) = match mode {
            Mode::Dynamic { dt } => (state.t + dt, dt),
            Mode::Static => (state.t, 0.0),
        };
        let mut report = StepReport {
            t: t1,
            dt,
            policy: self.policy.name(),
            ..StepReport::default()
        };
        // Initial iterate: v^n (dynamic) or x^n (static), constrained DOFs at their targets.
        let mut x = state.x.clone();
        let mut u = match mode {
            Mode::Dynamic { .. } => state.v.clone(),
            Mode::Static => state.x.clone(),
        };
        match mode {
            Mode::Dynamic { dt } => {
                self.apply_constraints(&mut x, Some((&mut u, &state.x)), t1, dt);
                for i in 0..n {
                    x[i] = state.x[i] + dt * u[i];
                }
            }
            Mode::Static => {
                self.apply_constraints(&mut x, None, t1, 0.0);
                u.copy_from_slice(&x);
            }
        }
        let fail_assembly = |source: AssemblyError, report: &StepReport| StepError::Assembly {
            source,
            report: Box::new(report.clone()),
        };
        let mut f = vec![0.0; n];
        let mut fd = vec![0.0; n];
        let mut r = vec![0.0; n];
        let mut r_free = vec![0.0; self.dofs.num_free()];
        let mut du_free = vec![0.0; self.dofs.num_free()];
        let mut du = vec![0.0; n];
        let mut tangent = match opts.newton.project {
            Projection::Always => Tangent::Projected,
            Projection::Never | Projection::WhenNeeded => Tangent::Exact,
        };
        // Solves whose result was not used (a failed choice before the fallback, an
        // exact-tangent attempt before projection), charged to the next iteration's report.
        let mut discarded: Vec<CandidateOutcome> = Vec::new();
        let mut iteration = 0;
        while iteration <= opts.newton.max_iterations {
            // `WhenNeeded` switches to the projected tangent once per step at most.
            let can_project =
                opts.newton.project == Projection::WhenNeeded && tangent == Tangent::Exact;
            let started = Instant::now();
            let mut energy = 0.0;
            self.asm
                .evaluate(
                    &x,
                    Outputs {
                        energy: Some(&mut energy),
                        forces: Some(&mut f),
                        stiffness: Some(&mut self.k),
                        tangent,
                    },
                )
                .map_err(|e| fail_assembly(e, &report))?;
            // Residual (the gradient of the merit function in u).
            match mode {
                Mode::Dynamic { dt } => {
                    self.asm
                        .damping_forces(opts.alpha, opts.gamma, &self.mass, &self.k, &u, &mut fd)
                        .map_err(|e| fail_assembly(e, &report))?;
                    let dv: Vec<f64> = u.iter().zip(&state.v).map(|(a, b)| a - b).collect();
                    self.asm
                        .mass_apply(&self.mass, &dv, &mut r)
                        .map_err(|e| fail_assembly(e, &report))?;
                    for i in 0..n {
                        r[i] -= dt * (f[i] + fd[i] + self.gravity_forces[i]);
                    }
                }
                Mode::Static => {
                    for i in 0..n {
                        r[i] = -(f[i] + self.gravity_forces[i]);
                    }
                }
            }
            self.dofs.restrict(&r, &mut r_free).expect("sizes match");
            let rn = norm(&r_free);
            if !rn.is_finite() {
                return Err(StepError::NonFinite {
                    what: "residual",
                    report: Box::new(report),
                });
            }
            if iteration == 0 {
                report.initial_residual = rn;
            }
            report.final_residual = rn;
            report.energy = energy;
            let last_update = report
                .iterations
                .last()
                .map_or(f64::INFINITY, |it| it.update);
            if rn
                <= opts
                    .newton
                    .abs
                    .max(opts.newton.rel * report.initial_residual)
                && (iteration > 0 || rn <= opts.newton.abs)
                || (iteration > 0 && last_update <= opts.newton.update)
            {
                report.converged = true;
                let v = match mode {
                    Mode::Dynamic { .. } => u,
                    Mode::Static => vec![0.0; n],
                };
                return Ok((State { x, v, t: t1 }, report));
            }
            if iteration == opts.newton.max_iterations {
                break;
            }
            // Newton matrix on the free DOFs.
            let (c_m, c_k) = match mode {
                Mode::Dynamic { dt } => (1.0 + dt * opts.alpha, dt * opts.gamma + dt * dt),
                Mode::Static => (0.0, 1.0),
            };
            self.asm
                .combine(c_m, &self.mass, c_k, &self.k, &mut self.a)
                .map_err(|e| fail_assembly(e, &report))?;
            self.dofs
                .restrict_matrix(&self.a, &mut self.a_free)
                .map_err(|e| fail_assembly(e, &report))?;
            let rhs: Vec<f64> = r_free.iter().map(|v| -v).collect();
            let point = NewtonPoint {
                x: &x,
                tangent,
                c_m,
                c_k,
            };
            // What the policy sees, before the solve and (with its outcome) after it.
            let (step, num_free, initial) = (
                self.steps_taken,
                self.dofs.num_free(),
                report.initial_residual,
            );
            let context = |history| PolicyContext {
                step,
                iteration,
                dt,
                num_free,
                residual: rn,
                initial_residual: initial,
                history,
            };
            let decision = self.policy.choose(&context(&report.iterations));
            du_free.iter_mut().for_each(|v| *v = 0.0);
            let attempt = self.linear_solve(
                point,
                &decision.solver,
                decision.rel_tolerance,
                decision.refresh,
                &rhs,
                &mut du_free,
            );
            let attempt = match attempt {
                Err(failed)
                    if opts.fallback_to_direct
                        && decision.solver != fallback_spec()
                        && !(can_project && failed.error.is_indefinite()) =>
                {
                    discarded.push(failed.outcome(&decision.solver));
                    du_free.iter_mut().for_each(|v| *v = 0.0);
                    self.linear_solve(point, &fallback_spec(), None, false, &rhs, &mut du_free)
                        .map(|(setup, solve)| (setup, solve, true))
                }
                other => other.map(|(setup, solve)| (setup, solve, false)),
            };
            let (setup, solve, fallback) = match attempt {
                Ok(done) => done,
                Err(failed) if can_project && failed.error.is_indefinite() => {
                    discarded.push(failed.outcome(&decision.solver));
                    tangent = Tangent::Projected;
                    continue;
                }
                Err(failed) => {
                    return Err(StepError::Solver {
                        source: failed.error,
                        report: Box::new(report),
                    });
                }
            };
            // An indefinite exact tangent can also give an ascent direction without failing.
            let slope: f64 = r_free.iter().zip(&du_free).map(|(a, b)| a * b).sum();
            if can_project && slope >= 0.0 {
                discarded.push(CandidateOutcome {
                    solver: decision.solver.clone(),
                    setup: Some(setup),
                    solve: Some(solve),
                    error: Some(format!("not a descent direction (r . du = {slope:e})")),
                    distance: f64::INFINITY,
                });
                tangent = Tangent::Projected;
                continue;
            }
            let candidates = if self.candidates.is_empty() {
                Vec::new()
            } else {
                self.run_candidates(point, &rhs, &du_free)
            };
            du.iter_mut().for_each(|v| *v = 0.0);
            self.dofs.scatter(&du_free, &mut du).expect("sizes match");
            // Backtracking line search on the merit function, K frozen at this iterate.
            let mut step_length = 1.0;
            if opts.newton.line_search && slope < 0.0 {
                let phi0 = self.merit(mode, state, &u, energy);
                // Near the solution the predicted decrease falls below the rounding noise of
                // the merit function; Armijo's test is then meaningless, so take the step.
                let noise = 1e-12 * phi0.abs();
                loop {
                    if -slope * step_length <= noise {
                        break;
                    }
                    let trial: Vec<f64> = u
                        .iter()
                        .zip(&du)
                        .map(|(a, b)| a + step_length * b)
                        .collect();
                    let xt = self.positions(mode, state, &trial);
                    let phi = match self.asm.energy(&xt) {
                        Ok(e) => self.merit(mode, state, &trial, e),
                        Err(AssemblyError::Inadmissible { .. }) => f64::INFINITY,
                        Err(e) => return Err(fail_assembly(e, &report)),
                    };
                    if phi <= phi0 + 1e-4 * step_length * slope + noise || step_length < 1e-4 {
                        break;
                    }
                    step_length *= 0.5;
                }
            }
            for i in 0..n {
                u[i] += step_length * du[i];
            }
            x = self.positions(mode, state, &u);
            let scale = match mode {
                Mode::Dynamic { dt } => dt,
                Mode::Static => 1.0,
            };
            let update = du
                .iter()
                .fold(0.0f64, |m, v| m.max((scale * step_length * v).abs()));
            if !update.is_finite() {
                return Err(StepError::NonFinite {
                    what: "update",
                    report: Box::new(report),
                });
            }
            let it = IterationReport {
                iteration,
                residual: rn,
                energy,
                solver: if fallback {
                    fallback_spec()
                } else {
                    decision.solver.clone()
                },
                setup,
                solve,
                fallback,
                step_length,
                update,
                seconds: started.elapsed().as_secs_f64(),
                candidates,
                discarded: std::mem::take(&mut discarded),
            };
            observer.iteration(&it);
            self.policy.observe(&context(&report.iterations), &it);
            report.iterations.push(it);
            iteration += 1;
        }
        Err(StepError::NotConverged {
            report: Box::new(report),
        })
    }

    /// Positions of the iterate `u`.
    fn positions(&self, mode: Mode, state: &State, u: &[f64]) -> Vec<f64> {
        match mode {
            Mode::Dynamic { dt } => state.x.iter().zip(u).map(|(x, v)| x + dt * v).collect(),
            Mode::Static => u.to_vec(),
        }
    }

    /// The merit function whose gradient in `u` is the residual (K frozen at the last
    /// assembly for the damping term).
    fn merit(&self, mode: Mode, state: &State, u: &[f64], energy: f64) -> f64 {
        let n = u.len();
        match mode {
            Mode::Dynamic { dt } => {
                let dv: Vec<f64> = u.iter().zip(&state.v).map(|(a, b)| a - b).collect();
                let mut mdv = vec![0.0; n];
                self.asm
                    .mass_apply(&self.mass, &dv, &mut mdv)
                    .expect("sizes match");
                let mut damp = vec![0.0; n];
                self.asm
                    .damping_forces(
                        self.options.alpha,
                        self.options.gamma,
                        &self.mass,
                        &self.k,
                        u,
                        &mut damp,
                    )
                    .expect("sizes match");
                let kinetic: f64 = 0.5 * dv.iter().zip(&mdv).map(|(a, b)| a * b).sum::<f64>();
                let damping: f64 = -0.5 * dt * u.iter().zip(&damp).map(|(a, b)| a * b).sum::<f64>();
                let gravity: f64 = dt
                    * u.iter()
                        .zip(&self.gravity_forces)
                        .map(|(a, b)| a * b)
                        .sum::<f64>();
                kinetic + energy + damping - gravity
            }
            Mode::Static => {
                energy
                    - u.iter()
                        .zip(&self.gravity_forces)
                        .map(|(a, b)| a * b)
                        .sum::<f64>()
            }
        }
    }

    /// Factorises (or sets up) and solves with the kept solver of `spec`.
    fn linear_solve(
        &mut self,
        point: NewtonPoint<'_>,
        spec: &SolverSpec,
        rel_tolerance: Option<f64>,
        refresh: bool,
        rhs: &[f64],
        x: &mut [f64],
    ) -> Result<(SetupStats, SolveStats), FailedSolve> {
        let (system, solvers, _) = self.system(point);
        system.solve(solvers, spec, rel_tolerance, refresh, rhs, x)
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
                a_free: &self.a_free.matrix,
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
                let outcome = system.solve(candidates, spec, None, false, rhs, &mut x);
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

/// Where the Newton matrix `c_m M + c_k K` is linearised, for matrix-free solves.
#[derive(Clone, Copy)]
struct NewtonPoint<'a> {
    x: &'a [f64],
    tangent: Tangent,
    c_m: f64,
    c_k: f64,
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
    point: NewtonPoint<'a>,
}

impl System<'_> {
    /// Solves with the instance of `spec` kept in `list` on the operator `spec` asks for.
    fn solve(
        &self,
        list: &mut KeptSolvers,
        spec: &SolverSpec,
        rel_tolerance: Option<f64>,
        refresh: bool,
        rhs: &[f64],
        x: &mut [f64],
    ) -> Result<(SetupStats, SolveStats), FailedSolve> {
        if !spec.is_matrix_free() {
            return solve_with(
                list,
                self,
                self.a_free,
                spec,
                rel_tolerance,
                refresh,
                rhs,
                x,
            );
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
        let op = MatrixFreeNewton::new(self.asm, tangents, self.mass, p.c_m, p.c_k);
        let reduced = Restricted::new(&op, self.dofs);
        solve_with(list, self, &reduced, spec, rel_tolerance, refresh, rhs, x)
    }
}

/// Factorises (or sets up) and solves with the instance of `spec` kept in `list` (built on
/// first use).
#[allow(clippy::too_many_arguments)]
fn solve_with(
    list: &mut KeptSolvers,
    system: &System<'_>,
    a: &dyn LinearOperator,
    spec: &SolverSpec,
    rel_tolerance: Option<f64>,
    refresh: bool,
    rhs: &[f64],
    x: &mut [f64],
) -> Result<(SetupStats, SolveStats), FailedSolve> {
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
    if refresh {
        solver.refresh();
    }
    if let Some(rel) = rel_tolerance {
        solver.set_relative_tolerance(rel)?;
    }
    let setup = solver.factorize(a)?;
    match solver.solve(a, rhs, x) {
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

fn retryable(e: &StepError) -> bool {
    !matches!(
        e,
        StepError::Assembly {
            source: AssemblyError::NonFinite { .. },
            ..
        }
    )
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|a| a * a).sum::<f64>().sqrt()
}
