//! Errors of the linear solvers; iterative failures keep their statistics.

use thiserror::Error;

use crate::stats::{SetupStats, SolveStats};

/// Why a solve failed.
#[derive(Debug, Clone, PartialEq, Error)]
#[non_exhaustive]
pub enum SolverError {
    /// A vector or matrix has the wrong size.
    #[error("{what} has length {found}, expected {expected}")]
    DimensionMismatch {
        /// Which argument.
        what: &'static str,
        /// Expected length.
        expected: usize,
        /// Actual length.
        found: usize,
    },
    /// An input holds NaN or infinity.
    #[error("{what} has a non-finite entry at index {index}")]
    NonFinite {
        /// Which argument.
        what: &'static str,
        /// First offending index.
        index: usize,
    },
    /// CG met a direction of non-positive curvature `p^T A p <= 0`: the matrix is not SPD.
    #[error("breakdown after {} iterations: p^T A p = {curvature:e} (the matrix is not positive definite)", stats.iterations)]
    Breakdown {
        /// The curvature found.
        curvature: f64,
        /// Statistics up to the breakdown.
        stats: Box<SolveStats>,
    },
    /// The tolerance was not reached within the iteration cap (or the iteration diverged).
    #[error("not converged after {} iterations: residual {:e}", stats.iterations, stats.final_residual())]
    NotConverged {
        /// Statistics of the failed solve.
        stats: Box<SolveStats>,
    },
    /// A factorisation or preconditioner set-up met a non-positive pivot.
    #[error("not positive definite: pivot {pivot} is {}", pivot_value(*.value))]
    NotPositiveDefinite {
        /// Row of the failing pivot.
        pivot: usize,
        /// Its value (NaN when the factorisation does not report it).
        value: f64,
        /// What the failed set-up spent, when it is large enough to count (a sparse
        /// factorisation: its whole flop count, as faer does not say how far it got).
        spent: Option<Box<SetupStats>>,
    },
    /// The operator cannot provide what this solver or preconditioner needs.
    #[error("unsupported: {0}")]
    Unsupported(&'static str),
    /// Memory for a factorisation could not be allocated.
    #[error("out of memory in the factorisation")]
    OutOfMemory,
    /// `solve` was called before `factorize`.
    #[error("solve called before factorize")]
    NotFactorized,
    /// A configuration value is out of range.
    #[error("invalid {field} = {value}: {reason}")]
    InvalidParameter {
        /// The field.
        field: &'static str,
        /// The rejected value.
        value: f64,
        /// The valid range.
        reason: &'static str,
    },
}

impl SolverError {
    /// The statistics of the failed solve, when it got as far as iterating (breakdown, not
    /// converged): its work is spent even though its result is not used.
    pub fn stats(&self) -> Option<&SolveStats> {
        match self {
            Self::Breakdown { stats, .. } | Self::NotConverged { stats } => Some(stats),
            _ => None,
        }
    }

    /// What a failed set-up spent before failing (see `NotPositiveDefinite::spent`).
    pub fn spent(&self) -> Option<&SetupStats> {
        match self {
            Self::NotPositiveDefinite { spent, .. } => spent.as_deref(),
            _ => None,
        }
    }

    /// The failure says the matrix is not positive definite (a non-positive pivot, or CG's
    /// non-positive curvature).
    pub fn is_indefinite(&self) -> bool {
        matches!(
            self,
            Self::Breakdown { .. } | Self::NotPositiveDefinite { .. }
        )
    }
}

/// Checks length and finiteness of a vector argument.
pub(crate) fn check_vector(
    what: &'static str,
    v: &[f64],
    expected: usize,
) -> Result<(), SolverError> {
    if v.len() != expected {
        return Err(SolverError::DimensionMismatch {
            what,
            expected,
            found: v.len(),
        });
    }
    match v.iter().position(|x| !x.is_finite()) {
        Some(index) => Err(SolverError::NonFinite { what, index }),
        None => Ok(()),
    }
}

/// A pivot's value for messages: "not positive" when it is unknown.
fn pivot_value(value: f64) -> String {
    if value.is_nan() {
        "not positive".to_owned()
    } else {
        format!("{value:e}")
    }
}
