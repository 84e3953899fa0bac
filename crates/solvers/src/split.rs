//! Tree-level parallelism for the sparse Cholesky: the first cut of a nested dissection.
//!
//! Ordered as nested dissection orders it, a matrix is `[A11 0 A13; 0 A22 A23; A31 A32 A33]`:
//! two parts that do not touch and their separator. Its factor is
//! `[L11 0 0; 0 L22 0; L31 L32 Ls]` with `Ls Ls^T = A33 - L31 L31^T - L32 L32^T`, the Schur
//! complement. faer parallelises inside large supernodes only (2 tasks gain about 1.1x on the
//! 55k-DOF beam), so the two halves `M_h = [Ahh Ah3; A3h A33]` (principal submatrices of an
//! SPD matrix, so SPD) are factorised on one thread each, concurrently. Each half's trailing
//! block is `Lc_h Lc_h^T = A33 - L3h L3h^T`, so the Schur complement is
//! `Lc1 Lc1^T + Lc2 Lc2^T - A33`, a small dense matrix (the separator is one cross-section)
//! factorised last. Solves run the two halves' triangular solves concurrently, stopping at
//! the separator. Every task's work is fixed by the cut, never by the pool: the factor's bits
//! do not depend on the thread count.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::{LltError, cholesky_in_place, cholesky_in_place_scratch};
use faer::linalg::matmul::matmul;
use faer::linalg::matmul::triangular::{self, BlockStructure};
use faer::linalg::triangular_solve::{
    solve_lower_triangular_in_place, solve_upper_triangular_in_place,
};
use faer::perm::PermRef;
use faer::reborrow::{Reborrow, ReborrowMut};
use faer::sparse::linalg::SupernodalThreshold;
use faer::sparse::linalg::cholesky::supernodal::{SupernodalLltRef, SymbolicSupernodalCholesky};
use faer::sparse::linalg::cholesky::{
    CholeskySymbolicParams, SymbolicCholesky, SymbolicCholeskyRaw, SymmetricOrdering,
    factorize_symbolic_cholesky,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Accum, MatMut, MatRef, Par, Side};

use crate::SolverError;
use crate::llt::{PARALLEL_TASKS, factor_counts, numeric_llt};
use crate::ordering::Elimination;

/// The two precisions a half is factorised in.
pub(crate) trait Scalar:
    faer::traits::ComplexField + Copy + Default + std::ops::SubAssign + Send + Sync
{
    fn from_f64(v: f64) -> Self;
    fn to_f64(self) -> f64;
}

impl Scalar for f64 {
    fn from_f64(v: f64) -> Self {
        v
    }
    fn to_f64(self) -> f64 {
        self
    }
}

impl Scalar for f32 {
    fn from_f64(v: f64) -> Self {
        v as f32
    }
    fn to_f64(self) -> f64 {
        f64::from(self)
    }
}

/// Why a split factorisation failed.
#[derive(Debug)]
pub(crate) enum Failure {
    /// A non-positive pivot at this original row.
    Pivot(usize),
    /// A non-finite entry in a factor.
    NonFinite,
    /// Out of memory.
    Error(SolverError),
}

impl From<SolverError> for Failure {
    fn from(e: SolverError) -> Self {
        Failure::Error(e)
    }
}

/// One part with the separator: `[Ahh Ah3; A3h A33]` in local numbering (the part's rows in
/// elimination order, then the separator's).
#[derive(Debug)]
struct Half {
    /// Original row of each local row.
    rows: Vec<usize>,
    /// Rows of the part; the separator's follow.
    part: usize,
    symbolic: SymbolicCholesky<usize>,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// For each local nonzero, its index in the full matrix's values.
    gather: Vec<usize>,
    values: Vec<f64>,
    values32: Vec<f32>,
}

/// The held factor: two halves and the separator's dense Schur-complement factor.
#[derive(Debug)]
pub(crate) struct Split {
    halves: [Half; 2],
    /// Original rows of the separator, in elimination order.
    sep_rows: Vec<usize>,
    /// `(index in the matrix's values, dense column-major index)` of the separator block's
    /// lower triangle.
    sep_gather: Vec<(usize, usize)>,
    /// Lower Cholesky factor of the Schur complement (column-major, separator order).
    sep_factor: Vec<f64>,
    /// Whether the halves hold single-precision factors.
    single: bool,
    /// The whole elimination order, for a whole-matrix analysis when this one cannot serve.
    pub order: Vec<usize>,
}

