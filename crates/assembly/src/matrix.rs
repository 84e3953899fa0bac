//! K on an assembly's pattern, as a type: refilled without checking its column indices.

use std::ops::Deref;
use std::sync::atomic::{AtomicU64, Ordering};

use sprs::CsMat;

/// Identity of an assembly's stiffness pattern: every [`crate::Assembly::new`] draws a new
/// one (its clones share it, as they share the pattern).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct PatternId(u64);

impl PatternId {
    pub(crate) fn fresh() -> Self {
        static NEXT: AtomicU64 = AtomicU64::new(0);
        Self(NEXT.fetch_add(1, Ordering::Relaxed))
    }
}

/// A `3N x 3N` CSR matrix on an assembly's stiffness pattern (full symmetric storage, sorted
/// columns): K from [`crate::Assembly::stiffness`], or `c_m M + c_k K` from
/// [`crate::Assembly::combine`]. Made by [`crate::Assembly::stiffness_matrix`] (or checked
/// once by [`crate::Assembly::adopt_stiffness_matrix`]).
///
/// Its values can be refilled and read, its pattern cannot change, so the assembly knows it
/// by an id instead of comparing its column indices at every use: that comparison read
/// 19 MB at 98k tets and took 10-20 % of an energy + forces + K assembly, and as much in
/// every product that checked it. It reads as a `CsMat` (`Deref`), or hands it over.
#[derive(Debug, Clone)]
pub struct StiffnessMatrix {
    csr: CsMat<f64>,
    pattern: PatternId,
}

impl StiffnessMatrix {
    pub(crate) fn new(csr: CsMat<f64>, pattern: PatternId) -> Self {
        Self { csr, pattern }
    }

    pub(crate) fn pattern(&self) -> PatternId {
        self.pattern
    }

    /// The CSR matrix.
    pub fn csr(&self) -> &CsMat<f64> {
        &self.csr
    }

    /// The values, one per non-zero in CSR order, to scale or overwrite in place.
    pub fn values_mut(&mut self) -> &mut [f64] {
        self.csr.data_mut()
    }

    /// The CSR matrix, given up.
    pub fn into_csr(self) -> CsMat<f64> {
        self.csr
    }
}

/// Equal as matrices: same pattern and values, whichever assembly made them.
impl PartialEq for StiffnessMatrix {
    fn eq(&self, other: &Self) -> bool {
        self.csr == other.csr
    }
}

impl Deref for StiffnessMatrix {
    type Target = CsMat<f64>;

    fn deref(&self) -> &CsMat<f64> {
        &self.csr
    }
}
