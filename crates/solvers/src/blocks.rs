//! Block CSR matrices with dense `r x c` blocks: the 3x3 vertex-block copy iterative solvers
//! multiply with, and the storage of the multigrid hierarchy (the finest operator in its
//! vertices' 3x3 blocks, prolongators in `3 x 6` (finest) or `6 x 6` blocks, coarse
//! operators in `6 x 6` blocks). Products work a block at a time (one lookup per block
//! instead of per entry), with block rows in parallel and each output row summed in a fixed
//! order, so every result is identical for any thread count. Values are stored in `f64` or
//! `f32` (the multigrid cycle's operators and prolongators: products with them are bound by
//! memory traffic); every sum is in `f64`, and a product of two matrices sums each output row
//! in `f64` before storing it in either precision.

use rayon::prelude::*;
use sprs::CsMat;

use crate::operator::LinearOperator;

/// A transformation of a product's block row `i` (its block columns and double-precision
/// values) before it is stored.
pub(crate) type RowFinish<'a> = dyn Fn(usize, &[u32], &mut [f64]) + Sync + 'a;

/// Block rows per parallel task.
const BLOCK_ROWS_PER_TASK: usize = 256;
/// Blocks per parallel task of an element-wise pass.
const BLOCKS_PER_TASK: usize = 4096;
/// Below this many stored entries, products with vectors run on one thread.
const PARALLEL_NNZ: usize = 200_000;

/// The value type of a block matrix.
pub(crate) trait Scalar: Copy + Default + Send + Sync + Into<f64> + 'static {
    /// `v` in this precision (rounded to nearest).
    fn from_f64(v: f64) -> Self;
}
impl Scalar for f64 {
    fn from_f64(v: f64) -> Self {
        v
    }
}
impl Scalar for f32 {
    fn from_f64(v: f64) -> Self {
        v as f32
    }
}

/// A block CSR matrix: block row `i` holds blocks `ptr[i]..ptr[i + 1]`, at block columns
/// `idx` (sorted), each `r x c` row-major in `val`.
#[derive(Debug, Clone)]
pub(crate) struct Blocks<T = f64> {
    pub r: usize,
    pub c: usize,
    pub rows: usize,
    pub cols: usize,
    pub ptr: Vec<usize>,
    pub idx: Vec<u32>,
    pub val: Vec<T>,
}

impl<T: Scalar> Blocks<T> {
    /// Scalar rows and columns.
    pub fn shape(&self) -> (usize, usize) {
        (self.rows * self.r, self.cols * self.c)
    }

    /// Stored entries (blocks times block size).
    pub fn nnz(&self) -> usize {
        self.val.len()
    }

    /// Block `k`'s values.
    pub fn block(&self, k: usize) -> &[T] {
        let size = self.r * self.c;
        &self.val[k * size..(k + 1) * size]
    }

    /// `y = self x` (any shape). Each row is one running sum over its blocks in column
    /// order, so a 3x3-block copy of a CSR matrix multiplies exactly like the CSR matrix.
    pub fn multiply_vector(&self, x: &[f64], y: &mut [f64]) {
        self.multiply_vector_with(x, y, |_, p, yi| *yi = p);
    }

    /// Calls `store(i, (self x)_i, &mut y_i)` for every scalar row `i`: a product whose
    /// entries are combined with `y` (and anything indexed by `i`) as they are stored, one
    /// pass over memory instead of a product and an element-wise pass after it. The sums
    /// are those of [`Self::multiply_vector`].
    pub fn multiply_vector_with(
        &self,
        x: &[f64],
        y: &mut [f64],
        store: impl Fn(usize, f64, &mut f64) + Sync + Send,
    ) {
        match (self.r, self.c) {
            (3, 3) => self.multiply_fixed::<3, 3>(x, y, store),
            (3, 6) => self.multiply_fixed::<3, 6>(x, y, store),
            (6, 3) => self.multiply_fixed::<6, 3>(x, y, store),
            (6, 6) => self.multiply_fixed::<6, 6>(x, y, store),
            (r, c) => self.for_row_tasks(y, |i, yi| {
                debug_assert_eq!(yi.len(), r);
                for (row, yv) in yi.iter_mut().enumerate() {
                    let mut acc = 0.0;
                    for k in self.ptr[i]..self.ptr[i + 1] {
                        let (block, xj) = (self.block(k), &x[self.idx[k] as usize * c..][..c]);
                        for (b, v) in block[row * c..(row + 1) * c].iter().zip(xj) {
                            acc += (*b).into() * v;
                        }
                    }
                    store(i * r + row, acc, yv);
                }
            }),
        }
    }