impl Split {
    /// The split of a symmetric pattern (full storage) along the elimination's first cut;
    /// `None` when there is no cut, a part is empty, or the separator does not separate.
    pub fn new(
        indptr: &[usize],
        indices: &[usize],
        elim: &Elimination,
    ) -> Result<Option<Self>, SolverError> {
        let Some((na, nb)) = elim.top else {
            return Ok(None);
        };
        if na == 0 || nb == 0 {
            return Ok(None);
        }
        let n = elim.order.len();
        let sep_rows = elim.order[na + nb..].to_vec();
        let s = sep_rows.len();
        let half = |start: usize, len: usize| {
            let rows: Vec<usize> = elim.order[start..start + len]
                .iter()
                .chain(&sep_rows)
                .copied()
                .collect();
            Half::new(indptr, indices, rows, len)
        };
        // The two symbolic factorisations are independent too.
        let (a, b) = rayon::join(|| half(0, na), || half(na, nb));
        let (Some(a), Some(b)) = (a?, b?) else {
            return Ok(None);
        };
        let mut local = vec![usize::MAX; n];
        for (j, &r) in sep_rows.iter().enumerate() {
            local[r] = j;
        }
        let mut sep_gather = Vec::new();
        for (j, &r) in sep_rows.iter().enumerate() {
            for k in indptr[r]..indptr[r + 1] {
                let i = local[indices[k]];
                if i != usize::MAX && i >= j {
                    sep_gather.push((k, i + s * j));
                }
            }
        }
        Ok(Some(Self {
            halves: [a, b],
            sep_rows,
            sep_gather,
            sep_factor: Vec::new(),
            single: false,
            order: elim.order.clone(),
        }))
    }

    pub fn nrows(&self) -> usize {
        self.order.len()
    }

    fn sep(&self) -> usize {
        self.sep_rows.len()
    }

    /// `(nnz, flops)` of the factor: both halves' (without their trailing blocks, which are
    /// scratch) and the separator's dense factor; flops count both halves whole, the two
    /// products `Lc Lc^T` and the dense factorisation.
    pub fn counts(&self) -> (usize, u64) {
        let s = self.sep();
        let dense_nnz = s * (s + 1) / 2;
        let dense_flops: u64 = (1..=s as u64).map(|r| r * r).sum();
        let (mut nnz, mut flops) = (dense_nnz, dense_flops);
        for h in &self.halves {
            let (hn, hf) = factor_counts(&h.symbolic);
            nnz += hn - dense_nnz;
            flops += hf + dense_flops;
        }
        (nnz, flops)
    }

    /// Factorises the matrix with values `data` (in the analysed pattern), the halves in
    /// single precision when `single`.
    pub fn factorize(&mut self, data: &[f64], single: bool) -> Result<(), Failure> {
        crate::kernels::confined(|| self.factorize_here(data, single))
    }

    fn factorize_here(&mut self, data: &[f64], single: bool) -> Result<(), Failure> {
        self.sep_factor = Vec::new();
        let [h0, h1] = &mut self.halves;
        let (t0, t1) = rayon::join(|| h0.factorize(data, single), || h1.factorize(data, single));
        let (mut schur, t1) = (t0?, t1?);
        self.single = single;
        // Lc1 Lc1^T + Lc2 Lc2^T - A33, lower triangle.
        for (a, b) in schur.iter_mut().zip(&t1) {
            *a += b;
        }
        for &(k, d) in &self.sep_gather {
            schur[d] -= data[k];
        }
        let s = self.sep();
        let par = Par::rayon(PARALLEL_TASKS);
        let req = cholesky_in_place_scratch::<f64>(s, par, Default::default());
        let mut mem = MemBuffer::try_new(req).map_err(|_| SolverError::OutOfMemory)?;
        let factor = MatMut::from_column_major_slice_mut(&mut schur, s, s);
        match cholesky_in_place(
            factor,
            Default::default(),
            par,
            MemStack::new(&mut mem),
            Default::default(),
        ) {
            Ok(_) => {}
            Err(LltError::NonPositivePivot { index }) => {
                return Err(Failure::Pivot(self.sep_rows[index.min(s - 1)]));
            }
        }
        if schur.iter().any(|v| !v.is_finite()) {
            return Err(Failure::NonFinite);
        }
        self.sep_factor = schur;
        Ok(())
    }

