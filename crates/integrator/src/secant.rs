//! Newton directions with the barrier's secant curvature (`NewtonOptions::barrier_secant`).
//!
//! Newton's linear model takes each contact pair's barrier curvature `b''(d)` at the
//! iterate, but `b''` changes by a factor of several over a fraction of `dhat`: a direction
//! that moves contacts by a tenth of `dhat` lands them a fiftieth of `dhat` off, and the
//! next residual is the barrier's. Given a direction, each pair's curvature is replaced by
//! the secant slope of `b'` to the distance the direction predicts
//! ([`ContactModel::secant_correction`]) and the same right-hand side solved again, from
//! the direction, with the solver's preconditioner as it is: the change is confined to the
//! contacts, so a few iterations do. Repeated, the rounds converge to the step whose
//! elasticity is linearised and whose barrier is exact along the predicted distances.

use deform_assembly::DofMap;
use deform_contact::{ContactHessian, ContactModel};
use deform_solvers::pcg::{Applied, Stop, pcg, pcg_error};
use deform_solvers::{LinearOperator, LinearSolver, SolveStats, SolverError, Termination};
use nalgebra::{Matrix3, Vector3};

/// What the secant rounds need of the Newton system.
#[derive(Clone, Copy)]
pub(crate) struct Secant<'a> {
    pub(crate) model: &'a ContactModel,
    pub(crate) dofs: &'a DofMap,
    /// Positions at the iterate (full `3N`).
    pub(crate) x: &'a [f64],
    /// Positions move `scale` times the unknown's update (`dt` for a dynamic step's
    /// velocity, 1 for positions).
    pub(crate) scale: f64,
    /// The factor of contact's Hessian in the Newton matrix.
    pub(crate) c_contact: f64,
    /// Rounds (0: none).
    pub(crate) rounds: usize,
}

/// `A + c dH` on the free DOFs: the Newton matrix with a correction of the contact
/// Hessian's blocks, kept as free block indices.
struct Corrected<'a> {
    base: &'a dyn LinearOperator,
    /// `(row, column, c B)`: free indices of each block's first DOF.
    blocks: Vec<(usize, usize, Matrix3<f64>)>,
}

impl<'a> Corrected<'a> {
    fn new(base: &'a dyn LinearOperator, delta: &ContactHessian, dofs: &DofMap, c: f64) -> Self {
        let free = dofs.free_dofs();
        let index = |v: usize| free.binary_search(&(3 * v)).ok();
        let coupled = delta.coupling.iter().map(|&(i, j, b)| (i, j, b));
        let blocks = delta
            .vertex
            .iter()
            .map(|&(v, b)| (v, v, b))
            .chain(coupled)
            .filter_map(|(i, j, b)| Some((index(i)?, index(j)?, b * c)))
            .collect();
        Self { base, blocks }
    }
}

impl LinearOperator for Corrected<'_> {
    fn nrows(&self) -> usize {
        self.base.nrows()
    }

    fn apply(&self, x: &[f64], y: &mut [f64]) {
        self.base.apply(x, y);
        for &(i, j, b) in &self.blocks {
            let bx = b * Vector3::new(x[j], x[j + 1], x[j + 2]);
            for k in 0..3 {
                y[i + k] += bx[k];
            }
        }
    }

    fn diagonal(&self, out: &mut [f64]) {
        self.base.diagonal(out);
        for &(i, _, b) in self.blocks.iter().filter(|(i, j, _)| i == j) {
            for k in 0..3 {
                out[i + k] += b[(k, k)];
            }
        }
    }

    fn block_diagonal(&self, out: &mut [Matrix3<f64>]) -> Result<(), SolverError> {
        self.base.block_diagonal(out)?;
        for &(i, _, b) in self.blocks.iter().filter(|(i, j, _)| i == j) {
            out[i / 3] += b;
        }
        Ok(())
    }

    fn apply_flops(&self) -> u64 {
        self.base.apply_flops() + 18 * self.blocks.len() as u64
    }
}

/// The loose solves' residual, relative to the right-hand side's: they only predict where
/// the contacts go.
const LOOSE: f64 = 1e-2;

