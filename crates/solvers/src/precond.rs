//! Preconditioners for PCG: diagonal (Jacobi), 3x3 block Jacobi, SSOR, IC(0), a stale
//! sparse Cholesky factor and smoothed-aggregation algebraic multigrid.

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use crate::amg::{Amg, AmgSmoother};

use crate::direct::{Cholesky, Indefinite, Precision};
use crate::ic0::{self, Ic0};
use crate::operator::{LinearOperator, positive_diagonal};
use crate::ordering::Ordering;
use crate::vector::update_from2;
use crate::{LinearSolver, SolverError};

/// Which preconditioner PCG uses.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub enum PreconditionerSpec {
    /// None (plain CG).
    Identity,
    /// `diag(A)^-1`.
    Jacobi,
    /// The inverse of each vertex's 3x3 diagonal block.
    BlockJacobi,
    /// Symmetric successive over-relaxation with relaxation `omega` in (0, 2). Needs CSR.
    Ssor {
        /// Relaxation factor.
        omega: f64,
    },
    /// Incomplete Cholesky with zero fill on the pattern of `A`. Needs CSR. A non-positive
    /// pivot is handled by retrying with a diagonal shift `A + s diag(A)`, `s = 1e-3, 1e-2, ...`.
    Ic0,
    /// The exact Cholesky factor of an earlier matrix (an earlier Newton iteration or time
    /// step), kept for up to `max_age` further `factorize` calls before it is recomputed.
    /// `max_age: 0` refactorises every time (PCG then converges in one iteration). Needs CSR.
    StaleCholesky {
        /// How many `factorize` calls may reuse one factor.
        max_age: usize,
        /// Fill-reducing ordering of the factorisation.
        #[serde(default)]
        ordering: Ordering,
        /// `Mixed`: the factor is computed and applied in single precision (half the
        /// memory traffic per PCG iteration); PCG itself stays in double, so the solution's
        /// accuracy is the same.
        #[serde(default)]
        precision: Precision,
    },
    /// Smoothed-aggregation algebraic multigrid with the rigid-body modes of the nodes'
    /// positions (given by `LinearSolver::set_coordinates`; translations only without them)
    /// as near-null space; one V-cycle per application. Needs CSR.
    Amg {
        /// Strength-of-connection threshold in `[0, 1)` on the node blocks' Frobenius norms;
        /// 0 (the default) makes every nonzero block strong.
        #[serde(default)]
        theta: f64,
        /// The smoother on every level.
        #[serde(default)]
        smoother: AmgSmoother,
        /// How many further `factorize` calls keep the hierarchy (aggregates and
        /// prolongators) and only recompute its operators from the new matrix; 0 rebuilds
        /// it every time.
        #[serde(default)]
        max_age: usize,
    },
}

/// A set-up preconditioner: `z = M^-1 r`.
#[derive(Debug)]
pub(crate) enum Preconditioner {
    Identity,
    Jacobi(Vec<f64>),
    BlockJacobi(Vec<Matrix3<f64>>),
    /// Sweeps read the operator's own CSR arrays at apply time: no copy of the matrix.
    Ssor {
        omega: f64,
        diag: Vec<f64>,
    },
    Ic0 {
        l: Box<Ic0>,
        shift: f64,
    },
    /// A Cholesky factor and how many `factorize` calls have reused it.
    Cholesky {
        factor: Box<Cholesky>,
        age: usize,
    },
    /// A multigrid hierarchy and how many `factorize` calls have refreshed it.
    Amg {
        amg: Box<Amg>,
        age: usize,
    },
}

impl Preconditioner {
    /// Sets up the preconditioner for `a`; returns it with the set-up flops. `coordinates`
    /// (one per 3 rows) order a stale-Cholesky factor geometrically.
    pub fn setup(
        spec: &PreconditionerSpec,
        a: &dyn LinearOperator,
        coordinates: Option<&[[f64; 3]]>,
    ) -> Result<(Self, u64), SolverError> {
        let n = a.nrows();
        let nu = n as u64;
        Ok(match *spec {
            PreconditionerSpec::Identity => (Preconditioner::Identity, 0),
            PreconditionerSpec::Jacobi => {
                let inv = positive_diagonal(a)?.iter().map(|x| 1.0 / x).collect();
                (Preconditioner::Jacobi(inv), nu)
            }
            PreconditionerSpec::BlockJacobi => {
                if !n.is_multiple_of(3) {
                    return Err(SolverError::Unsupported(
                        "block Jacobi needs a multiple of 3 rows",
                    ));
                }
                let mut blocks = vec![Matrix3::zeros(); n / 3];
                a.block_diagonal(&mut blocks)?;
                for (v, b) in blocks.iter_mut().enumerate() {
                    let chol = b.cholesky().ok_or(SolverError::NotPositiveDefinite {
                        pivot: 3 * v,
                        value: b[(0, 0)],
                        spent: None,
                    })?;
                    *b = chol.inverse();
                }
                // Cholesky and inverse of each 3x3 block: about 40 flops a row.
                (Preconditioner::BlockJacobi(blocks), 40 * nu)
            }
            PreconditionerSpec::Ssor { omega } => {
                a.csr().ok_or(SolverError::Unsupported(
                    "SSOR needs an assembled CSR matrix",
                ))?;
                let diag = positive_diagonal(a)?;
                (Preconditioner::Ssor { omega, diag }, nu)
            }
            PreconditionerSpec::Ic0 => {
                let csr = a.csr().ok_or(SolverError::Unsupported(
                    "IC(0) needs an assembled CSR matrix",
                ))?;
                let (indptr, indices, data) = (
                    csr.indptr().raw_storage().to_vec(),
                    csr.indices(),
                    csr.data(),
                );
                let mut shift = 0.0;
                let mut flops = 0;
                loop {
                    flops += ic0::flops(&indptr, indices);
                    match Ic0::new(&indptr, indices, data, shift) {
                        Ok(l) => {
                            break (
                                Preconditioner::Ic0 {
                                    l: Box::new(l),
                                    shift,
                                },
                                flops,
                            );
                        }
                        Err(e) if shift >= 1e3 => return Err(e),
                        Err(_) => shift = if shift == 0.0 { 1e-3 } else { shift * 10.0 },
                    }
                }
            }
            PreconditionerSpec::StaleCholesky {
                ordering,
                precision,
                ..
            } => {
                let mut factor = Box::new(Cholesky::new(ordering, Indefinite::Error));
                factor.set_coordinates(coordinates);
                factor.set_precision(precision);
                let stats = factor.factorize(a)?;
                (Preconditioner::Cholesky { factor, age: 0 }, stats.flops)
            }
            PreconditionerSpec::Amg {
                theta, smoother, ..
            } => {
                let csr = a.csr().ok_or(SolverError::Unsupported(
                    "AMG needs an assembled CSR matrix",
                ))?;
                let (amg, flops) = Amg::new(csr, coordinates, theta, smoother)?;
                (
                    Preconditioner::Amg {
                        amg: Box::new(amg),
                        age: 0,
                    },
                    flops,
                )
            }
        })
    }

