//! The block copy iterative solvers multiply with: a CSR matrix whose rows come in 3x3
//! blocks, as block CSR ([`Bsr3`]), behind the [`LinearOperator`] trait.

use nalgebra::Matrix3;
use sprs::CsMat;

use crate::SolverError;
use crate::blocks::Blocks;
use crate::operator::{LinearOperator, PARALLEL_NNZ};

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
