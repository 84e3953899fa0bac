//! The one preconditioned conjugate-gradient loop. [`crate::Iterative`]'s CG and PCG run it
//! with their preconditioners; the integrator's secant rounds run it preconditioned by a
//! direct solver's factor of another matrix. One loop, so one meaning of each
//! [`Termination`]: a non-finite residual or curvature is `Diverged`, a finite curvature
//! that is not positive is `Breakdown`.

use crate::SolverError;
use crate::operator::LinearOperator;
use crate::stats::{SolveStats, Termination};
use crate::vector::{dot, norm, update_and_norm, update_from};

/// What one application of a preconditioner cost.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[non_exhaustive]
pub struct Applied {
    /// Its flops.
    pub flops: u64,
    /// Those of them in sequential sweeps over a sparse triangle (IC(0), SSOR).
    pub sweep_flops: u64,
}

impl Applied {
    /// An application of `flops` flops, `sweep_flops` of them in sequential sweeps.
    pub fn new(flops: u64, sweep_flops: u64) -> Self {
        Self { flops, sweep_flops }
    }
}

/// A preconditioner for [`pcg`]: writes `z = M^-1 r` and says what it cost, or fails.
pub type Precondition<'a> = dyn FnMut(&[f64], &mut [f64]) -> Result<Applied, SolverError> + 'a;

/// When [`pcg`] stops.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub struct Stop {
    /// Converged once the residual's norm is at most this.
    pub threshold: f64,
    /// Iterations at most.
    pub max_iterations: usize,
}

impl Stop {
    /// Converged at `threshold`, after `max_iterations` at most.
    pub fn new(threshold: f64, max_iterations: usize) -> Self {
        Self {
            threshold,
            max_iterations,
        }
    }
}

/// Conjugate gradients on `a x = b` from `x`, preconditioned by `precondition` (`z = M^-1 r`,
/// fallible), until [`Stop`] says. Adds to `stats` the residuals, iterations, products and
/// flops (per iteration the product, the preconditioner's [`Applied`] cost and `12 n` for
/// the dots and updates) and sets its termination: `Converged`, `MaxIterations`,
/// `Breakdown` (a curvature `p^T A p` that is finite but not positive: `a` or the
/// preconditioner is not positive definite) or `Diverged` (a non-finite residual or
/// curvature). Returns the last curvature (NaN before the first iteration), which a
/// breakdown error reports. The bits of `x` do not depend on the number of threads.
///
/// # Errors
/// The preconditioner's own error, returned as it is (`stats` then holds what was done).
pub fn pcg(
    a: &dyn LinearOperator,
    b: &[f64],
    x: &mut [f64],
    precondition: &mut Precondition<'_>,
    stop: Stop,
    stats: &mut SolveStats,
) -> Result<f64, SolverError> {
    let n = b.len();
    let (mut r, mut z, mut ap) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
    a.apply(x, &mut r);
    stats.matvecs += 1;
    stats.flops += a.apply_flops() + n as u64;
    update_from(&mut r, b, |ri, bi| *ri = bi - *ri);
    let rn = norm(&r);
    stats.residuals.push(rn);
    let mut curvature = f64::NAN;
    if rn <= stop.threshold {
        stats.termination = Termination::Converged;
        return Ok(curvature);
    }
    if stop.max_iterations == 0 {
        stats.termination = Termination::MaxIterations;
        return Ok(curvature);
    }
    let mut applied = precondition(&r, &mut z)?;
    let mut p = z.clone();
    let mut rz = dot(&r, &z);
    loop {
        a.apply(&p, &mut ap);
        stats.matvecs += 1;
        stats.flops += a.apply_flops() + applied.flops + 12 * n as u64;
        stats.sweep_flops += applied.sweep_flops;
        curvature = dot(&p, &ap);
        if !(curvature > 0.0) {
            stats.termination = if curvature.is_finite() {
                Termination::Breakdown
            } else {
                Termination::Diverged
            };
            return Ok(curvature);
        }
        let rn = update_and_norm(x, &mut r, rz / curvature, &p, &ap);
        stats.iterations += 1;
        stats.residuals.push(rn);
        stats.termination = if !rn.is_finite() {
            Termination::Diverged
        } else if rn <= stop.threshold {
            Termination::Converged
        } else if stats.iterations >= stop.max_iterations {
            // No preconditioner application for a direction that will not be taken.
            Termination::MaxIterations
        } else {
            applied = precondition(&r, &mut z)?;
            let rz_new = dot(&r, &z);
            let beta = rz_new / rz;
            rz = rz_new;
            update_from(&mut p, &z, |pi, zi| *pi = zi + beta * *pi);
            continue;
        };
        return Ok(curvature);
    }
}