    /// [`Self::multiply_vector_with`] with the block shape known at compile time (unrolled).
    fn multiply_fixed<const R: usize, const C: usize>(
        &self,
        x: &[f64],
        y: &mut [f64],
        store: impl Fn(usize, f64, &mut f64) + Sync + Send,
    ) {
        self.for_row_tasks(y, |i, yi| {
            let mut acc = [0.0; R];
            for k in self.ptr[i]..self.ptr[i + 1] {
                let j = self.idx[k] as usize * C;
                let (block, xj) = (&self.val[k * R * C..(k + 1) * R * C], &x[j..j + C]);
                for (row, a) in acc.iter_mut().enumerate() {
                    for col in 0..C {
                        *a += block[row * C + col].into() * xj[col];
                    }
                }
            }
            for (row, (yv, a)) in yi.iter_mut().zip(acc).enumerate() {
                store(i * R + row, a, yv);
            }
        });
    }

    /// Calls `f(i, y_i)` for every block row `i` and its `r` entries of `y`, in parallel
    /// tasks of whole block rows when the matrix is large.
    fn for_row_tasks(&self, y: &mut [f64], f: impl Fn(usize, &mut [f64]) + Sync + Send) {
        let r = self.r;
        let task = |(t, ys): (usize, &mut [f64])| {
            for (local, yi) in ys.chunks_exact_mut(r).enumerate() {
                f(t * BLOCK_ROWS_PER_TASK + local, yi);
            }
        };
        if self.nnz() < PARALLEL_NNZ {
            y.chunks_mut(r * BLOCK_ROWS_PER_TASK)
                .enumerate()
                .for_each(task);
        } else {
            y.par_chunks_mut(r * BLOCK_ROWS_PER_TASK)
                .enumerate()
                .for_each(task);
        }
    }

    /// The scalar diagonal of a square matrix with square blocks.
    pub fn scalar_diagonal(&self, out: &mut [f64]) {
        let b = self.r;
        for i in 0..self.rows {
            let row = &self.idx[self.ptr[i]..self.ptr[i + 1]];
            let block = row
                .binary_search(&(i as u32))
                .ok()
                .map(|k| self.block(self.ptr[i] + k));
            for d in 0..b {
                out[i * b + d] = block.map_or(0.0, |v| v[d * b + d].into());
            }
        }
    }
}

impl<T: Scalar> Blocks<T> {
    /// `a` in `b x b` blocks (a block is stored where `a` has any entry; missing entries of
    /// a stored block are zero). `None` unless `a` is square with a multiple of `b` rows.
    pub fn from_csr(a: &CsMat<f64>, b: usize) -> Option<Self> {
        Self::copy_csr(a, b, true)
    }

    /// `a` in `b x b` blocks when every block row of `a` is made of whole aligned blocks
    /// (how deform assembles every FEM matrix); `None` otherwise.
    pub fn from_aligned_csr(a: &CsMat<f64>, b: usize) -> Option<Self> {
        Self::copy_csr(a, b, false)
    }

