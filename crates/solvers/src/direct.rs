//! Sparse direct Cholesky through faer, with the symbolic analysis kept across
//! refactorisations of the same pattern.

use std::time::Instant;

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::ldlt::factor::LdltRegularization;
use faer::perm::PermRef;
use faer::sparse::linalg::cholesky::{
    CholeskySymbolicParams, LdltRef, LltRef, SymbolicCholesky, SymbolicCholeskyRaw,
    SymmetricOrdering, factorize_symbolic_cholesky,
};
use faer::sparse::linalg::{SupernodalThreshold, SymbolicSupernodalParams};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Par, Side};
use serde::{Deserialize, Serialize};

use crate::error::check_vector;
use crate::llt::{PARALLEL_TASKS, factor_counts, numeric_llt};
use crate::operator::LinearOperator;
use crate::ordering::{Elimination, Ordering, order_rows};
use crate::split::{Failure, Split};
use crate::stats::{SetupStats, SolveStats, Termination};
use crate::vector::norm;
use crate::{LinearSolver, SolverError};

/// What the direct solver does with a matrix that is not positive definite.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum Indefinite {
    /// Report [`SolverError::NotPositiveDefinite`].
    #[default]
    Error,
    /// Factorise `L D L^T` instead (no pivoting: a zero pivot is still an error).
    Ldlt,
}

/// The arithmetic of the factorisation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum Precision {
    /// Factor and solve in `f64`.
    #[default]
    Double,
    /// Factor in `f32` (half the memory traffic, twice the SIMD width) and refine the
    /// solution in `f64` (`x += L^-T L^-1 (b - A x)`) until the residual is as small as a
    /// double factor's or stops shrinking (mixed-precision iterative refinement, as LAPACK's
    /// `dsposv`). When the single-precision factor fails (a non-positive pivot) or its
    /// refinement does not contract (`cond(A) eps_32` near 1), the matrix is refactorised in
    /// `f64`, charged to that call. Only positive definite matrices: an `Ldlt` fallback is
    /// always in double.
    Mixed,
}

/// Mixed precision: refinement stops below this relative residual ...
const REFINE_RELATIVE: f64 = 1e-13;
/// ... or when a step shrinks the residual by less than this factor ...
const REFINE_STALL: f64 = 0.5;
/// ... or after this many steps.
const REFINE_MAX_STEPS: usize = 12;

/// Above this many rows `Ordering::Auto` uses nested dissection without trying AMD.
const AUTO_ND_ONLY_ROWS: usize = 30_000;

/// Which factor a split analysis holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Llt,
    /// `L L^T` in single precision.
    Llt32,
}

/// The numeric factor of a whole analysis.
#[derive(Debug)]
enum Numeric {
    Llt(Vec<f64>),
    Ldlt(Vec<f64>),
    /// `L L^T` in single precision.
    Llt32(Vec<f32>),
}

/// What the solver holds: nothing, the whole matrix's analysis (and its factor once
/// factorised), or the analysis split at nested dissection's first cut (and the kind of its
/// factor once factorised).
#[derive(Debug, Default)]
#[allow(clippy::large_enum_variant)] // one per solver; boxing the analysis gains nothing
enum Factor {
    #[default]
    Empty,
    Whole {
        symbolic: SymbolicCholesky<usize>,
        numeric: Option<Numeric>,
    },
    Split {
        split: Box<Split>,
        kind: Option<Kind>,
    },
}

/// Sparse Cholesky `A = L L^T` (or `L D L^T`) of a symmetric CSR matrix in full storage.
///
/// The CSR arrays are handed to faer as the CSC arrays of `A^T = A`, without copying.
/// [`LinearSolver::analyze`] orders and factorises symbolically; `factorize` reuses that
/// analysis while the pattern is unchanged (and redoes it, reported in [`SetupStats`], when
/// the pattern changed). Matrices of at least 20,000 rows are factorised as two fixed
/// parallel tasks (the halves of nested dissection's first cut, [`Cholesky::set_parallel`]);
/// smaller ones on one thread. Either way the factor's bits do not depend on the thread
/// count. What is held (nothing, the whole analysis and its factor, or the split one) is one
/// state.
#[derive(Debug)]
pub struct Cholesky {
    ordering: Ordering,
    indefinite: Indefinite,
    /// The pattern the symbolic analysis belongs to.
    pattern: Option<(Vec<usize>, Vec<usize>)>,
    analyze_seconds: f64,
    parallel: bool,
    precision: Precision,
    /// The analysis and the factor held.
    factor: Factor,
    /// Scratch: the matrix's values rounded to `f32`.
    matrix32: Vec<f32>,
    /// Coordinates of the nodes (one per 3 rows) for geometric nested dissection.
    coordinates: Option<Vec<[f64; 3]>>,
    /// Rows from which a parallel nested-dissection factorisation is split.
    pub(crate) split_min_rows: usize,
}

