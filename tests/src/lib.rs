//! Shared helpers of the workspace-level tests (asset paths).