/// Solves `a du = rhs` (free DOFs; `du` holds the start) with `solver`, set up for `a`,
/// and the secant rounds: a loose first solve of `a`, then each round's corrected matrix
/// solved from the last solution with the preconditioner of `a`, loosely but for the last
/// round, which stops at `floor` (and the solver's own tolerance). A `direct` solver's
/// rounds are conjugate gradients preconditioned by its factor ([`factor_cg`]). The
/// rounds' iterations and work are added up; a round whose solve fails ends them (the
/// direction of the round before stands, solved to the full tolerance on its own matrix).
///
/// # Errors
/// As the solver's `solve` on `a`.
pub(crate) fn solve(
    secant: &Secant<'_>,
    solver: &mut dyn LinearSolver,
    a: &dyn LinearOperator,
    rhs: &[f64],
    du: &mut [f64],
    floor: f64,
    direct: bool,
) -> Result<SolveStats, SolverError> {
    let loose = floor.max(LOOSE * deform_solvers::vector::norm(rhs));
    let mut round = |op: Option<&Corrected<'_>>, du: &mut [f64], stop: f64| match op {
        Some(op) if direct => factor_cg(solver, a, op, rhs, du, stop),
        _ => {
            solver.set_residual_floor(stop);
            let done = solver.solve(op.map_or(a, |op| op as &dyn LinearOperator), rhs, du);
            solver.set_residual_floor(floor);
            done
        }
    };
    let mut stats = round(None, du, loose)?;
    let mut dx = vec![0.0; secant.x.len()];
    let (mut delta, mut kept) = (ContactHessian::default(), ContactHessian::default());
    for k in 0..secant.rounds {
        secant.dofs.scatter(du, &mut dx).expect("sizes match");
        dx.iter_mut().for_each(|d| *d *= secant.scale);
        if secant.model.secant_correction(secant.x, &dx, &mut delta) == 0 {
            break;
        }
        let op = Corrected::new(a, &delta, secant.dofs, secant.c_contact);
        let last = k + 1 == secant.rounds;
        let before = du.to_vec();
        match round(Some(&op), du, if last { floor } else { loose }) {
            Ok(done) => {
                add(&mut stats, &done);
                if last {
                    return Ok(stats);
                }
                std::mem::swap(&mut kept, &mut delta);
            }
            Err(_) => {
                du.copy_from_slice(&before);
                break;
            }
        }
    }
    // The last matrix the rounds reached, to the full tolerance; `a` itself when none did
    // (a preconditioner applied through `a`'s CSR fails on the corrected operator) or when
    // that fails (an indefinite factor breaks conjugate gradients down).
    let reached =
        (!kept.is_empty()).then(|| Corrected::new(a, &kept, secant.dofs, secant.c_contact));
    let before = du.to_vec();
    let done = match reached.as_ref().map(|op| round(Some(op), du, floor)) {
        Some(Ok(done)) => done,
        _ => {
            du.copy_from_slice(&before);
            round(None, du, floor)?
        }
    };
    add(&mut stats, &done);
    Ok(stats)
}

/// Conjugate gradients on `op` from `du`, preconditioned by the direct `solver`'s factor
/// of `a` (its solve), until the residual is at most `stop` or for [`FACTOR_CG_CAP`]
/// iterations. `op - a` is the secant correction, confined to the contacts: the
/// preconditioned operator is the identity but for a few eigenvalues, which conjugate
/// gradients find first.
///
/// # Errors
/// The factor's solve failing, a breakdown (`op` or the factor not positive definite) or a
/// divergence (a non-finite value), as [`pcg`] says.
fn factor_cg(
    solver: &mut dyn LinearSolver,
    a: &dyn LinearOperator,
    op: &dyn LinearOperator,
    rhs: &[f64],
    du: &mut [f64],
    stop: f64,
) -> Result<SolveStats, SolverError> {
    let started = std::time::Instant::now();
    let mut stats = SolveStats::new(
        format!("{}+cg", solver.name()),
        deform_solvers::vector::norm(rhs),
    );
    let mut precondition = |r: &[f64], z: &mut [f64]| {
        z.fill(0.0);
        let done = solver.solve(a, r, z)?;
        Ok(Applied::new(done.flops, done.sweep_flops))
    };
    let stop = Stop::new(stop, FACTOR_CG_CAP);
    let curvature = pcg(op, rhs, du, &mut precondition, stop, &mut stats)?;
    stats.seconds = started.elapsed().as_secs_f64();
    match stats.termination {
        // A round is capped: its last iterate is the round's result.
        Termination::Converged | Termination::MaxIterations => Ok(stats),
        _ => Err(pcg_error(stats, curvature)),
    }
}

