//! Zero-fill incomplete Cholesky, factorised level by level (issue 42).
//!
//! Row `i` of `L` depends on the rows `j < i` of its pattern; its *level* is one more than
//! the highest of theirs, so the rows of one level are independent and are factorised in
//! parallel. Storage stays in the matrix's own numbering (a row's neighbours stay near it
//! in memory); only the schedule follows the levels. A wide level's rows are computed side
//! by side into a buffer and then written back; a narrow one runs on the calling thread,
//! and on one thread the schedule is the matrix's order. Every row sums in the order of
//! the sequential algorithm, so the factor is the same bits for any number of threads.
//! The triangular sweeps stay sequential: swept level by level they measured 3x slower on
//! the beam (docs/benchmarks.md), their rows scattered through memory.

use rayon::prelude::*;

use crate::SolverError;

/// Rows of a level below which it runs on the calling thread.
const PARALLEL_MIN_ROWS: usize = 256;
/// Rows per parallel task.
const ROWS_PER_TASK: usize = 64;

/// A compressed-row triangle in the matrix's numbering.
#[derive(Debug, Clone)]
struct Rows {
    indptr: Vec<usize>,
    indices: Vec<usize>,
    data: Vec<f64>,
}

impl Rows {
    fn range(&self, i: usize) -> std::ops::Range<usize> {
        self.indptr[i]..self.indptr[i + 1]
    }
}

/// The factor `L` of `A + shift diag(A)`.
#[derive(Debug)]
pub(crate) struct Ic0 {
    /// `L`: each row's columns below the diagonal in increasing order, then the diagonal.
    lower: Rows,
}

impl Ic0 {
    /// The factor of the symmetric CSR matrix `(indptr, indices, data)` (full storage,
    /// sorted columns) plus `shift diag(A)`.
    ///
    /// # Errors
    /// [`SolverError::NotPositiveDefinite`] at the first non-positive pivot in level order.
    pub(crate) fn new(
        indptr: &[usize],
        indices: &[usize],
        data: &[f64],
        shift: f64,
    ) -> Result<Self, SolverError> {
        let n = indptr.len() - 1;
        // On one thread the matrix's own order (each row a level of its own) keeps the
        // sweep through memory sequential; the bits are the same either way.
        let (schedule, levels) = if rayon::current_num_threads() > 1 {
            level_order(indptr, indices)
        } else {
            ((0..n).collect(), (0..=n).collect())
        };
        let mut lp = Vec::with_capacity(n + 1);
        lp.push(0);
        for i in 0..n {
            let below = indices[indptr[i]..indptr[i + 1]].partition_point(|&j| j < i);
            lp.push(lp[i] + below + 1);
        }
        let nnz = lp[n];
        let (mut li, mut lv) = (vec![0; nnz], vec![0.0; nnz]);
        let fill = |(i, (cols, vals)): (usize, (&mut [usize], &mut [f64]))| {
            let row = indptr[i]..indptr[i + 1];
            let below = cols.len() - 1;
            cols[..below].copy_from_slice(&indices[row.start..row.start + below]);
            vals[..below].copy_from_slice(&data[row.start..row.start + below]);
            // A missing diagonal is a zero pivot.
            let diag = indices[row.clone()]
                .binary_search(&i)
                .map_or(0.0, |k| data[row.start + k]);
            (cols[below], vals[below]) = (i, diag * (1.0 + shift));
        };
        let rows = rows_mut(&mut li, &lp)
            .into_iter()
            .zip(rows_mut(&mut lv, &lp));
        (rows.enumerate().collect::<Vec<_>>().into_par_iter())
            .with_min_len(ROWS_PER_TASK)
            .for_each(fill);
        let mut lower = Rows {
            indptr: lp,
            indices: li,
            data: lv,
        };
        let mut scratch = Vec::new();
        factorise(&schedule, &levels, &mut lower, &mut scratch)?;
        Ok(Self { lower })
    }

    /// Nonzeros of `L`.
    pub(crate) fn nnz(&self) -> usize {
        self.lower.indices.len()
    }

    /// `z = (L L^T)^-1 r`: forward and column-oriented backward sweeps in the matrix's
    /// order, on the calling thread (level-ordered sweeps measured 3x slower here, their
    /// scattered rows defeating the cache; docs/benchmarks.md).
    pub(crate) fn apply(&self, r: &[f64], z: &mut [f64]) {
        let l = &self.lower;
        for i in 0..z.len() {
            let k = l.range(i);
            let mut acc = r[i];
            for k in k.start..k.end - 1 {
                acc -= l.data[k] * z[l.indices[k]];
            }
            z[i] = acc / l.data[k.end - 1];
        }
        for i in (0..z.len()).rev() {
            let k = l.range(i);
            z[i] /= l.data[k.end - 1];
            let zi = z[i];
            for k in k.start..k.end - 1 {
                z[l.indices[k]] -= l.data[k] * zi;
            }
        }
    }
}

