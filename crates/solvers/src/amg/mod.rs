//! Smoothed-aggregation algebraic multigrid (Vaněk, Mandel & Brezina 1996) as a PCG
//! preconditioner, for elasticity: the near-null space is the six rigid-body modes of the
//! nodes' positions, so each coarse node carries up to six unknowns (three translations and
//! three rotations of its aggregate), which is what keeps the iteration count flat as the
//! mesh is refined.
//!
//! Set-up per level: strength of connection on the node graph (3x3 blocks on the finest
//! level, `k x k` blocks below), greedy aggregation, a tentative prolongator from a QR of the
//! near-null space on each aggregate, one damped-Jacobi smoothing of it, and the Galerkin
//! operator `P^T A P` (its upper triangle, mirrored); the coarsest level is factorised by
//! the sparse Cholesky. Every matrix of the hierarchy is block CSR ([`crate::blocks`]): each
//! coarse node keeps all `k` unknowns, a near-null-space column that is dependent on a small
//! aggregate becomes a zero column of `P` and its coarse unknown an identity row nothing
//! couples to, so the blocks stay uniform. The cycle's matrices are kept in single precision
//! (see [`Level`]). One V-cycle with symmetric smoothing (Chebyshev or damped Jacobi, the
//! same before and after) is the preconditioner, so PCG sees an SPD operator. Every product
//! runs rows in parallel with each row summed in a fixed order: the hierarchy and the cycle
//! are identical for any thread count.

use std::borrow::Cow;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sprs::CsMat;

use crate::blocks::Blocks;

use crate::direct::{Cholesky, Indefinite};
use crate::operator::{LinearOperator, positive_diagonal};
use crate::ordering::Ordering;
use crate::vector::{dot, for_each_entry, norm, update_from, update_from2};
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