    /// The copy in two parallel passes: blocks per block row, then each row's blocks
    /// written in place; a row not made of whole blocks is padded when `pad`, else refused.
    fn copy_csr(a: &CsMat<f64>, b: usize, pad: bool) -> Option<Self> {
        let n = a.rows();
        if a.cols() != n || !n.is_multiple_of(b) || !a.is_csr() || n / b > u32::MAX as usize {
            return None;
        }
        let (indptr, indices, data) = (a.indptr(), a.indices(), a.data());
        let indptr = indptr.raw_storage();
        let rows = n / b;
        let size = b * b;
        // Each block row's blocks and whether they are aligned (`None`: refused).
        let counts: Vec<Option<(usize, bool)>> = (0..rows)
            .into_par_iter()
            .with_min_len(BLOCK_ROWS_PER_TASK)
            .map(|i| match aligned_blocks(indptr, indices, b, i) {
                Some(count) => Some((count, true)),
                None => pad.then(|| (padded_columns(indptr, indices, b, i).len(), false)),
            })
            .collect();
        let mut ptr = Vec::with_capacity(rows + 1);
        let mut aligned = Vec::with_capacity(rows);
        ptr.push(0);
        for count in &counts {
            let (count, whole) = (*count)?;
            ptr.push(ptr[ptr.len() - 1] + count);
            aligned.push(whole);
        }
        let blocks = ptr[rows];
        let mut copy = Self {
            r: b,
            c: b,
            rows,
            cols: rows,
            ptr,
            idx: zeroed(blocks),
            val: zeroed(blocks * size),
        };
        copy.for_each_row_mut(|i, idx, val| {
            if aligned[i] {
                let first = &indices[indptr[b * i]..indptr[b * i + 1]];
                for (slot, g) in idx.iter_mut().zip(first.chunks_exact(b)) {
                    *slot = (g[0] / b) as u32;
                }
                for (local, row) in (b * i..b * (i + 1)).enumerate() {
                    for block in 0..idx.len() {
                        let from = &data[indptr[row] + block * b..][..b];
                        let to = &mut val[block * size + local * b..][..b];
                        for (t, &f) in to.iter_mut().zip(from) {
                            *t = T::from_f64(f);
                        }
                    }
                }
            } else {
                let columns = padded_columns(indptr, indices, b, i);
                for (slot, &j) in idx.iter_mut().zip(&columns) {
                    *slot = j as u32;
                }
                for (local, row) in (b * i..b * (i + 1)).enumerate() {
                    for k in indptr[row]..indptr[row + 1] {
                        let j = indices[k];
                        let slot = columns.binary_search(&(j / b)).expect("listed");
                        val[slot * size + local * b + j % b] = T::from_f64(data[k]);
                    }
                }
            }
        });
        Some(copy)
    }

    /// Calls `f(i, columns, values)` with each block row's columns and values, in parallel
    /// tasks of whole block rows.
    pub fn for_each_row_mut(&mut self, f: impl Fn(usize, &mut [u32], &mut [T]) + Sync + Send) {
        self.for_each_row_mut_init(|| (), |(), i, idx, val| f(i, idx, val));
    }

    /// [`Self::for_each_row_mut`] with a scratch value per task made by `init`.
    pub fn for_each_row_mut_init<S>(
        &mut self,
        init: impl Fn() -> S + Sync + Send,
        f: impl Fn(&mut S, usize, &mut [u32], &mut [T]) + Sync + Send,
    ) {
        let (rows, size, ptr) = (self.rows, self.r * self.c, &self.ptr);
        let mut tasks = Vec::with_capacity(rows.div_ceil(BLOCK_ROWS_PER_TASK));
        let (mut idx_rest, mut val_rest) = (self.idx.as_mut_slice(), self.val.as_mut_slice());
        for first in (0..rows).step_by(BLOCK_ROWS_PER_TASK) {
            let last = (first + BLOCK_ROWS_PER_TASK).min(rows);
            let len = ptr[last] - ptr[first];
            let (idx, rest) = std::mem::take(&mut idx_rest).split_at_mut(len);
            let (val, val_tail) = std::mem::take(&mut val_rest).split_at_mut(len * size);
            (idx_rest, val_rest) = (rest, val_tail);
            tasks.push((first..last, idx, val));
        }
        tasks
            .into_par_iter()
            .for_each_init(init, |scratch, (range, idx, val)| {
                let offset = ptr[range.start];
                for i in range {
                    let (at, count) = (ptr[i] - offset, ptr[i + 1] - ptr[i]);
                    f(
                        scratch,
                        i,
                        &mut idx[at..at + count],
                        &mut val[at * size..][..count * size],
                    );
                }
            });
    }