/// The error a [`pcg`] run that did not converge is reported as: `Breakdown` with its
/// curvature, or `NotConverged` (at its cap, or diverged), each carrying the statistics.
pub fn pcg_error(stats: SolveStats, curvature: f64) -> SolverError {
    match stats.termination {
        Termination::Breakdown => SolverError::Breakdown {
            curvature,
            stats: Box::new(stats),
        },
        _ => SolverError::NotConverged {
            stats: Box::new(stats),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sprs::{CsMat, TriMat};

    /// A tridiagonal matrix with diagonal `d` and off-diagonal -1.
    fn tridiagonal(n: usize, d: f64) -> CsMat<f64> {
        let mut t = TriMat::new((n, n));
        for i in 0..n {
            t.add_triplet(i, i, d);
            if i + 1 < n {
                t.add_triplet(i, i + 1, -1.0);
                t.add_triplet(i + 1, i, -1.0);
            }
        }
        t.to_csr()
    }

    fn identity(
        calls: &mut usize,
    ) -> impl FnMut(&[f64], &mut [f64]) -> Result<Applied, SolverError> + '_ {
        move |r, z| {
            *calls += 1;
            z.copy_from_slice(r);
            Ok(Applied::new(0, 0))
        }
    }

    fn run(a: &CsMat<f64>, stop: Stop, calls: &mut usize) -> (SolveStats, Vec<f64>, f64) {
        let b: Vec<f64> = (0..a.rows())
            .map(|i| (i as f64 * 0.3).sin() + 0.5)
            .collect();
        let mut x = vec![0.0; a.rows()];
        let mut stats = SolveStats::new("cg".to_owned(), norm(&b));
        let c = pcg(a, &b, &mut x, &mut identity(calls), stop, &mut stats).unwrap();
        (stats, x, c)
    }

    /// SPD: converges to the solution; a cap stops it without a wasted preconditioner
    /// application; an indefinite matrix breaks down, a NaN diverges.
    #[test]
    fn one_loop_one_meaning_of_each_termination() {
        let a = tridiagonal(40, 2.5);
        let mut calls = 0;
        let (stats, x, _) = run(&a, Stop::new(1e-12, 100), &mut calls);
        assert_eq!(stats.termination, Termination::Converged);
        let mut ax = vec![0.0; 40];
        a.apply(&x, &mut ax);
        let b: Vec<f64> = (0..40).map(|i| (i as f64 * 0.3).sin() + 0.5).collect();
        let error: f64 = ax.iter().zip(&b).map(|(p, q)| (p - q).powi(2)).sum();
        assert!(error.sqrt() <= 1e-12);
        assert_eq!(
            calls, stats.iterations,
            "one application per direction taken"
        );
        let mut calls = 0;
        let (stats, _, _) = run(&a, Stop::new(0.0, 3), &mut calls);
        assert_eq!(
            (stats.termination, stats.iterations, calls),
            (Termination::MaxIterations, 3, 3)
        );
        let (stats, _, curvature) = run(&tridiagonal(40, -2.5), Stop::new(1e-12, 100), &mut 0);
        assert_eq!(stats.termination, Termination::Breakdown);
        assert!(curvature <= 0.0 && curvature.is_finite());
        let (stats, _, _) = run(&tridiagonal(40, f64::NAN), Stop::new(1e-12, 100), &mut 0);
        assert_eq!(stats.termination, Termination::Diverged);
        let e = pcg_error(stats, f64::NAN);
        assert!(matches!(e, SolverError::NotConverged { .. }), "{e}");
    }

    /// A failing preconditioner's error comes back as it is.
    #[test]
    fn a_failing_preconditioner_ends_the_loop_with_its_error() {
        let a = tridiagonal(10, 3.0);
        let b = vec![1.0; 10];
        let mut x = vec![0.0; 10];
        let mut stats = SolveStats::new("cg".to_owned(), norm(&b));
        let mut failing = |_: &[f64], _: &mut [f64]| Err(SolverError::NotFactorized);
        let e = pcg(
            &a,
            &b,
            &mut x,
            &mut failing,
            Stop::new(1e-12, 10),
            &mut stats,
        );
        assert!(matches!(e, Err(SolverError::NotFactorized)));
    }
}
