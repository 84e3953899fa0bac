//! Linear solvers for deform's Newton systems, behind one trait with a symbolic / numeric
//! split: [`LinearSolver::analyze`] once per sparsity pattern, [`LinearSolver::factorize`]
//! (or preconditioner set-up) per matrix, [`LinearSolver::solve`] per right-hand side with
//! the initial guess in `x`. Every solve returns [`SolveStats`] (iterations, residual
//! history, termination, wall time and a deterministic flop count); failures keep them.
//!
//! Operators are anything implementing [`LinearOperator`]: the assembled CSR matrix
//! (`sprs::CsMat<f64>`, full symmetric storage) or a matrix-free operator.
//!
//! Solvers: weighted Jacobi, CG, PCG with Jacobi, 3x3 block-Jacobi, SSOR, IC(0),
//! stale-Cholesky and smoothed-aggregation multigrid preconditioners (the rigid-body modes
//! of [`LinearSolver::set_coordinates`]' positions as near-null space), and a sparse direct Cholesky ([`Cholesky`], faer's
//! supernodal/simplicial factorisation behind a nested-dissection ordering of the vertex
//! graph or of the vertices' positions; above 20,000 rows the two halves of the first cut
//! are factorised concurrently and the separator's Schur complement after them; single
//! precision with double refinement on request; LDLT on request for indefinite matrices).
//!
//! ```
//! use deform_solvers::{LinearSolver, SolverSpec};
//! use sprs::TriMat;
//!
//! // A 1D Laplacian plus identity: SPD.
//! let n = 50;
//! let mut t = TriMat::new((n, n));
//! for i in 0..n {
//!     t.add_triplet(i, i, 3.0);
//!     if i + 1 < n {
//!         t.add_triplet(i, i + 1, -1.0);
//!         t.add_triplet(i + 1, i, -1.0);
//!     }
//! }
//! let a: sprs::CsMat<f64> = t.to_csr();
//! let b = vec![1.0; n];
//! let mut x = vec![0.0; n];
//! let mut solver = ron::from_str::<SolverSpec>("Pcg(preconditioner: Jacobi)").unwrap().build().unwrap();
//! solver.analyze(&a).unwrap();
//! solver.factorize(&a).unwrap();
//! let stats = solver.solve(&a, &b, &mut x).unwrap();
//! assert!(stats.relative_residual() <= 1e-8);
//! ```

mod amg;
mod blocks;
mod bsr3;
mod direct;
mod error;
mod ic0;
mod iterative;
pub mod kernels;
mod llt;
mod operator;
mod ordering;
pub mod pcg;
mod precond;
mod spec;
mod split;
mod stats;
pub mod vector;

pub use amg::AmgSmoother;
pub use direct::{Cholesky, Indefinite, Precision};
pub use error::SolverError;
pub use iterative::{Iterative, Method, Tolerance};
pub use operator::LinearOperator;
pub use ordering::Ordering;
pub use precond::PreconditionerSpec;
pub use spec::SolverSpec;
pub use stats::{SetupStats, SolveStats, Termination, WorkWeights};

/// A linear solver for symmetric systems `A x = b`.
pub trait LinearSolver: Send {
    /// A short description, e.g. `pcg(Ic0)`.
    fn name(&self) -> String;

    /// Symbolic work for `a`'s sparsity pattern (orderings, symbolic factorisation); a no-op
    /// for iterative solvers.
    ///
    /// # Errors
    /// When the pattern is unusable.
    fn analyze(&mut self, _a: &dyn LinearOperator) -> Result<(), SolverError> {
        Ok(())
    }

    /// Numeric set-up for `a`'s current values (factorisation or preconditioner); says what
    /// it did and what it cost.
    ///
    /// # Errors
    /// [`SolverError::NotPositiveDefinite`] and the like.
    fn factorize(&mut self, a: &dyn LinearOperator) -> Result<SetupStats, SolverError>;

    /// Sets the relative residual tolerance of later solves (adaptive forcing terms); a
    /// no-op for direct solvers.
    ///
    /// # Errors
    /// [`SolverError::InvalidParameter`] for a value outside `(0, 1)`.
    fn set_relative_tolerance(&mut self, _rel: f64) -> Result<(), SolverError> {
        Ok(())
    }

    /// Makes later solves stop once the residual norm is at or below `floor`, whatever the
    /// relative and absolute tolerances ask (0 clears it); a no-op for direct solvers.
    /// Newton sets it from its own tolerance: a linear residual far below the one Newton
    /// accepts buys no accuracy in the step's result.
    fn set_residual_floor(&mut self, _floor: f64) {}

    /// Makes the next `factorize` recompute anything it would otherwise reuse (a stale
    /// preconditioner); a no-op for solvers that keep nothing.
    fn refresh(&mut self) {}

    /// Positions of the matrix's nodes, one per 3 rows (a mesh's free vertices in row order),
    /// for fill-reducing orderings that use geometry (nested dissection by median planes,
    /// [`Cholesky::set_coordinates`]); a no-op for solvers that do not factorise. Takes effect
    /// at the next analysis.
    fn set_coordinates(&mut self, _coordinates: Option<&[[f64; 3]]>) {}

    /// Solves `a x = b`; `x` holds the initial guess on entry and the solution on exit.
    ///
    /// # Errors
    /// Dimension mismatch, non-finite input, breakdown or non-convergence (with stats).
    fn solve(
        &mut self,
        a: &dyn LinearOperator,
        b: &[f64],
        x: &mut [f64],
    ) -> Result<SolveStats, SolverError>;
}