    /// An `r x c`-block matrix of this pattern (`lengths[i]` blocks in block row `i`, at the
    /// block columns `idx`, row after row) with every value zero.
    fn with_pattern(r: usize, c: usize, cols: usize, lengths: &[usize], idx: Vec<u32>) -> Self {
        let mut ptr = Vec::with_capacity(lengths.len() + 1);
        ptr.push(0);
        for len in lengths {
            ptr.push(ptr[ptr.len() - 1] + len);
        }
        assert_eq!(ptr[lengths.len()], idx.len(), "one column per block");
        Self {
            r,
            c,
            rows: lengths.len(),
            cols,
            ptr,
            val: zeroed(idx.len() * r * c),
            idx,
        }
    }

    /// The same matrix as scalar CSR (every stored block entry, zeros included).
    pub fn to_csr(&self) -> CsMat<f64> {
        let (n, m) = self.shape();
        let mut indptr = Vec::with_capacity(n + 1);
        let mut indices = Vec::with_capacity(self.nnz());
        let mut data = Vec::with_capacity(self.nnz());
        indptr.push(0);
        for i in 0..self.rows {
            for local in 0..self.r {
                for k in self.ptr[i]..self.ptr[i + 1] {
                    let j = self.idx[k] as usize;
                    let block = self.block(k);
                    for col in 0..self.c {
                        indices.push(j * self.c + col);
                        data.push(block[local * self.c + col].into());
                    }
                }
                indptr.push(indices.len());
            }
        }
        CsMat::new((n, m), indptr, indices, data)
    }

    /// Sets zero diagonal entries to `value` (the unknowns of dropped near-null-space
    /// columns, which nothing couples to).
    pub fn fill_zero_diagonal(&mut self, value: f64) {
        let b = self.r;
        for i in 0..self.rows {
            let row = &self.idx[self.ptr[i]..self.ptr[i + 1]];
            if let Ok(k) = row.binary_search(&(i as u32)) {
                let at = (self.ptr[i] + k) * b * b;
                for d in 0..b {
                    if self.val[at + d * b + d].into() == 0.0 {
                        self.val[at + d * b + d] = T::from_f64(value);
                    }
                }
            }
        }
    }
}

/// Products (summed in double whatever the factors' and the result's storage) and transposes.
impl<T: Scalar> Blocks<T> {
    /// `self * other` stored in precision `O` ([`Self::multiply_into`] without a transformation).
    pub fn multiply<U: Scalar, O: Scalar>(&self, other: &Blocks<U>) -> Blocks<O> {
        self.product(other, false, &|_, _, _| {})
    }

    /// `self * other` stored in precision `O`: block rows in parallel; each output block
    /// accumulates its products in double, in the order of `self`'s blocks, then `other`'s;
    /// `finish(i, columns, values)` transforms each block row's double-precision values
    /// before they are rounded and stored, so a product that feeds single-precision storage
    /// is written once, at half the memory traffic and page faults.
    pub fn multiply_into<U: Scalar, O: Scalar>(
        &self,
        other: &Blocks<U>,
        finish: &RowFinish,
    ) -> Blocks<O> {
        self.product(other, false, finish)
    }