impl Cholesky {
    /// A solver with the given ordering and indefinite-matrix policy.
    pub fn new(ordering: Ordering, indefinite: Indefinite) -> Self {
        Self {
            ordering,
            indefinite,
            pattern: None,
            analyze_seconds: 0.0,
            parallel: true,
            precision: Precision::Double,
            factor: Factor::Empty,
            matrix32: Vec::new(),
            coordinates: None,
            split_min_rows: PARALLEL_MIN_ROWS,
        }
    }

    /// Positions of the matrix's nodes, one per 3 rows (the free vertices of a mesh, in row
    /// order): nested dissection then cuts each part by the median plane across its longest
    /// extent instead of by a graph level set. Takes effect at the next analysis; ignored
    /// when the length does not match.
    pub fn set_coordinates(&mut self, coordinates: Option<&[[f64; 3]]>) {
        self.coordinates = coordinates.map(<[[f64; 3]]>::to_vec);
        self.pattern = None;
    }

    /// Factorise in double (default) or single precision with refinement ([`Precision`]).
    pub fn set_precision(&mut self, precision: Precision) {
        self.precision = precision;
    }

    /// The configured precision.
    pub fn precision(&self) -> Precision {
        self.precision
    }

    /// Whether a large factorisation (at least `PARALLEL_MIN_ROWS` rows) runs as
    /// `PARALLEL_TASKS` parallel tasks (the default) or on one thread. With a nested
    /// dissection ordering the tasks are the two parts of its first cut, factorised
    /// concurrently, and the separator's Schur complement after them; otherwise faer's
    /// kernels are split. The tasks are fixed, not the pool's thread count, so the result is
    /// bit-identical on any pool; small matrices always run on one thread, where parallel
    /// overhead outweighs the gain. A change takes effect at the next analysis (the split is
    /// part of it), which `factorize` then redoes.
    pub fn set_parallel(&mut self, parallel: bool) {
        if parallel != self.parallel {
            self.parallel = parallel;
            self.pattern = None;
        }
    }

    fn par(&self, rows: usize) -> Par {
        if self.parallel && rows >= PARALLEL_MIN_ROWS {
            Par::rayon(PARALLEL_TASKS)
        } else {
            Par::Seq
        }
    }

    /// Nonzeros stored for the factor `L` (0 before `analyze`).
    pub fn factor_nnz(&self) -> usize {
        self.counts().0
    }

    /// Floating-point operations of one numeric factorisation with the held analysis (0
    /// before `analyze`): the deterministic work figure of `SetupStats::flops`.
    pub fn factor_flops(&self) -> u64 {
        self.counts().1
    }

    fn counts(&self) -> (usize, u64) {
        match &self.factor {
            Factor::Split { split, .. } => split.counts(),
            Factor::Whole { symbolic, .. } => factor_counts(symbolic),
            Factor::Empty => (0, 0),
        }
    }

    /// The order of the held analysis (`None` before `analyze`).
    pub fn nrows(&self) -> Option<usize> {
        match &self.factor {
            Factor::Split { split, .. } => Some(split.nrows()),
            Factor::Whole { symbolic, .. } => Some(symbolic.nrows()),
            Factor::Empty => None,
        }
    }

    /// Whether a factor for the current values exists.
    pub fn is_factorized(&self) -> bool {
        matches!(
            self.factor,
            Factor::Whole {
                numeric: Some(_),
                ..
            } | Factor::Split { kind: Some(_), .. }
        )
    }