    /// `z = M^-1 r`.
    ///
    /// `a` is the operator being solved; SSOR sweeps its CSR arrays.
    ///
    /// # Panics
    /// For SSOR, if `a` has no CSR matrix (the solver checks this before iterating).
    pub fn apply(&self, a: &dyn LinearOperator, r: &[f64], z: &mut [f64]) {
        match self {
            Preconditioner::Identity => z.copy_from_slice(r),
            Preconditioner::Jacobi(inv) => update_from2(z, r, inv, |zi, ri, di| *zi = ri * di),
            Preconditioner::BlockJacobi(blocks) => {
                for (v, b) in blocks.iter().enumerate() {
                    let y = b * Vector3::new(r[3 * v], r[3 * v + 1], r[3 * v + 2]);
                    z[3 * v..3 * v + 3].copy_from_slice(y.as_slice());
                }
            }
            Preconditioner::Ssor { omega, diag } => {
                let csr = a.csr().expect("SSOR is applied to a CSR operator");
                let (indptr, indices, data) = (csr.indptr(), csr.indices(), csr.data());
                let indptr = indptr.raw_storage();
                // M = (D + wL) D^-1 (D + wU) / (w (2 - w)): solve (D + wL) y = r forward,
                // scale by D, solve (D + wU) z = D y backward, scale by w (2 - w).
                let n = diag.len();
                for i in 0..n {
                    let mut acc = r[i];
                    for k in indptr[i]..indptr[i + 1] {
                        let j = indices[k];
                        if j < i {
                            acc -= omega * data[k] * z[j];
                        }
                    }
                    z[i] = acc / diag[i];
                }
                for i in 0..n {
                    z[i] *= diag[i];
                }
                for i in (0..n).rev() {
                    let mut acc = z[i];
                    for k in indptr[i]..indptr[i + 1] {
                        let j = indices[k];
                        if j > i {
                            acc -= omega * data[k] * z[j];
                        }
                    }
                    z[i] = acc / diag[i];
                }
                let scale = omega * (2.0 - omega);
                for zi in z.iter_mut() {
                    *zi *= scale;
                }
            }
            Preconditioner::Cholesky { factor, .. } => {
                z.copy_from_slice(r);
                factor
                    .solve_in_place(z)
                    .expect("a held factor solves vectors of its size");
            }
            Preconditioner::Amg { amg, .. } => amg.apply(r, z),
            Preconditioner::Ic0 { l, .. } => l.apply(r, z),
        }
    }

    /// Floating-point operations of one `apply`.
    pub fn flops(&self, a: &dyn LinearOperator, n: usize) -> u64 {
        match self {
            Preconditioner::Identity => 0,
            Preconditioner::Jacobi(_) => n as u64,
            Preconditioner::BlockJacobi(_) => 5 * n as u64,
            Preconditioner::Ssor { .. } => a.apply_flops() + 4 * n as u64,
            Preconditioner::Ic0 { l, .. } => 4 * l.nnz() as u64,
            Preconditioner::Cholesky { factor, .. } => factor.solve_flops(),
            Preconditioner::Amg { amg, .. } => amg.flops(),
        }
    }

    /// The part of [`Self::flops`] spent in sequential sweeps over a sparse triangle.
    pub fn sweep_flops(&self, a: &dyn LinearOperator, n: usize) -> u64 {
        match self {
            Preconditioner::Ssor { .. } | Preconditioner::Ic0 { .. } => self.flops(a, n),
            _ => 0,
        }
    }

    /// Whether `apply` reads the operator's CSR arrays.
    pub fn needs_csr(&self) -> bool {
        matches!(self, Preconditioner::Ssor { .. })
    }

    /// The diagonal shift IC(0) needed (0 otherwise).
    pub fn shift(&self) -> f64 {
        match self {
            Preconditioner::Ic0 { shift, .. } => *shift,
            _ => 0.0,
        }
    }
}
