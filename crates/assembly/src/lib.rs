//! Assembly of linear tetrahedral FEM: total elastic energy, elastic forces, force
//! differentials (matrix-free), the sparse stiffness matrix `K = d2E/dx2` on a pattern built
//! once per mesh, mass and Rayleigh damping, parameter gradients, and Dirichlet conditions by
//! elimination.
//!
//! Sign conventions (docs/theory.md): `E(x) = sum_e W_e Psi(F_e)`, elastic forces
//! `f = -dE/dx`, stiffness `K = d2E/dx2 = -df/dx` (positive near rest), damping forces
//! `-(alpha M + gamma K) v`. Positions are flat `3N` slices `[x0, y0, z0, x1, ...]`.
//!
//! Everything runs in parallel over elements (rayon) and gives bit-identical results for any
//! number of threads: elements write their own buffers, and fixed-order gathers sum them.

mod assembly;
mod differential;
mod dof;
mod error;
mod field;
mod kernel;
mod mass;
mod matrix;
mod params;

pub use assembly::{Assembly, Outputs, StiffnessShift, Tangent};
pub use differential::ElementTangents;
pub use dof::{DofMap, ReducedMatrix};
pub use error::AssemblyError;
pub use field::MaterialField;
pub use mass::Mass;
pub use matrix::StiffnessMatrix;
pub use params::{Grouping, TermJacobian};