    /// Whether the held factor is `L D L^T` (the matrix was not positive definite).
    pub fn is_ldlt(&self) -> bool {
        matches!(
            self.factor,
            Factor::Whole {
                numeric: Some(Numeric::Ldlt(_)),
                ..
            }
        )
    }

    /// Whether the held analysis is split at nested dissection's first cut.
    #[cfg(test)]
    pub(crate) fn is_split(&self) -> bool {
        matches!(self.factor, Factor::Split { .. })
    }

    /// Whether the held factor is in single precision.
    fn is_single(&self) -> bool {
        matches!(
            self.factor,
            Factor::Whole {
                numeric: Some(Numeric::Llt32(_)),
                ..
            } | Factor::Split {
                kind: Some(Kind::Llt32),
                ..
            }
        )
    }

    /// Forgets the numeric factor (the analysis stays).
    fn forget_numeric(&mut self) {
        match &mut self.factor {
            Factor::Whole { numeric, .. } => *numeric = None,
            Factor::Split { kind, .. } => *kind = None,
            Factor::Empty => {}
        }
    }

    /// Wall time of the last symbolic analysis.
    pub fn analyze_seconds(&self) -> f64 {
        self.analyze_seconds
    }

    fn csr(a: &dyn LinearOperator) -> Result<&sprs::CsMat<f64>, SolverError> {
        a.csr().ok_or(SolverError::Unsupported(
            "the direct solver needs an assembled CSR matrix",
        ))
    }

    fn same_pattern(&self, indptr: &[usize], indices: &[usize]) -> bool {
        self.pattern
            .as_ref()
            .is_some_and(|(p, i)| p == indptr && i == indices)
    }

    /// Solves with the held factor, in place (`x` holds `b` on entry).
    pub(crate) fn solve_in_place(&self, x: &mut [f64]) -> Result<(), SolverError> {
        crate::kernels::confined(|| self.solve_here(x))
    }

    fn solve_here(&self, x: &mut [f64]) -> Result<(), SolverError> {
        let n = self.nrows().ok_or(SolverError::NotFactorized)?;
        if !self.is_factorized() {
            return Err(SolverError::NotFactorized);
        }
        if x.len() != n {
            return Err(SolverError::DimensionMismatch {
                what: "x",
                expected: n,
                found: x.len(),
            });
        }
        let (symbolic, numeric) = match &self.factor {
            Factor::Split { split, .. } => {
                split.solve_in_place(x);
                return Ok(());
            }
            Factor::Whole {
                symbolic,
                numeric: Some(numeric),
            } => (symbolic, numeric),
            _ => return Err(SolverError::NotFactorized),
        };
        let par = self.par(n);
        if let Numeric::Llt32(values) = numeric {
            let mut x32: Vec<f32> = x.iter().map(|&v| v as f32).collect();
            let req = symbolic.solve_in_place_scratch::<f32>(1, par);
            let mut mem = MemBuffer::try_new(req).map_err(|_| SolverError::OutOfMemory)?;
            let rhs = MatMut::from_column_major_slice_mut(&mut x32, n, 1);
            LltRef::new(symbolic, values).solve_in_place_with_conj(
                Conj::No,
                rhs,
                par,
                MemStack::new(&mut mem),
            );
            for (xi, v) in x.iter_mut().zip(&x32) {
                *xi = f64::from(*v);
            }
            return Ok(());
        }
        let req = symbolic.solve_in_place_scratch::<f64>(1, par);
        let mut mem = MemBuffer::try_new(req).map_err(|_| SolverError::OutOfMemory)?;
        let stack = MemStack::new(&mut mem);
        let rhs = MatMut::from_column_major_slice_mut(x, n, 1);
        match numeric {
            Numeric::Llt(values) => {
                LltRef::new(symbolic, values).solve_in_place_with_conj(Conj::No, rhs, par, stack)
            }
            Numeric::Ldlt(values) => {
                LdltRef::new(symbolic, values).solve_in_place_with_conj(Conj::No, rhs, par, stack)
            }
            Numeric::Llt32(_) => unreachable!("handled above"),
        }
        Ok(())
    }

    /// Flops of one solve with the factor (forward and backward substitution).
    pub(crate) fn solve_flops(&self) -> u64 {
        4 * self.factor_nnz() as u64
    }
}

