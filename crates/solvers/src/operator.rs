//! Operators: what a solver needs from a matrix, assembled (CSR) or matrix-free.

use nalgebra::Matrix3;
use rayon::prelude::*;
use sprs::CsMat;

use crate::SolverError;

/// A square symmetric linear operator `y = A x` on flat vectors.
///
/// Matrix-free operators (element-by-element force differentials) implement `apply` and
/// `diagonal`; an assembled matrix also exposes its CSR arrays, which incomplete
/// factorisations, SSOR and direct solvers need.
pub trait LinearOperator: Sync {
    /// Number of rows (and columns).
    fn nrows(&self) -> usize;

    /// `y = A x`.
    fn apply(&self, x: &[f64], y: &mut [f64]);

    /// The diagonal of `A`.
    fn diagonal(&self, out: &mut [f64]);

    /// The 3x3 diagonal blocks of `A` (one per vertex, `nrows` divisible by 3).
    ///
    /// # Errors
    /// [`SolverError::Unsupported`] when the operator cannot provide them.
    fn block_diagonal(&self, _out: &mut [Matrix3<f64>]) -> Result<(), SolverError> {
        Err(SolverError::Unsupported(
            "this operator has no 3x3 block diagonal",
        ))
    }

    /// The assembled CSR matrix, if there is one.
    fn csr(&self) -> Option<&CsMat<f64>> {
        None
    }

    /// Floating-point operations of one `apply`, for the deterministic work count.
    fn apply_flops(&self) -> u64;
}

/// CSR with full symmetric storage and sorted columns, as deform assembles K.
impl LinearOperator for CsMat<f64> {
    fn nrows(&self) -> usize {
        self.rows()
    }

    fn apply(&self, x: &[f64], y: &mut [f64]) {
        let (indptr, indices, data) = (self.indptr(), self.indices(), self.data());
        let indptr = indptr.raw_storage();
        // Rows in parallel, each row summed in order: identical for any thread count.
        let rows = |(c, ys): (usize, &mut [f64])| {
            for (r, yi) in ys.iter_mut().enumerate() {
                let i = c * ROW_CHUNK + r;
                let mut acc = 0.0;
                for k in indptr[i]..indptr[i + 1] {
                    acc += data[k] * x[indices[k]];
                }
                *yi = acc;
            }
        };
        if self.nnz() < PARALLEL_NNZ {
            y.chunks_mut(ROW_CHUNK).enumerate().for_each(rows);
        } else {
            y.par_chunks_mut(ROW_CHUNK).enumerate().for_each(rows);
        }
    }

    fn diagonal(&self, out: &mut [f64]) {
        let (indptr, indices, data) = (self.indptr(), self.indices(), self.data());
        let indptr = indptr.raw_storage();
        for (i, d) in out.iter_mut().enumerate() {
            let row = &indices[indptr[i]..indptr[i + 1]];
            *d = row.binary_search(&i).map_or(0.0, |k| data[indptr[i] + k]);
        }
    }

    fn block_diagonal(&self, out: &mut [Matrix3<f64>]) -> Result<(), SolverError> {
        if !self.rows().is_multiple_of(3) {
            return Err(SolverError::Unsupported(
                "block diagonal needs a multiple of 3 rows",
            ));
        }
        let (indptr, indices, data) = (self.indptr(), self.indices(), self.data());
        let indptr = indptr.raw_storage();
        for (v, block) in out.iter_mut().enumerate() {
            *block = Matrix3::zeros();
            for r in 0..3 {
                let i = 3 * v + r;
                for k in indptr[i]..indptr[i + 1] {
                    let j = indices[k];
                    if j / 3 == v {
                        block[(r, j % 3)] = data[k];
                    }
                }
            }
        }
        Ok(())
    }

    fn csr(&self) -> Option<&CsMat<f64>> {
        Some(self)
    }

    fn apply_flops(&self) -> u64 {
        2 * self.nnz() as u64
    }
}

/// Rows per parallel task of the CSR product (a multiple of 3 for the block product).
const ROW_CHUNK: usize = 1020;
/// Below this many nonzeros the product runs on the calling thread (same arithmetic).
pub(crate) const PARALLEL_NNZ: usize = 200_000;
/// The diagonal of `a`, all of it positive, or [`SolverError::NotPositiveDefinite`] at the
/// first entry that is not.
pub(crate) fn positive_diagonal(a: &dyn LinearOperator) -> Result<Vec<f64>, SolverError> {
    let mut d = vec![0.0; a.nrows()];
    a.diagonal(&mut d);
    match d.iter().position(|&x| !(x > 0.0)) {
        Some(i) => Err(SolverError::NotPositiveDefinite {
            pivot: i,
            value: d[i],
            spent: None,
        }),
        None => Ok(d),
    }
}
