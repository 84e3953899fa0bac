//! Smoothed-aggregation algebraic multigrid (Vaněk, Mandel & Brezina 1996) as a PCG
//! preconditioner, for elasticity: the near-null space is the six rigid-body modes of the
//! nodes' positions, so each coarse node carries up to six unknowns (three translations and
//! three rotations of its aggregate), which is what keeps the iteration count flat as the
//! mesh is refined.
//!
//! Set-up per level: strength of connection on the node graph (3x3 blocks on the finest
//! level, `k x k` blocks below), greedy aggregation, a tentative prolongator from a QR of the
//! near-null space on each aggregate, one damped-Jacobi smoothing of it, and the Galerkin
//! operator `P^T A P`; the coarsest level is factorised by the sparse Cholesky. One V-cycle
//! with symmetric smoothing (Chebyshev or damped Jacobi, the same before and after) is the
//! preconditioner, so PCG sees an SPD operator. Every product runs rows in parallel with
//! each row summed in a fixed order: the hierarchy and the cycle are identical for any
//! thread count.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sprs::CsMat;

use crate::direct::{Cholesky, Indefinite};
use crate::operator::{LinearOperator, dot, for_each_entry, norm};
use crate::ordering::Ordering;
use crate::{LinearSolver, SolverError};

/// The smoother on every level of the multigrid cycle.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub enum AmgSmoother {
    /// `sweeps` damped-Jacobi sweeps, `x += 4/(3 lambda) D^-1 (b - A x)` with `lambda` the
    /// estimated largest eigenvalue of `D^-1 A`.
    Jacobi {
        /// Sweeps before and after the coarse correction.
        sweeps: usize,
    },
    /// A Chebyshev polynomial of `degree` in `D^-1 A` damping the eigenvalues in
    /// `[lambda / 30, 1.1 lambda]` (one product with `A` per degree).
    Chebyshev {
        /// The polynomial's degree, before and after the coarse correction.
        degree: usize,
    },
}

impl Default for AmgSmoother {
    fn default() -> Self {
        AmgSmoother::Chebyshev { degree: 2 }
    }
}

/// Checks the parameters of an AMG preconditioner.
pub(crate) fn validate(theta: f64, smoother: AmgSmoother) -> Result<(), SolverError> {
    if !(0.0..1.0).contains(&theta) {
        return Err(SolverError::InvalidParameter {
            field: "theta",
            value: theta,
            reason: "must be in [0, 1)",
        });
    }
    let (field, steps) = match smoother {
        AmgSmoother::Jacobi { sweeps } => ("sweeps", sweeps),
        AmgSmoother::Chebyshev { degree } => ("degree", degree),
    };
    if steps == 0 {
        return Err(SolverError::InvalidParameter {
            field,
            value: 0.0,
            reason: "must be at least 1",
        });
    }
    Ok(())
}

/// Levels stop coarsening at this many unknowns; the last one is factorised.
const MAX_COARSE: usize = 2000;
/// At most this many levels (the finest included).
const MAX_LEVELS: usize = 12;
/// Rows per parallel task of the sparse products.
const ROWS_PER_TASK: usize = 512;
/// Power iterations of the spectral-radius estimate of `D^-1 A`.
const POWER_ITERATIONS: usize = 15;

/// Nodes of one level: node `i` owns unknowns `ptr[i]..ptr[i + 1]`.
#[derive(Debug, Clone)]
struct Nodes {
    ptr: Vec<usize>,
}

impl Nodes {
    fn uniform(n: usize, size: usize) -> Self {
        Self {
            ptr: (0..=n / size).map(|i| i * size).collect(),
        }
    }

    fn len(&self) -> usize {
        self.ptr.len() - 1
    }

    fn dofs(&self, i: usize) -> std::ops::Range<usize> {
        self.ptr[i]..self.ptr[i + 1]
    }

    /// The node of every unknown.
    fn owners(&self) -> Vec<usize> {
        let mut owner = vec![0; *self.ptr.last().unwrap_or(&0)];
        for i in 0..self.len() {
            owner[self.dofs(i)].fill(i);
        }
        owner
    }
}

/// One level above the coarsest: its smoother and the transfer to the next level.
#[derive(Debug)]
struct Level {
    /// This level's operator; `None` on the finest, where the operator being solved is used.
    a: Option<CsMat<f64>>,
    inv_diag: Vec<f64>,
    /// Estimated largest eigenvalue of `D^-1 A`.
    lambda: f64,
    /// Prolongation to this level from the next one, and its transpose.
    p: CsMat<f64>,
    r: CsMat<f64>,
    /// This level's nodes and the next level's (row groups sharing their columns).
    nodes: Nodes,
    coarse_nodes: Nodes,
}

/// A set-up multigrid hierarchy.
#[derive(Debug)]
pub(crate) struct Amg {
    levels: Vec<Level>,
    coarse: Box<Cholesky>,
    smoother: AmgSmoother,
}