impl AmgSmoother {
    /// Sweeps or degree: products with `A` per smoothing.
    fn steps(self) -> usize {
        match self {
            AmgSmoother::Jacobi { sweeps } => sweeps,
            AmgSmoother::Chebyshev { degree } => degree,
        }
    }
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
    let field = match smoother {
        AmgSmoother::Jacobi { .. } => "sweeps",
        AmgSmoother::Chebyshev { .. } => "degree",
    };
    if smoother.steps() == 0 {
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
/// Lanczos steps of the estimate of the largest eigenvalue of `D^-1 A`. Eight come 6 % below
/// it on both levels of the n = 32 beam (against 30 steps), which the smoother's margin
/// covers, and take one PCG iteration fewer there than 12 steps (15 -> 14) at four products
/// fewer per level.
const LANCZOS_STEPS: usize = 8;

/// One level above the coarsest: its smoother and the transfer to the next level.
///
/// Its matrices are stored in single precision (half the memory and the memory traffic of
/// products that are bound by it; every sum is in double): the operator, on the finest level
/// a copy of the matrix the hierarchy was set up for, so the preconditioner is one fixed
/// operator; and the prolongator, rounded before the Galerkin product, so the coarse
/// operator is the Galerkin operator of the prolongator the cycle uses (summed in double,
/// up to the rounding of `A P` and of the result, which are stored in single precision
/// too; the coarsest level factorises its operator as rounded).
#[derive(Debug)]
struct Level {
    /// This level's operator.
    a: Blocks<f32>,
    inv_diag: Vec<f64>,
    /// Estimated largest eigenvalue of `D^-1 A`.
    lambda: f64,
    /// Prolongation to this level from the next one, and its transpose.
    p: Blocks<f32>,
    r: Blocks<f32>,
}

/// Vectors of one level's part of a cycle, allocated once per hierarchy.
#[derive(Debug, Default)]
struct Scratch {
    /// Residuals and transfers on this level.
    work: Vec<f64>,
    /// The Chebyshev smoother's step.
    step: Vec<f64>,
    /// Right-hand side and solution on the next level.
    bc: Vec<f64>,
    xc: Vec<f64>,
}

/// A set-up multigrid hierarchy.
#[derive(Debug)]
pub(crate) struct Amg {
    levels: Vec<Level>,
    coarse: Box<Cholesky>,
    smoother: AmgSmoother,
    /// One [`Scratch`] per level; `apply` takes `&self`, so the cycle borrows them here
    /// instead of allocating vectors in every PCG iteration.
    scratch: std::sync::Mutex<Vec<Scratch>>,
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
        let mut modes = near_null_space(a.rows(), coordinates);
        let mut current = finest_blocks(a)?;
        let mut levels: Vec<Level> = Vec::new();
        let mut flops = 0;
        while current.shape().0 > MAX_COARSE && levels.len() + 1 < MAX_LEVELS {
            let (aggregate_of, count) = aggregate(&strength(&current, theta));
            if count == current.rows {
                break;
            }
            let (inv_diag, lambda, f) = smoother_data(&current)?;
            flops += f;
            let (t, coarse_modes) = tentative(&modes, current.r, &aggregate_of, count);
            let p = smoothed_prolongator(&current, &t, &inv_diag, lambda);
            flops += current.product_flops(&t);
            let r = p.transpose();
            let (next, f) = galerkin(&current, &p, &r);
            flops += f;
            levels.push(Level {
                a: std::mem::replace(&mut current, next),
                inv_diag,
                lambda,
                p,
                r,
            });
            modes = coarse_modes;
        }
        let mut coarse = Box::new(Cholesky::new(Ordering::Amd, Indefinite::Error));
        coarse.set_parallel(false);
        let last = (!levels.is_empty()).then_some(&current);
        flops += coarse.factorize(coarsest(a, last).as_ref())?.flops;
        let scratch = levels
            .iter()
            .map(|l| {
                let (n, nc) = (l.p.shape().0, l.p.shape().1);
                Scratch {
                    work: vec![0.0; n],
                    step: vec![0.0; n],
                    bc: vec![0.0; nc],
                    xc: vec![0.0; nc],
                }
            })
            .collect();
        Ok((
            Self {
                levels,
                coarse,
                smoother,
                scratch: std::sync::Mutex::new(scratch),
            },
            flops,
        ))
    }

    /// New values for `a` on the same hierarchy: the prolongators are kept, the Galerkin
    /// operators, smoothers and the coarse factor are recomputed. Returns the flops.
    pub fn refresh(&mut self, a: &CsMat<f64>) -> Result<u64, SolverError> {
        let mut flops = 0;
        let mut current = finest_blocks(a)?;
        for level in &mut self.levels {
            let (inv_diag, lambda, f) = smoother_data(&current)?;
            let (next, g) = galerkin(&current, &level.p, &level.r);
            level.a = std::mem::replace(&mut current, next);
            (level.inv_diag, level.lambda) = (inv_diag, lambda);
            flops += f + g;
        }
        let last = (!self.levels.is_empty()).then_some(&current);
        flops += self.coarse.factorize(coarsest(a, last).as_ref())?.flops;
        Ok(flops)
    }

    /// Rows of the finest level.
    pub fn nrows(&self) -> usize {
        self.levels
            .first()
            .map_or(self.coarse.nrows().unwrap_or(0), |l| l.p.shape().0)
    }

    /// Rows of each level, finest first (the coarsest last).
    pub fn level_sizes(&self) -> Vec<usize> {
        let mut sizes: Vec<usize> = self.levels.iter().map(|l| l.p.shape().0).collect();
        sizes.push(self.coarse.nrows().unwrap_or(0));
        sizes
    }

    /// `z = M^-1 r`: one V-cycle from a zero guess.
    pub fn apply(&self, r: &[f64], z: &mut [f64]) {
        z.fill(0.0);
        let mut scratch = self
            .scratch
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        self.cycle(0, r, z, &mut scratch);
    }

    /// One V-cycle from level `l` down; `x` is zero on entry.
    fn cycle(&self, l: usize, b: &[f64], x: &mut [f64], scratch: &mut [Scratch]) {
        let (Some(level), Some((s, deeper))) = (self.levels.get(l), scratch.split_first_mut())
        else {
            x.copy_from_slice(b);
            self.coarse
                .solve_in_place(x)
                .expect("the coarsest factor solves vectors of its size");
            return;
        };
        let a = &level.a;
        self.smooth(level, b, x, true, s);
        a.multiply_vector_with(x, &mut s.work, |i, ax, w| *w = b[i] - ax);
        level.r.multiply_vector(&s.work, &mut s.bc);
        s.xc.fill(0.0);
        self.cycle(l + 1, &s.bc, &mut s.xc, deeper);
        level.p.multiply_vector(&s.xc, &mut s.work);
        let work = &s.work;
        update_from(x, work, |xi, wi| *xi += wi);
        self.smooth(level, b, x, false, s);
    }

    /// Smooths `A x = b` in place; `zero` says `x` is zero on entry (saves a product); `x`
    /// is zero on entry to every `cycle`.
    fn smooth(&self, level: &Level, b: &[f64], x: &mut [f64], zero: bool, s: &mut Scratch) {
        let (a, work, step) = (&level.a, &mut s.work, &mut s.step);
        let d = &level.inv_diag;
        // Each residual `D^-1 (b - A x)` is formed as the product is stored.
        match self.smoother {
            AmgSmoother::Jacobi { sweeps } => {
                let omega = 4.0 / (3.0 * level.lambda);
                for s in 0..sweeps {
                    if zero && s == 0 {
                        update_from2(work, d, b, |w, di, bi| *w = di * bi);
                    } else {
                        a.multiply_vector_with(x, work, |i, ax, w| *w = d[i] * (b[i] - ax));
                    }
                    update_from(x, work, |xi, wi| *xi += omega * wi);
                }
            }
            AmgSmoother::Chebyshev { degree } => {
                let upper = 1.1 * level.lambda;
                let lower = upper / 30.0;
                let (theta, delta) = (0.5 * (upper + lower), 0.5 * (upper - lower));
                let sigma = theta / delta;
                let mut rho = 1.0 / sigma;
                if zero {
                    update_from2(step, d, b, |v, di, bi| *v = di * bi / theta);
                } else {
                    a.multiply_vector_with(x, step, |i, ax, v| *v = d[i] * (b[i] - ax) / theta);
                }
                for _ in 1..degree {
                    update_from(x, step, |xi, si| *xi += si);
                    let rho_next = 1.0 / (2.0 * sigma - rho);
                    let (c1, c2) = (rho_next * rho, 2.0 * rho_next / delta);
                    // step = c1 step + c2 D^-1 (b - A x)
                    a.multiply_vector_with(x, step, |i, ax, s| {
                        *s = c1 * *s + c2 * (d[i] * (b[i] - ax));
                    });
                    rho = rho_next;
                }
                update_from(x, step, |xi, si| *xi += si);
            }
        }
    }

    /// Floating-point operations of one `apply`.
    pub fn flops(&self) -> u64 {
        let per_smooth = self.smoother.steps() as u64;
        let mut total = self.coarse.solve_flops();
        for level in &self.levels {
            let (apply, n) = (level.a.apply_flops(), level.a.nrows() as u64);
            // Pre- and post-smoothing (the first product is skipped), the residual, the
            // two transfers and the vector updates.
            total += (2 * per_smooth) * apply + 2 * 2 * level.p.nnz() as u64 + 12 * n;
        }
        total
    }
}

/// The finest operator in 3x3 blocks (1x1 when the rows are not a multiple of 3), rounded
/// to single precision: the cycle multiplies it, and the hierarchy is built from it, so the
/// coarse operators are the Galerkin operators of what the cycle applies.
fn finest_blocks(a: &CsMat<f64>) -> Result<Blocks<f32>, SolverError> {
    let b = if a.rows().is_multiple_of(3) { 3 } else { 1 };
    Blocks::from_csr(a, b).ok_or(SolverError::Unsupported("AMG needs a square CSR matrix"))
}

/// The matrix the coarsest level factorises: the last Galerkin operator (as the cycle would
/// multiply it, in single precision), or `a` itself when the hierarchy has no level above
/// the coarsest.
fn coarsest<'a>(a: &'a CsMat<f64>, last: Option<&Blocks<f32>>) -> Cow<'a, CsMat<f64>> {
    last.map_or(Cow::Borrowed(a), |b| Cow::Owned(b.to_csr()))
}