    /// `x = A^-1 x` with the held factor.
    pub fn solve_in_place(&self, x: &mut [f64]) {
        crate::kernels::confined(|| self.solve_here(x));
    }

    fn solve_here(&self, x: &mut [f64]) {
        let [h0, h1] = &self.halves;
        if self.single {
            self.solve_with(x, [&h0.values32, &h1.values32]);
        } else {
            self.solve_with(x, [&h0.values, &h1.values]);
        }
    }

    fn solve_with<T: Scalar>(&self, x: &mut [f64], values: [&[T]; 2]) {
        let [h0, h1] = &self.halves;
        let s = self.sep();
        // Forward: each half's part, leaving `-L3h yh` in its separator rows.
        let (mut y0, mut y1) =
            rayon::join(|| h0.forward(values[0], x), || h1.forward(values[1], x));
        let mut z: Vec<f64> = self.sep_rows.iter().map(|&r| x[r]).collect();
        for (j, zj) in z.iter_mut().enumerate() {
            *zj += y0[h0.part + j].to_f64() + y1[h1.part + j].to_f64();
        }
        let ls = MatRef::from_column_major_slice(&self.sep_factor, s, s);
        let mut zm = MatMut::from_column_major_slice_mut(&mut z, s, 1);
        solve_lower_triangular_in_place(ls, zm.rb_mut(), Par::Seq);
        solve_upper_triangular_in_place(ls.transpose(), zm.rb_mut(), Par::Seq);
        for (j, &zj) in z.iter().enumerate() {
            y0[h0.part + j] = T::from_f64(zj);
            y1[h1.part + j] = T::from_f64(zj);
        }
        rayon::join(
            || h0.backward(values[0], &mut y0),
            || h1.backward(values[1], &mut y1),
        );
        for (h, y) in [(h0, &y0), (h1, &y1)] {
            for (&r, v) in h.rows[..h.part].iter().zip(y) {
                x[r] = v.to_f64();
            }
        }
        for (&r, &zj) in self.sep_rows.iter().zip(&z) {
            x[r] = zj;
        }
    }
}

impl Half {
    /// The half of `rows` (the part's `part` rows, then the separator's); `None` when a part
    /// row has an entry outside the half (the cut does not separate).
    fn new(
        indptr: &[usize],
        indices: &[usize],
        rows: Vec<usize>,
        part: usize,
    ) -> Result<Option<Self>, SolverError> {
        let mut local = vec![usize::MAX; indptr.len() - 1];
        for (i, &r) in rows.iter().enumerate() {
            local[r] = i;
        }
        let (mut col_ptr, mut row_idx, mut gather) = (vec![0], Vec::new(), Vec::new());
        let mut separates = true;
        for (j, &r) in rows.iter().enumerate() {
            for k in indptr[r]..indptr[r + 1] {
                let i = local[indices[k]];
                if i != usize::MAX {
                    row_idx.push(i);
                    gather.push(k);
                } else if j < part {
                    separates = false;
                }
            }
            col_ptr.push(row_idx.len());
        }
        if !separates {
            return Ok(None);
        }
        let m = rows.len();
        let identity: Vec<usize> = (0..m).collect();
        let pattern = SymbolicSparseColMatRef::new_unsorted_checked(m, m, &col_ptr, None, &row_idx);
        let symbolic = factorize_symbolic_cholesky(
            pattern,
            Side::Lower,
            SymmetricOrdering::Custom(PermRef::new_checked(&identity, &identity, m)),
            CholeskySymbolicParams {
                supernodal_flop_ratio_threshold: SupernodalThreshold::FORCE_SUPERNODAL,
                ..Default::default()
            },
        )
        .map_err(|_| SolverError::OutOfMemory)?;
        Ok(Some(Self {
            rows,
            part,
            symbolic,
            col_ptr,
            row_idx,
            gather,
            values: Vec::new(),
            values32: Vec::new(),
        }))
    }

    fn supernodal(&self) -> &SymbolicSupernodalCholesky<usize> {
        match self.symbolic.raw() {
            SymbolicCholeskyRaw::Supernodal(s) => s,
            SymbolicCholeskyRaw::Simplicial(_) => unreachable!("forced supernodal"),
        }
    }