/// The rows in level order (by level, in increasing index within one) and the levels'
/// starts in it.
fn level_order(indptr: &[usize], indices: &[usize]) -> (Vec<usize>, Vec<usize>) {
    let n = indptr.len() - 1;
    let mut level = vec![0usize; n];
    for i in 0..n {
        let cols = &indices[indptr[i]..indptr[i + 1]];
        level[i] = (cols.iter().take_while(|&&j| j < i))
            .map(|&j| level[j] + 1)
            .max()
            .unwrap_or(0);
    }
    let levels = level.iter().max().map_or(0, |&m| m + 1);
    let mut starts = vec![0usize; levels + 1];
    for &l in &level {
        starts[l + 1] += 1;
    }
    for k in 0..levels {
        starts[k + 1] += starts[k];
    }
    let (mut next, mut schedule) = (starts.clone(), vec![0; n]);
    for (i, &l) in level.iter().enumerate() {
        schedule[next[l]] = i;
        next[l] += 1;
    }
    (schedule, starts)
}

/// Row `i` of the factor into `out` (its pattern's values of `A`, in `lower`'s order),
/// from the finished rows it depends on.
fn factor_row(lower: &Rows, i: usize, out: &mut [f64]) -> Result<(), SolverError> {
    let own = lower.range(i);
    out.copy_from_slice(&lower.data[own.clone()]);
    let cols = &lower.indices[own];
    let below = cols.len() - 1;
    let mut d = out[below];
    for a in 0..below {
        // L_ij = (A_ij - sum_{m < j} L_im L_jm) / L_jj over the common columns.
        let j = cols[a];
        let theirs = lower.range(j);
        let their_cols = &lower.indices[theirs.start..theirs.end - 1];
        let mut s = out[a];
        let (mut p, mut q) = (0, 0);
        while p < a && q < their_cols.len() {
            match cols[p].cmp(&their_cols[q]) {
                std::cmp::Ordering::Less => p += 1,
                std::cmp::Ordering::Greater => q += 1,
                std::cmp::Ordering::Equal => {
                    s -= out[p] * lower.data[theirs.start + q];
                    p += 1;
                    q += 1;
                }
            }
        }
        out[a] = s / lower.data[theirs.end - 1];
        d -= out[a] * out[a];
    }
    if !(d > 0.0) {
        return Err(SolverError::NotPositiveDefinite {
            pivot: i,
            value: d,
            spent: None,
        });
    }
    out[below] = d.sqrt();
    Ok(())
}

/// The factorisation in place on `lower` (A's lower triangle and shifted diagonal), level
/// by level; a wide level's rows side by side into `buffer`, then written back.
///
/// A failed pivot is reported as the row-by-row algorithm would: the lowest failing row.
/// The rows below it do not depend on it, so after a failure the levels go on with the
/// lower rows only, and the report does not depend on the schedule (nor on the threads).
fn factorise(
    schedule: &[usize],
    levels: &[usize],
    lower: &mut Rows,
    buffer: &mut Vec<f64>,
) -> Result<(), SolverError> {
    let (mut row, mut starts, mut kept) = (Vec::new(), Vec::new(), Vec::new());
    let mut failed: Option<(usize, SolverError)> = None;
    for level in levels.windows(2) {
        let mut rows = &schedule[level[0]..level[1]];
        if let Some((first, _)) = &failed {
            kept.clear();
            kept.extend(rows.iter().copied().filter(|i| i < first));
            rows = &kept;
        }
        let lowest = |errors: Vec<(usize, SolverError)>, failed: &mut Option<_>| {
            for (i, e) in errors {
                if failed.as_ref().is_none_or(|(f, _)| i < *f) {
                    *failed = Some((i, e));
                }
            }
        };
        if rows.len() < PARALLEL_MIN_ROWS {
            for &i in rows {
                row.resize(lower.range(i).len(), 0.0);
                match factor_row(lower, i, &mut row) {
                    Ok(()) => {
                        let k = lower.range(i);
                        lower.data[k].copy_from_slice(&row);
                    }
                    Err(e) => lowest(vec![(i, e)], &mut failed),
                }
            }
            continue;
        }
        starts.clear();
        starts.push(0);
        for &i in rows {
            starts.push(starts.last().copied().unwrap_or(0) + lower.range(i).len());
        }
        buffer.resize(starts[rows.len()], 0.0);
        let read: &Rows = lower;
        let outs = rows_mut(&mut buffer[..starts[rows.len()]], &starts);
        let errors: Vec<(usize, SolverError)> = (outs.into_par_iter().zip(rows.par_iter()))
            .with_min_len(ROWS_PER_TASK)
            .filter_map(|(out, &i)| factor_row(read, i, out).err().map(|e| (i, e)))
            .collect();
        lowest(errors, &mut failed);
        for (t, &i) in rows.iter().enumerate() {
            let k = lower.range(i);
            lower.data[k].copy_from_slice(&buffer[starts[t]..starts[t + 1]]);
        }
    }
    failed.map_or(Ok(()), |(_, e)| Err(e))
}

