//! Weighted Jacobi iteration and (preconditioned) conjugate gradients.

use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::bsr3::fast_operator;
use crate::error::check_vector;
use crate::operator::{LinearOperator, positive_diagonal};
use crate::pcg::{Applied, Stop, pcg, pcg_error};
use crate::precond::{Preconditioner, PreconditionerSpec};
use crate::stats::{SetupStats, SolveStats, Termination};
use crate::vector::norm;
use crate::{LinearSolver, SolverError};

/// Stopping rule: converged when `||b - A x|| <= max(abs, rel ||b||)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
#[non_exhaustive]
pub struct Tolerance {
    /// Relative tolerance on the residual norm.
    pub rel: f64,
    /// Absolute tolerance on the residual norm.
    pub abs: f64,
    /// Iteration cap.
    pub max_iterations: usize,
}

deform_setters::setters!(Tolerance {
    rel: f64,
    abs: f64,
    max_iterations: usize
});

impl Default for Tolerance {
    fn default() -> Self {
        Self {
            rel: 1e-8,
            abs: 0.0,
            max_iterations: 10_000,
        }
    }
}

impl Tolerance {
    /// Validates the fields.
    ///
    /// # Errors
    /// [`SolverError::InvalidParameter`] naming `rel`, `abs` or `max_iterations`.
    pub fn validate(&self) -> Result<(), SolverError> {
        if !(self.rel.is_finite() && self.rel >= 0.0) {
            return Err(SolverError::InvalidParameter {
                field: "rel",
                value: self.rel,
                reason: "must be finite and >= 0",
            });
        }
        if !(self.abs.is_finite() && self.abs >= 0.0) {
            return Err(SolverError::InvalidParameter {
                field: "abs",
                value: self.abs,
                reason: "must be finite and >= 0",
            });
        }
        if self.rel == 0.0 && self.abs == 0.0 {
            return Err(SolverError::InvalidParameter {
                field: "rel",
                value: 0.0,
                reason: "rel and abs cannot both be 0",
            });
        }
        if self.max_iterations == 0 {
            return Err(SolverError::InvalidParameter {
                field: "max_iterations",
                value: 0.0,
                reason: "must be at least 1",
            });
        }
        Ok(())
    }

    fn threshold(&self, rhs_norm: f64) -> f64 {
        self.abs.max(self.rel * rhs_norm)
    }
}

/// Which iteration an [`Iterative`] solver runs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Method {
    /// `x += omega D^-1 (b - A x)`.
    Jacobi {
        /// Relaxation factor in (0, 2); 2/3 is the classic smoother choice.
        omega: f64,
    },
    /// Conjugate gradients with a preconditioner (`Identity` gives plain CG).
    Pcg(PreconditionerSpec),
}

/// An iterative solver: weighted Jacobi, CG or PCG.
#[derive(Debug)]
pub struct Iterative {
    method: Method,
    tolerance: Tolerance,
    precond: Option<Preconditioner>,
    /// The next `factorize` recomputes a stale preconditioner whatever its age.
    refresh: bool,
    /// Jacobi's inverse diagonal, set by `factorize`.
    inv_diag: Vec<f64>,
    /// Node positions for a stale-Cholesky factor's ordering.
    coordinates: Option<Vec<[f64; 3]>>,
    /// Solves stop at or below this residual norm whatever the tolerance asks (0: none).
    floor: f64,
}

impl Iterative {
    /// A validated solver.
    ///
    /// # Errors
    /// [`SolverError::InvalidParameter`] for a bad tolerance or relaxation factor.
    pub fn try_new(method: Method, tolerance: Tolerance) -> Result<Self, SolverError> {
        tolerance.validate()?;
        let omega = match method {
            Method::Jacobi { omega } | Method::Pcg(PreconditionerSpec::Ssor { omega }) => {
                Some(omega)
            }
            Method::Pcg(_) => None,
        };
        if let Some(omega) = omega
            && !(omega > 0.0 && omega < 2.0)
        {
            return Err(SolverError::InvalidParameter {
                field: "omega",
                value: omega,
                reason: "must be in (0, 2)",
            });
        }
        if let Method::Pcg(PreconditionerSpec::Amg {
            theta, smoother, ..
        }) = method
        {
            crate::amg::validate(theta, smoother)?;
        }
        Ok(Self {
            method,
            tolerance,
            precond: None,
            refresh: false,
            inv_diag: Vec::new(),
            coordinates: None,
            floor: 0.0,
        })
    }

