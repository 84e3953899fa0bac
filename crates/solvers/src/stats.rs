//! Statistics every solve returns, on success and on failure.

use serde::{Deserialize, Serialize};

/// How a solve ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Termination {
    /// The residual met the tolerance.
    Converged,
    /// The iteration cap was reached first.
    MaxIterations,
    /// Non-positive curvature (CG on a matrix that is not SPD).
    Breakdown,
    /// The residual became non-finite.
    Diverged,
    /// A direct solve (no iterations).
    Direct,
}

/// What a solve did and what it cost.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct SolveStats {
    /// The solver's name.
    pub solver: String,
    /// Iterations performed (0 for a warm start at the solution, and for direct solves).
    pub iterations: usize,
    /// Euclidean norm of the residual `b - A x` before the first and after each iteration.
    pub residuals: Vec<f64>,
    /// `||b||`, the scale of the relative tolerance.
    pub rhs_norm: f64,
    /// How it ended.
    pub termination: Termination,
    /// Wall time in seconds (noisy; learn on `flops`).
    pub seconds: f64,
    /// Operator applications (matrix-vector products).
    pub matvecs: usize,
    /// Deterministic work estimate in floating-point operations (operator, preconditioner
    /// and vector updates), identical on every machine and thread count.
    pub flops: u64,
    /// The part of `flops` spent in sequential sweeps over a sparse triangle (IC(0)'s
    /// triangular solves, SSOR's sweeps), which run one row after another on one core.
    #[serde(default)]
    pub sweep_flops: u64,
}

deform_setters::setters!(SolveStats { solver: String, iterations: usize, residuals: Vec<f64>, rhs_norm: f64, termination: Termination, seconds: f64, matvecs: usize, flops: u64, sweep_flops: u64 });

impl SolveStats {
    /// Empty statistics of a solve by `solver` of a right-hand side of norm `rhs_norm`, for
    /// solvers written outside this crate.
    pub fn new(solver: String, rhs_norm: f64) -> Self {
        Self {
            solver,
            iterations: 0,
            residuals: Vec::new(),
            rhs_norm,
            termination: Termination::MaxIterations,
            seconds: 0.0,
            matvecs: 0,
            flops: 0,
            sweep_flops: 0,
        }
    }

    /// Its work: flops, with sweep flops weighted by `weights.sweep`.
    pub fn work(&self, weights: WorkWeights) -> f64 {
        weights.solve(self.flops as f64, self.sweep_flops as f64)
    }

    /// The last residual norm (`NaN` if none was computed).
    pub fn final_residual(&self) -> f64 {
        self.residuals.last().copied().unwrap_or(f64::NAN)
    }

    /// The last residual relative to `||b||` (absolute when `b = 0`).
    pub fn relative_residual(&self) -> f64 {
        let r = self.final_residual();
        if self.rhs_norm > 0.0 {
            r / self.rhs_norm
        } else {
            r
        }
    }
}

/// How deterministic work weighs flops of different kinds against one flop of a parallel,
/// memory-bound sparse product (matrix-vector products, multigrid cycles): the ratios of
/// their measured rates, see docs/benchmarks.md. Plain flops are `WorkWeights::default()`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct WorkWeights {
    /// A factorisation flop: a dense supernodal Cholesky runs at many more flops per second,
    /// so this is below 1.
    pub factor: f64,
    /// A flop of a sequential sweep over a sparse triangle (see [`SolveStats::sweep_flops`]):
    /// one core and a dependent chain per row, so this is above 1.
    pub sweep: f64,
}

deform_setters::setters!(WorkWeights { sweep: f64 });

impl Default for WorkWeights {
    fn default() -> Self {
        Self {
            factor: 1.0,
            sweep: 1.0,
        }
    }
}

/// The work's formula, e.g. `solve flops + 0.1 x factorisation flops + 4 x sweep flops`
/// (the sweeps are part of the solve flops, counted `sweep` times in all).
impl std::fmt::Display for WorkWeights {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "solve flops + {} x factorisation flops", self.factor)?;
        if self.sweep != 1.0 {
            write!(f, ", sweep flops x {}", self.sweep)?;
        }
        Ok(())
    }
}

impl WorkWeights {
    /// The work of a solve of `flops`, `sweep_flops` of them in sequential sweeps.
    pub fn solve(&self, flops: f64, sweep_flops: f64) -> f64 {
        flops + (self.sweep - 1.0) * sweep_flops
    }

    /// Factorisation flops weighted by `factor`, every other flop by 1.
    pub fn factor(factor: f64) -> Self {
        Self {
            factor,
            ..Self::default()
        }
    }
}

/// What a `factorize` call did and what it cost.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct SetupStats {
    /// The symbolic analysis was (re)done, because the pattern was new.
    pub analyzed: bool,
    /// An earlier factor or preconditioner was kept instead of computing a new one (stale
    /// Cholesky preconditioning), or an AMG hierarchy was kept with only its operators
    /// recomputed.
    pub reused: bool,
    /// Deterministic work estimate of the set-up in floating-point operations.
    pub flops: u64,
    /// Nonzeros of a Cholesky factor computed by this call (0 otherwise).
    pub factor_nnz: usize,
    /// Wall time in seconds.
    pub seconds: f64,
}

deform_setters::setters!(SetupStats {
    analyzed: bool,
    reused: bool,
    flops: u64,
    factor_nnz: usize,
    seconds: f64
});

impl SetupStats {
    /// Work of the set-up with factorisation flops weighted by `weights.factor`: a dense
    /// supernodal Cholesky runs at many more flops per second than memory-bound sparse
    /// kernels, so plain flops overstate its cost in time.
    pub fn work(&self, weights: WorkWeights) -> f64 {
        let w = if self.factor_nnz > 0 {
            weights.factor
        } else {
            1.0
        };
        w * self.flops as f64
    }
}