    /// `self * other` for a product known to be symmetric (a Galerkin operator `P^T (A P)`):
    /// the blocks on and above the diagonal are computed as by [`Self::multiply_into`] and mirrored
    /// below it, so the result is exactly symmetric at about half the arithmetic.
    pub fn multiply_symmetric<U: Scalar, O: Scalar>(&self, other: &Blocks<U>) -> Blocks<O> {
        assert_eq!(
            (self.rows, self.r),
            (other.cols, other.c),
            "a square product"
        );
        let mut upper: Blocks<O> = self.product(other, true, &|_, _, _| {});
        let b = upper.r;
        upper.for_each_row_mut(|i, idx, val| {
            // The diagonal block, first in an upper row, mirrored within itself too.
            if idx.first() == Some(&(i as u32)) {
                for x in 0..b {
                    for y in 0..x {
                        val[x * b + y] = val[y * b + x];
                    }
                }
            }
        });
        let lower = upper.transpose();
        // Rows of the transpose list the columns below the diagonal, then the diagonal.
        let below = |i: usize| {
            let row = &lower.idx[lower.ptr[i]..lower.ptr[i + 1]];
            row.len() - usize::from(row.last() == Some(&(i as u32)))
        };
        let (mut lengths, mut idx) = (Vec::with_capacity(upper.rows), Vec::new());
        for i in 0..upper.rows {
            idx.extend_from_slice(&lower.idx[lower.ptr[i]..lower.ptr[i] + below(i)]);
            idx.extend_from_slice(&upper.idx[upper.ptr[i]..upper.ptr[i + 1]]);
            lengths.push(below(i) + upper.ptr[i + 1] - upper.ptr[i]);
        }
        let mut full = Blocks::with_pattern(b, b, upper.cols, &lengths, idx);
        let size = b * b;
        full.for_each_row_mut(|i, _, val| {
            let (low, up) = (
                lower.ptr[i]..lower.ptr[i] + below(i),
                upper.ptr[i]..upper.ptr[i + 1],
            );
            let split = low.len() * size;
            val[..split].copy_from_slice(&lower.val[low.start * size..low.end * size]);
            val[split..].copy_from_slice(&upper.val[up.start * size..up.end * size]);
        });
        full
    }

    /// `self * other`, only the blocks on and above the diagonal when `upper`: the pattern
    /// first (each row's sorted columns), then the values summed in place, so the result is
    /// written once.
    fn product<U: Scalar, O: Scalar>(
        &self,
        other: &Blocks<U>,
        upper: bool,
        finish: &RowFinish,
    ) -> Blocks<O> {
        assert_eq!(self.c, other.r, "inner block sizes");
        assert_eq!(self.cols, other.rows, "inner dimensions");
        let (r, inner, c) = (self.r, self.c, other.c);
        let size = r * c;
        // The blocks of `other`'s row `j` that output row `i` takes.
        let taken = |i: usize, j: usize| {
            let (start, end) = (other.ptr[j], other.ptr[j + 1]);
            let skip = if upper {
                other.idx[start..end].partition_point(|&col| (col as usize) < i)
            } else {
                0
            };
            start + skip..end
        };
        let patterns: Vec<(Vec<usize>, Vec<u32>)> = (0..self.rows.div_ceil(BLOCK_ROWS_PER_TASK))
            .into_par_iter()
            .map_init(
                || vec![false; other.cols],
                |seen, task| {
                    let (mut lengths, mut idx) = (Vec::new(), Vec::new());
                    let end = ((task + 1) * BLOCK_ROWS_PER_TASK).min(self.rows);
                    for i in task * BLOCK_ROWS_PER_TASK..end {
                        let start = idx.len();
                        for ka in self.ptr[i]..self.ptr[i + 1] {
                            for kb in taken(i, self.idx[ka] as usize) {
                                let col = other.idx[kb];
                                if !std::mem::replace(&mut seen[col as usize], true) {
                                    idx.push(col);
                                }
                            }
                        }
                        let row = &mut idx[start..];
                        row.sort_unstable();
                        row.iter().for_each(|&col| seen[col as usize] = false);
                        lengths.push(row.len());
                    }
                    (lengths, idx)
                },
            )
            .collect();
        let (mut lengths, mut idx) = (Vec::with_capacity(self.rows), Vec::new());
        for (task_lengths, task_idx) in patterns {
            lengths.extend(task_lengths);
            idx.extend(task_idx);
        }
        let mut out = Blocks::with_pattern(r, c, other.cols, &lengths, idx);
        out.for_each_row_mut_init(
            || (vec![0u32; other.cols], Vec::new()),
            |(slot, sums), i, idx, val| {
                for (s, &col) in idx.iter().enumerate() {
                    slot[col as usize] = s as u32;
                }
                sums.clear();
                sums.resize(val.len(), 0.0);
                // Each block sums in the order of `self`'s blocks, then `other`'s.
                for ka in self.ptr[i]..self.ptr[i + 1] {
                    let a = self.block(ka);
                    for kb in taken(i, self.idx[ka] as usize) {
                        let s = slot[other.idx[kb] as usize] as usize;
                        block_product(
                            r,
                            inner,
                            c,
                            a,
                            other.block(kb),
                            &mut sums[s * size..][..size],
                        );
                    }
                }
                finish(i, idx, sums);
                for (v, &sum) in val.iter_mut().zip(sums.iter()) {
                    *v = O::from_f64(sum);
                }
            },
        );
        out
    }

