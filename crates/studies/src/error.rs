//! Why a report could not be rendered or written ([`RenderError`]). Its own module, so that
//! rendering ([`crate::render`]) and drawing ([`crate::plot`]) both use it.

use std::path::PathBuf;

/// What rendering returns.
pub type Result<T, E = RenderError> = std::result::Result<T, E>;

/// Why a report could not be rendered or written.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RenderError {
    /// Formatting the markdown (it is written into a string, so not expected).
    #[error("formatting the report: {0}")]
    Format(#[from] std::fmt::Error),
    /// Drawing a plot.
    #[error("plot {title}: {reason}")]
    Plot {
        /// The plot's title.
        title: String,
        /// The drawing backend's message.
        reason: String,
    },
    /// Writing a file.
    #[error("writing {}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// Writing `report.md`.
    #[error(transparent)]
    Write(#[from] deform_fs::WriteError),
    /// Writing a material as RON.
    #[error("writing a material as RON: {0}")]
    Ron(#[from] ron::Error),
}
