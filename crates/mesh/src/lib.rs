//! Linear tetrahedral meshes for the deform finite element workspace.
//!
//! A [`TetMesh`] holds rest positions and tetrahedra, validated once at construction,
//! together with what every later stage needs from the rest shape: `Dm^-1`, rest volumes,
//! shape-function gradients and lumped or consistent mass. Around it:
//!
//! - [`topology`]: boundary faces, edges, vertex-to-element adjacency and the block sparsity
//!   pattern of the `3N x 3N` stiffness matrix,
//! - [`select`]: vertex selectors for boundary conditions,
//! - [`generate`]: deterministic box and beam generators (5- or 6-tet cube splits),
//! - [`quality`]: dihedral angles, aspect ratios, volume range, inverted count,
//! - [`io`]: Gmsh `.msh` (2.2 and 4.1, ASCII and binary), TetGen `.node`/`.ele`,
//!   VTK `.vtu` + `.pvd` for ParaView, and surface `.obj`, all written atomically,
//! - [`embed`]: points located in a mesh (element and barycentric weights), to carry a fine
//!   model's states onto a coarse mesh,
//! - [`memory`]: what a mesh and its simulation need, refused when the machine lacks it,
//! - [`Surface`]: triangle surfaces (a mesh's boundary, or read by [`io::read_surface`]),
//!   as contact's obstacles are given.
//!
//! ```
//! use deform_mesh::generate::{BoxGrid, Split};
//!
//! let mesh = BoxGrid::beam(2).build().unwrap(); // the n = 2 member of the benchmark beam family
//! assert_eq!(mesh.num_tets(), 6 * 8 * 2 * 2);
//! let volume: f64 = mesh.volumes().iter().sum();
//! assert!((volume - 0.25 * 0.25).abs() < 1e-12);
//! let mass = mesh.lumped_mass(1000.0);
//! assert!((mass.iter().sum::<f64>() - 1000.0 * volume).abs() < 1e-9);
//! # let _ = Split::Six;
//! ```

pub mod embed;
pub mod error;
pub mod generate;
mod info;
pub mod io;
mod mass;
pub mod memory;
mod mesh;
pub mod quality;
pub mod select;
mod surface;
pub mod topology;

pub use error::MeshError;
pub use info::MeshInfo;
pub use mass::ConsistentMass;
pub use mesh::{BuildReport, MeshOptions, TetMesh, Unreferenced};
pub use surface::Surface;

/// Re-exported so users build positions with the same nalgebra version.
pub use nalgebra::Vector3;
