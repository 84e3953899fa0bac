//! Hyperelastic energy densities for deform.
//!
//! Each model maps a deformation gradient `F` (`Matrix3<f64>`) to an energy density
//! `Psi(F)`, the first Piola-Kirchhoff stress `P = dPsi/dF`, its differential `dP(F; dF)` and
//! the 9x9 tangent `dP/dF` (in the column-major [`vec9`] ordering), without allocation.
//! The [`Material`] trait documents the contract; [`Model`] holds any model behind static
//! dispatch; [`MaterialSpec`] builds one from RON.
//!
//! | model | energy |
//! |---|---|
//! | [`LinearElastic`] | `mu eps:eps + lambda/2 tr(eps)^2` |
//! | [`CorotatedLinear`] | `mu ||F - R||^2 + lambda/2 tr(R^T F - I)^2` |
//! | [`FixedCorotated`] | `mu ||F - R||^2 + lambda/2 (J - 1)^2` |
//! | [`StVenantKirchhoff`] | `mu E:E + lambda/2 tr(E)^2` |
//! | [`NeoHookean`] | `mu/2 (I1 - 3) - mu log J + lambda/2 (log J)^2` |
//! | [`StableNeoHookean`] | Smith et al. 2018, re-parametrised to share the Lame limit |
//! | [`Ensemble`] | `sum_m w_m Psi_m` |
//!
//! All models share the small-strain limit of linear elasticity with their Lame pair, are
//! linear in their parameters (an exact split for learning), and can project their tangent
//! to PSD (analytic eigensystems for the isotropic ones). `docs/theory.md` derives them.
//!
//! ```
//! use deform_materials::{Lame, Material, NeoHookean};
//! use nalgebra::Matrix3;
//!
//! let nh = NeoHookean { lame: Lame::from_young(1e6, 0.4).unwrap() };
//! let f = Matrix3::new(1.1, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0); // 10% stretch in x
//! let p = nh.first_piola(&f);
//! assert!(p[(0, 0)] > 0.0); // tension
//! let (_, tangent) = nh.first_piola_and_tangent(&f, true);
//! assert_eq!(tangent.nrows(), 9);
//! ```

mod error;
mod isotropic;
mod lame;
mod material;
mod model;
mod models;
mod spec;
mod svd3;

pub use error::MaterialError;
pub use lame::{Lame, Moduli};
pub use material::{Material, Matrix9, Vector9, mat3, project_psd, vec9};
pub use model::{Ensemble, Model, Parametric};
pub use models::{
    CorotatedLinear, FixedCorotated, LinearElastic, NeoHookean, StVenantKirchhoff, StableNeoHookean,
};
/// The linear-algebra crate of the API (`Matrix3` arguments), re-exported so that users
/// need no version of their own.
pub use nalgebra;
pub use spec::{EnsembleMember, MaterialSpec};
