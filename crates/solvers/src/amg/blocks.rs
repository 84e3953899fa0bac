//! Block CSR matrices with dense `r x c` blocks, the storage of the multigrid hierarchy: the
//! finest operator in its vertices' 3x3 blocks, prolongators in `3 x 6` (finest) or `6 x 6`
//! blocks, coarse operators in `6 x 6` blocks. Products work a block at a time (one lookup
//! per block instead of per entry), with block rows in parallel and each output block summed
//! in a fixed order, so every result is identical for any thread count.

use rayon::prelude::*;
use sprs::CsMat;

use crate::operator::LinearOperator;

/// Block rows per parallel task.
const BLOCK_ROWS_PER_TASK: usize = 256;

/// A block CSR matrix: block row `i` holds blocks `ptr[i]..ptr[i + 1]`, at block columns
/// `idx` (sorted), each `r x c` row-major in `val`.
#[derive(Debug, Clone)]
pub(crate) struct Blocks {
    pub r: usize,
    pub c: usize,
    pub rows: usize,
    pub cols: usize,
    pub ptr: Vec<usize>,
    pub idx: Vec<u32>,
    pub val: Vec<f64>,
}

impl Blocks {
    /// Scalar rows and columns.
    pub fn shape(&self) -> (usize, usize) {
        (self.rows * self.r, self.cols * self.c)
    }

    /// Stored entries (blocks times block size).
    pub fn nnz(&self) -> usize {
        self.val.len()
    }

    /// Block `k`'s values.
    pub fn block(&self, k: usize) -> &[f64] {
        let size = self.r * self.c;
        &self.val[k * size..(k + 1) * size]
    }

    /// `a` in `b x b` blocks (a block is stored where `a` has any entry; missing entries of
    /// a stored block are zero). `None` unless `a` is square with a multiple of `b` rows.
    pub fn from_csr(a: &CsMat<f64>, b: usize) -> Option<Self> {
        let n = a.rows();
        if a.cols() != n || !n.is_multiple_of(b) || !a.is_csr() || n / b > u32::MAX as usize {
            return None;
        }
        let (indptr, indices, data) = (a.indptr(), a.indices(), a.data());
        let indptr = indptr.raw_storage();
        let rows = n / b;
        let size = b * b;
        let tasks: Vec<(Vec<usize>, Vec<u32>, Vec<f64>)> = (0..rows.div_ceil(BLOCK_ROWS_PER_TASK))
            .into_par_iter()
            .map(|task| {
                let (mut lengths, mut idx, mut val) = (Vec::new(), Vec::new(), Vec::new());
                let mut columns: Vec<usize> = Vec::new();
                for i in task * BLOCK_ROWS_PER_TASK..((task + 1) * BLOCK_ROWS_PER_TASK).min(rows) {
                    if let Some(count) =
                        copy_full_blocks(indptr, indices, data, b, i, &mut idx, &mut val)
                    {
                        lengths.push(count);
                        continue;
                    }
                    columns.clear();
                    for row in b * i..b * (i + 1) {
                        columns
                            .extend(indices[indptr[row]..indptr[row + 1]].iter().map(|&j| j / b));
                    }
                    columns.sort_unstable();
                    columns.dedup();
                    let start = val.len();
                    val.resize(start + columns.len() * size, 0.0);
                    for (local, row) in (b * i..b * (i + 1)).enumerate() {
                        for k in indptr[row]..indptr[row + 1] {
                            let j = indices[k];
                            let slot = columns.binary_search(&(j / b)).expect("listed above");
                            val[start + slot * size + local * b + j % b] = data[k];
                        }
                    }
                    idx.extend(columns.iter().map(|&j| j as u32));
                    lengths.push(columns.len());
                }
                (lengths, idx, val)
            })
            .collect();
        Some(Self::concatenate(b, b, rows, rows, tasks))
    }

