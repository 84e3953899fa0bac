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

/// Rows per parallel task of the CSR product.
const ROW_CHUNK: usize = 1024;
/// Below this many nonzeros the product runs on the calling thread (same arithmetic).
const PARALLEL_NNZ: usize = 200_000;
/// Entries per partial sum of dot products and per task of vector updates.
const VECTOR_CHUNK: usize = 8192;
/// Below this length vector operations run on the calling thread (same arithmetic).
const PARALLEL_LEN: usize = 4 * VECTOR_CHUNK;

/// `sqrt(x . x)`.
pub(crate) fn norm(x: &[f64]) -> f64 {
    dot(x, x).sqrt()
}

/// `x . y` as partial sums over fixed chunks of `VECTOR_CHUNK` entries, added in chunk
/// order: the same arithmetic whether the chunks run in parallel or not, so the result does
/// not depend on the thread count.
pub(crate) fn dot(x: &[f64], y: &[f64]) -> f64 {
    let partial = |(a, b): (&[f64], &[f64])| a.iter().zip(b).map(|(p, q)| p * q).sum::<f64>();
    if x.len() < PARALLEL_LEN {
        x.chunks(VECTOR_CHUNK)
            .zip(y.chunks(VECTOR_CHUNK))
            .map(partial)
            .sum()
    } else {
        let parts: Vec<f64> = x
            .par_chunks(VECTOR_CHUNK)
            .zip(y.par_chunks(VECTOR_CHUNK))
            .map(partial)
            .collect();
        parts.iter().sum()
    }
}

/// Applies `f(i, &mut y[i])` to every entry, in parallel chunks for long vectors.
pub(crate) fn for_each_entry(y: &mut [f64], f: impl Fn(usize, &mut f64) + Sync + Send) {
    let chunk = |(c, ys): (usize, &mut [f64])| {
        for (k, v) in ys.iter_mut().enumerate() {
            f(c * VECTOR_CHUNK + k, v);
        }
    };
    if y.len() < PARALLEL_LEN {
        y.chunks_mut(VECTOR_CHUNK).enumerate().for_each(chunk);
    } else {
        y.par_chunks_mut(VECTOR_CHUNK).enumerate().for_each(chunk);
    }
}
