//! Errors of material construction and evaluation.

use thiserror::Error;

/// Why a material cannot be built or evaluated.
#[derive(Debug, Clone, PartialEq, Error)]
#[non_exhaustive]
pub enum MaterialError {
    /// A parameter is out of its valid range; `field` names it as in the configuration.
    #[error("invalid {field} = {value}: {reason}")]
    InvalidParameter {
        /// The parameter's name (e.g. `nu`, `weights[2]`).
        field: String,
        /// The rejected value.
        value: f64,
        /// The valid range.
        reason: &'static str,
    },
    /// A parameter vector has the wrong length.
    #[error("expected {expected} parameters, got {found}")]
    ParameterCount {
        /// Expected length.
        expected: usize,
        /// Given length.
        found: usize,
    },
    /// An ensemble is empty or nested.
    #[error("invalid ensemble: {0}")]
    InvalidEnsemble(&'static str),
    /// The deformation gradient is outside the model's domain (e.g. `det F <= 0` for Neo-Hookean).
    #[error("deformation gradient not admissible for {model}: det F = {det}")]
    NotAdmissible {
        /// The model's name.
        model: &'static str,
        /// `det F`.
        det: f64,
    },
}