    fn concatenate(
        r: usize,
        c: usize,
        rows: usize,
        cols: usize,
        tasks: Vec<(Vec<usize>, Vec<u32>, Vec<f64>)>,
    ) -> Self {
        let blocks = tasks.iter().map(|t| t.1.len()).sum();
        let mut ptr = Vec::with_capacity(rows + 1);
        let mut idx = Vec::with_capacity(blocks);
        let mut val = Vec::with_capacity(blocks * r * c);
        ptr.push(0);
        for (lengths, i, v) in tasks {
            for len in lengths {
                ptr.push(ptr.last().unwrap() + len);
            }
            idx.extend(i);
            val.extend(v);
        }
        Self {
            r,
            c,
            rows,
            cols,
            ptr,
            idx,
            val,
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
                        data.push(block[local * self.c + col]);
                    }
                }
                indptr.push(indices.len());
            }
        }
        CsMat::new((n, m), indptr, indices, data)
    }

    /// `self * other`: block rows in parallel; each output block accumulates its products in
    /// the order of `self`'s blocks, then `other`'s.
    pub fn multiply(&self, other: &Blocks) -> Blocks {
        assert_eq!(self.c, other.r, "inner block sizes");
        assert_eq!(self.cols, other.rows, "inner dimensions");
        let (r, inner, c) = (self.r, self.c, other.c);
        let size = r * c;
        let tasks = (0..self.rows.div_ceil(BLOCK_ROWS_PER_TASK))
            .into_par_iter()
            .map_init(
                || vec![usize::MAX; other.cols],
                |slot, task| {
                    let (mut lengths, mut idx, mut val) = (Vec::new(), Vec::new(), Vec::new());
                    let mut columns: Vec<u32> = Vec::new();
                    let mut acc: Vec<f64> = Vec::new();
                    let end = ((task + 1) * BLOCK_ROWS_PER_TASK).min(self.rows);
                    for i in task * BLOCK_ROWS_PER_TASK..end {
                        columns.clear();
                        acc.clear();
                        for ka in self.ptr[i]..self.ptr[i + 1] {
                            let j = self.idx[ka] as usize;
                            let a = self.block(ka);
                            for kb in other.ptr[j]..other.ptr[j + 1] {
                                let col = other.idx[kb] as usize;
                                if slot[col] == usize::MAX {
                                    slot[col] = columns.len();
                                    columns.push(col as u32);
                                    acc.resize(acc.len() + size, 0.0);
                                }
                                let out = &mut acc[slot[col] * size..(slot[col] + 1) * size];
                                block_product(r, inner, c, a, other.block(kb), out);
                            }
                        }
                        let mut order: Vec<u32> = columns.clone();
                        order.sort_unstable();
                        for &col in &order {
                            let s = slot[col as usize];
                            val.extend_from_slice(&acc[s * size..(s + 1) * size]);
                        }
                        for &col in &columns {
                            slot[col as usize] = usize::MAX;
                        }
                        idx.extend_from_slice(&order);
                        lengths.push(order.len());
                    }
                    (lengths, idx, val)
                },
            )
            .collect();
        Self::concatenate(r, c, self.rows, other.cols, tasks)
    }

    /// Flops of `self * other`: two per product of scalar entries.
    pub fn product_flops(&self, other: &Blocks) -> u64 {
        let per_pair = (2 * self.r * self.c * other.c) as u64;
        self.idx
            .iter()
            .map(|&j| (other.ptr[j as usize + 1] - other.ptr[j as usize]) as u64)
            .sum::<u64>()
            * per_pair
    }

    /// The transpose, with each block transposed.
    pub fn transpose(&self) -> Blocks {
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
        let mut val = vec![0.0; self.val.len()];
        for i in 0..self.rows {
            for k in self.ptr[i]..self.ptr[i + 1] {
                let j = self.idx[k] as usize;
                let at = next[j];
                next[j] += 1;
                idx[at] = i as u32;
                let (src, dst) = (self.block(k), &mut val[at * size..(at + 1) * size]);
                for x in 0..r {
                    for y in 0..c {
                        dst[y * r + x] = src[x * c + y];
                    }
                }
            }
        }
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

    /// `y = self x` (any shape).
    pub fn multiply_vector(&self, x: &[f64], y: &mut [f64]) {
        let (r, c) = (self.r, self.c);
        let rows = |(task, ys): (usize, &mut [f64])| {
            for (local, yi) in ys.chunks_exact_mut(r).enumerate() {
                let i = task * BLOCK_ROWS_PER_TASK + local;
                yi.fill(0.0);
                for k in self.ptr[i]..self.ptr[i + 1] {
                    let j = self.idx[k] as usize;
                    let (block, xj) = (self.block(k), &x[j * c..(j + 1) * c]);
                    for (row, yv) in yi.iter_mut().enumerate() {
                        let mut acc = 0.0;
                        for (b, v) in block[row * c..(row + 1) * c].iter().zip(xj) {
                            acc += b * v;
                        }
                        *yv += acc;
                    }
                }
            }
        };
        if self.nnz() < 200_000 {
            y.chunks_mut(r * BLOCK_ROWS_PER_TASK)
                .enumerate()
                .for_each(rows);
        } else {
            y.par_chunks_mut(r * BLOCK_ROWS_PER_TASK)
                .enumerate()
                .for_each(rows);
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
                out[i * b + d] = block.map_or(0.0, |v| v[d * b + d]);
            }
        }
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
                    if self.val[at + d * b + d] == 0.0 {
                        self.val[at + d * b + d] = value;
                    }
                }
            }
        }
    }
}