/// Near-null-space vectors, row-major: `values[i * k + j]` is mode `j` at unknown `i`.
#[derive(Debug, Clone)]
struct Modes {
    k: usize,
    values: Vec<f64>,
}

/// The rigid-body modes of the nodes (translations, and rotations about the centroid when
/// positions are given), row-major `n x k`; a single constant without 3x3 blocks.
fn near_null_space(n: usize, coordinates: Option<&[[f64; 3]]>) -> Modes {
    let blocked = n.is_multiple_of(3);
    let coordinates = coordinates.filter(|c| blocked && c.len() * 3 == n);
    let Some(points) = coordinates else {
        if !blocked {
            return Modes {
                k: 1,
                values: vec![1.0; n],
            };
        }
        let values = (0..n)
            .flat_map(|i| std::array::from_fn::<f64, 3, _>(|c| f64::from(u8::from(c == i % 3))))
            .collect();
        return Modes { k: 3, values };
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
    Modes { k: 6, values }
}

/// `D^-1` of `a` (the cycle's single-precision operator), the estimated largest eigenvalue
/// of `D^-1 A`, and the flops spent.
fn smoother_data(a: &Blocks<f32>) -> Result<(Vec<f64>, f64, u64), SolverError> {
    let n = a.nrows();
    let inv: Vec<f64> = positive_diagonal(a)?.iter().map(|x| 1.0 / x).collect();
    let lambda = largest_eigenvalue(a, &inv);
    if !(lambda.is_finite() && lambda > 0.0) {
        return Err(SolverError::NotPositiveDefinite {
            pivot: 0,
            value: lambda,
            spent: None,
        });
    }
    let flops = LANCZOS_STEPS as u64 * (a.apply_flops() + 12 * n as u64);
    Ok((inv, lambda, flops))
}

/// The largest eigenvalue of `D^-1 A` (that of `D^-1/2 A D^-1/2`), as the largest Ritz value
/// of a few Lanczos steps from a fixed pseudo-random start: within a few per cent where as
/// many power iterations can be off by tens of per cent (and a Chebyshev smoother above its
/// upper bound amplifies instead of damping).
fn largest_eigenvalue(a: &Blocks<f32>, inv_diag: &[f64]) -> f64 {
    let n = inv_diag.len();
    let scale: Vec<f64> = inv_diag.iter().map(|x| x.sqrt()).collect();
    let mut v: Vec<f64> = (0..n)
        .map(|i| {
            let h = (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
            (h >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        })
        .collect();
    let length = norm(&v);
    for_each_entry(&mut v, |_, x| *x /= length);
    let (mut previous, mut u, mut w) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
    let (mut alphas, mut betas) = (Vec::new(), Vec::new());
    let mut beta = 0.0;
    for _ in 0..LANCZOS_STEPS {
        update_from2(&mut u, &scale, &v, |x, si, vi| *x = si * vi);
        a.apply(&u, &mut w);
        update_from(&mut w, &scale, |x, si| *x *= si);
        let alpha = dot(&w, &v);
        update_from2(&mut w, &v, &previous, |x, vi, pi| {
            *x -= alpha * vi + beta * pi
        });
        alphas.push(alpha);
        beta = norm(&w);
        if !(beta > 1e-12 * alpha.abs()) {
            break;
        }
        betas.push(beta);
        std::mem::swap(&mut previous, &mut v);
        update_from(&mut v, &w, |x, wi| *x = wi / beta);
    }
    let k = alphas.len();
    let tridiagonal = nalgebra::DMatrix::from_fn(k, k, |i, j| match i.abs_diff(j) {
        0 => alphas[i],
        1 => betas[i.min(j)],
        _ => 0.0,
    });
    tridiagonal.symmetric_eigenvalues().max()
}

/// The strong neighbours of each node (block row), sorted: `||A_IJ||_F >= theta
/// sqrt(||A_II||_F ||A_JJ||_F)` with a nonzero block.
fn strength(a: &Blocks<f32>, theta: f64) -> Vec<Vec<usize>> {
    let squared = |k: usize| {
        a.block(k)
            .iter()
            .map(|&v| f64::from(v).powi(2))
            .sum::<f64>()
    };
    let diag: Vec<f64> = (0..a.rows)
        .map(|i| {
            let row = &a.idx[a.ptr[i]..a.ptr[i + 1]];
            row.binary_search(&(i as u32))
                .map_or(0.0, |k| squared(a.ptr[i] + k))
        })
        .collect();
    let theta2 = theta * theta;
    (0..a.rows)
        .into_par_iter()
        .with_min_len(256)
        .map(|i| {
            (a.ptr[i]..a.ptr[i + 1])
                .filter_map(|k| {
                    let j = a.idx[k] as usize;
                    let s = squared(k);
                    (j != i && s > 0.0 && s >= theta2 * (diag[i] * diag[j]).sqrt()).then_some(j)
                })
                .collect()
        })
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

/// The tentative prolongator in `b x k` blocks (one per fine node, at its aggregate): on
/// each aggregate, the near-null space's rows orthonormalised (`B_agg = Q R` by
/// twice-applied modified Gram-Schmidt), `Q` as the aggregate's block column and `R` as the
/// coarse near-null space; a column dependent on the earlier ones (a small aggregate) is
/// left zero in `Q` and `R`. Returns `T` and the coarse modes.
fn tentative(modes: &Modes, b: usize, aggregate_of: &[usize], count: usize) -> (Blocks, Modes) {
    let k = modes.k;
    let mut members: Vec<Vec<usize>> = vec![Vec::new(); count];
    for (node, &g) in aggregate_of.iter().enumerate() {
        members[g].push(node);
    }
    // Per aggregate: Q (rows x k, column-major) and R (k x k, row-major).
    let factors: Vec<(Vec<f64>, Vec<f64>)> = members
        .par_iter()
        .map(|nodes| {
            let m = nodes.len() * b;
            let mut q = vec![0.0; m * k];
            for (local, &node) in nodes.iter().enumerate() {
                for d in 0..b {
                    let row = node * b + d;
                    for c in 0..k {
                        q[c * m + local * b + d] = modes.values[row * k + c];
                    }
                }
            }
            let mut r = vec![0.0; k * k];
            for c in 0..k {
                let original = norm(&q[c * m..(c + 1) * m]);
                for _ in 0..2 {
                    for j in 0..c {
                        let (done, rest) = q.split_at_mut(c * m);
                        let (qj, col) = (&done[j * m..(j + 1) * m], &mut rest[..m]);
                        let h = dot(qj, col);
                        r[j * k + c] += h;
                        for (x, y) in col.iter_mut().zip(qj) {
                            *x -= h * y;
                        }
                    }
                }
                let col = &mut q[c * m..(c + 1) * m];
                let length = norm(col);
                if length > 1e-10 * original && length > 0.0 {
                    r[c * k + c] = length;
                    col.iter_mut().for_each(|x| *x /= length);
                } else {
                    col.fill(0.0);
                }
            }
            (q, r)
        })
        .collect();
    let n = aggregate_of.len();
    let mut position = vec![0; n];
    for nodes in &members {
        for (local, &node) in nodes.iter().enumerate() {
            position[node] = local;
        }
    }
    let mut val = Vec::with_capacity(n * b * k);
    for node in 0..n {
        let g = aggregate_of[node];
        let (q, m) = (&factors[g].0, members[g].len() * b);
        for d in 0..b {
            for c in 0..k {
                val.push(q[c * m + position[node] * b + d]);
            }
        }
    }
    let t = Blocks {
        r: b,
        c: k,
        rows: n,
        cols: count,
        ptr: (0..=n).collect(),
        idx: aggregate_of.iter().map(|&g| g as u32).collect(),
        val,
    };
    let values = factors.into_iter().flat_map(|(_, r)| r).collect();
    (t, Modes { k, values })
}

/// `P = (I - omega D^-1 A) T` with `omega = 4 / (3 lambda)`, in single precision: each row
/// of the product `A T` is smoothed in double before it is rounded, so `P` is written once.
fn smoothed_prolongator(a: &Blocks<f32>, t: &Blocks, inv_diag: &[f64], lambda: f64) -> Blocks<f32> {
    let omega = 4.0 / (3.0 * lambda);
    a.multiply_into(t, &|i, idx, at| {
        smooth_prolongator_row(t, i, idx, at, inv_diag, omega);
    })
}

/// Block row `i` of `P = (I - omega D^-1 A) T`, given that of `A T` (its columns `idx` and
/// values `at`, overwritten); `T`'s blocks lie inside `A T`'s (the diagonal blocks of `A` are
/// stored).
fn smooth_prolongator_row(
    t: &Blocks,
    i: usize,
    idx: &[u32],
    at: &mut [f64],
    inv_diag: &[f64],
    omega: f64,
) {
    let (b, k) = (t.r, t.c);
    let size = b * k;
    for block in at.chunks_exact_mut(size) {
        for d in 0..b {
            let scale = -omega * inv_diag[i * b + d];
            block[d * k..(d + 1) * k]
                .iter_mut()
                .for_each(|v| *v *= scale);
        }
    }
    let at_block = idx
        .binary_search(&t.idx[i])
        .expect("T's blocks lie inside A T's");
    for (v, tv) in at[at_block * size..(at_block + 1) * size]
        .iter_mut()
        .zip(t.block(i))
    {
        *v += tv;
    }
}

/// `P^T A P` (a zero diagonal entry, from a zero column of `P`, set to 1), summed in double
/// and stored in single precision, and its flops.
fn galerkin(a: &Blocks<f32>, p: &Blocks<f32>, r: &Blocks<f32>) -> (Blocks<f32>, u64) {
    // `A P` in single precision: the largest buffer of the set-up (171 MB in double on the
    // n = 32 beam), written once and read once.
    let ap: Blocks<f32> = a.multiply(p);
    // The symmetric product computes about half of `R (A P)`'s blocks.
    let flops = a.product_flops(p) + r.product_flops(&ap) / 2;
    let mut coarse = r.multiply_symmetric(&ap);
    coarse.fill_zero_diagonal(1.0);
    (coarse, flops)
}

#[cfg(test)]
mod tests {
    use super::*;
    use sprs::TriMat;

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
            amg.apply(&u, &mut mu);
            amg.apply(&v, &mut mv);
            let (umv, vmu) = (dot(&u, &mv), dot(&v, &mu));
            assert!(
                (umv - vmu).abs() <= 1e-10 * umv.abs().max(vmu.abs()),
                "{umv} vs {vmu}"
            );
            assert!(dot(&u, &mu) > 0.0 && dot(&v, &mv) > 0.0);
        }
    }

    #[test]
    fn the_eigenvalue_estimate_is_within_five_per_cent_below_the_largest() {
        let (a, _) = grid_operator(6, 0.5);
        let blocks = Blocks::<f32>::from_csr(&a, 3).unwrap();
        let (inv, estimate, _) = smoother_data(&blocks).unwrap();
        let n = a.rows();
        let dense = a.to_dense();
        let scaled =
            nalgebra::DMatrix::from_fn(n, n, |i, j| dense[[i, j]] * (inv[i] * inv[j]).sqrt());
        let largest = scaled.symmetric_eigenvalues().max();
        assert!(
            // The operator is rounded to single precision: its eigenvalues move by ~1e-7.
            // The Chebyshev smoother does not amplify up to 1.1 x 1.033 x the estimate (where
            // its polynomial of ratio 30 returns to 1): 5 % low is safe.
            estimate <= largest * (1.0 + 1e-6) && estimate >= 0.95 * largest,
            "{estimate} vs {largest}"
        );
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
        let points: Vec<[f64; 3]> = (0..13)
            .map(|i| [f64::from(i % 3), f64::from(i / 3 % 2), f64::from(i / 6)])
            .collect();
        let modes = near_null_space(39, Some(&points));
        // Three aggregates of 4 nodes and one of a single node, where only 3 of the 6 modes
        // are independent.
        let aggregate_of: Vec<usize> = (0..13).map(|i| i / 4).collect();
        let (t, coarse) = tentative(&modes, 3, &aggregate_of, 4);
        assert_eq!((t.shape(), coarse.k), ((39, 24), 6));
        // T B_c = B, and T's columns are orthonormal or zero (3 on the single node).
        let dt = t.to_csr().to_dense();
        for i in 0..39 {
            for c in 0..6 {
                let v: f64 = (0..24).map(|j| dt[[i, j]] * coarse.values[j * 6 + c]).sum();
                assert!((v - modes.values[i * 6 + c]).abs() < 1e-12, "{i} {c}: {v}");
            }
        }
        let gram = dt.t().dot(&dt);
        let mut zero = 0;
        for i in 0..24 {
            for j in 0..24 {
                let expected = if i == j && gram[[i, i]] > 0.5 {
                    1.0
                } else {
                    0.0
                };
                assert!((gram[[i, j]] - expected).abs() < 1e-12);
            }
            zero += usize::from(gram[[i, i]] == 0.0);
        }
        assert_eq!(zero, 3);
    }

    #[test]
    fn the_smoothed_prolongator_is_jacobi_smoothing_of_the_tentative_one() {
        let (a, points) = grid_operator(4, 0.5);
        let blocks = Blocks::<f32>::from_csr(&a, 3).unwrap();
        let modes = near_null_space(a.rows(), Some(&points));
        let (aggregate_of, count) = aggregate(&strength(&blocks, 0.0));
        let (t, _) = tentative(&modes, 3, &aggregate_of, count);
        let (inv_diag, lambda, _) = smoother_data(&blocks).unwrap();
        let p = smoothed_prolongator(&blocks, &t, &inv_diag, lambda);
        // Dense (I - omega D^-1 A) T, with A as rounded for the hierarchy.
        let omega = 4.0 / (3.0 * lambda);
        let (da, dt, dp) = (
            blocks.to_csr().to_dense(),
            t.to_csr().to_dense(),
            p.to_csr().to_dense(),
        );
        let (n, m) = (da.nrows(), dt.ncols());
        let at = da.dot(&dt);
        let mut largest: f64 = 0.0;
        let mut worst: f64 = 0.0;
        for i in 0..n {
            for j in 0..m {
                let expected = dt[[i, j]] - omega * inv_diag[i] * at[[i, j]];
                largest = largest.max(expected.abs());
                worst = worst.max((dp[[i, j]] - expected).abs());
            }
        }
        // Single-precision storage: within its rounding of the largest entry.
        assert!(
            largest > 0.1 && worst <= 1e-6 * largest,
            "{worst} vs {largest}"
        );
    }

    #[test]
    fn a_refreshed_hierarchy_equals_a_new_one_on_the_same_matrix() {
        let (a, points) = grid_operator(12, 1e-2);
        let smoother = AmgSmoother::default();
        let (fresh, _) = Amg::new(&a, Some(&points), 0.0, smoother).unwrap();
        let (b, _) = grid_operator(12, 1.0);
        let (mut refreshed, _) = Amg::new(&b, Some(&points), 0.0, smoother).unwrap();
        refreshed.refresh(&a).unwrap();
        let r: Vec<f64> = (0..a.rows()).map(|i| (i as f64 * 0.1).sin()).collect();
        let (mut z1, mut z2) = (vec![0.0; r.len()], vec![0.0; r.len()]);
        fresh.apply(&r, &mut z1);
        refreshed.apply(&r, &mut z2);
        // Same aggregates (the strength graph does not depend on the shift), but P was
        // smoothed with the other matrix's diagonal: close, not equal.
        let diff: f64 = z1
            .iter()
            .zip(&z2)
            .map(|(x, y)| (x - y).powi(2))
            .sum::<f64>()
            .sqrt();
        assert!(diff < 0.5 * norm(&z1), "{diff} vs {}", norm(&z1));
        assert_eq!(fresh.level_sizes(), refreshed.level_sizes());
    }
}