    /// Factorises the half and returns `Lc Lc^T` (dense, lower triangle, column-major).
    fn factorize(&mut self, data: &[f64], single: bool) -> Result<Vec<f64>, Failure> {
        // One factor at a time: a double fallback frees the single one and vice versa.
        if single {
            self.values = Vec::new();
            let mut values = std::mem::take(&mut self.values32);
            let schur = self.factorize_with(data, &mut values);
            self.values32 = values;
            schur
        } else {
            self.values32 = Vec::new();
            let mut values = std::mem::take(&mut self.values);
            let schur = self.factorize_with(data, &mut values);
            self.values = values;
            schur
        }
    }

    fn factorize_with<T: Scalar>(
        &self,
        data: &[f64],
        values: &mut Vec<T>,
    ) -> Result<Vec<f64>, Failure> {
        let m = self.rows.len();
        let matrix: Vec<T> = self.gather.iter().map(|&k| T::from_f64(data[k])).collect();
        let pattern =
            SymbolicSparseColMatRef::new_unsorted_checked(m, m, &self.col_ptr, None, &self.row_idx);
        let llt = numeric_llt(
            &self.symbolic,
            values,
            SparseColMatRef::new(pattern, &matrix),
            Par::Seq,
        )?;
        if let Err(LltError::NonPositivePivot { index }) = llt {
            values.clear();
            return Err(Failure::Pivot(self.rows[index.min(m - 1)]));
        }
        if values.iter().any(|v| !v.to_f64().is_finite()) {
            values.clear();
            return Err(Failure::NonFinite);
        }
        // The trailing block Lc (separator columns), dense.
        let (part, s) = (self.part, m - self.part);
        let mut lc = vec![T::default(); s * s];
        let sn = self.supernodal();
        let factor = SupernodalLltRef::new(sn, values);
        for k in 0..sn.n_supernodes() {
            let node = factor.supernode(k);
            let (start, val) = (node.start(), node.val());
            let w = val.ncols();
            if start + w <= part {
                continue;
            }
            for jj in part.saturating_sub(start)..w {
                let col = s * (start + jj - part);
                for i in jj..w {
                    lc[col + start + i - part] = val[(i, jj)];
                }
                for (p, &row) in node.pattern().iter().enumerate() {
                    lc[col + row - part] = val[(w + p, jj)];
                }
            }
        }
        let mut t = vec![T::default(); s * s];
        let lc = MatRef::from_column_major_slice(&lc, s, s);
        triangular::matmul(
            MatMut::from_column_major_slice_mut(&mut t, s, s),
            BlockStructure::TriangularLower,
            Accum::Replace,
            lc,
            BlockStructure::TriangularLower,
            lc.transpose(),
            BlockStructure::TriangularUpper,
            T::from_f64(1.0),
            Par::Seq,
        );
        Ok(t.into_iter().map(T::to_f64).collect())
    }

    /// The part's columns of each supernode, in elimination order.
    fn part_blocks<'a, T>(
        &'a self,
        values: &'a [T],
    ) -> impl DoubleEndedIterator<Item = PartBlock<'a, T>> {
        let sn = self.supernodal();
        let factor = SupernodalLltRef::new(sn, values);
        let part = self.part;
        (0..sn.n_supernodes())
            .map(move |k| factor.supernode(k))
            .filter(move |node| node.start() < part)
            .map(move |node| {
                let val = node.val();
                let cols = val.ncols().min(part - node.start());
                PartBlock {
                    start: node.start(),
                    cols,
                    top: val.submatrix(0, 0, cols, cols),
                    below: val.submatrix(cols, 0, val.nrows() - cols, cols),
                    own: val.ncols() - cols,
                    pattern: node.pattern(),
                }
            })
    }

    /// The forward substitution of the part's columns on `b` (the part's rows; the
    /// separator's start at zero and end as `-L3h y`).
    fn forward<T: Scalar>(&self, values: &[T], b: &[f64]) -> Vec<T> {
        let mut x: Vec<T> = self.rows[..self.part]
            .iter()
            .map(|&r| T::from_f64(b[r]))
            .collect();
        x.resize(self.rows.len(), T::default());
        let mut tmp = Vec::new();
        for block in self.part_blocks(values) {
            tmp.clear();
            tmp.resize(block.below.nrows(), T::default());
            let (start, cols) = (block.start, block.cols);
            let mut top = MatMut::from_column_major_slice_mut(&mut x[start..start + cols], cols, 1);
            solve_lower_triangular_in_place(block.top, top.rb_mut(), Par::Seq);
            matmul(
                MatMut::from_column_major_slice_mut(&mut tmp, block.below.nrows(), 1),
                Accum::Replace,
                block.below,
                top.rb(),
                T::from_f64(1.0),
                Par::Seq,
            );
            for (idx, &t) in tmp.iter().enumerate() {
                x[block.row(idx)] -= t;
            }
        }
        x
    }

    /// The backward substitution of the part's columns, the separator's rows holding their
    /// solution.
    fn backward<T: Scalar>(&self, values: &[T], x: &mut [T]) {
        let mut tmp = Vec::new();
        for block in self.part_blocks(values).rev() {
            tmp.clear();
            tmp.extend((0..block.below.nrows()).map(|idx| x[block.row(idx)]));
            let (start, cols) = (block.start, block.cols);
            let mut top = MatMut::from_column_major_slice_mut(&mut x[start..start + cols], cols, 1);
            matmul(
                top.rb_mut(),
                Accum::Add,
                block.below.transpose(),
                MatRef::from_column_major_slice(&tmp, block.below.nrows(), 1),
                T::from_f64(-1.0),
                Par::Seq,
            );
            solve_upper_triangular_in_place(block.top.transpose(), top.rb_mut(), Par::Seq);
        }
    }
}

