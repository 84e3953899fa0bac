//! Shared helpers of deform's workspace-level tests.

use std::path::{Path, PathBuf};

/// Path of a file under the workspace's `assets/`.
pub fn asset(relative: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../assets")
        .join(relative)
}

/// Path of a test fixture of the mesh crate.
pub fn mesh_fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../crates/mesh/tests/data")
        .join(name)
}

/// The README's Rust blocks, run as doc tests (`xtask/tests/guide.rs` runs its other blocks).
#[doc = include_str!("../../README.md")]
pub mod readme {}

/// The guide's pages: their Rust blocks run as doc tests.
pub mod guide {
    #[doc = include_str!("../../docs/guide/01-simulate.md")]
    pub mod simulate {}
    #[doc = include_str!("../../docs/guide/03-fit-material.md")]
    pub mod fit_material {}
}