/// Factorises a split analysis: `Ok(Ok(kind))` when done (its cost added to `setup`),
/// `Ok(Err(order))` when the matrix is indefinite and `policy` asks for `L D L^T` of the
/// whole matrix in `order`.
fn factorize_split(
    split: &mut Split,
    data: &[f64],
    precision: Precision,
    policy: Indefinite,
    setup: &mut SetupStats,
    start: Instant,
) -> Result<Result<Kind, Elimination>, SolverError> {
    let done = |kind, setup: &mut SetupStats, split: &Split| {
        let (nnz, flops) = split.counts();
        setup.flops += flops;
        setup.factor_nnz = nnz;
        setup.seconds += start.elapsed().as_secs_f64();
        Ok(Ok(kind))
    };
    if precision == Precision::Mixed {
        match split.factorize(data, true) {
            Ok(()) => return done(Kind::Llt32, setup, split),
            // Charged, and the double factorisation is tried.
            Err(Failure::Pivot(_) | Failure::NonFinite) => setup.flops += split.counts().1,
            Err(Failure::Error(e)) => return Err(e),
        }
    }
    match split.factorize(data, false) {
        Ok(()) => done(Kind::Llt, setup, split),
        Err(Failure::Error(e)) => Err(e),
        Err(Failure::NonFinite) => Err(SolverError::NonFinite {
            what: "factor",
            index: 0,
        }),
        Err(Failure::Pivot(row)) if policy == Indefinite::Error => {
            let (nnz, flops) = split.counts();
            setup.flops += flops;
            setup.factor_nnz = nnz;
            setup.seconds += start.elapsed().as_secs_f64();
            Err(SolverError::NotPositiveDefinite {
                pivot: row,
                value: f64::NAN,
                spent: Some(Box::new(*setup)),
            })
        }
        Err(Failure::Pivot(_)) => {
            setup.flops += split.counts().1;
            Ok(Err(Elimination {
                order: std::mem::take(&mut split.order),
                top: None,
            }))
        }
    }
}

/// `L D L^T` of `matrix` into `values` (no pivoting: a zero pivot is an error, charged).
fn numeric_ldlt(
    symbolic: &SymbolicCholesky<usize>,
    values: &mut Vec<f64>,
    matrix: SparseColMatRef<'_, usize, f64>,
    par: Par,
    setup: SetupStats,
    start: Instant,
) -> Result<(), SolverError> {
    crate::llt::zeroed(values, symbolic.len_val())?;
    let req = symbolic.factorize_numeric_ldlt_scratch::<f64>(par, Default::default());
    let mut mem = MemBuffer::try_new(req).map_err(|_| SolverError::OutOfMemory)?;
    let factor = || {
        symbolic
            .factorize_numeric_ldlt(
                values,
                matrix,
                Side::Lower,
                LdltRegularization::default(),
                par,
                MemStack::new(&mut mem),
                Default::default(),
            )
            .map(|_| ())
    };
    crate::kernels::confined(factor).map_err(|e| match e {
        faer::linalg::cholesky::ldlt::factor::LdltError::ZeroPivot { index } => {
            SolverError::NotPositiveDefinite {
                pivot: permuted_row(symbolic, index),
                value: 0.0,
                spent: Some(Box::new(spent(symbolic, setup, start))),
            }
        }
    })
}

/// The set-up stats of a factorisation that failed: charged as a whole one.
fn spent(symbolic: &SymbolicCholesky<usize>, mut setup: SetupStats, start: Instant) -> SetupStats {
    let (nnz, flops) = factor_counts(symbolic);
    setup.flops += flops;
    setup.factor_nnz = nnz;
    setup.seconds += start.elapsed().as_secs_f64();
    setup
}

impl LinearSolver for Cholesky {
    fn set_coordinates(&mut self, coordinates: Option<&[[f64; 3]]>) {
        Cholesky::set_coordinates(self, coordinates);
    }

    fn name(&self) -> String {
        match self.precision {
            Precision::Double => format!("cholesky({:?})", self.ordering),
            Precision::Mixed => format!("cholesky({:?}, mixed)", self.ordering),
        }
    }

