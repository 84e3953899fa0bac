//! Barrier contact for deform (IPC: Li et al. 2020).
//!
//! Contact is one more potential in the incremental potential that Backward Euler's Newton
//! minimises: `B(x) = sum b(d)` over vertex-obstacle distances `d` closer than `dhat`, with
//! the log barrier `b` ([`Barrier`]). Its forces `-grad B` join the elastic forces, its
//! Hessian (projected to positive semidefinite per vertex) joins Newton's matrix, and
//! [`ContactModel::step_bound`] caps the line search so that no trial state interpenetrates.
//!
//! Friction is lagged and smoothed Coulomb friction ([`FrictionSpec`], [`FrictionLag`]):
//! one more potential during a step's Newton solve.
//!
//! This crate knows nothing of meshes or time stepping: positions are flat `3N` slices and
//! the vertices that can touch are given by index.

mod barrier;
mod bvh;
mod contact;
mod distance;
mod friction;
mod jet;
mod obstacle;
mod surface_contact;

pub use barrier::Barrier;
pub use contact::{
    ADAPT_BELOW, ADAPT_MAX, ContactError, ContactHessian, ContactModel, ContactSpec,
    ContactSummary, CouplingBlock, MeshObstacle, STEP_MARGIN, VertexBlock,
};
pub use friction::{FrictionLag, FrictionPair, FrictionSpec};
pub use obstacle::{DistanceJet, Obstacle, ObstacleMotion, Surface};
pub use surface_contact::SurfacePair;
