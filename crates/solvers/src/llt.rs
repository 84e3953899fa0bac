//! The numeric `L L^T` kernel and its counts, shared by the whole factorisation
//! ([`crate::direct`]) and the one split at nested dissection's first cut ([`crate::split`]).

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::sparse::SparseColMatRef;
use faer::sparse::linalg::cholesky::{SymbolicCholesky, SymbolicCholeskyRaw};
use faer::{Par, Side};

use crate::SolverError;

/// `values` as `len` zeros, or [`SolverError::OutOfMemory`] when they do not fit: a large
/// factor under an address-space limit (`ulimit -v`) is refused as an error instead of
/// aborting the process.
pub(crate) fn zeroed<T: Default + Clone>(
    values: &mut Vec<T>,
    len: usize,
) -> Result<(), SolverError> {
    values.clear();
    values
        .try_reserve_exact(len)
        .map_err(|_| SolverError::OutOfMemory)?;
    values.resize(len, T::default());
    Ok(())
}

/// `L L^T` of `matrix` into `values` (sized to the analysis), in the precision of `T`; the
/// outer error is an allocation failure, the inner one faer's non-positive pivot.
pub(crate) fn numeric_llt<T: faer::traits::ComplexField + Default + Copy + Send + Sync>(
    symbolic: &SymbolicCholesky<usize>,
    values: &mut Vec<T>,
    matrix: SparseColMatRef<'_, usize, T>,
    par: Par,
) -> Result<Result<(), faer::linalg::cholesky::llt::factor::LltError>, SolverError> {
    zeroed(values, symbolic.len_val())?;
    let req = symbolic.factorize_numeric_llt_scratch::<T>(par, Default::default());
    let mut mem = MemBuffer::try_new(req).map_err(|_| SolverError::OutOfMemory)?;
    let factor = || {
        symbolic
            .factorize_numeric_llt(
                values,
                matrix,
                Side::Lower,
                LltRegularization::default(),
                par,
                MemStack::new(&mut mem),
                Default::default(),
            )
            .map(|_| ())
    };
    Ok(crate::kernels::confined(factor))
}

/// `(nnz(L), flops of the numeric factorisation)` from the symbolic structure.
pub(crate) fn factor_counts(symbolic: &SymbolicCholesky<usize>) -> (usize, u64) {
    match symbolic.raw() {
        SymbolicCholeskyRaw::Simplicial(s) => {
            let cp = s.col_ptr();
            let mut flops = 0u64;
            for j in 0..s.nrows() {
                let c = (cp[j + 1] - cp[j]) as u64;
                flops += c * c;
            }
            (s.len_val(), flops)
        }
        SymbolicCholeskyRaw::Supernodal(s) => {
            let (begin, end, rp) = (
                s.supernode_begin(),
                s.supernode_end(),
                s.col_ptr_for_row_idx(),
            );
            let (mut nnz, mut flops) = (0usize, 0u64);
            for k in 0..s.n_supernodes() {
                let w = end[k] - begin[k];
                let below = rp[k + 1] - rp[k];
                nnz += w * (w + 1) / 2 + w * below;
                for c in 0..w {
                    let rows = (w - c + below) as u64;
                    flops += rows * rows;
                }
            }
            (nnz, flops)
        }
    }
}

/// Tasks a parallel factorisation is split into, whatever the pool's size: faer's
/// parallel kernels partition by this number, so fixing it (rather than asking rayon for its
/// thread count) makes the factor's bits independent of the thread count.
pub(crate) const PARALLEL_TASKS: usize = 2;

#[cfg(test)]
mod tests {
    use super::*;

    /// A factor too large for the address space is an error, not an abort.
    #[test]
    fn a_factor_that_cannot_be_allocated_is_an_error() {
        let mut values: Vec<f64> = vec![1.0; 4];
        assert!(matches!(
            zeroed(&mut values, usize::MAX / 4),
            Err(SolverError::OutOfMemory)
        ));
        zeroed(&mut values, 3).unwrap();
        assert_eq!(values, [0.0; 3]);
    }
}
