//! Backward-Euler time integration of deformable solids (the seed's Section 2, Eq. 7-9).
//!
//! Each step solves, by Newton's method on the velocity `v = v^{n+1}`,
//! `M (v - v^n) = dt (f_e(x^n + dt v) - (alpha M + gamma K) v + M g)` on the free degrees of
//! freedom, with the linearisation (K held at the iterate, docs/theory.md)
//! `((1 + dt alpha) M + (dt gamma + dt^2) K) dv = -r`. Constrained vertices (fixed or moving
//! along a prescribed [`Motion`]) are eliminated through the assembly's DOF map. A
//! [`SolverPolicy`] picks the linear solver at each Newton iteration; every iteration is
//! reported ([`StepReport`], with per-stage times); failures are typed ([`StepError`]) and
//! carry the report; an option retries with halved steps. [`Integrator::run`] is the one
//! loop over steps: until a step count or a time, with an [`Observer`] passed per call,
//! returning a [`RunSummary`]. What building an integrator takes ([`MaterialField`],
//! [`MaterialSpec`], [`TetMesh`], ...) is re-exported here.
//!
//! ```
//! use deform_integrator::{
//!     Constraint, Integrator, IntegratorOptions, MaterialField, MaterialSpec, Motion,
//!     NoObserver, PolicySpec, RunOptions,
//! };
//! use deform_mesh::generate::BoxGrid;
//!
//! let mesh = BoxGrid::beam(1).build().unwrap();
//! let model = ron::from_str::<MaterialSpec>("NeoHookean(Young(e: 1e6, nu: 0.4))").unwrap().build().unwrap();
//! let clamp: Vec<usize> = (0..mesh.num_vertices()).filter(|&v| mesh.rest_positions()[v].x == 0.0).collect();
//! let mut sim = Integrator::builder(&mesh, MaterialField::Uniform(model))
//!     .constraints(vec![Constraint { vertices: clamp, motion: Motion::Fixed }])
//!     .options(IntegratorOptions::default())
//!     .policy(PolicySpec::default().build().unwrap())
//!     .build()
//!     .unwrap();
//! let mut state = sim.rest_state();
//! let report = sim.step(&mut state).unwrap();
//! assert!(report.converged && state.x.iter().all(|v| v.is_finite()));
//! let run = sim.run(&mut state, &RunOptions::steps(3), &mut NoObserver);
//! assert_eq!(run.into_result().unwrap().steps, 3);
//! ```

pub mod benchmark;
mod conditions;
mod contact;
mod integrator;
mod matrix_free;
mod observer;
mod policy;
mod report;
mod run;
pub mod scene;
mod secant;
// `crate::setters!` and `deform_integrator::setters!` name the one macro of deform-setters.
pub use deform_setters::setters;
mod simulate;
mod state;

pub use conditions::{Conditions, Load, LoadForce, LoadSpec};
/// What building an [`Integrator`] takes, re-exported from the crates below.
pub use deform_assembly::MaterialField;
pub use deform_contact::{
    Barrier, ContactError, ContactHessian, ContactModel, ContactSpec, ContactSummary, FrictionLag,
    FrictionPair, FrictionSpec, MeshObstacle, Obstacle, ObstacleMotion,
};
pub use deform_materials::{Lame, MaterialSpec, Model, Moduli};
pub use deform_mesh::TetMesh;
pub use integrator::{
    Integrator, IntegratorBuilder, IntegratorError, IntegratorOptions, MassKind, NewtonOptions,
    Projection,
};
pub use matrix_free::MatrixFreeNewton;
pub use observer::{NoObserver, Observer, OnStep};
pub use policy::{
    Decision, EisenstatWalker, Fixed, PolicyContext, PolicyError, PolicySpec, Schedule,
    SolverPolicy, StaleFactor,
};
pub use report::{CandidateOutcome, IterationReport, StageSeconds, StepError, StepReport};
pub use run::{RunError, RunOptions, RunSummary, Termination, Until};
pub use scene::{Scene, SceneError};
pub use simulate::{SimulateError, Simulation, simulate};
pub use state::{Constraint, Motion, State};
