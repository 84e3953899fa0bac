//! `SolverSpec`: the serde (RON) description of any solver.

use serde::{Deserialize, Serialize};

use crate::direct::{Cholesky, Indefinite, Precision};
use crate::iterative::{Iterative, Method, Tolerance};
use crate::ordering::Ordering;
use crate::precond::PreconditionerSpec;
use crate::{LinearSolver, SolverError};

/// A linear solver as a configuration states it. Unknown fields are rejected.
///
/// ```
/// use deform_solvers::SolverSpec;
/// let spec: SolverSpec = ron::from_str("Pcg(preconditioner: Ic0, tolerance: (rel: 1e-6))").unwrap();
/// let solver = spec.build().unwrap();
/// assert!(solver.name().contains("Ic0"));
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub enum SolverSpec {
    /// Weighted Jacobi iteration.
    Jacobi {
        /// Relaxation factor in (0, 2).
        #[serde(default = "default_omega")]
        omega: f64,
        /// Stopping rule.
        #[serde(default)]
        tolerance: Tolerance,
    },
    /// Conjugate gradients.
    Cg {
        /// Stopping rule.
        #[serde(default)]
        tolerance: Tolerance,
    },
    /// Preconditioned conjugate gradients.
    Pcg {
        /// The preconditioner.
        preconditioner: PreconditionerSpec,
        /// Stopping rule.
        #[serde(default)]
        tolerance: Tolerance,
    },
    /// Sparse direct Cholesky (faer).
    Direct {
        /// Fill-reducing ordering.
        #[serde(default)]
        ordering: Ordering,
        /// What to do with a matrix that is not positive definite.
        #[serde(default)]
        indefinite: Indefinite,
        /// Split factorisations of at least 20,000 rows into a fixed number of parallel
        /// tasks (default): bit-identical for any thread count, 1.2x faster on 2 cores at
        /// 55k DOFs. `false` keeps every factorisation on one thread.
        #[serde(default = "yes")]
        parallel: bool,
        /// Factor in double (default), or in single precision refined in double.
        #[serde(default)]
        precision: Precision,
    },
    /// An iterative solver on a matrix-free operator instead of the assembled matrix: the
    /// caller supplies products with element-by-element force differentials (the
    /// integrator's Newton matrix without K). Only preconditioners that need no matrix
    /// entries qualify: none (CG), Jacobi, block Jacobi; or the Jacobi iteration.
    MatrixFree(Box<SolverSpec>),
}

fn yes() -> bool {
    true
}

fn default_omega() -> f64 {
    2.0 / 3.0
}

impl SolverSpec {
    /// A short name for reports: `direct(Auto)`, `pcg(Jacobi)`, `matrix-free pcg(...)`.
    pub fn name(&self) -> String {
        match self {
            SolverSpec::MatrixFree(inner) => format!("matrix-free {}", inner.name()),
            SolverSpec::Jacobi { omega, .. } => format!("jacobi({omega})"),
            SolverSpec::Cg { .. } => "cg".into(),
            SolverSpec::Pcg { preconditioner, .. } => format!("pcg({preconditioner:?})"),
            SolverSpec::Direct {
                ordering,
                parallel,
                precision,
                ..
            } => format!(
                "direct({ordering:?}{}{})",
                if *parallel { "" } else { ", one thread" },
                if *precision == Precision::Mixed {
                    ", mixed"
                } else {
                    ""
                }
            ),
        }
    }

    /// PCG preconditioned by a stale Cholesky factor (a factor kept across solves).
    pub fn is_stale_cholesky(&self) -> bool {
        matches!(
            self,
            SolverSpec::Pcg {
                preconditioner: PreconditionerSpec::StaleCholesky { .. },
                ..
            }
        )
    }

    /// PCG whose preconditioner set-up is kept across solves and rebuilt on request: a stale
    /// Cholesky factor, or an AMG hierarchy (refreshed in between).
    pub fn keeps_preconditioner(&self) -> bool {
        matches!(
            self,
            SolverSpec::Pcg {
                preconditioner: PreconditionerSpec::StaleCholesky { .. }
                    | PreconditionerSpec::Amg { .. },
                ..
            }
        )
    }

    /// The same iterative solver with its relative tolerance replaced; `None` for the
    /// direct solver.
    pub fn with_relative_tolerance(&self, rel: f64) -> Option<SolverSpec> {
        let set = |t: &Tolerance| Tolerance { rel, ..*t };
        Some(match self {
            SolverSpec::Jacobi { omega, tolerance } => SolverSpec::Jacobi {
                omega: *omega,
                tolerance: set(tolerance),
            },
            SolverSpec::Cg { tolerance } => SolverSpec::Cg {
                tolerance: set(tolerance),
            },
            SolverSpec::Pcg {
                preconditioner,
                tolerance,
            } => SolverSpec::Pcg {
                preconditioner: *preconditioner,
                tolerance: set(tolerance),
            },
            SolverSpec::Direct { .. } => return None,
            SolverSpec::MatrixFree(inner) => {
                SolverSpec::MatrixFree(Box::new(inner.with_relative_tolerance(rel)?))
            }
        })
    }

    /// The stopping rule of an iterative configuration (`None` for the direct solver).
    pub fn tolerance(&self) -> Option<Tolerance> {
        match *self {
            SolverSpec::Jacobi { tolerance, .. }
            | SolverSpec::Cg { tolerance }
            | SolverSpec::Pcg { tolerance, .. } => Some(tolerance),
            SolverSpec::Direct { .. } => None,
            SolverSpec::MatrixFree(ref inner) => inner.tolerance(),
        }
    }

    /// Whether the solver runs on a matrix-free operator.
    pub fn is_matrix_free(&self) -> bool {
        matches!(self, SolverSpec::MatrixFree(_))
    }

    /// Validates and builds the solver.
    ///
    /// # Errors
    /// [`SolverError::InvalidParameter`] naming the field.
    pub fn build(&self) -> Result<Box<dyn LinearSolver>, SolverError> {
        Ok(match *self {
            SolverSpec::Jacobi { omega, tolerance } => {
                Box::new(Iterative::try_new(Method::Jacobi { omega }, tolerance)?)
            }
            SolverSpec::Cg { tolerance } => Box::new(Iterative::try_new(
                Method::Pcg(PreconditionerSpec::Identity),
                tolerance,
            )?),
            SolverSpec::Pcg {
                preconditioner,
                tolerance,
            } => Box::new(Iterative::try_new(Method::Pcg(preconditioner), tolerance)?),
            SolverSpec::Direct {
                ordering,
                indefinite,
                parallel,
                precision,
            } => {
                let mut c = Cholesky::new(ordering, indefinite);
                c.set_parallel(parallel);
                c.set_precision(precision);
                Box::new(c)
            }
            SolverSpec::MatrixFree(ref inner) => match **inner {
                SolverSpec::Jacobi { .. }
                | SolverSpec::Cg { .. }
                | SolverSpec::Pcg {
                    preconditioner:
                        PreconditionerSpec::Identity
                        | PreconditionerSpec::Jacobi
                        | PreconditionerSpec::BlockJacobi,
                    ..
                } => inner.build()?,
                _ => {
                    return Err(SolverError::Unsupported(
                        "MatrixFree needs Jacobi, Cg or Pcg with Identity, Jacobi or BlockJacobi",
                    ));
                }
            },
        })
    }
}

impl std::fmt::Display for SolverSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.name())
    }
}
