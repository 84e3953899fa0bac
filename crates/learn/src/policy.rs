//! A learned solver policy: from the features of a Newton iteration to the candidate
//! configuration with the lowest predicted cost among those predicted to succeed.
//!
//! Deliberately simple and inspectable: a k-nearest-neighbour model on standardised
//! features (the policy-independent ones: Newton iteration, residual level and decrease,
//! dt, size, stiffness). For each candidate it predicts the success rate, the solve flops
//! and the set-up flops of the neighbours, and picks the cheapest whose success rate reaches
//! `min_success`; when none does, the safest. The set-up cost depends on the policy's own
//! state: a stale-Cholesky candidate whose factor the policy holds (younger than its
//! `max_age`) costs no factorisation, one without a factor costs a full one, so the policy
//! can factorise once and reuse. The integrator's direct fallback covers mispredictions.
//! Costs are deterministic flop counts, so the policy is reproducible.

use deform_integrator::{Decision, IterationReport, PolicyContext, SolverPolicy, spec_name};
use deform_solvers::{PreconditionerSpec, SolverSpec};

use crate::solver_data::{SolverDataset, feature_vector};

/// Feature columns the neighbours are found on (the others depend on the policy that ran).
const USED: [usize; 7] = [1, 2, 3, 4, 5, 6, 7];

#[derive(Debug, Clone, Copy)]
struct Target {
    ok: bool,
    solve: f64,
    setup: f64,
}

/// `max_age` of a stale-Cholesky candidate.
fn max_age(spec: &SolverSpec) -> Option<usize> {
    match spec {
        SolverSpec::Pcg {
            preconditioner: PreconditionerSpec::StaleCholesky { max_age, .. },
            ..
        } => Some(*max_age),
        _ => None,
    }
}

/// A k-nearest-neighbour cost model over a [`SolverDataset`].
#[derive(Debug, Clone)]
pub struct LearnedPolicy {
    candidates: Vec<SolverSpec>,
    /// Standardised training features (used columns only).
    points: Vec<Vec<f64>>,
    /// Per sample and candidate: success, solve flops, set-up flops, set-up reused.
    targets: Vec<Vec<Target>>,
    /// Mean factorisation (non-reused set-up) flops per candidate over all samples.
    fresh_setup: Vec<f64>,
    /// Age of the factor the policy's own instance of each stale-Cholesky candidate holds.
    ages: Vec<Option<usize>>,
    /// The candidate chosen last.
    last: Option<usize>,
    mean: Vec<f64>,
    scale: Vec<f64>,
    k: usize,
    min_success: f64,
    young: f64,
}

impl LearnedPolicy {
    /// Trains on `data` (all of it) with `k` neighbours; `young` is the Young's modulus of
    /// the material the policy will run on (a feature).
    ///
    /// # Panics
    /// If `data` is empty.
    pub fn train(data: &SolverDataset, k: usize, min_success: f64, young: f64) -> Self {
        assert!(!data.is_empty(), "no samples to learn from");
        let raw: Vec<Vec<f64>> = data
            .features
            .iter()
            .map(|f| USED.iter().map(|&j| f[j]).collect())
            .collect();
        let d = USED.len();
        let n = raw.len() as f64;
        let mean: Vec<f64> = (0..d)
            .map(|j| raw.iter().map(|r| r[j]).sum::<f64>() / n)
            .collect();
        let scale: Vec<f64> = (0..d)
            .map(|j| {
                let var = raw.iter().map(|r| (r[j] - mean[j]).powi(2)).sum::<f64>() / n;
                if var > 1e-24 { var.sqrt() } else { 1.0 }
            })
            .collect();
        let points = raw
            .iter()
            .map(|r| (0..d).map(|j| (r[j] - mean[j]) / scale[j]).collect())
            .collect();
        let targets: Vec<Vec<Target>> = data
            .outcomes
            .iter()
            .map(|o| {
                o.iter()
                    .map(|c| Target {
                        ok: c.ok,
                        solve: (c.flops - c.setup_flops).max(0.0),
                        setup: c.setup_flops,
                    })
                    .collect()
            })
            .collect();
        let c = data.meta.candidates.len();
        let fresh_setup = (0..c)
            .map(|j| {
                let fresh: Vec<f64> = data
                    .outcomes
                    .iter()
                    .filter(|o| !o[j].reused)
                    .map(|o| o[j].setup_flops)
                    .collect();
                if fresh.is_empty() {
                    0.0
                } else {
                    fresh.iter().sum::<f64>() / fresh.len() as f64
                }
            })
            .collect();
        Self {
            candidates: data.meta.candidates.clone(),
            points,
            targets,
            fresh_setup,
            ages: vec![None; c],
            last: None,
            mean,
            scale,
            k: k.max(1),
            min_success,
            young,
        }
    }