    fn analyze(&mut self, a: &dyn LinearOperator) -> Result<(), SolverError> {
        let start = Instant::now();
        let csr = Self::csr(a)?;
        let indptr_view = csr.indptr();
        let (indptr, indices) = (indptr_view.raw_storage(), csr.indices());
        let coords = self.coordinates.as_deref();
        self.factor = Factor::Empty;
        let n = indptr.len() - 1;
        let order = |ordering| order_rows(ordering, indptr, indices, coords);
        // The order, and its symbolic factorisation when it had to be computed to choose.
        let (elim, whole) = match self.ordering {
            // Past about 10k vertices nested dissection has won on every mesh measured (by
            // 25 % fill on the 55k-DOF beam), so the AMD analysis is not worth its time.
            Ordering::Auto if indptr.len() > AUTO_ND_ONLY_ROWS => {
                (order(Ordering::NestedDissection), None)
            }
            Ordering::Auto => {
                let (amd, nd) = (order(Ordering::Amd), order(Ordering::NestedDissection));
                let (sa, sn) = (
                    symbolic_of(&amd, indptr, indices)?,
                    symbolic_of(&nd, indptr, indices)?,
                );
                if factor_counts(&sn).1 < factor_counts(&sa).1 {
                    (nd, Some(sn))
                } else {
                    (amd, Some(sa))
                }
            }
            ordering => (order(ordering), None),
        };
        // A nested-dissection order has a first cut: large parallel factorisations split there.
        let split = if self.parallel && n >= self.split_min_rows {
            Split::new(indptr, indices, &elim)?
        } else {
            None
        };
        self.factor = match split {
            Some(split) => Factor::Split {
                split: Box::new(split),
                kind: None,
            },
            None => Factor::Whole {
                symbolic: match whole {
                    Some(s) => s,
                    None => symbolic_of(&elim, indptr, indices)?,
                },
                numeric: None,
            },
        };
        self.pattern = Some((indptr.to_vec(), indices.to_vec()));
        self.analyze_seconds = start.elapsed().as_secs_f64();
        Ok(())
    }

    fn factorize(&mut self, a: &dyn LinearOperator) -> Result<SetupStats, SolverError> {
        self.factorize_in(a, self.precision)
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
        if self.nrows() != Some(n) || !self.is_factorized() {
            return Err(SolverError::NotFactorized);
        }
        let start = Instant::now();
        let mut stats = SolveStats::new(self.name(), norm(b));
        if self.is_single() {
            self.refine(a, b, x, &mut stats)?;
        } else {
            self.double_solve(a, b, x, &mut stats)?;
        }
        stats.seconds = start.elapsed().as_secs_f64();
        stats.termination = if stats.final_residual().is_finite() {
            Termination::Direct
        } else {
            Termination::Diverged
        };
        if stats.termination == Termination::Diverged {
            return Err(SolverError::NotConverged {
                stats: Box::new(stats),
            });
        }
        Ok(stats)
    }
}

