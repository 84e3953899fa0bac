//! Operators: what a solver needs from a matrix, assembled (CSR) or matrix-free.

use nalgebra::Matrix3;
use rayon::prelude::*;
use sprs::CsMat;

use crate::SolverError;
use crate::blocks::Blocks;

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
const PARALLEL_NNZ: usize = 200_000;
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

/// A copy of a CSR matrix whose rows come in 3x3 blocks (every FEM matrix deform assembles,
/// reduced or not), stored as block CSR: 76 bytes per nine entries instead of 144, so the
/// memory-bound product moves about half the data. Each row is still summed in column order,
/// so the product equals the CSR product bit for bit.
pub(crate) struct Bsr3<'a> {
    blocks: Blocks,
    csr: &'a CsMat<f64>,
}

impl<'a> Bsr3<'a> {
    /// The block copy, or `None` when the pattern is not made of aligned 3x3 blocks.
    pub fn from_csr(a: &'a CsMat<f64>) -> Option<Self> {
        Some(Self {
            blocks: Blocks::from_aligned_csr(a, 3)?,
            csr: a,
        })
    }
}

impl LinearOperator for Bsr3<'_> {
    fn nrows(&self) -> usize {
        self.csr.rows()
    }

    fn apply(&self, x: &[f64], y: &mut [f64]) {
        self.blocks.multiply_vector(x, y);
    }

    fn diagonal(&self, out: &mut [f64]) {
        self.csr.diagonal(out);
    }

    fn block_diagonal(&self, out: &mut [Matrix3<f64>]) -> Result<(), SolverError> {
        self.csr.block_diagonal(out)
    }

    fn csr(&self) -> Option<&CsMat<f64>> {
        Some(self.csr)
    }

    fn apply_flops(&self) -> u64 {
        self.csr.apply_flops()
    }
}

/// The operator iterative solvers should multiply with: a block copy of a large blocked CSR
/// matrix (faster, same results), or `a` itself.
pub(crate) fn fast_operator(a: &dyn LinearOperator) -> Option<Bsr3<'_>> {
    a.csr()
        .filter(|m| m.nnz() >= PARALLEL_NNZ)
        .and_then(Bsr3::from_csr)
}

#[cfg(test)]
mod tests {
    use super::*;
    use sprs::TriMat;

    #[test]
    fn the_block_copy_multiplies_exactly_like_the_csr_matrix() {
        // A block-tridiagonal pattern of 3x3 blocks with irrational-ish values.
        let nb = 40;
        let n = 3 * nb;
        let mut t = TriMat::new((n, n));
        for i in 0..nb {
            for j in i.saturating_sub(1)..(i + 2).min(nb) {
                for r in 0..3 {
                    for c in 0..3 {
                        let v = ((7 * (3 * i + r) + 13 * (3 * j + c)) as f64).sin();
                        t.add_triplet(3 * i + r, 3 * j + c, v);
                    }
                }
            }
        }
        let a: CsMat<f64> = t.to_csr();
        let bsr = Bsr3::from_csr(&a).expect("a blocked pattern");
        let x: Vec<f64> = (0..n).map(|i| (i as f64 * 0.37).cos()).collect();
        let (mut y1, mut y2) = (vec![0.0; n], vec![0.0; n]);
        a.apply(&x, &mut y1);
        bsr.apply(&x, &mut y2);
        assert_eq!(y1, y2);
        // Not blocked: one extra entry breaks the triples.
        let mut t2 = TriMat::new((n, n));
        for (v, (i, j)) in a.iter() {
            t2.add_triplet(i, j, *v);
        }
        t2.add_triplet(0, n - 1, 1.0);
        assert!(Bsr3::from_csr(&t2.to_csr()).is_none());
    }
}