impl Amg {
    /// Builds the hierarchy for `a` with strength threshold `theta`; `coordinates` (one per 3
    /// rows) give the rotations of the near-null space, without them only translations are
    /// used. Returns it with the set-up flops.
    pub fn new(
        a: &CsMat<f64>,
        coordinates: Option<&[[f64; 3]]>,
        theta: f64,
        smoother: AmgSmoother,
    ) -> Result<(Self, u64), SolverError> {
        let n = a.rows();
        let (mut nodes, mut modes) = near_null_space(n, coordinates);
        let mut levels: Vec<Level> = Vec::new();
        let mut coarse_a: Option<CsMat<f64>> = None;
        let mut flops = 0;
        loop {
            let current = coarse_a.as_ref().unwrap_or(a);
            if current.rows() <= MAX_COARSE || levels.len() + 1 >= MAX_LEVELS {
                break;
            }
            let (inv_diag, lambda, f) = smoother_data(current)?;
            flops += f;
            let graph = strength(current, &nodes, theta);
            let (aggregate_of, count) = aggregate(&graph);
            if count == nodes.len() {
                break;
            }
            let (t, coarse_nodes, coarse_modes) = tentative(&nodes, &modes, &aggregate_of, count);
            let at = multiply_grouped(current, &nodes, &t, &nodes);
            flops += product_flops(current, &t);
            let p = smooth_prolongator(&t, &at, &inv_diag, 4.0 / (3.0 * lambda));
            let r = transpose(&p);
            let (next, f) = galerkin(current, &p, &r, &nodes, &coarse_nodes);
            flops += f;
            levels.push(Level {
                a: coarse_a.take(),
                inv_diag,
                lambda,
                p,
                r,
                nodes,
                coarse_nodes: coarse_nodes.clone(),
            });
            coarse_a = Some(next);
            nodes = coarse_nodes;
            modes = coarse_modes;
        }
        let mut coarse = Box::new(Cholesky::new(Ordering::Amd, Indefinite::Error));
        coarse.set_parallel(false);
        flops += coarse.factorize(coarse_a.as_ref().unwrap_or(a))?.flops;
        Ok((
            Self {
                levels,
                coarse,
                smoother,
            },
            flops,
        ))
    }

    /// New values for `a` on the same hierarchy: the prolongators are kept, the Galerkin
    /// operators, smoothers and the coarse factor are recomputed. Returns the flops.
    pub fn refresh(&mut self, a: &CsMat<f64>) -> Result<u64, SolverError> {
        let mut flops = 0;
        let mut next: Option<CsMat<f64>> = None;
        for (l, level) in self.levels.iter_mut().enumerate() {
            if l > 0 {
                level.a = next.take();
            }
            let current = level.a.as_ref().unwrap_or(a);
            let (inv_diag, lambda, f) = smoother_data(current)?;
            let (coarse, g) = galerkin(
                current,
                &level.p,
                &level.r,
                &level.nodes,
                &level.coarse_nodes,
            );
            (level.inv_diag, level.lambda) = (inv_diag, lambda);
            flops += f + g;
            next = Some(coarse);
        }
        flops += self.coarse.factorize(next.as_ref().unwrap_or(a))?.flops;
        Ok(flops)
    }

    /// Rows of the finest level.
    pub fn nrows(&self) -> usize {
        self.levels
            .first()
            .map_or(self.coarse.nrows().unwrap_or(0), |l| l.p.rows())
    }

    /// Rows of each level, finest first (the coarsest last).
    pub fn level_sizes(&self) -> Vec<usize> {
        let mut sizes: Vec<usize> = self.levels.iter().map(|l| l.p.rows()).collect();
        sizes.push(self.coarse.nrows().unwrap_or(0));
        sizes
    }

    /// `z = M^-1 r`: one V-cycle from a zero guess, `a0` the finest operator.
    pub fn apply(&self, a0: &dyn LinearOperator, r: &[f64], z: &mut [f64]) {
        z.fill(0.0);
        self.cycle(0, a0, r, z);
    }

    fn cycle(&self, l: usize, a0: &dyn LinearOperator, b: &[f64], x: &mut [f64]) {
        let Some(level) = self.levels.get(l) else {
            x.copy_from_slice(b);
            self.coarse
                .solve_in_place(x)
                .expect("the coarsest factor solves vectors of its size");
            return;
        };
        let a: &dyn LinearOperator = match &level.a {
            Some(m) => m,
            None => a0,
        };
        let n = b.len();
        let mut work = vec![0.0; n];
        self.smooth(level, a, b, x, true, &mut work);
        a.apply(x, &mut work);
        for_each_entry(&mut work, |i, w| *w = b[i] - *w);
        let nc = level.r.rows();
        let (mut bc, mut xc) = (vec![0.0; nc], vec![0.0; nc]);
        level.r.apply(&work, &mut bc);
        self.cycle(l + 1, a0, &bc, &mut xc);
        level.p.apply(&xc, &mut work);
        for_each_entry(x, |i, xi| *xi += work[i]);
        self.smooth(level, a, b, x, false, &mut work);
    }

