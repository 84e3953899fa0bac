//! Which linear solver runs at each Newton iteration.
//!
//! A [`SolverPolicy`] sees what happened so far in the step (and the previous steps'
//! outcomes, through `observe`) and returns a [`Decision`]: a solver configuration, an
//! optional relative tolerance for this solve (adaptive forcing terms), and whether a stale
//! preconditioner must be refreshed. Solvers are kept between iterations and steps, keyed by
//! their configuration, so factorisations and symbolic analyses are reused.

use deform_solvers::{PreconditionerSpec, SolverSpec, Tolerance};
use serde::{Deserialize, Serialize};

use crate::report::IterationReport;

/// What the policy can see before a linear solve.
#[derive(Debug, Clone)]
pub struct PolicyContext<'a> {
    /// Time step index (0 for the first step of the integrator).
    pub step: usize,
    /// Newton iteration index within the step.
    pub iteration: usize,
    /// Time step size.
    pub dt: f64,
    /// Free degrees of freedom.
    pub num_free: usize,
    /// Norm of the current Newton residual.
    pub residual: f64,
    /// Norm of the residual at the first iteration of this step.
    pub initial_residual: f64,
    /// The iterations of this step so far.
    pub history: &'a [IterationReport],
}

/// A policy's choice for one linear solve.
#[derive(Debug, Clone, PartialEq)]
pub struct Decision {
    /// The solver configuration (also the key of the kept solver instance).
    pub solver: SolverSpec,
    /// Relative residual tolerance for this solve only (iterative solvers); `None` keeps the
    /// configuration's.
    pub rel_tolerance: Option<f64>,
    /// Recompute a stale preconditioner before this solve.
    pub refresh: bool,
}

impl Decision {
    /// `solver` as configured.
    pub fn solver(solver: SolverSpec) -> Self {
        Self {
            solver,
            rel_tolerance: None,
            refresh: false,
        }
    }
}

/// Chooses the linear solver for each Newton iteration.
pub trait SolverPolicy: Send {
    /// A short description for reports.
    fn name(&self) -> String;