    /// Flops of `self * other`: two per product of scalar entries.
    pub fn product_flops<U: Scalar>(&self, other: &Blocks<U>) -> u64 {
        let per_pair = (2 * self.r * self.c * other.c) as u64;
        self.idx
            .iter()
            .map(|&j| (other.ptr[j as usize + 1] - other.ptr[j as usize]) as u64)
            .sum::<u64>()
            * per_pair
    }

    /// The transpose, with each block transposed: the pattern in one pass over the block
    /// columns, the values gathered in parallel.
    pub fn transpose(&self) -> Blocks<T> {
        let (r, c) = (self.r, self.c);
        let size = r * c;
        let mut counts = vec![0usize; self.cols + 1];
        for &j in &self.idx {
            counts[j as usize + 1] += 1;
        }
        for j in 0..self.cols {
            counts[j + 1] += counts[j];
        }
        let mut next = counts.clone();
        let mut idx = vec![0u32; self.idx.len()];
        // The block of `self` each block of the transpose comes from.
        let mut source = vec![0usize; self.idx.len()];
        for i in 0..self.rows {
            for k in self.ptr[i]..self.ptr[i + 1] {
                let j = self.idx[k] as usize;
                (idx[next[j]], source[next[j]]) = (i as u32, k);
                next[j] += 1;
            }
        }
        let mut val = zeroed(self.val.len());
        val.par_chunks_mut(size * BLOCKS_PER_TASK)
            .zip(source.par_chunks(BLOCKS_PER_TASK))
            .for_each(|(out, from)| {
                for (dst, &k) in out.chunks_exact_mut(size).zip(from) {
                    let src = self.block(k);
                    for x in 0..r {
                        for y in 0..c {
                            dst[y * r + x] = src[x * c + y];
                        }
                    }
                }
            });
        Blocks {
            r: c,
            c: r,
            rows: self.cols,
            cols: self.rows,
            ptr: counts,
            idx,
            val,
        }
    }
}

/// `len` zeros, written in parallel before use: on this kind of machine, faulting the pages
/// of a large new buffer in a plain fill costs a fraction of faulting them one at a time
/// inside the passes that compute its values (measured: the product `A P` of the n = 32
/// beam's multigrid set-up took 0.41 s with its output faulted during the product, 0.10 s
/// with it zeroed first).
fn zeroed<T: Copy + Default + Send + Sync>(len: usize) -> Vec<T> {
    let mut v = vec![T::default(); len];
    v.par_chunks_mut(1 << 16)
        .for_each(|chunk| chunk.fill(T::default()));
    v
}

/// The number of blocks of block row `i` of a CSR matrix when its `b` rows share their
/// columns in whole aligned groups of `b`; `None` for any other pattern.
fn aligned_blocks(indptr: &[usize], indices: &[usize], b: usize, i: usize) -> Option<usize> {
    let first = &indices[indptr[b * i]..indptr[b * i + 1]];
    let full = first.len().is_multiple_of(b)
        && first
            .chunks_exact(b)
            .all(|g| g[0].is_multiple_of(b) && g.iter().enumerate().all(|(t, &j)| j == g[0] + t))
        && (b * i + 1..b * (i + 1)).all(|row| &indices[indptr[row]..indptr[row + 1]] == first);
    full.then_some(first.len() / b)
}