impl Cholesky {
    /// Factorises `a` in `precision` (the configured one, or double when refinement with
    /// a single factor failed), reusing the analysis while the pattern is unchanged.
    fn factorize_in(
        &mut self,
        a: &dyn LinearOperator,
        precision: Precision,
    ) -> Result<SetupStats, SolverError> {
        let csr = Self::csr(a)?;
        if csr.rows() != csr.cols() {
            return Err(SolverError::DimensionMismatch {
                what: "columns",
                expected: csr.rows(),
                found: csr.cols(),
            });
        }
        check_vector("matrix values", csr.data(), csr.nnz())?;
        let indptr_view = csr.indptr();
        let (indptr, indices) = (indptr_view.raw_storage(), csr.indices());
        let mut setup = SetupStats::default();
        if !self.same_pattern(indptr, indices) {
            self.analyze(a)?;
            setup.analyzed = true;
            setup.seconds += self.analyze_seconds;
        }
        let start = Instant::now();
        let n = csr.rows();
        self.forget_numeric();
        // Set when the split `L L^T` found the matrix indefinite: straight to `L D L^T`.
        let mut indefinite = false;
        if let Factor::Split { split, kind } = &mut self.factor {
            let policy = self.indefinite;
            match factorize_split(split, csr.data(), precision, policy, &mut setup, start)? {
                Ok(done) => {
                    *kind = Some(done);
                    return Ok(setup);
                }
                Err(order) => {
                    // `L D L^T` of the whole matrix in the same order, kept for this pattern.
                    self.factor = Factor::Whole {
                        symbolic: symbolic_of(&order, indptr, indices)?,
                        numeric: None,
                    };
                    indefinite = true;
                }
            }
        }
        let par = self.par(n);
        let Factor::Whole { symbolic, numeric } = &mut self.factor else {
            unreachable!("analysed above")
        };
        let pattern = SymbolicSparseColMatRef::new_unsorted_checked(n, n, indptr, None, indices);
        // The held factor's buffer is reused; only one precision is held at a time.
        let (mut values, mut values32) = match numeric.take() {
            Some(Numeric::Llt(v) | Numeric::Ldlt(v)) => (v, Vec::new()),
            Some(Numeric::Llt32(v)) => (Vec::new(), v),
            None => (Vec::new(), Vec::new()),
        };
        if precision == Precision::Mixed && !indefinite {
            self.matrix32.clear();
            self.matrix32.extend(csr.data().iter().map(|&v| v as f32));
            let matrix = SparseColMatRef::new(pattern, &self.matrix32);
            let single = numeric_llt(symbolic, &mut values32, matrix, par)?;
            let (nnz, flops) = factor_counts(symbolic);
            setup.flops += flops;
            setup.factor_nnz = nnz;
            if single.is_ok() && values32.iter().all(|v| v.is_finite()) {
                *numeric = Some(Numeric::Llt32(values32));
                setup.seconds += start.elapsed().as_secs_f64();
                return Ok(setup);
            }
            // Not positive definite in single precision: try double (both charged).
        }
        drop(values32);
        let matrix = SparseColMatRef::new(pattern, csr.data());
        let llt = (!indefinite)
            .then(|| numeric_llt(symbolic, &mut values, matrix, par))
            .transpose()?;
        let ldlt = match llt {
            Some(Ok(())) => false,
            Some(Err(faer::linalg::cholesky::llt::factor::LltError::NonPositivePivot {
                index,
            })) if self.indefinite == Indefinite::Error => {
                return Err(SolverError::NotPositiveDefinite {
                    pivot: permuted_row(symbolic, index),
                    value: f64::NAN,
                    spent: Some(Box::new(spent(symbolic, setup, start))),
                });
            }
            _ => {
                numeric_ldlt(symbolic, &mut values, matrix, par, setup, start)?;
                true
            }
        };
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(SolverError::NonFinite {
                what: "factor",
                index: i,
            });
        }
        let (nnz, flops) = factor_counts(symbolic);
        *numeric = Some(if ldlt {
            Numeric::Ldlt(values)
        } else {
            Numeric::Llt(values)
        });
        setup.flops += flops;
        setup.factor_nnz = nnz;
        setup.seconds += start.elapsed().as_secs_f64();
        Ok(setup)
    }

    /// Mixed precision: `x = 0`, then `x += solve_32(b - A x)` until the residual is below
    /// `REFINE_RELATIVE ||b||` or stalls; refactorises in double when it stalls far above.
    fn refine(
        &mut self,
        a: &dyn LinearOperator,
        b: &[f64],
        x: &mut [f64],
        stats: &mut SolveStats,
    ) -> Result<(), SolverError> {
        let n = b.len();
        let step_flops = self.solve_flops() + a.apply_flops() + 5 * n as u64;
        let bn = norm(b).max(f64::MIN_POSITIVE);
        x.iter_mut().for_each(|v| *v = 0.0);
        let (mut r, mut d) = (b.to_vec(), vec![0.0; n]);
        let mut best = (f64::INFINITY, vec![0.0; n]);
        for _ in 0..REFINE_MAX_STEPS {
            d.copy_from_slice(&r);
            self.solve_in_place(&mut d)?;
            for (xi, di) in x.iter_mut().zip(&d) {
                *xi += di;
            }
            residual_into(a, b, x, &mut r);
            let rn = norm(&r);
            stats.residuals.push(rn);
            stats.iterations += 1;
            stats.matvecs += 1;
            stats.flops += step_flops;
            let stalled = !(rn < REFINE_STALL * best.0);
            if rn < best.0 {
                best.0 = rn;
                best.1.copy_from_slice(x);
            }
            if rn <= REFINE_RELATIVE * bn || stalled {
                break;
            }
        }
        // A stall at the rounding level of double is a converged solve; far above it, the
        // single factor is too inaccurate for this matrix.
        if best.0 <= 1e3 * REFINE_RELATIVE * bn {
            x.copy_from_slice(&best.1);
            if stats.final_residual() != best.0 {
                stats.residuals.push(best.0);
            }
            return Ok(());
        }
        let setup = self.factorize_in(a, Precision::Double)?;
        stats.flops += setup.flops;
        self.double_solve(a, b, x, stats)
    }

    /// `x = A^-1 b` with the held double factor and one residual evaluation, so callers see
    /// the accuracy they got.
    fn double_solve(
        &self,
        a: &dyn LinearOperator,
        b: &[f64],
        x: &mut [f64],
        stats: &mut SolveStats,
    ) -> Result<(), SolverError> {
        x.copy_from_slice(b);
        self.solve_in_place(x)?;
        let mut r = vec![0.0; b.len()];
        residual_into(a, b, x, &mut r);
        stats.residuals.push(norm(&r));
        stats.matvecs += 1;
        stats.flops += self.solve_flops() + a.apply_flops() + 3 * b.len() as u64;
        Ok(())
    }
}

