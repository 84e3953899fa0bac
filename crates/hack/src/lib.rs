//! No code. This crate pins the features of dependencies that the runner (`xtask`), the
//! Python module (`deform-python`) and the test build share, so that cargo builds each of
//! them once for all three; see its `Cargo.toml`.