    /// Smooths `A x = b` in place; `zero` says `x` is zero on entry (saves a product); `x`
    /// is zero on entry to every `cycle`.
    fn smooth(
        &self,
        level: &Level,
        a: &dyn LinearOperator,
        b: &[f64],
        x: &mut [f64],
        zero: bool,
        work: &mut [f64],
    ) {
        let d = &level.inv_diag;
        // work = D^-1 (b - A x)
        let residual = |x: &[f64], work: &mut [f64], skip: bool| {
            if skip {
                for_each_entry(work, |i, w| *w = d[i] * b[i]);
            } else {
                a.apply(x, work);
                for_each_entry(work, |i, w| *w = d[i] * (b[i] - *w));
            }
        };
        match self.smoother {
            AmgSmoother::Jacobi { sweeps } => {
                let omega = 4.0 / (3.0 * level.lambda);
                for s in 0..sweeps {
                    residual(x, work, zero && s == 0);
                    for_each_entry(x, |i, xi| *xi += omega * work[i]);
                }
            }
            AmgSmoother::Chebyshev { degree } => {
                let upper = 1.1 * level.lambda;
                let lower = upper / 30.0;
                let (theta, delta) = (0.5 * (upper + lower), 0.5 * (upper - lower));
                let sigma = theta / delta;
                let mut rho = 1.0 / sigma;
                residual(x, work, zero);
                let mut step: Vec<f64> = work.iter().map(|w| w / theta).collect();
                for _ in 1..degree {
                    for_each_entry(x, |i, xi| *xi += step[i]);
                    residual(x, work, false);
                    let rho_next = 1.0 / (2.0 * sigma - rho);
                    let (c1, c2) = (rho_next * rho, 2.0 * rho_next / delta);
                    for_each_entry(&mut step, |i, s| *s = c1 * *s + c2 * work[i]);
                    rho = rho_next;
                }
                for_each_entry(x, |i, xi| *xi += step[i]);
            }
        }
    }

    /// Floating-point operations of one `apply` with finest operator `a0`.
    pub fn flops(&self, a0: &dyn LinearOperator) -> u64 {
        let per_smooth = match self.smoother {
            AmgSmoother::Jacobi { sweeps } => sweeps as u64,
            AmgSmoother::Chebyshev { degree } => degree as u64,
        };
        let mut total = self.coarse.solve_flops();
        for level in &self.levels {
            let (apply, n) = match &level.a {
                Some(m) => (2 * m.nnz() as u64, m.rows() as u64),
                None => (a0.apply_flops(), a0.nrows() as u64),
            };
            // Pre- and post-smoothing (the first product is skipped), the residual, the
            // two transfers and the vector updates.
            total += (2 * per_smooth) * apply + 2 * 2 * level.p.nnz() as u64 + 12 * n;
        }
        total
    }
}

/// The rigid-body modes of the nodes (translations, and rotations about the centroid when
/// positions are given), row-major `n x k`, with the finest level's nodes (3 rows each, or
/// 1 when `n` is not a multiple of 3).
fn near_null_space(n: usize, coordinates: Option<&[[f64; 3]]>) -> (Nodes, Modes) {
    let blocked = n.is_multiple_of(3);
    let coordinates = coordinates.filter(|c| blocked && c.len() * 3 == n);
    let Some(points) = coordinates else {
        let nodes = Nodes::uniform(n, if blocked { 3 } else { 1 });
        let values = if blocked {
            (0..n)
                .flat_map(|i| std::array::from_fn::<f64, 3, _>(|c| f64::from(u8::from(c == i % 3))))
                .collect()
        } else {
            vec![1.0; n]
        };
        let k = if blocked { 3 } else { 1 };
        return (nodes, Modes { k, values });
    };
    let count = points.len().max(1) as f64;
    let mut centre = [0.0; 3];
    for p in points {
        for c in 0..3 {
            centre[c] += p[c] / count;
        }
    }
    // Scaled to unit size so the rotations' columns weigh like the translations'.
    let size = points
        .iter()
        .flat_map(|p| (0..3).map(move |c| (p[c] - centre[c]).abs()))
        .fold(0.0, f64::max)
        .max(f64::MIN_POSITIVE);
    let mut values = Vec::with_capacity(6 * n);
    for p in points {
        let [x, y, z] = std::array::from_fn(|c| (p[c] - centre[c]) / size);
        values.extend_from_slice(&[1.0, 0.0, 0.0, 0.0, z, -y]);
        values.extend_from_slice(&[0.0, 1.0, 0.0, -z, 0.0, x]);
        values.extend_from_slice(&[0.0, 0.0, 1.0, y, -x, 0.0]);
    }
    (Nodes::uniform(n, 3), Modes { k: 6, values })
}

/// Near-null-space vectors, row-major: `values[i * k + j]` is mode `j` at unknown `i`.
#[derive(Debug, Clone)]
struct Modes {
    k: usize,
    values: Vec<f64>,
}

