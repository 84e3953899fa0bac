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