/// `r = b - A x`.
fn residual_into(a: &dyn LinearOperator, b: &[f64], x: &[f64], r: &mut [f64]) {
    a.apply(x, r);
    for (ri, bi) in r.iter_mut().zip(b) {
        *ri = bi - *ri;
    }
}

/// The symbolic factorisation of a pattern in a given elimination order.
fn symbolic_of(
    elim: &Elimination,
    indptr: &[usize],
    indices: &[usize],
) -> Result<SymbolicCholesky<usize>, SolverError> {
    let n = indptr.len() - 1;
    let pattern = SymbolicSparseColMatRef::new_unsorted_checked(n, n, indptr, None, indices);
    // Always a custom permutation: faer's `Identity` ordering reads the pattern as given,
    // while the permuting path extracts the requested triangle of full storage.
    let fwd = &elim.order;
    let mut inv = vec![0; n];
    for (new, &old) in fwd.iter().enumerate() {
        inv[old] = new;
    }
    let ordering = SymmetricOrdering::Custom(PermRef::new_checked(fwd, &inv, n));
    let symbolic = |params| {
        factorize_symbolic_cholesky(pattern, Side::Lower, ordering, params)
            .map_err(|_| SolverError::OutOfMemory)
    };
    let default = symbolic(CholeskySymbolicParams::default())?;
    if let SymbolicCholeskyRaw::Supernodal(_) = default.raw() {
        return Ok(default);
    }
    // faer picks the simplicial kernels below 40 flops per nonzero, which factor the few
    // hundred DOFs of coarse models at half the speed of the supernodal ones (measured: 500
    // against 290 us a Backward-Euler step at 216 DOFs). Without relaxed supernodes the
    // factor has the simplicial one's structure, so its flop count (the work figure) is
    // the same.
    symbolic(CholeskySymbolicParams {
        supernodal_flop_ratio_threshold: SupernodalThreshold::FORCE_SUPERNODAL,
        supernodal_params: SymbolicSupernodalParams { relax: None },
        ..Default::default()
    })
}

/// The original row of failing pivot `index` of the permuted matrix as faer reports it
/// (its simplicial kernels count from 1, the supernodal ones from 0).
fn permuted_row(symbolic: &SymbolicCholesky<usize>, index: usize) -> usize {
    let index = match symbolic.raw() {
        SymbolicCholeskyRaw::Simplicial(_) => index.saturating_sub(1),
        SymbolicCholeskyRaw::Supernodal(_) => index,
    };
    symbolic
        .perm()
        .map_or(index, |p| p.arrays().0.get(index).copied().unwrap_or(index))
}

/// Rows below which factorisations and solves run on one thread.
const PARALLEL_MIN_ROWS: usize = 20_000;