/// `data` split into its rows by `indptr` (which starts at 0).
fn rows_mut<'a, T>(data: &'a mut [T], indptr: &[usize]) -> Vec<&'a mut [T]> {
    let mut rows = Vec::with_capacity(indptr.len().saturating_sub(1));
    let mut rest = data;
    for w in indptr.windows(2) {
        let (row, tail) = rest.split_at_mut(w[1] - w[0]);
        rows.push(row);
        rest = tail;
    }
    rows
}

/// Flops of one IC(0) factorisation: each row's sparse dot products, bounded by the square
/// of its lower length.
pub(crate) fn flops(indptr: &[usize], indices: &[usize]) -> u64 {
    (0..indptr.len() - 1)
        .map(|i| {
            let lower = indices[indptr[i]..indptr[i + 1]]
                .iter()
                .filter(|&&j| j < i)
                .count() as u64;
            lower * lower + 2 * lower + 1
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The 7-point Laplacian of a `m^3` grid plus `shift` on the diagonal, with one
    /// off-diagonal perturbed per row so that rows differ: full symmetric CSR.
    fn grid(m: usize, shift: f64) -> (Vec<usize>, Vec<usize>, Vec<f64>) {
        let id = |x: usize, y: usize, z: usize| (z * m + y) * m + x;
        let (mut indptr, mut indices, mut data) = (vec![0], Vec::new(), Vec::new());
        for z in 0..m {
            for y in 0..m {
                for x in 0..m {
                    let i = id(x, y, z);
                    let mut row = vec![(i, 6.0 + shift)];
                    let mut near = |j: usize| {
                        let w = -1.0 - 0.1 * (((i + j) * 7919) % 13) as f64 / 13.0;
                        row.push((j, w));
                    };
                    if x > 0 {
                        near(id(x - 1, y, z));
                    }
                    if x + 1 < m {
                        near(id(x + 1, y, z));
                    }
                    if y > 0 {
                        near(id(x, y - 1, z));
                    }
                    if y + 1 < m {
                        near(id(x, y + 1, z));
                    }
                    if z > 0 {
                        near(id(x, y, z - 1));
                    }
                    if z + 1 < m {
                        near(id(x, y, z + 1));
                    }
                    row.sort_by_key(|e| e.0);
                    indices.extend(row.iter().map(|e| e.0));
                    data.extend(row.iter().map(|e| e.1));
                    indptr.push(indices.len());
                }
            }
        }
        (indptr, indices, data)
    }

    /// The row-by-row algorithm (factor in original numbering, then the column-oriented
    /// backward sweep): what the level-scheduled one must reproduce bit for bit.
    fn sequential(
        ip: &[usize],
        ix: &[usize],
        dv: &[f64],
        r: &[f64],
    ) -> (Vec<Vec<(usize, f64)>>, Vec<f64>) {
        let n = ip.len() - 1;
        let mut l: Vec<Vec<(usize, f64)>> = Vec::with_capacity(n);
        for i in 0..n {
            let mut row: Vec<(usize, f64)> = (ip[i]..ip[i + 1])
                .filter(|&k| ix[k] < i)
                .map(|k| (ix[k], dv[k]))
                .collect();
            let mut d = (ip[i]..ip[i + 1])
                .find(|&k| ix[k] == i)
                .map_or(0.0, |k| dv[k]);
            for a in 0..row.len() {
                let j = row[a].0;
                let theirs = &l[j][..l[j].len() - 1];
                let (mut s, mut p, mut q) = (row[a].1, 0, 0);
                while p < a && q < theirs.len() {
                    match row[p].0.cmp(&theirs[q].0) {
                        std::cmp::Ordering::Less => p += 1,
                        std::cmp::Ordering::Greater => q += 1,
                        std::cmp::Ordering::Equal => {
                            s -= row[p].1 * theirs[q].1;
                            p += 1;
                            q += 1;
                        }
                    }
                }
                row[a].1 = s / l[j].last().unwrap().1;
                d -= row[a].1 * row[a].1;
            }
            row.push((i, d.sqrt()));
            l.push(row);
        }
        let mut z = vec![0.0; n];
        for i in 0..n {
            let (below, diag) = l[i].split_at(l[i].len() - 1);
            let acc = below.iter().fold(r[i], |acc, &(j, v)| acc - v * z[j]);
            z[i] = acc / diag[0].1;
        }
        for i in (0..n).rev() {
            let (below, diag) = l[i].split_at(l[i].len() - 1);
            z[i] /= diag[0].1;
            let zi = z[i];
            for &(j, v) in below {
                z[j] -= v * zi;
            }
        }
        (l, z)
    }

    #[test]
    fn level_scheduled_ic0_is_the_sequential_one_bit_for_bit_on_any_thread_count() {
        let (ip, ix, dv) = grid(30, 0.05);
        let n = ip.len() - 1;
        let r: Vec<f64> = (0..n)
            .map(|i| ((i * 37) % 101) as f64 / 50.0 - 1.0)
            .collect();
        let (l, expected) = sequential(&ip, &ix, &dv, &r);
        let on = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let f = Ic0::new(&ip, &ix, &dv, 0.0).unwrap();
                let mut z = vec![0.0; n];
                f.apply(&r, &mut z);
                (f, z)
            })
        };
        let (_, z1) = on(1);
        let (f, z2) = on(2);
        // Levels large enough to run in parallel, and the level order is a true schedule.
        let (schedule, levels) = level_order(&ip, &ix);
        let widest = levels.windows(2).map(|w| w[1] - w[0]).max().unwrap();
        assert!(widest >= PARALLEL_MIN_ROWS, "widest level {widest}");
        assert_eq!(levels.len() - 1, 3 * (30 - 1) + 1);
        let mut level = vec![0; n];
        for (k, w) in levels.windows(2).enumerate() {
            schedule[w[0]..w[1]].iter().for_each(|&i| level[i] = k);
        }
        for i in 0..n {
            assert!((ip[i]..ip[i + 1]).all(|k| ix[k] >= i || level[ix[k]] < level[i]));
        }
        // The factor: the same entries, bit for bit.
        for (i, row) in l.iter().enumerate() {
            let got: Vec<(usize, u64)> = (f.lower.range(i))
                .map(|k| (f.lower.indices[k], f.lower.data[k].to_bits()))
                .collect();
            let want: Vec<(usize, u64)> = row.iter().map(|&(j, v)| (j, v.to_bits())).collect();
            assert_eq!(got, want, "row {i}");
        }
        let bits = |z: &[f64]| z.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&z1), bits(&expected));
        assert_eq!(bits(&z2), bits(&expected));
        // And it is an incomplete Cholesky factor: (L L^T)_ij = A_ij on A's pattern.
        for i in (0..n).step_by(97) {
            for k in ip[i]..ip[i + 1] {
                let j = ix[k];
                let dot: f64 = l[i]
                    .iter()
                    .filter_map(|&(c, v)| l[j].iter().find(|e| e.0 == c).map(|e| v * e.1))
                    .sum();
                assert!(
                    (dot - dv[k]).abs() < 1e-12 * dv[k].abs().max(1.0),
                    "({i}, {j})"
                );
            }
        }
    }

    #[test]
    fn a_non_positive_pivot_is_refused() {
        let (ip, ix, mut dv) = grid(4, 0.0);
        let k = (ip[20]..ip[21]).find(|&k| ix[k] == 20).unwrap();
        dv[k] = -1.0;
        assert!(matches!(
            Ic0::new(&ip, &ix, &dv, 0.0),
            Err(SolverError::NotPositiveDefinite { pivot: 20, .. })
        ));
    }

    /// Two failing pivots, the lower one in a later level than the higher one: the report
    /// names the lower on any thread count, as the row-by-row algorithm does.
    #[test]
    fn the_lowest_failing_pivot_is_reported_on_any_thread_count() {
        let m = 30;
        let (ip, ix, mut dv) = grid(m, 0.0);
        let id = |x: usize, y: usize, z: usize| (z * m + y) * m + x;
        // A row's level is x + y + z: the lower row (899) is at level 58, the higher
        // (930) at level 2, so the level schedule meets the higher one first.
        let (low, high) = (id(29, 29, 0), id(0, 1, 1));
        assert!(low < high);
        for i in [low, high] {
            let k = (ip[i]..ip[i + 1]).find(|&k| ix[k] == i).unwrap();
            dv[k] = -1.0;
        }
        for threads in [1, 2] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let result = pool.install(|| Ic0::new(&ip, &ix, &dv, 0.0));
            assert!(
                matches!(result, Err(SolverError::NotPositiveDefinite { pivot, .. }) if pivot == low),
                "{threads} threads: {result:?}"
            );
        }
    }
}