/// The sorted block columns of block row `i`: every block holding an entry.
fn padded_columns(indptr: &[usize], indices: &[usize], b: usize, i: usize) -> Vec<usize> {
    let mut columns: Vec<usize> = indices[indptr[b * i]..indptr[b * (i + 1)]]
        .iter()
        .map(|&j| j / b)
        .collect();
    columns.sort_unstable();
    columns.dedup();
    columns
}

/// `out += a b` for dense row-major blocks `a` (`r x m`) and `b` (`m x c`), with the sizes
/// known at compile time for the hierarchy's common shapes (unrolled, vectorised loops).
fn block_product<S: Scalar, U: Scalar>(
    r: usize,
    m: usize,
    c: usize,
    a: &[S],
    b: &[U],
    out: &mut [f64],
) {
    fn fixed<S: Scalar, U: Scalar, const R: usize, const M: usize, const C: usize>(
        a: &[S],
        b: &[U],
        out: &mut [f64],
    ) {
        // Known lengths: no bounds checks in the unrolled loops.
        let (a, b, out) = (&a[..R * M], &b[..M * C], &mut out[..R * C]);
        for x in 0..R {
            for y in 0..M {
                let s: f64 = a[x * M + y].into();
                for z in 0..C {
                    out[x * C + z] += s * b[y * C + z].into();
                }
            }
        }
    }
    match (r, m, c) {
        (3, 3, 6) => fixed::<S, U, 3, 3, 6>(a, b, out),
        (6, 3, 6) => fixed::<S, U, 6, 3, 6>(a, b, out),
        (6, 6, 6) => fixed::<S, U, 6, 6, 6>(a, b, out),
        (3, 3, 3) => fixed::<S, U, 3, 3, 3>(a, b, out),
        _ => {
            for x in 0..r {
                for y in 0..m {
                    let s: f64 = a[x * m + y].into();
                    for z in 0..c {
                        out[x * c + z] += s * b[y * c + z].into();
                    }
                }
            }
        }
    }
}

/// A square block matrix as an operator (a level of the multigrid hierarchy).
impl<T: Scalar> LinearOperator for Blocks<T> {
    fn nrows(&self) -> usize {
        self.rows * self.r
    }

    fn apply(&self, x: &[f64], y: &mut [f64]) {
        self.multiply_vector(x, y);
    }

    fn diagonal(&self, out: &mut [f64]) {
        self.scalar_diagonal(out);
    }