/// `D^-1` of `a`, the estimated largest eigenvalue of `D^-1 A`, and the flops spent.
fn smoother_data(a: &CsMat<f64>) -> Result<(Vec<f64>, f64, u64), SolverError> {
    let n = a.rows();
    let mut d = vec![0.0; n];
    a.diagonal(&mut d);
    if let Some(i) = d.iter().position(|&x| !(x > 0.0)) {
        return Err(SolverError::NotPositiveDefinite {
            pivot: i,
            value: d[i],
            spent: None,
        });
    }
    let inv: Vec<f64> = d.iter().map(|x| 1.0 / x).collect();
    // Power iteration on D^-1 A from a fixed pseudo-random start (Rayleigh quotient in the
    // D inner product, where D^-1 A is symmetric).
    let mut v: Vec<f64> = (0..n)
        .map(|i| {
            let h = (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
            (h >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        })
        .collect();
    let mut w = vec![0.0; n];
    let mut lambda: f64 = 0.0;
    for _ in 0..POWER_ITERATIONS {
        let scale = norm(&v);
        for_each_entry(&mut v, |_, x| *x /= scale);
        a.apply(&v, &mut w);
        let vav = dot(&v, &w);
        let vdv: f64 = v.iter().zip(&d).map(|(x, di)| x * x * di).sum();
        lambda = lambda.max(vav / vdv);
        for_each_entry(&mut w, |i, x| *x *= inv[i]);
        std::mem::swap(&mut v, &mut w);
    }
    if !(lambda.is_finite() && lambda > 0.0) {
        return Err(SolverError::NotPositiveDefinite {
            pivot: 0,
            value: lambda,
            spent: None,
        });
    }
    Ok((
        inv,
        lambda,
        POWER_ITERATIONS as u64 * (2 * a.nnz() as u64 + 6 * n as u64),
    ))
}

/// The strong neighbours of each node (compressed rows): `||A_IJ||_F >= theta
/// sqrt(||A_II||_F ||A_JJ||_F)` with a nonzero block.
fn strength(a: &CsMat<f64>, nodes: &Nodes, theta: f64) -> Vec<Vec<usize>> {
    let owner = nodes.owners();
    let (indptr, indices, data) = (a.indptr(), a.indices(), a.data());
    let indptr = indptr.raw_storage();
    let block_norms = |i: usize, acc: &mut Vec<f64>, seen: &mut Vec<usize>| {
        for row in nodes.dofs(i) {
            for k in indptr[row]..indptr[row + 1] {
                let j = owner[indices[k]];
                if acc[j] == 0.0 && !seen.contains(&j) {
                    seen.push(j);
                }
                acc[j] += data[k] * data[k];
            }
        }
    };
    let mut diag = vec![0.0; nodes.len()];
    for (i, d) in diag.iter_mut().enumerate() {
        for row in nodes.dofs(i) {
            for k in indptr[row]..indptr[row + 1] {
                if owner[indices[k]] == i {
                    *d += data[k] * data[k];
                }
            }
        }
    }
    let theta2 = theta * theta;
    (0..nodes.len())
        .into_par_iter()
        .with_min_len(ROWS_PER_TASK)
        .map_init(
            || (vec![0.0; nodes.len()], Vec::new()),
            |(acc, seen), i| {
                seen.clear();
                block_norms(i, acc, seen);
                let mut strong: Vec<usize> = seen
                    .iter()
                    .copied()
                    .filter(|&j| {
                        j != i && acc[j] > 0.0 && acc[j] >= theta2 * (diag[i] * diag[j]).sqrt()
                    })
                    .collect();
                for &j in seen.iter() {
                    acc[j] = 0.0;
                }
                strong.sort_unstable();
                strong
            },
        )
        .collect()
}

/// Greedy aggregation (Vaněk et al.): a node whose strong neighbours are all free starts an
/// aggregate with them; a left-over node joins the aggregate of its first aggregated strong
/// neighbour; what remains forms aggregates with its free neighbours. Returns each node's
/// aggregate and the number of aggregates.
fn aggregate(graph: &[Vec<usize>]) -> (Vec<usize>, usize) {
    const FREE: usize = usize::MAX;
    let n = graph.len();
    let mut of = vec![FREE; n];
    let mut count = 0;
    for i in 0..n {
        if of[i] == FREE && graph[i].iter().all(|&j| of[j] == FREE) {
            of[i] = count;
            for &j in &graph[i] {
                of[j] = count;
            }
            count += 1;
        }
    }
    let first_pass = of.clone();
    for i in 0..n {
        if of[i] == FREE
            && let Some(&j) = graph[i].iter().find(|&&j| first_pass[j] != FREE)
        {
            of[i] = first_pass[j];
        }
    }
    for i in 0..n {
        if of[i] == FREE {
            of[i] = count;
            for &j in &graph[i] {
                if of[j] == FREE {
                    of[j] = count;
                }
            }
            count += 1;
        }
    }
    (of, count)
}

/// The tentative prolongator: on each aggregate, the near-null space's rows orthonormalised
/// (`B_agg = Q R` by twice-applied modified Gram-Schmidt, dropping dependent columns), `Q` as
/// the aggregate's block of columns and `R` as the coarse near-null space. Returns `T`, the
/// coarse nodes (one per aggregate, one unknown per kept column) and the coarse modes.
fn tentative(
    nodes: &Nodes,
    modes: &Modes,
    aggregate_of: &[usize],
    count: usize,
) -> (CsMat<f64>, Nodes, Modes) {
    let k = modes.k;
    let mut members: Vec<Vec<usize>> = vec![Vec::new(); count];
    for (i, &g) in aggregate_of.iter().enumerate() {
        members[g].extend(nodes.dofs(i));
    }
    // Per aggregate: Q (rows x kept, column-major over kept) and R (kept x k).
    let factors: Vec<(Vec<f64>, Vec<f64>, usize)> = members
        .par_iter()
        .map(|rows| {
            let m = rows.len();
            let mut q = vec![0.0; m * k];
            for (r, &row) in rows.iter().enumerate() {
                for c in 0..k {
                    q[c * m + r] = modes.values[row * k + c];
                }
            }
            let mut kept = 0;
            let mut r_full = vec![0.0; k * k];
            for c in 0..k {
                let mut col = q[c * m..(c + 1) * m].to_vec();
                let original = norm(&col);
                let mut coefficients = vec![0.0; kept];
                for _ in 0..2 {
                    for (j, coef) in coefficients.iter_mut().enumerate() {
                        let qj = &q[j * m..(j + 1) * m];
                        let h = dot(qj, &col);
                        *coef += h;
                        for (x, y) in col.iter_mut().zip(qj) {
                            *x -= h * y;
                        }
                    }
                }
                let length = norm(&col);
                for (j, coef) in coefficients.iter().enumerate() {
                    r_full[j * k + c] = *coef;
                }
                if length > 1e-10 * original.max(f64::MIN_POSITIVE) && length > 0.0 {
                    r_full[kept * k + c] = length;
                    for (dst, x) in q[kept * m..(kept + 1) * m].iter_mut().zip(&col) {
                        *dst = x / length;
                    }
                    kept += 1;
                }
            }
            q.truncate(kept * m);
            r_full.truncate(kept * k);
            (q, r_full, kept)
        })
        .collect();
    let mut ptr = Vec::with_capacity(count + 1);
    ptr.push(0);
    for (_, _, kept) in &factors {
        ptr.push(ptr.last().unwrap() + kept);
    }
    let coarse = Nodes { ptr };
    let n = *nodes.ptr.last().unwrap_or(&0);
    let mut row_of = vec![(0, 0); n];
    for (g, rows) in members.iter().enumerate() {
        for (r, &row) in rows.iter().enumerate() {
            row_of[row] = (g, r);
        }
    }
    let mut indptr = Vec::with_capacity(n + 1);
    let mut indices = Vec::new();
    let mut values = Vec::new();
    indptr.push(0);
    for &(g, r) in &row_of {
        let (q, _, kept) = &factors[g];
        let m = members[g].len();
        for c in 0..*kept {
            indices.push(coarse.ptr[g] + c);
            values.push(q[c * m + r]);
        }
        indptr.push(indices.len());
    }
    let t = CsMat::new((n, coarse.ptr[count]), indptr, indices, values);
    let coarse_values = factors.into_iter().flat_map(|(_, r, _)| r).collect();
    (
        t,
        coarse,
        Modes {
            k,
            values: coarse_values,
        },
    )
}

/// `P = (I - omega D^-1 A) T`, given `A T`; `T`'s pattern lies inside `A T`'s (the diagonal
/// of `A` is stored).
fn smooth_prolongator(t: &CsMat<f64>, at: &CsMat<f64>, inv_diag: &[f64], omega: f64) -> CsMat<f64> {
    let (t_ptr, t_idx, t_val) = (t.indptr(), t.indices(), t.data());
    let t_ptr = t_ptr.raw_storage();
    let (p_ptr, p_idx, at_val) = (at.indptr(), at.indices(), at.data());
    let p_ptr = p_ptr.raw_storage();
    let data: Vec<f64> = (0..at.rows())
        .into_par_iter()
        .with_min_len(ROWS_PER_TASK)
        .flat_map_iter(|i| {
            let row = p_ptr[i]..p_ptr[i + 1];
            let scale = -omega * inv_diag[i];
            let mut values: Vec<f64> = at_val[row.clone()].iter().map(|v| scale * v).collect();
            for m in t_ptr[i]..t_ptr[i + 1] {
                let offset = p_idx[row.clone()]
                    .binary_search(&t_idx[m])
                    .expect("T's pattern lies inside A T's");
                values[offset] += t_val[m];
            }
            values
        })
        .collect();
    CsMat::new((at.rows(), at.cols()), p_ptr.to_vec(), p_idx.to_vec(), data)
}

/// `P^T A P` and its flops; `fine` and `coarse` group the rows of `A` and of `P^T`.
fn galerkin(
    a: &CsMat<f64>,
    p: &CsMat<f64>,
    r: &CsMat<f64>,
    fine: &Nodes,
    coarse: &Nodes,
) -> (CsMat<f64>, u64) {
    let ap = multiply_grouped(a, fine, p, fine);
    let flops = product_flops(a, p) + product_flops(r, &ap);
    (multiply_grouped(r, coarse, &ap, fine), flops)
}

/// Flops of `a * b`: two per product of entries.
fn product_flops(a: &CsMat<f64>, b: &CsMat<f64>) -> u64 {
    let b_ptr = b.indptr();
    let b_ptr = b_ptr.raw_storage();
    2 * a
        .indices()
        .iter()
        .map(|&k| (b_ptr[k + 1] - b_ptr[k]) as u64)
        .sum::<u64>()
}

/// Whether the rows of each group have the same columns.
fn rows_share_columns(m: &CsMat<f64>, groups: &Nodes) -> bool {
    let (ptr, idx) = (m.indptr(), m.indices());
    let ptr = ptr.raw_storage();
    *groups.ptr.last().unwrap_or(&0) == m.rows()
        && (0..groups.len()).into_par_iter().all(|g| {
            let rows = groups.dofs(g);
            let first = &idx[ptr[rows.start]..ptr[rows.start + 1]];
            rows.skip(1)
                .all(|row| &idx[ptr[row]..ptr[row + 1]] == first)
        })
}

/// One group of a grouped product: `(row lengths, columns, values)`.
type RowsOut = (Vec<usize>, Vec<usize>, Vec<f64>);

/// `a * b` for block-structured operands, the same values as [`multiply`]: `a`'s rows come in
/// `a_groups` that share their columns, those columns cover whole groups of `b`'s rows
/// (`b_groups`), whose rows share theirs too. Each group of output rows then has one column
/// set, found once, and each block pair is a small dense product through a position table
/// (no per-entry search or sort). Falls back to [`multiply`] when the structure is not there.
fn multiply_grouped(
    a: &CsMat<f64>,
    a_groups: &Nodes,
    b: &CsMat<f64>,
    b_groups: &Nodes,
) -> CsMat<f64> {
    multiply_blocks(a, a_groups, b, b_groups).unwrap_or_else(|| multiply(a, b))
}

/// The grouped product of [`multiply_grouped`], `None` without the block structure.
fn multiply_blocks(
    a: &CsMat<f64>,
    a_groups: &Nodes,
    b: &CsMat<f64>,
    b_groups: &Nodes,
) -> Option<CsMat<f64>> {
    if !(rows_share_columns(a, a_groups) && rows_share_columns(b, b_groups)) {
        return None;
    }
    let owner = b_groups.owners();
    let (a_ptr, a_idx, a_val) = (a.indptr(), a.indices(), a.data());
    let a_ptr = a_ptr.raw_storage();
    let (b_ptr, b_idx, b_val) = (b.indptr(), b.indices(), b.data());
    let b_ptr = b_ptr.raw_storage();
    let group = |g: usize, pos: &mut Vec<usize>, out: &mut RowsOut| -> Option<()> {
        let rows = a_groups.dofs(g);
        let (m, r0) = (rows.len(), rows.start);
        let a_cols = &a_idx[a_ptr[r0]..a_ptr[r0 + 1]];
        // The row's columns as whole groups of b's rows: (group, offset in the row).
        let mut segments = Vec::new();
        let mut k = 0;
        while k < a_cols.len() {
            let j = owner[a_cols[k]];
            let range = b_groups.dofs(j);
            let len = range.len();
            if k + len > a_cols.len() || !a_cols[k..k + len].iter().copied().eq(range) {
                return None;
            }
            segments.push((j, k));
            k += len;
        }
        let mut cols: Vec<usize> = Vec::new();
        for &(j, _) in &segments {
            let first = b_groups.ptr[j];
            for &c in &b_idx[b_ptr[first]..b_ptr[first + 1]] {
                if pos[c] == usize::MAX {
                    pos[c] = 0;
                    cols.push(c);
                }
            }
        }
        cols.sort_unstable();
        for (t, &c) in cols.iter().enumerate() {
            pos[c] = t;
        }
        let u = cols.len();
        let start = out.2.len();
        out.2.resize(start + m * u, 0.0);
        let acc = &mut out.2[start..];
        let mut local = Vec::new();
        // Entries are added in the order of a's row, as in `multiply`.
        for &(j, offset) in &segments {
            let b_rows = b_groups.dofs(j);
            local.clear();
            local.extend(
                b_idx[b_ptr[b_rows.start]..b_ptr[b_rows.start + 1]]
                    .iter()
                    .map(|&c| pos[c]),
            );
            for ii in 0..m {
                let a_row = a_ptr[r0 + ii] + offset;
                let target = &mut acc[ii * u..(ii + 1) * u];
                for (jj, b_row) in b_rows.clone().enumerate() {
                    let x = a_val[a_row + jj];
                    let values = &b_val[b_ptr[b_row]..b_ptr[b_row + 1]];
                    for (&p, &v) in local.iter().zip(values) {
                        target[p] += x * v;
                    }
                }
            }
        }
        for &c in &cols {
            pos[c] = usize::MAX;
        }
        for _ in 0..m {
            out.0.push(u);
            out.1.extend_from_slice(&cols);
        }
        Some(())
    };
    const GROUPS_PER_TASK: usize = 128;
    let tasks: Option<Vec<RowsOut>> = (0..a_groups.len().div_ceil(GROUPS_PER_TASK))
        .into_par_iter()
        .map_init(
            || vec![usize::MAX; b.cols()],
            |pos, task| {
                let mut out = (Vec::new(), Vec::new(), Vec::new());
                let groups =
                    task * GROUPS_PER_TASK..((task + 1) * GROUPS_PER_TASK).min(a_groups.len());
                for g in groups {
                    if group(g, pos, &mut out).is_none() {
                        // Leave the table clean for the thread's next task.
                        pos.fill(usize::MAX);
                        return None;
                    }
                }
                Some(out)
            },
        )
        .collect();
    Some(concatenate(a.rows(), b.cols(), tasks?))
}

/// A CSR matrix from consecutive row blocks `(row lengths, columns, values)`.
fn concatenate(rows: usize, cols: usize, tasks: Vec<RowsOut>) -> CsMat<f64> {
    let nnz = tasks.iter().map(|t| t.1.len()).sum();
    let mut indptr = Vec::with_capacity(rows + 1);
    let (mut indices, mut values) = (Vec::with_capacity(nnz), Vec::with_capacity(nnz));
    indptr.push(0);
    for (lengths, idx, val) in tasks {
        for len in lengths {
            indptr.push(indptr.last().unwrap() + len);
        }
        indices.extend(idx);
        values.extend(val);
    }
    CsMat::new((rows, cols), indptr, indices, values)
}

/// The CSR product `a * b`, sorted columns; rows in parallel, each summed in entry order.
fn multiply(a: &CsMat<f64>, b: &CsMat<f64>) -> CsMat<f64> {
    let (rows, cols) = (a.rows(), b.cols());
    let (a_ptr, a_idx, a_val) = (a.indptr(), a.indices(), a.data());
    let a_ptr = a_ptr.raw_storage();
    let (b_ptr, b_idx, b_val) = (b.indptr(), b.indices(), b.data());
    let b_ptr = b_ptr.raw_storage();
    let tasks: Vec<(Vec<usize>, Vec<usize>, Vec<f64>)> = (0..rows.div_ceil(ROWS_PER_TASK))
        .into_par_iter()
        .map_init(
            || (vec![usize::MAX; cols], vec![0.0; cols]),
            |(mark, acc), task| {
                let (mut lengths, mut idx, mut val) = (Vec::new(), Vec::new(), Vec::new());
                for i in task * ROWS_PER_TASK..((task + 1) * ROWS_PER_TASK).min(rows) {
                    let start = idx.len();
                    for ka in a_ptr[i]..a_ptr[i + 1] {
                        let (j, x) = (a_idx[ka], a_val[ka]);
                        for kb in b_ptr[j]..b_ptr[j + 1] {
                            let c = b_idx[kb];
                            if mark[c] != i {
                                mark[c] = i;
                                acc[c] = 0.0;
                                idx.push(c);
                            }
                            acc[c] += x * b_val[kb];
                        }
                    }
                    idx[start..].sort_unstable();
                    val.extend(idx[start..].iter().map(|&c| acc[c]));
                    lengths.push(idx.len() - start);
                }
                (lengths, idx, val)
            },
        )
        .collect();
    concatenate(rows, cols, tasks)
}

/// The transpose of a CSR matrix, as CSR with sorted columns.
fn transpose(m: &CsMat<f64>) -> CsMat<f64> {
    let (rows, cols) = (m.rows(), m.cols());
    let (ptr, idx, val) = (m.indptr(), m.indices(), m.data());
    let ptr = ptr.raw_storage();
    let mut counts = vec![0usize; cols + 1];
    for &c in idx {
        counts[c + 1] += 1;
    }
    for c in 0..cols {
        counts[c + 1] += counts[c];
    }
    let mut next = counts.clone();
    let mut indices = vec![0; idx.len()];
    let mut values = vec![0.0; idx.len()];
    for i in 0..rows {
        for k in ptr[i]..ptr[i + 1] {
            let slot = &mut next[idx[k]];
            indices[*slot] = i;
            values[*slot] = val[k];
            *slot += 1;
        }
    }
    CsMat::new((cols, rows), counts, indices, values)
}

#[cfg(test)]
mod tests {
    use super::*;
    use sprs::TriMat;

    fn random(rows: usize, cols: usize, seed: u64) -> CsMat<f64> {
        let mut t = TriMat::new((rows, cols));
        let mut s = seed;
        for i in 0..rows {
            for _ in 0..3 {
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
    fn products_and_transposes_match_dense_arithmetic() {
        let (a, b) = (random(40, 30, 1), random(30, 25, 2));
        let c = multiply(&a, &b);
        let (da, db, dc) = (a.to_dense(), b.to_dense(), c.to_dense());
        let expected = da.dot(&db);
        for i in 0..40 {
            for j in 0..25 {
                assert!((dc[[i, j]] - expected[[i, j]]).abs() < 1e-14);
            }
        }
        let t = transpose(&a).to_dense();
        for i in 0..40 {
            for j in 0..30 {
                assert_eq!(t[[j, i]], da[[i, j]]);
            }
        }
        assert!(c.indptr().raw_storage().windows(2).all(|w| w[0] <= w[1]));
    }

    /// A `cells^3` grid's graph Laplacian coupling 3 components plus `shift I`, and the
    /// grid's points.
    fn grid_operator(cells: usize, shift: f64) -> (CsMat<f64>, Vec<[f64; 3]>) {
        let index = |x: usize, y: usize, z: usize| (z * cells + y) * cells + x;
        let nodes = cells * cells * cells;
        let mut t = TriMat::new((3 * nodes, 3 * nodes));
        let mut points = Vec::new();
        for z in 0..cells {
            for y in 0..cells {
                for x in 0..cells {
                    let i = index(x, y, z);
                    points.push([x as f64, y as f64, z as f64]);
                    let mut neighbours = Vec::new();
                    for (dx, dy, dz) in [(1, 0, 0), (0, 1, 0), (0, 0, 1)] {
                        if x + dx < cells && y + dy < cells && z + dz < cells {
                            neighbours.push(index(x + dx, y + dy, z + dz));
                        }
                        if x >= dx && y >= dy && z >= dz {
                            neighbours.push(index(x - dx, y - dy, z - dz));
                        }
                    }
                    // (Laplacian (x) B) + shift I with B = I + 0.1 (ones - I): full 3x3
                    // blocks, as FEM matrices have.
                    for c in 0..3 {
                        for d in 0..3 {
                            let b = if c == d { 1.0 } else { 0.1 };
                            let diagonal = neighbours.len() as f64 * b;
                            let shift = if c == d { shift } else { 0.0 };
                            t.add_triplet(3 * i + c, 3 * i + d, diagonal + shift);
                            for &j in &neighbours {
                                t.add_triplet(3 * i + c, 3 * j + d, -b);
                            }
                        }
                    }
                }
            }
        }
        (t.to_csr(), points)
    }

    #[test]
    fn grouped_products_equal_plain_ones_bit_for_bit_and_fall_back_without_blocks() {
        let (a, points) = grid_operator(8, 0.1);
        let (nodes, modes) = near_null_space(a.rows(), Some(&points));
        let graph = strength(&a, &nodes, 0.0);
        let (aggregate_of, count) = aggregate(&graph);
        let (t, coarse, _) = tentative(&nodes, &modes, &aggregate_of, count);
        let same = |x: &CsMat<f64>, y: &CsMat<f64>| {
            x.indptr().raw_storage() == y.indptr().raw_storage()
                && x.indices() == y.indices()
                && x.data() == y.data()
        };
        let at = multiply_blocks(&a, &nodes, &t, &nodes).unwrap();
        assert!(same(&at, &multiply(&a, &t)));
        let r = transpose(&at);
        let rat = multiply_blocks(&r, &coarse, &at, &nodes).unwrap();
        assert!(same(&rat, &multiply(&r, &at)));
        // Rows of a group that do not share columns: the plain product.
        let b = random(30, 30, 5);
        let groups = Nodes::uniform(30, 3);
        assert!(multiply_blocks(&b, &groups, &b, &groups).is_none());
        assert!(same(
            &multiply_grouped(&b, &groups, &b, &groups),
            &multiply(&b, &b)
        ));
    }

    #[test]
    fn the_cycle_is_a_symmetric_positive_definite_operator() {
        let (a, points) = grid_operator(12, 1e-3);
        for smoother in [
            AmgSmoother::Chebyshev { degree: 3 },
            AmgSmoother::Jacobi { sweeps: 1 },
        ] {
            let (amg, _) = Amg::new(&a, Some(&points), 0.0, smoother).unwrap();
            assert!(amg.level_sizes().len() >= 2, "{:?}", amg.level_sizes());
            let n = a.rows();
            let vector = |seed: u64| -> Vec<f64> {
                (0..n as u64)
                    .map(|i| (((i + 1) * seed * 0x9E37_79B9) % 1000) as f64 / 500.0 - 1.0)
                    .collect()
            };
            let (u, v) = (vector(3), vector(7));
            let (mut mu, mut mv) = (vec![0.0; n], vec![0.0; n]);
            amg.apply(&a, &u, &mut mu);
            amg.apply(&a, &v, &mut mv);
            let (umv, vmu) = (dot(&u, &mv), dot(&v, &mu));
            assert!(
                (umv - vmu).abs() <= 1e-10 * umv.abs().max(vmu.abs()),
                "{umv} vs {vmu}"
            );
            assert!(dot(&u, &mu) > 0.0 && dot(&v, &mv) > 0.0);
        }
    }

    #[test]
    fn aggregation_covers_every_node_once_with_connected_aggregates() {
        // A path of 10 nodes.
        let graph: Vec<Vec<usize>> = (0..10)
            .map(|i: usize| {
                [i.checked_sub(1), (i + 1 < 10).then_some(i + 1)]
                    .into_iter()
                    .flatten()
                    .collect()
            })
            .collect();
        let (of, count) = aggregate(&graph);
        assert!((10 / 3..10).contains(&count));
        for g in 0..count {
            let members: Vec<usize> = (0..10).filter(|&i| of[i] == g).collect();
            assert!(!members.is_empty());
            assert!(members.windows(2).all(|w| w[1] == w[0] + 1), "{members:?}");
        }
    }

    #[test]
    fn the_tentative_prolongator_reproduces_the_rigid_modes() {
        let points: Vec<[f64; 3]> = (0..12)
            .map(|i| [f64::from(i % 3), f64::from(i / 3 % 2), f64::from(i / 6)])
            .collect();
        let (nodes, modes) = near_null_space(36, Some(&points));
        let aggregate_of: Vec<usize> = (0..12).map(|i| i / 4).collect();
        let (t, coarse, coarse_modes) = tentative(&nodes, &modes, &aggregate_of, 3);
        assert_eq!(coarse.len(), 3);
        // T B_c = B, and T has orthonormal columns.
        let (dt, kc) = (t.to_dense(), coarse_modes.k);
        for i in 0..36 {
            for c in 0..6 {
                let v: f64 = (0..t.cols())
                    .map(|j| dt[[i, j]] * coarse_modes.values[j * kc + c])
                    .sum();
                assert!((v - modes.values[i * 6 + c]).abs() < 1e-12);
            }
        }
        let gram = dt.t().dot(&dt);
        for i in 0..t.cols() {
            for j in 0..t.cols() {
                let expected = if i == j { 1.0 } else { 0.0 };
                assert!((gram[[i, j]] - expected).abs() < 1e-12);
            }
        }
    }
}