    /// The residual norm a solve of a right-hand side of norm `rhs_norm` stops at: the
    /// tolerance's, or the residual floor when that is larger.
    fn threshold(&self, rhs_norm: f64) -> f64 {
        self.tolerance.threshold(rhs_norm).max(self.floor)
    }

    /// The stopping rule.
    pub fn tolerance(&self) -> Tolerance {
        self.tolerance
    }

    /// Replaces the stopping rule (e.g. an adaptive forcing term per Newton iteration).
    ///
    /// # Errors
    /// As [`Tolerance::validate`].
    pub fn set_tolerance(&mut self, tolerance: Tolerance) -> Result<(), SolverError> {
        tolerance.validate()?;
        self.tolerance = tolerance;
        Ok(())
    }

    /// Makes the next `factorize` recompute a stale-Cholesky preconditioner (e.g. when PCG
    /// iterations grow); other preconditioners are recomputed every time anyway.
    pub fn refresh_preconditioner(&mut self) {
        self.refresh = true;
    }

    /// How many `factorize` calls the current stale-Cholesky factor has been reused for, or
    /// the current AMG hierarchy refreshed for (`None` for other preconditioners or before
    /// the first set-up).
    pub fn preconditioner_age(&self) -> Option<usize> {
        match self.precond {
            Some(Preconditioner::Cholesky { age, .. } | Preconditioner::Amg { age, .. }) => {
                Some(age)
            }
            _ => None,
        }
    }

    /// The diagonal shift IC(0) needed to stay positive (0 for other preconditioners).
    pub fn preconditioner_shift(&self) -> f64 {
        self.precond.as_ref().map_or(0.0, Preconditioner::shift)
    }

    /// Rows of each level of the current AMG hierarchy, finest first (empty for other
    /// preconditioners or before the first set-up).
    pub fn amg_levels(&self) -> Vec<usize> {
        match &self.precond {
            Some(Preconditioner::Amg { amg, .. }) => amg.level_sizes(),
            _ => Vec::new(),
        }
    }

    fn jacobi(
        &self,
        a: &dyn LinearOperator,
        b: &[f64],
        x: &mut [f64],
        omega: f64,
        stats: &mut SolveStats,
    ) {
        let n = b.len();
        let mut r = vec![0.0; n];
        let threshold = self.threshold(stats.rhs_norm);
        loop {
            a.apply(x, &mut r);
            stats.matvecs += 1;
            stats.flops += a.apply_flops() + 2 * n as u64;
            for (ri, bi) in r.iter_mut().zip(b) {
                *ri = bi - *ri;
            }
            let rn = norm(&r);
            stats.residuals.push(rn);
            if !rn.is_finite() {
                stats.termination = Termination::Diverged;
                return;
            }
            if rn <= threshold {
                stats.termination = Termination::Converged;
                return;
            }
            if stats.iterations == self.tolerance.max_iterations {
                stats.termination = Termination::MaxIterations;
                return;
            }
            for ((xi, ri), d) in x.iter_mut().zip(&r).zip(&self.inv_diag) {
                *xi += omega * d * ri;
            }
            stats.flops += 3 * n as u64;
            stats.iterations += 1;
        }
    }
}

impl LinearSolver for Iterative {
    fn set_coordinates(&mut self, coordinates: Option<&[[f64; 3]]>) {
        self.coordinates = coordinates.map(<[[f64; 3]]>::to_vec);
    }

    fn name(&self) -> String {
        match self.method {
            Method::Jacobi { omega } => format!("jacobi(omega={omega})"),
            Method::Pcg(PreconditionerSpec::Identity) => "cg".to_owned(),
            Method::Pcg(p) => format!("pcg({p:?})"),
        }
    }

    fn set_residual_floor(&mut self, floor: f64) {
        self.floor = if floor.is_finite() {
            floor.max(0.0)
        } else {
            0.0
        };
    }

    fn set_relative_tolerance(&mut self, rel: f64) -> Result<(), SolverError> {
        if !(rel > 0.0 && rel < 1.0) {
            return Err(SolverError::InvalidParameter {
                field: "rel",
                value: rel,
                reason: "must be in (0, 1)",
            });
        }
        self.set_tolerance(Tolerance {
            rel,
            ..self.tolerance
        })
    }

    fn refresh(&mut self) {
        self.refresh_preconditioner();
    }

