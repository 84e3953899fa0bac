//! Learning from trajectories: the seed's Section 2.1. Data are pairs
//! `((x^n, v^n), (x^n+1, v^n+1))` produced by a base model (any scene) or imported from
//! elsewhere; they fit material parameters and Rayleigh damping ([`fit`], [`output`]),
//! weighted ensembles of energy models ([`ensemble`]), a learned linear-solver policy
//! ([`solver_data`], [`policy`]) and solver parameters ([`tuning`]). These are the methods;
//! the studies built on them (experiment files, tasks, reports) are the `deform-studies`
//! crate above this one. [`compare`] measures policies on whole simulations;
//! [`rollout`] holds the one definition of the rollout error; [`coarsen`] carries a fine
//! model's trajectories onto a coarse mesh, so a cheap model learns from an accurate one, with
//! coefficient fields per element, per region or smooth ([`basis`]).
//!
//! Datasets live on disk as RON metadata plus `.npy` arrays ([`dataset`], [`npy`]), made by a
//! base model or imported from elsewhere ([`import`]); every
//! random choice comes from a seeded generator ([`rng`]) so a dataset regenerates bit for bit.

pub mod basis;
pub mod coarsen;
pub mod compare;
pub mod dataset;
pub mod ensemble;
mod error;
pub mod fit;
pub mod import;
mod lanes;
mod markers;
pub mod observe;
pub mod output;
/// `.npy` arrays (re-exported from `deform-fs`, where the integrator reads coefficient fields).
pub use deform_fs::npy;
pub mod policy;
pub mod rng;
pub mod rollout;
pub mod solver_data;
pub mod tuning;

pub use dataset::{
    Dataset, DatasetError, DatasetMeta, DatasetSpec, Noise, Split, Trajectory, Variations,
};
pub use ensemble::{EnsembleFit, FittedMember, Member, fit_ensemble, refine_ensemble};
pub use error::LearnError;
pub use fit::{
    EquationErrorFit, EquationErrorOptions, FieldLayout, FitError, Unusable, fit_equation_error,
    fit_equation_error_field,
};
pub use output::{
    Field, OutputError, OutputErrorFit, OutputErrorOptions, Regularisation, StartPrior,
    Termination, face_neighbours, field_of, fit_output_error, fit_output_error_field,
    term_coefficients, with_term_coefficients,
};