/// Conjugate-gradient iterations a round takes at most with a factor as preconditioner.
/// A back-substitution costs about a twentieth of a factorisation (n = 16 beam: 0.026 s
/// against 0.49 s); four iterations a round saved Newton iterations on every contact step
/// of the n = 16 drop, where 8 and 12 spent more than the rounds saved on impact.
const FACTOR_CG_CAP: usize = 4;

fn add(stats: &mut SolveStats, round: &SolveStats) {
    stats.iterations += round.iterations;
    stats.matvecs += round.matvecs;
    stats.flops += round.flops;
    stats.sweep_flops += round.sweep_flops;
    stats.seconds += round.seconds;
    stats.residuals.extend_from_slice(&round.residuals);
    stats.termination = round.termination;
}

#[cfg(test)]
mod tests {
    use super::*;
    use deform_solvers::{Cholesky, Indefinite, Ordering};
    use sprs::{CsMat, TriMat};

    /// `A + sum c_k e_k e_k^T`: a correction on a few rows, as contacts give.
    struct OnRows<'a> {
        a: &'a CsMat<f64>,
        rows: &'a [(usize, f64)],
    }

    impl LinearOperator for OnRows<'_> {
        fn nrows(&self) -> usize {
            self.a.rows()
        }
        fn apply(&self, x: &[f64], y: &mut [f64]) {
            self.a.apply(x, y);
            for &(i, c) in self.rows {
                y[i] += c * x[i];
            }
        }
        fn diagonal(&self, out: &mut [f64]) {
            self.a.diagonal(out);
        }
        fn apply_flops(&self) -> u64 {
            self.a.apply_flops()
        }
    }

    /// Preconditioned by the factor of `A`, the corrected matrix is the identity plus a
    /// matrix of rank 2: conjugate gradients converge in 3 iterations at most (one per
    /// distinct eigenvalue), to the corrected system's solution.
    #[test]
    fn factor_cg_solves_a_correction_of_rank_two_in_three_iterations() {
        let n = 30;
        let mut t = TriMat::new((n, n));
        for i in 0..n {
            t.add_triplet(i, i, 4.0 + (i % 3) as f64);
            if i + 1 < n {
                t.add_triplet(i, i + 1, -1.0);
                t.add_triplet(i + 1, i, -1.0);
            }
        }
        let a: CsMat<f64> = t.to_csr();
        let mut solver = Cholesky::new(Ordering::Amd, Indefinite::Error);
        solver.analyze(&a).unwrap();
        solver.factorize(&a).unwrap();
        let rhs: Vec<f64> = (0..n).map(|i| (i as f64 * 0.7).sin()).collect();
        let rows = [(4, 50.0), (17, 3.0)];
        let op = OnRows { a: &a, rows: &rows };
        let mut du = vec![0.0; n];
        solver.solve(&a, &rhs, &mut du).unwrap();
        let stop = 1e-12 * deform_solvers::vector::norm(&rhs);
        let stats = factor_cg(&mut solver, &a, &op, &rhs, &mut du, stop).unwrap();
        assert!(stats.iterations <= 3, "{} iterations", stats.iterations);
        assert_eq!(stats.termination, Termination::Converged);
        let mut r = vec![0.0; n];
        op.apply(&du, &mut r);
        let residual = r
            .iter()
            .zip(&rhs)
            .map(|(y, b)| (y - b).powi(2))
            .sum::<f64>()
            .sqrt();
        assert!(residual <= stop * 1.01, "residual {residual:e}");
    }
}