    fn factorize(&mut self, a: &dyn LinearOperator) -> Result<SetupStats, SolverError> {
        let start = Instant::now();
        let mut setup = SetupStats::default();
        match self.method {
            Method::Jacobi { .. } => {
                self.inv_diag = positive_diagonal(a)?.iter().map(|x| 1.0 / x).collect();
                setup.flops = a.nrows() as u64;
            }
            Method::Pcg(spec) => {
                let refresh = std::mem::take(&mut self.refresh);
                if let (PreconditionerSpec::StaleCholesky { max_age, .. }, false) = (spec, refresh)
                    && let Some(Preconditioner::Cholesky { factor, age }) = &mut self.precond
                    && *age < max_age
                    && factor.nrows() == Some(a.nrows())
                {
                    *age += 1;
                    setup.reused = true;
                } else if let (PreconditionerSpec::StaleCholesky { .. }, Some(m)) =
                    (spec, self.precond.as_mut())
                    && let Preconditioner::Cholesky { factor, age } = m
                    && factor.nrows() == Some(a.nrows())
                {
                    // Refactorise in place: the symbolic analysis of the pattern is reused.
                    match factor.factorize(a) {
                        Ok(stats) => {
                            *age = 0;
                            setup.analyzed = stats.analyzed;
                            setup.flops = stats.flops;
                            setup.factor_nnz = factor.factor_nnz();
                        }
                        Err(e) => {
                            self.precond = None;
                            return Err(e);
                        }
                    }
                } else if let (PreconditionerSpec::Amg { max_age, .. }, false) = (spec, refresh)
                    && let Some(Preconditioner::Amg { amg, age }) = &mut self.precond
                    && *age < max_age
                    && amg.nrows() == a.nrows()
                {
                    let csr = a.csr().ok_or(SolverError::Unsupported(
                        "AMG needs an assembled CSR matrix",
                    ))?;
                    match amg.refresh(csr) {
                        Ok(flops) => {
                            *age += 1;
                            setup.reused = true;
                            setup.flops = flops;
                        }
                        Err(e) => {
                            self.precond = None;
                            return Err(e);
                        }
                    }
                } else {
                    // Drop the old set-up first: a stale factor can be large.
                    self.precond = None;
                    let (m, flops) = Preconditioner::setup(&spec, a, self.coordinates.as_deref())?;
                    setup.flops = flops;
                    if let Preconditioner::Cholesky { factor, .. } = &m {
                        setup.factor_nnz = factor.factor_nnz();
                    }
                    self.precond = Some(m);
                }
            }
        }
        setup.seconds = start.elapsed().as_secs_f64();
        Ok(setup)
    }

    fn solve(
        &mut self,
        a: &dyn LinearOperator,
        b: &[f64],
        x: &mut [f64],
    ) -> Result<SolveStats, SolverError> {
        let n = a.nrows();
        check_vector("b", b, n)?;
        check_vector("x", x, n)?;
        let start = Instant::now();
        // Large blocked matrices are multiplied in a 3x3 block copy (same results, about half
        // the memory traffic); the copy costs about one product.
        let blocked = fast_operator(a);
        let a: &dyn LinearOperator = match &blocked {
            Some(bsr) => bsr,
            None => a,
        };
        let mut stats = SolveStats::new(self.name(), norm(b));
        let mut curvature = f64::NAN;
        match self.method {
            Method::Jacobi { omega } => {
                if self.inv_diag.len() != n {
                    return Err(SolverError::NotFactorized);
                }
                self.jacobi(a, b, x, omega, &mut stats);
            }
            Method::Pcg(_) => {
                let m = self.precond.as_ref().ok_or(SolverError::NotFactorized)?;
                if m.needs_csr() && a.csr().is_none() {
                    return Err(SolverError::Unsupported(
                        "this preconditioner needs an assembled CSR matrix",
                    ));
                }
                let stop = Stop::new(
                    self.threshold(stats.rhs_norm),
                    self.tolerance.max_iterations,
                );
                let cost = Applied::new(m.flops(a, n), m.sweep_flops(a, n));
                let mut precondition = |r: &[f64], z: &mut [f64]| {
                    m.apply(a, r, z);
                    Ok(cost)
                };
                curvature = pcg(a, b, x, &mut precondition, stop, &mut stats)?;
            }
        }
        stats.seconds = start.elapsed().as_secs_f64();
        match stats.termination {
            Termination::Converged => Ok(stats),
            _ => Err(pcg_error(stats, curvature)),
        }
    }
}