/// Block row `i` of a CSR matrix whose `b` rows share their columns, in whole aligned groups
/// of `b` (how deform assembles every FEM matrix): its blocks appended by a straight copy,
/// returning their count; `None` (nothing appended) for any other pattern.
fn copy_full_blocks(
    indptr: &[usize],
    indices: &[usize],
    data: &[f64],
    b: usize,
    i: usize,
    idx: &mut Vec<u32>,
    val: &mut Vec<f64>,
) -> Option<usize> {
    let first = &indices[indptr[b * i]..indptr[b * i + 1]];
    let full = first.len().is_multiple_of(b)
        && first
            .chunks_exact(b)
            .all(|g| g[0].is_multiple_of(b) && g.iter().enumerate().all(|(t, &j)| j == g[0] + t))
        && (b * i + 1..b * (i + 1)).all(|row| &indices[indptr[row]..indptr[row + 1]] == first);
    if !full {
        return None;
    }
    let count = first.len() / b;
    idx.extend(first.chunks_exact(b).map(|g| (g[0] / b) as u32));
    for block in 0..count {
        for row in b * i..b * (i + 1) {
            let at = indptr[row] + block * b;
            val.extend_from_slice(&data[at..at + b]);
        }
    }
    Some(count)
}

/// `out += a b` for dense row-major blocks `a` (`r x m`) and `b` (`m x c`), with the sizes
/// known at compile time for the hierarchy's common shapes (unrolled, vectorised loops).
fn block_product(r: usize, m: usize, c: usize, a: &[f64], b: &[f64], out: &mut [f64]) {
    fn fixed<const R: usize, const M: usize, const C: usize>(
        a: &[f64],
        b: &[f64],
        out: &mut [f64],
    ) {
        for x in 0..R {
            for y in 0..M {
                let s = a[x * M + y];
                for z in 0..C {
                    out[x * C + z] += s * b[y * C + z];
                }
            }
        }
    }
    match (r, m, c) {
        (3, 3, 6) => fixed::<3, 3, 6>(a, b, out),
        (6, 3, 6) => fixed::<6, 3, 6>(a, b, out),
        (6, 6, 6) => fixed::<6, 6, 6>(a, b, out),
        (3, 3, 3) => fixed::<3, 3, 3>(a, b, out),
        _ => {
            for x in 0..r {
                for y in 0..m {
                    let s = a[x * m + y];
                    for z in 0..c {
                        out[x * c + z] += s * b[y * c + z];
                    }
                }
            }
        }
    }
}

/// A square block matrix as the operator of a coarse level.
impl LinearOperator for Blocks {
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
        let a = Blocks::from_csr(&random(36, 36, 1), 3).unwrap();
        let b = Blocks::from_csr(&random(36, 36, 2), 3).unwrap();
        let (da, db) = (a.to_csr().to_dense(), b.to_csr().to_dense());
        let c = a.multiply(&b).to_csr().to_dense();
        let expected = da.dot(&db);
        let t = a.transpose().to_csr().to_dense();
        for i in 0..36 {
            for j in 0..36 {
                assert!((c[[i, j]] - expected[[i, j]]).abs() < 1e-14);
                assert_eq!(t[[j, i]], da[[i, j]]);
            }
        }
        let x: Vec<f64> = (0..36).map(|i| (i as f64 * 0.3).sin()).collect();
        let mut y = vec![0.0; 36];
        a.multiply_vector(&x, &mut y);
        for i in 0..36 {
            let e: f64 = (0..36).map(|j| da[[i, j]] * x[j]).sum();
            assert!((y[i] - e).abs() < 1e-14);
        }
        // Every scalar entry survives the block copy.
        let original = random(36, 36, 1).to_dense();
        assert_eq!(da, original);
        assert!(Blocks::from_csr(&random(35, 35, 1), 3).is_none());
    }
}