/// The part's columns of one supernode: `cols` columns from `start`, their lower triangular
/// diagonal block `top` and the rows `below` it: first the supernode's own remaining `own`
/// rows, then those of its pattern.
struct PartBlock<'a, T> {
    start: usize,
    cols: usize,
    top: MatRef<'a, T>,
    below: MatRef<'a, T>,
    own: usize,
    pattern: &'a [usize],
}

impl<T> PartBlock<'_, T> {
    /// The local row of row `idx` of `below`.
    fn row(&self, idx: usize) -> usize {
        if idx < self.own {
            self.start + self.cols + idx
        } else {
            self.pattern[idx - self.own]
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::{Cholesky, Indefinite, LinearSolver, Ordering, Precision, SolverError};

    /// An elasticity-like matrix on an `a x b x c` grid of nodes (3 rows each): one PSD
    /// block `w (I + d d^T)` per edge to the 26 neighbours, `shift I` added; with the nodes'
    /// coordinates.
    fn grid_matrix(a: usize, b: usize, c: usize, shift: f64) -> (sprs::CsMat<f64>, Vec<[f64; 3]>) {
        let id = |i: usize, j: usize, k: usize| (i * b + j) * c + k;
        let n = 3 * a * b * c;
        let mut t = sprs::TriMat::new((n, n));
        let mut coords = vec![[0.0; 3]; a * b * c];
        for i in 0..a {
            for j in 0..b {
                for k in 0..c {
                    let u = id(i, j, k);
                    coords[u] = [i as f64, j as f64, k as f64];
                    for r in 0..3 {
                        t.add_triplet(3 * u + r, 3 * u + r, shift);
                    }
                    for (di, dj, dk) in itertools_offsets() {
                        let (ii, jj, kk) = (i as i64 + di, j as i64 + dj, k as i64 + dk);
                        if ii < 0 || jj < 0 || kk < 0 {
                            continue;
                        }
                        let (ii, jj, kk) = (ii as usize, jj as usize, kk as usize);
                        if ii >= a || jj >= b || kk >= c {
                            continue;
                        }
                        let v = id(ii, jj, kk);
                        let d = [di as f64, dj as f64, dk as f64];
                        let len2 = d.iter().map(|x| x * x).sum::<f64>();
                        let w = 1.0 + 0.1 * ((u * v + u + v) % 5) as f64;
                        for r in 0..3 {
                            for s in 0..3 {
                                let e = w * (f64::from(u8::from(r == s)) + d[r] * d[s] / len2);
                                t.add_triplet(3 * u + r, 3 * u + s, e);
                                t.add_triplet(3 * u + r, 3 * v + s, -e);
                            }
                        }
                    }
                }
            }
        }
        (t.to_csr(), coords)
    }

    fn itertools_offsets() -> impl Iterator<Item = (i64, i64, i64)> {
        (-1..=1)
            .flat_map(|i| (-1..=1).flat_map(move |j| (-1..=1).map(move |k| (i, j, k))))
            .filter(|&o| o != (0, 0, 0))
    }

    fn solver(split: bool, precision: Precision, coords: &[[f64; 3]]) -> Cholesky {
        let mut c = Cholesky::new(Ordering::NestedDissection, Indefinite::Error);
        c.split_min_rows = if split { 0 } else { usize::MAX };
        c.set_precision(precision);
        c.set_coordinates(Some(coords));
        c
    }

    fn rhs(n: usize) -> Vec<f64> {
        (0..n).map(|i| ((i * 37) % 11) as f64 - 5.0).collect()
    }

    fn solve(c: &mut Cholesky, a: &sprs::CsMat<f64>) -> Vec<f64> {
        let b = rhs(a.rows());
        let mut x = vec![0.0; a.rows()];
        c.factorize(a).unwrap();
        c.solve(a, &b, &mut x).unwrap();
        x
    }

    #[test]
    fn the_split_factor_solves_as_the_whole_one() {
        let (a, coords) = grid_matrix(14, 6, 5, 0.05);
        let mut whole = solver(false, Precision::Double, &coords);
        let reference = solve(&mut whole, &a);
        assert!(!whole.is_split());
        // AMD has no cut to split at.
        let mut amd = Cholesky::new(Ordering::Amd, Indefinite::Error);
        amd.split_min_rows = 0;
        let x = solve(&mut amd, &a);
        assert!(!amd.is_split());
        assert!(x.iter().zip(&reference).all(|(p, q)| (p - q).abs() < 1e-9));
        for precision in [Precision::Double, Precision::Mixed] {
            let mut split = solver(true, precision, &coords);
            let x = solve(&mut split, &a);
            assert!(split.is_split(), "{precision:?}");
            let err = x
                .iter()
                .zip(&reference)
                .map(|(p, q)| (p - q).abs())
                .fold(0.0, f64::max);
            let scale = reference.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            assert!(err <= 1e-10 * scale, "{precision:?}: {err} vs {scale}");
            // The same factor, counted in the same order, up to relaxed supernodes.
            let (ns, nw) = (split.factor_nnz() as f64, whole.factor_nnz() as f64);
            assert!((ns / nw - 1.0).abs() < 0.1, "nnz {ns} vs {nw}");
            assert!(split.factor_flops() >= whole.factor_flops() / 2);
        }
    }

    #[test]
    fn the_split_factor_does_not_depend_on_the_thread_count() {
        let (a, coords) = grid_matrix(12, 5, 5, 0.05);
        let on = |threads: usize, precision| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| solve(&mut solver(true, precision, &coords), &a))
        };
        for precision in [Precision::Double, Precision::Mixed] {
            let one = on(1, precision);
            assert_eq!(one, on(2, precision), "{precision:?}");
            assert_eq!(one, on(3, precision), "{precision:?}");
        }
    }

    #[test]
    fn an_indefinite_matrix_is_reported_or_factorised_as_ldlt() {
        // A negative shift pushes a few eigenvalues below zero.
        let (a, coords) = grid_matrix(12, 5, 5, -0.3);
        let mut c = solver(true, Precision::Mixed, &coords);
        c.analyze(&a).unwrap();
        assert!(c.is_split());
        match c.factorize(&a) {
            Err(SolverError::NotPositiveDefinite { pivot, spent, .. }) => {
                assert!(pivot < a.rows());
                assert!(spent.is_some_and(|s| s.flops > 0));
            }
            other => panic!("expected not positive definite, got {other:?}"),
        }
        for precision in [Precision::Double, Precision::Mixed] {
            let mut ldlt = Cholesky::new(Ordering::NestedDissection, Indefinite::Ldlt);
            ldlt.split_min_rows = 0;
            ldlt.set_precision(precision);
            ldlt.set_coordinates(Some(&coords));
            ldlt.analyze(&a).unwrap();
            let split_flops = ldlt.factor_flops();
            let setup = ldlt.factorize(&a).unwrap();
            assert!(ldlt.is_ldlt() && !ldlt.is_split());
            // The failed split attempts (one per precision tried) and the L D L^T are charged.
            let tries = if precision == Precision::Mixed { 2 } else { 1 };
            assert_eq!(setup.flops, tries * split_flops + ldlt.factor_flops());
            let b = rhs(a.rows());
            let mut x = vec![0.0; a.rows()];
            let stats = ldlt.solve(&a, &b, &mut x).unwrap();
            // The residual `b - A x` evaluated after the solve.
            assert!(
                stats.relative_residual() <= 1e-8,
                "{precision:?}: {stats:?}"
            );
        }
    }
}