    /// The candidate index chosen for a feature vector (in `FEATURES` order).
    pub fn choose_index(&self, features: &[f64]) -> usize {
        let q: Vec<f64> = USED
            .iter()
            .enumerate()
            .map(|(j, &c)| (features[c] - self.mean[j]) / self.scale[j])
            .collect();
        let mut order: Vec<(f64, usize)> = self
            .points
            .iter()
            .enumerate()
            .map(|(i, p)| {
                (
                    p.iter().zip(&q).map(|(a, b)| (a - b).powi(2)).sum::<f64>(),
                    i,
                )
            })
            .collect();
        // Ties broken by sample index: deterministic.
        order.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let near = &order[..self.k.min(order.len())];
        let stats: Vec<(f64, f64)> = (0..self.candidates.len())
            .map(|c| {
                let ok: Vec<&Target> = near
                    .iter()
                    .map(|(_, i)| &self.targets[*i][c])
                    .filter(|t| t.ok)
                    .collect();
                let rate = ok.len() as f64 / near.len() as f64;
                if ok.is_empty() {
                    return (rate, f64::INFINITY);
                }
                let solve = ok.iter().map(|t| t.solve).sum::<f64>() / ok.len() as f64;
                let setup = match (max_age(&self.candidates[c]), self.ages[c]) {
                    // The policy holds a young enough factor: reused, no factorisation.
                    (Some(max), Some(age)) if age < max => 0.0,
                    (Some(_), _) => self.fresh_setup[c],
                    (None, _) => ok.iter().map(|t| t.setup).sum::<f64>() / ok.len() as f64,
                };
                (rate, (solve + setup).max(1.0).log10())
            })
            .collect();
        let acceptable = (0..stats.len()).filter(|&c| stats[c].0 >= self.min_success);
        acceptable
            .min_by(|&a, &b| stats[a].1.total_cmp(&stats[b].1))
            .unwrap_or_else(|| {
                (0..stats.len())
                    .max_by(|&a, &b| {
                        stats[a]
                            .0
                            .total_cmp(&stats[b].0)
                            .then(stats[b].1.total_cmp(&stats[a].1))
                    })
                    .unwrap_or(0)
            })
    }
}

impl SolverPolicy for LearnedPolicy {
    fn name(&self) -> String {
        let names: Vec<String> = self.candidates.iter().map(spec_name).collect();
        format!("learned-knn(k={}, over [{}])", self.k, names.join(", "))
    }

    fn choose(&mut self, c: &PolicyContext<'_>) -> Decision {
        let previous = c.history.last();
        let features = feature_vector(
            c.step,
            c.iteration,
            c.residual,
            c.initial_residual,
            previous.map(|p| p.residual),
            previous.map_or(0, |p| p.solve.iterations),
            c.dt,
            c.num_free,
            self.young,
        );
        let chosen = self.choose_index(&features);
        // Mirror the chosen instance's factor age (see `Iterative::factorize`).
        if let Some(max) = max_age(&self.candidates[chosen]) {
            self.ages[chosen] = match self.ages[chosen] {
                Some(age) if age < max => Some(age + 1),
                _ => Some(0),
            };
        }
        self.last = Some(chosen);
        Decision::solver(self.candidates[chosen].clone())
    }

    fn observe(&mut self, _context: &PolicyContext<'_>, outcome: &IterationReport) {
        // A fallback means the chosen instance failed; its factor state is unknown, so
        // assume it must be recomputed.
        if outcome.fallback
            && let Some(last) = self.last
        {
            self.ages[last] = None;
        }
    }
}