    /// The solver for the next linear solve.
    fn choose(&mut self, context: &PolicyContext<'_>) -> Decision;

    /// Called after each Newton iteration with its outcome (for policies that adapt or learn).
    fn observe(&mut self, _context: &PolicyContext<'_>, _outcome: &IterationReport) {}

    /// A copy for a new, independent run, with what it adapted to in earlier runs forgotten
    /// (see [`crate::Integrator::fork`]); `None`, the default, for a policy that cannot be
    /// copied: its integrator then runs its rollouts one after another.
    fn fork(&self) -> Option<Box<dyn SolverPolicy>> {
        None
    }
}

/// The same solver at every iteration.
#[derive(Debug, Clone)]
pub struct Fixed(pub SolverSpec);

impl SolverPolicy for Fixed {
    fn name(&self) -> String {
        format!("fixed({})", self.0.name())
    }

    fn choose(&mut self, _: &PolicyContext<'_>) -> Decision {
        Decision::solver(self.0.clone())
    }

    fn fork(&self) -> Option<Box<dyn SolverPolicy>> {
        Some(Box::new(self.clone()))
    }
}

/// One solver for small systems and another for large ones, by the number of free DOFs.
#[derive(Debug, Clone)]
pub struct BySize {
    /// The solver below `large_from` free DOFs.
    pub small: SolverSpec,
    /// The solver from `large_from` free DOFs on.
    pub large: SolverSpec,
    /// The first system size that gets `large`.
    pub large_from: usize,
}

impl Default for BySize {
    /// `BySize(small: Direct(), large: Pcg(preconditioner: Amg(max_age: 20), tolerance:
    /// (rel: 1e-8)), large_from: 150000)`: deform's default policy.
    fn default() -> Self {
        Self {
            small: SolverSpec::Direct {
                ordering: Default::default(),
                indefinite: Default::default(),
                parallel: true,
                precision: Default::default(),
            },
            large: SolverSpec::Pcg {
                preconditioner: PreconditionerSpec::Amg {
                    theta: 0.0,
                    smoother: Default::default(),
                    max_age: 20,
                },
                tolerance: Tolerance::default().rel(1e-8),
            },
            large_from: default_large_from(),
        }
    }
}

impl SolverPolicy for BySize {
    fn name(&self) -> String {
        format!(
            "by size({} below {} free DOFs, else {})",
            self.small.name(),
            self.large_from,
            self.large.name()
        )
    }

    fn choose(&mut self, c: &PolicyContext<'_>) -> Decision {
        Decision::solver(if c.num_free < self.large_from {
            self.small.clone()
        } else {
            self.large.clone()
        })
    }

    fn fork(&self) -> Option<Box<dyn SolverPolicy>> {
        Some(Box::new(self.clone()))
    }
}

/// `iterations[k]` at Newton iteration `k`, `otherwise` after the list.
#[derive(Debug, Clone)]
pub struct Schedule {
    /// Solvers for the first iterations.
    pub iterations: Vec<SolverSpec>,
    /// The solver after them.
    pub otherwise: SolverSpec,
}

impl SolverPolicy for Schedule {
    fn name(&self) -> String {
        let list: Vec<String> = self.iterations.iter().map(SolverSpec::name).collect();
        format!(
            "schedule([{}], then {})",
            list.join(", "),
            self.otherwise.name()
        )
    }

    fn choose(&mut self, c: &PolicyContext<'_>) -> Decision {
        Decision::solver(
            self.iterations
                .get(c.iteration)
                .unwrap_or(&self.otherwise)
                .clone(),
        )
    }

    fn fork(&self) -> Option<Box<dyn SolverPolicy>> {
        Some(Box::new(self.clone()))
    }
}

/// Eisenstat-Walker forcing terms (their "choice 2"): the relative tolerance of iteration
/// `k` is `eta_k = gamma (||r_k|| / ||r_{k-1}||)^alpha`, safeguarded by
/// `max(eta_k, gamma eta_{k-1}^alpha)` when that exceeds 0.1, and clamped to
/// `[eta_min, eta_max]`. Solves are loose while Newton is far from the solution and tight
/// near it.
#[derive(Debug, Clone)]
pub struct EisenstatWalker {
    /// An iterative solver configuration.
    pub solver: SolverSpec,
    /// First iteration's tolerance and upper clamp.
    pub eta_max: f64,
    /// Lower clamp.
    pub eta_min: f64,
    /// `gamma` in (0, 1].
    pub gamma: f64,
    /// `alpha` in (1, 2].
    pub alpha: f64,
    last_eta: f64,
}

impl EisenstatWalker {
    /// With the usual constants `gamma = 0.9`, `alpha = 2`, `eta_max = 0.1`, `eta_min = 1e-10`.
    pub fn new(solver: SolverSpec) -> Self {
        Self {
            solver,
            eta_max: 0.1,
            eta_min: 1e-10,
            gamma: 0.9,
            alpha: 2.0,
            last_eta: 0.1,
        }
    }
}

impl EisenstatWalker {
    /// With a given upper clamp (also the first tolerance) and `gamma`.
    pub fn with_constants(solver: SolverSpec, eta_max: f64, gamma: f64) -> Self {
        Self {
            eta_max,
            gamma,
            last_eta: eta_max,
            ..Self::new(solver)
        }
    }
}

impl SolverPolicy for EisenstatWalker {
    fn name(&self) -> String {
        format!("eisenstat-walker({})", self.solver.name())
    }

    fn choose(&mut self, c: &PolicyContext<'_>) -> Decision {
        let eta = match c.history.last() {
            None => self.eta_max,
            Some(previous) if previous.residual > 0.0 => {
                let mut eta = self.gamma * (c.residual / previous.residual).powf(self.alpha);
                let safeguard = self.gamma * self.last_eta.powf(self.alpha);
                if safeguard > 0.1 {
                    eta = eta.max(safeguard);
                }
                eta
            }
            Some(_) => self.eta_min,
        };
        let eta = eta.clamp(self.eta_min, self.eta_max);
        self.last_eta = eta;
        Decision {
            solver: self.solver.clone(),
            rel_tolerance: Some(eta),
            refresh: false,
        }
    }

    fn fork(&self) -> Option<Box<dyn SolverPolicy>> {
        Some(Box::new(Self {
            last_eta: self.eta_max,
            ..self.clone()
        }))
    }
}

/// The hand schedule of stale-factor reuse: PCG preconditioned by a kept Cholesky factor
/// (factorised at the first solve), refactorised before the next solve whenever the last one
/// needed more than `refactor_above` iterations or fell back to the direct solver. The factor
/// then serves later Newton iterations and time steps while it stays a good preconditioner.
/// With an AMG preconditioner the same rule rebuilds the hierarchy (its operators are
/// refreshed at every set-up in between, up to its `max_age`).
#[derive(Debug, Clone)]
pub struct StaleFactor {
    /// PCG with a `StaleCholesky` or `Amg` preconditioner (its `max_age` caps the reuse).
    pub solver: SolverSpec,
    /// Refactorise after a solve that took more iterations than this.
    pub refactor_above: usize,
    refresh: bool,
}

impl StaleFactor {
    /// `solver` must keep its preconditioner (stale Cholesky or AMG; see
    /// [`PolicySpec::build`]).
    pub fn new(solver: SolverSpec, refactor_above: usize) -> Self {
        Self {
            solver,
            refactor_above,
            refresh: false,
        }
    }
}

impl SolverPolicy for StaleFactor {
    fn name(&self) -> String {
        format!(
            "stale-factor({}, refactor above {})",
            self.solver.name(),
            self.refactor_above
        )
    }

    fn choose(&mut self, _: &PolicyContext<'_>) -> Decision {
        Decision {
            solver: self.solver.clone(),
            rel_tolerance: None,
            refresh: std::mem::take(&mut self.refresh),
        }
    }

    fn observe(&mut self, _: &PolicyContext<'_>, outcome: &IterationReport) {
        self.refresh = outcome.fallback || outcome.solve.iterations > self.refactor_above;
    }

    fn fork(&self) -> Option<Box<dyn SolverPolicy>> {
        Some(Box::new(Self::new(
            self.solver.clone(),
            self.refactor_above,
        )))
    }
}

/// A policy as a configuration states it. Unknown fields are rejected.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub enum PolicySpec {
    /// One solver throughout.
    Fixed(SolverSpec),
    /// A solver per Newton iteration index, then a default.
    Schedule {
        /// Solvers for the first iterations.
        iterations: Vec<SolverSpec>,
        /// The solver after them.
        otherwise: SolverSpec,
    },
    /// Eisenstat-Walker adaptive tolerances for an iterative solver.
    EisenstatWalker {
        /// The iterative solver.
        solver: SolverSpec,
        /// Upper clamp and first tolerance.
        #[serde(default = "default_eta_max")]
        eta_max: f64,
    },
    /// `small` for systems of fewer than `large_from` free DOFs, `large` from there on. The default: a direct factorisation while its fill is affordable,
    /// PCG with smoothed-aggregation multigrid beyond.
    BySize {
        /// The solver below `large_from` free DOFs.
        small: SolverSpec,
        /// The solver from `large_from` free DOFs on.
        large: SolverSpec,
        /// The first system size that gets `large`.
        #[serde(default = "default_large_from")]
        large_from: usize,
    },
    /// Stale-factor reuse ([`StaleFactor`]).
    StaleFactor {
        /// PCG with a `StaleCholesky` or `Amg` preconditioner.
        solver: SolverSpec,
        /// Refactorise after a solve that took more iterations than this.
        #[serde(default = "default_refactor_above")]
        refactor_above: usize,
    },
}

/// Where the default policy leaves the direct solver: at 55k free DOFs a factorisation takes
/// 0.6 s and 0.3 GB, at 418k 26 s and 4.1 GB, where PCG-AMG takes 4-6 s a step in 2.1 GB
/// (docs/benchmarks.md).
fn default_large_from() -> usize {
    150_000
}

fn default_refactor_above() -> usize {
    20
}

fn default_eta_max() -> f64 {
    0.1
}

impl Default for PolicySpec {
    /// The `BySize` policy's default: a direct solver below 150,000 free DOFs, PCG-AMG
    /// from there on.
    fn default() -> Self {
        let BySize {
            small,
            large,
            large_from,
        } = BySize::default();
        PolicySpec::BySize {
            small,
            large,
            large_from,
        }
    }
}

/// Why a policy configuration does not build.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum PolicyError {
    /// A solver configuration of the policy does not build.
    #[error("solver: {0}")]
    Solver(#[from] deform_solvers::SolverError),
    /// A value is out of range or a solver does not suit the policy.
    #[error("{field}: {reason}")]
    Invalid {
        /// The field.
        field: &'static str,
        /// Why.
        reason: String,
    },
}

impl PolicySpec {
    /// Builds the policy.
    ///
    /// # Errors
    /// [`PolicyError`] naming the bad field.
    pub fn build(&self) -> Result<Box<dyn SolverPolicy>, PolicyError> {
        let check = |s: &SolverSpec| s.build().map(|_| ());
        let invalid = |field, reason: &str| {
            Err(PolicyError::Invalid {
                field,
                reason: reason.to_owned(),
            })
        };
        Ok(match self {
            PolicySpec::Fixed(s) => {
                check(s)?;
                Box::new(Fixed(s.clone()))
            }
            PolicySpec::Schedule {
                iterations,
                otherwise,
            } => {
                for s in iterations {
                    check(s)?;
                }
                check(otherwise)?;
                Box::new(Schedule {
                    iterations: iterations.clone(),
                    otherwise: otherwise.clone(),
                })
            }
            PolicySpec::EisenstatWalker { solver, eta_max } => {
                check(solver)?;
                if !(*eta_max > 0.0 && *eta_max < 1.0) {
                    return invalid("eta_max", &format!("{eta_max} must be in (0, 1)"));
                }
                if matches!(solver, SolverSpec::Direct { .. }) {
                    return invalid("solver", "Eisenstat-Walker needs an iterative solver");
                }
                Box::new(EisenstatWalker::with_constants(
                    solver.clone(),
                    *eta_max,
                    0.9,
                ))
            }
            PolicySpec::BySize {
                small,
                large,
                large_from,
            } => {
                check(small)?;
                check(large)?;
                Box::new(BySize {
                    small: small.clone(),
                    large: large.clone(),
                    large_from: *large_from,
                })
            }
            PolicySpec::StaleFactor {
                solver,
                refactor_above,
            } => {
                check(solver)?;
                if !solver.keeps_preconditioner() {
                    return invalid(
                        "solver",
                        "StaleFactor needs Pcg(preconditioner: StaleCholesky(..) or Amg(..))",
                    );
                }
                Box::new(StaleFactor::new(solver.clone(), *refactor_above))
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn context(num_free: usize) -> PolicyContext<'static> {
        PolicyContext {
            step: 0,
            iteration: 0,
            dt: 0.01,
            num_free,
            residual: 1.0,
            initial_residual: 1.0,
            history: &[],
        }
    }

    #[test]
    fn the_default_policy_factorises_small_systems_and_uses_multigrid_on_large_ones() {
        let mut policy = PolicySpec::default().build().unwrap();
        assert!(matches!(
            policy.choose(&context(55_488)).solver,
            SolverSpec::Direct { .. }
        ));
        let large = policy.choose(&context(418_176)).solver;
        assert!(
            matches!(
                large,
                SolverSpec::Pcg {
                    preconditioner: PreconditionerSpec::Amg { .. },
                    ..
                }
            ),
            "{large:?}"
        );
        let text = "BySize(small: Direct(), large: Pcg(preconditioner: Ic0), large_from: 10)";
        let mut custom = ron::from_str::<PolicySpec>(text).unwrap().build().unwrap();
        assert!(matches!(
            custom.choose(&context(10)).solver,
            SolverSpec::Pcg { .. }
        ));
        assert!(
            ron::from_str::<PolicySpec>("BySize(small: Direct(), large: Direct(), above: 3)")
                .is_err()
        );
    }
}
