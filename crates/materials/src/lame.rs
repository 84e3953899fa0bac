//! Elastic moduli: the Lame pair and Young's modulus with Poisson's ratio.

use serde::{Deserialize, Serialize};

use crate::MaterialError;

/// The Lame pair `(mu, lambda)`: shear modulus and Lame's first parameter, in Pa.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Lame {
    /// Shear modulus `mu > 0`.
    pub mu: f64,
    /// First Lame parameter, `3 lambda + 2 mu > 0` (positive bulk modulus).
    pub lambda: f64,
}

impl Lame {
    /// Validated Lame pair.
    ///
    /// # Errors
    /// [`MaterialError::InvalidParameter`] naming `mu` or `lambda`.
    pub fn try_new(mu: f64, lambda: f64) -> Result<Self, MaterialError> {
        if !(mu.is_finite() && mu > 0.0) {
            return Err(invalid("mu", mu, "must be finite and > 0"));
        }
        if !(lambda.is_finite() && 3.0 * lambda + 2.0 * mu > 0.0) {
            return Err(invalid(
                "lambda",
                lambda,
                "must be finite with 3 lambda + 2 mu > 0",
            ));
        }
        Ok(Self { mu, lambda })
    }

    /// The Lame pair of an ensemble member, which may carry volume only: `mu >= 0` and
    /// `3 lambda + 2 mu > 0` (so `mu = 0` needs `lambda > 0`). The ensemble as a whole still
    /// has a positive shear modulus wherever another member carries one.
    ///
    /// # Errors
    /// [`MaterialError::InvalidParameter`] naming `mu` or `lambda`.
    pub fn try_member(mu: f64, lambda: f64) -> Result<Self, MaterialError> {
        if mu == 0.0 && lambda.is_finite() && lambda > 0.0 {
            return Ok(Self { mu, lambda });
        }
        Self::try_new(mu, lambda)
    }

    /// From Young's modulus `E > 0` and Poisson's ratio `-1 < nu < 0.5`:
    /// `mu = E / (2 (1 + nu))`, `lambda = E nu / ((1 + nu)(1 - 2 nu))`.
    ///
    /// # Errors
    /// [`MaterialError::InvalidParameter`] naming `E` or `nu`.
    pub fn from_young(e: f64, nu: f64) -> Result<Self, MaterialError> {
        if !(e.is_finite() && e > 0.0) {
            return Err(invalid("E", e, "must be finite and > 0"));
        }
        if !(nu.is_finite() && nu > -1.0 && nu < 0.5) {
            return Err(invalid("nu", nu, "must be finite with -1 < nu < 0.5"));
        }
        Ok(Self {
            mu: e / (2.0 * (1.0 + nu)),
            lambda: e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)),
        })
    }

    /// Young's modulus and Poisson's ratio `(E, nu)`.
    pub fn to_young(&self) -> (f64, f64) {
        let (mu, lambda) = (self.mu, self.lambda);
        (
            mu * (3.0 * lambda + 2.0 * mu) / (lambda + mu),
            lambda / (2.0 * (lambda + mu)),
        )
    }

    /// Bulk modulus `lambda + 2 mu / 3`.
    pub fn bulk(&self) -> f64 {
        self.lambda + 2.0 * self.mu / 3.0
    }
}

pub(crate) fn invalid(field: &str, value: f64, reason: &'static str) -> MaterialError {
    MaterialError::InvalidParameter {
        field: field.to_owned(),
        value,
        reason,
    }
}

/// Moduli as a configuration states them.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub enum Moduli {
    /// Young's modulus `e` (Pa) and Poisson's ratio `nu`.
    Young {
        /// Young's modulus.
        e: f64,
        /// Poisson's ratio.
        nu: f64,
    },
    /// The Lame pair directly.
    Lame {
        /// Shear modulus.
        mu: f64,
        /// First Lame parameter.
        lambda: f64,
    },
}

impl Moduli {
    /// The validated Lame pair.
    ///
    /// # Errors
    /// [`MaterialError::InvalidParameter`] naming the field.
    pub fn to_lame(&self) -> Result<Lame, MaterialError> {
        match *self {
            Moduli::Young { e, nu } => Lame::from_young(e, nu),
            Moduli::Lame { mu, lambda } => Lame::try_new(mu, lambda),
        }
    }

    /// The validated Lame pair of an ensemble member ([`Lame::try_member`]).
    ///
    /// # Errors
    /// [`MaterialError::InvalidParameter`] naming the field.
    pub fn to_member_lame(&self) -> Result<Lame, MaterialError> {
        match *self {
            Moduli::Young { e, nu } => Lame::from_young(e, nu),
            Moduli::Lame { mu, lambda } => Lame::try_member(mu, lambda),
        }
    }
}