    fn apply_flops(&self) -> u64 {
        2 * self.nnz() as u64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sprs::TriMat;

    fn random(rows: usize, cols: usize, seed: u64) -> CsMat<f64> {
        let mut t = TriMat::new((rows, cols));
        let mut s = seed;
        for i in 0..rows {
            for _ in 0..4 {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let j = (s >> 33) as usize % cols;
                t.add_triplet(i, j, (s >> 11) as f64 / (1u64 << 53) as f64 - 0.5);
            }
        }
        t.to_csr()
    }

    #[test]
    fn block_products_transposes_and_vectors_match_dense_arithmetic() {
        let a = Blocks::<f64>::from_csr(&random(36, 36, 1), 3).unwrap();
        let b = Blocks::<f64>::from_csr(&random(36, 36, 2), 3).unwrap();
        let (da, db) = (a.to_csr().to_dense(), b.to_csr().to_dense());
        let c = a.multiply::<_, f64>(&b).to_csr().to_dense();
        let expected = da.dot(&db);
        let t = a.transpose().to_csr().to_dense();
        for i in 0..36 {
            for j in 0..36 {
                assert!((c[[i, j]] - expected[[i, j]]).abs() < 1e-14);
                assert_eq!(t[[j, i]], da[[i, j]]);
            }
        }
        // Stored in single precision after a per-row transformation: the double-precision
        // values, transformed, then rounded.
        let finish = |i: usize, _: &[u32], v: &mut [f64]| v.iter_mut().for_each(|x| *x *= i as f64);
        let single: Blocks<f32> = a.multiply_into(&b, &finish);
        let double: Blocks = a.multiply_into(&b, &finish);
        assert_eq!((&single.ptr, &single.idx), (&double.ptr, &double.idx));
        let rounded: Vec<f32> = double.val.iter().map(|&v| v as f32).collect();
        assert_eq!(single.val, rounded);
        let transformed = double.to_csr().to_dense();
        for i in 0..36 {
            for j in 0..36 {
                assert_eq!(transformed[[i, j]], (i / 3) as f64 * c[[i, j]]);
            }
        }
        let x: Vec<f64> = (0..36).map(|i| (i as f64 * 0.3).sin()).collect();
        let mut y = vec![0.0; 36];
        a.multiply_vector(&x, &mut y);
        for i in 0..36 {
            let e: f64 = (0..36).map(|j| da[[i, j]] * x[j]).sum();
            assert!((y[i] - e).abs() < 1e-14);
        }
        // In single precision: within the values' rounding. A single-precision copy made
        // straight from the CSR is the rounded double one.
        let single = Blocks::<f32>::from_csr(&random(36, 36, 1), 3).unwrap();
        assert_eq!(
            single.val,
            a.val.iter().map(|&v| v as f32).collect::<Vec<_>>()
        );
        assert_eq!((&single.ptr, &single.idx), (&a.ptr, &a.idx));
        let mut y32 = vec![0.0; 36];
        single.multiply_vector(&x, &mut y32);
        for i in 0..36 {
            let bound: f64 = (0..36).map(|j| (da[[i, j]] * x[j]).abs()).sum();
            assert!(
                (y32[i] - y[i]).abs() <= 1e-7 * bound,
                "{} vs {}",
                y32[i],
                y[i]
            );
        }
        // Every scalar entry survives the block copy; a pattern of partial blocks is padded
        // by `from_csr` and refused by `from_aligned_csr`.
        let original = random(36, 36, 1).to_dense();
        assert_eq!(da, original);
        assert!(Blocks::<f64>::from_csr(&random(35, 35, 1), 3).is_none());
        assert!(Blocks::<f64>::from_aligned_csr(&random(36, 36, 1), 3).is_none());
    }

    #[test]
    fn the_symmetric_product_equals_the_full_one_and_is_exactly_symmetric() {
        // B^T (A B) with A symmetric: 3x3 blocks times 3x6 blocks, as on the finest level.
        let a = random(36, 36, 3);
        let a = &a + &a.transpose_view().to_csr();
        let a = Blocks::<f64>::from_csr(&a, 3).unwrap();
        let b = random(36, 24, 4).to_dense();
        let mut t = TriMat::new((36, 24));
        for ((i, j), v) in b.indexed_iter() {
            if *v != 0.0 {
                t.add_triplet(i, j, *v);
            }
        }
        // Blocks of 3x6: row blocks of 3, column blocks of 6, padded like `from_csr`.
        let csr: CsMat<f64> = t.to_csr();
        let mut p = Blocks {
            r: 3,
            c: 6,
            rows: 12,
            cols: 4,
            ptr: vec![0],
            idx: Vec::new(),
            val: Vec::new(),
        };
        for i in 0..12 {
            for g in 0..4u32 {
                let block: Vec<f64> = (0..18)
                    .map(|e| b[[3 * i + e / 6, 6 * g as usize + e % 6]])
                    .collect();
                if block.iter().any(|v| *v != 0.0) {
                    p.idx.push(g);
                    p.val.extend(block);
                }
            }
            p.ptr.push(p.idx.len());
        }
        assert_eq!(p.to_csr().to_dense(), csr.to_dense());
        let ap: Blocks = a.multiply(&p);
        let r = p.transpose();
        let (full, half) = (
            r.multiply::<_, f64>(&ap).to_csr().to_dense(),
            r.multiply_symmetric::<_, f64>(&ap),
        );
        let half = half.to_csr().to_dense();
        for i in 0..24 {
            for j in 0..24 {
                assert_eq!(half[[i, j]], half[[j, i]]);
                assert!((half[[i, j]] - full[[i, j]]).abs() <= 1e-14 * full[[i, j]].abs().max(1.0));
            }
        }
    }
}
