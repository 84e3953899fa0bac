//! A learned solver policy: at every Newton iteration, the candidate configuration with the
//! lowest predicted work, where holding a factorisation is valued over its lifetime.
//!
//! Three parts, each simple enough to inspect:
//!
//! - **Iterations** are learned: a k-nearest-neighbour model on standardised,
//!   policy-independent features (Newton iteration, residual level and decrease, dt, size,
//!   stiffness) predicts each candidate's success rate and iteration count from the
//!   counterfactual logs; for a stale-factor candidate it predicts the count at each age of
//!   the factor (solves since it was computed), the profile of how the factor degrades.
//! - **Work per iteration and per set-up** is measured, not guessed: once a candidate has run
//!   in the current simulation its exact flops per iteration and per set-up are known; before
//!   that they are extrapolated from the training sizes by a power law in the number of free
//!   DOFs (with the asymptotic exponents of 3D problems when the training data has one size).
//!   Work is deterministic: flops weighted by kind (`WorkWeights`: a dense supernodal
//!   factorisation runs at many more flops per second than memory-bound sparse solves, and
//!   IC(0)'s sequential sweeps at fewer; the weights are those ratios, measured by `cargo
//!   xtask bench step` and `cargo xtask bench solvers`).
//! - **Holding a factor is a renewal problem.** A factor costs `F` once; the stale solves
//!   after it cost `c_1 <= c_2 <= ...` as the matrix drifts. The average work per solve of a
//!   cycle of `T` solves, `(F + c_0 + ... + c_{T-1}) / T`, is least when the next solve's
//!   predicted cost first exceeds the cycle's average so far, so the policy keeps the factor
//!   exactly while `c_next <= average` and otherwise compares a new cycle (its predicted
//!   least average) with every other candidate's cost for this solve. The next stale cost is
//!   calibrated online: the last observed iterations times the learned growth ratio.
//!
//! Iteration predictions of the candidates that have run are calibrated online as well (the
//! running geometric mean of observed over predicted iterations), so a scene harder than the
//! training scenes (a finer mesh needs more PCG iterations) corrects the model after one
//! solve. The integrator's direct fallback covers mispredictions; a fallback ends the cycle.
//! Everything is deterministic, so the policy is reproducible.

use deform_integrator::{Decision, EisenstatWalker, IterationReport, PolicyContext, SolverPolicy};
use deform_solvers::{PreconditionerSpec, SolverSpec, WorkWeights};

use crate::solver_data::{SolverDataset, feature_vector};

/// Feature columns the neighbours are found on (the others depend on the policy that ran).
const USED: [usize; 7] = [1, 2, 3, 4, 5, 6, 7];
/// Column of `log10_free_dofs` in `FEATURES`.
const LOG_DOFS: usize = 6;

/// Default neighbours of the iteration model.
pub const DEFAULT_NEIGHBOURS: usize = 5;
/// Default minimum predicted success rate.
pub const DEFAULT_MIN_SUCCESS: f64 = 0.9;
/// Default Eisenstat-Walker forcing terms `(eta_max, gamma)` of inexact Newton.
pub const DEFAULT_FORCING: (f64, f64) = (0.1, 0.9);

/// Options of the learned policy.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub struct PolicyOptions {
    /// Neighbours of the iteration model.
    pub neighbours: usize,
    /// Minimum predicted success rate of a chosen candidate.
    pub min_success: f64,
    /// Work of one factorisation flop and of one sweep flop relative to one solve flop.
    pub weights: WorkWeights,
    /// Young's modulus of the material the policy runs on (a feature).
    pub young: f64,
    /// Inexact Newton: iterative solves stop at the Eisenstat-Walker forcing term (with
    /// these `eta_max` and `gamma`) instead of their configured tolerance, never tighter.
    /// Iteration predictions scale by `ln eta / ln rel` (CG's linear convergence).
    pub forcing: Option<(f64, f64)>,
}

impl PolicyOptions {
    /// For a material of Young's modulus `young`: [`DEFAULT_NEIGHBOURS`],
    /// [`DEFAULT_MIN_SUCCESS`], plain flops as work, and the solvers' own tolerances (no
    /// forcing term); the setters change the rest.
    pub fn new(young: f64) -> Self {
        Self {
            neighbours: DEFAULT_NEIGHBOURS,
            min_success: DEFAULT_MIN_SUCCESS,
            weights: WorkWeights::default(),
            young,
            forcing: None,
        }
    }
}

deform_setters::setters!(PolicyOptions {
    neighbours: usize,
    min_success: f64,
    weights: WorkWeights,
    young: f64,
    forcing: Option<(f64, f64)>,
});

/// Work per iteration and per set-up of a candidate, as `log10 w = a + b log10 n`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct PowerLaw {
    a: f64,
    b: f64,
}

impl PowerLaw {
    /// Least squares in log-log space; with one size, the exponent `default_b`.
    fn fit(points: &[(f64, f64)], default_b: f64) -> Option<Self> {
        if points.is_empty() {
            return None;
        }
        let m = points.len() as f64;
        let (mx, my) = points
            .iter()
            .fold((0.0, 0.0), |(a, b), (x, y)| (a + x / m, b + y / m));
        let sxx: f64 = points.iter().map(|(x, _)| (x - mx).powi(2)).sum();
        let b = if sxx > 1e-6 {
            points.iter().map(|(x, y)| (x - mx) * (y - my)).sum::<f64>() / sxx
        } else {
            default_b
        };
        Some(Self { a: my - b * mx, b })
    }

    fn at(&self, log_n: f64) -> f64 {
        10f64.powf(self.a + self.b * log_n)
    }
}

/// What one candidate costs.
#[derive(Debug, Clone, Default)]
struct CostModel {
    /// Work of a fresh set-up, by size.
    setup: Option<PowerLaw>,
    /// Work of one iteration, by size.
    iteration: Option<PowerLaw>,
    /// Measured in the current simulation.
    observed_setup: Option<f64>,
    observed_iteration: Option<f64>,
}

/// The factor the policy's stale-factor candidate holds.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Cycle {
    candidate: usize,
    /// Solves since the factorisation (0 for the solve that computed it).
    age: usize,
    /// Work of the cycle so far (factorisation included).
    work: f64,
    /// Solves in the cycle so far.
    solves: usize,
    /// Iterations of the last solve with this factor, once observed.
    last_iterations: Option<f64>,
}

/// A training sample: standardised features and, per candidate, success, iterations, age.
#[derive(Debug, Clone)]
struct Sample {
    point: Vec<f64>,
    outcomes: Vec<(bool, f64, usize)>,
}

/// The learned policy; see the module documentation.
#[derive(Debug, Clone)]
pub struct LearnedPolicy {
    candidates: Vec<SolverSpec>,
    samples: Vec<Sample>,
    /// Per candidate, the oldest factor age the data has.
    oldest: Vec<usize>,
    costs: Vec<CostModel>,
    mean: Vec<f64>,
    scale: Vec<f64>,
    options: PolicyOptions,
    cycle: Option<Cycle>,
    /// The candidate chosen last and its uncalibrated predicted iterations.
    last: Option<(usize, f64)>,
    /// Per candidate: observed over predicted iterations in this simulation (geometric
    /// running mean; `None` until the candidate has run).
    calibration: Vec<Option<f64>>,
    /// The forcing-term rule and this solve's factor on predicted iterations.
    forcing: Option<EisenstatWalker>,
    iteration_factor: f64,
}

/// The largest factor age a stale-Cholesky configuration allows.
fn max_age(spec: &SolverSpec) -> Option<usize> {
    match spec {
        SolverSpec::Pcg {
            preconditioner: PreconditionerSpec::StaleCholesky { max_age, .. },
            ..
        } => Some(*max_age),
        _ => None,
    }
}

/// Whether a candidate's set-up is a sparse Cholesky factorisation.
fn factorises(spec: &SolverSpec) -> bool {
    matches!(spec, SolverSpec::Direct { .. }) || spec.is_stale_cholesky()
}

impl LearnedPolicy {
    /// Learns from `data` (all of it).
    ///
    /// # Panics
    /// If `data` is empty.
    pub fn train(data: &SolverDataset, options: PolicyOptions) -> Self {
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
        let samples = raw
            .iter()
            .zip(&data.outcomes)
            .map(|(r, o)| Sample {
                point: (0..d).map(|j| (r[j] - mean[j]) / scale[j]).collect(),
                outcomes: o
                    .iter()
                    .map(|c| (c.ok, c.iterations.max(1.0), c.age as usize))
                    .collect(),
            })
            .collect();
        let candidates = data.meta.candidates.clone();
        let oldest = (0..candidates.len())
            .map(|c| {
                data.outcomes
                    .iter()
                    .map(|o| o[c].age as usize)
                    .max()
                    .unwrap_or(0)
            })
            .collect();
        let costs = candidates
            .iter()
            .enumerate()
            .map(|(c, spec)| {
                let weight = if factorises(spec) {
                    options.weights.factor
                } else {
                    1.0
                };
                let (mut setup, mut iteration) = (Vec::new(), Vec::new());
                for (f, o) in data.features.iter().zip(&data.outcomes) {
                    let o = &o[c];
                    if !o.ok {
                        continue;
                    }
                    if !o.reused && o.setup_flops > 0.0 {
                        setup.push((f[LOG_DOFS], (weight * o.setup_flops).log10()));
                    }
                    // A direct solve reports no iterations: it is one "iteration" here, as in
                    // the iteration model.
                    let solve = options
                        .weights
                        .solve(o.flops - o.setup_flops, o.sweep_flops);
                    if solve > 0.0 {
                        iteration.push((f[LOG_DOFS], (solve / o.iterations.max(1.0)).log10()));
                    }
                }
                // 3D nested dissection: factorisation O(n^2), nnz(L) O(n^(4/3)); sparse
                // iterations and incomplete factorisations O(n).
                let (bs, bi) = if factorises(spec) {
                    (2.0, 4.0 / 3.0)
                } else {
                    (1.0, 1.0)
                };
                CostModel {
                    setup: PowerLaw::fit(&setup, bs),
                    iteration: PowerLaw::fit(&iteration, bi),
                    ..CostModel::default()
                }
            })
            .collect();
        Self {
            candidates,
            samples,
            oldest,
            costs,
            mean,
            scale,
            options,
            cycle: None,
            last: None,
            calibration: vec![None; data.meta.candidates.len()],
            forcing: options.forcing.map(|(eta_max, gamma)| {
                EisenstatWalker::with_constants(data.meta.candidates[0].clone(), eta_max, gamma)
            }),
            iteration_factor: 1.0,
        }
    }

    /// The `k` samples nearest to `features` (in `FEATURES` order) among those `keep` accepts.
    fn neighbours(&self, features: &[f64], keep: impl Fn(&Sample) -> bool) -> Vec<&Sample> {
        let q: Vec<f64> = USED
            .iter()
            .enumerate()
            .map(|(j, &c)| (features[c] - self.mean[j]) / self.scale[j])
            .collect();
        let mut order: Vec<(f64, usize)> = self
            .samples
            .iter()
            .enumerate()
            .filter(|(_, s)| keep(s))
            .map(|(i, s)| {
                let d = s.point.iter().zip(&q).map(|(a, b)| (a - b).powi(2)).sum();
                (d, i)
            })
            .collect();
        // Ties broken by sample index: a total order, so the k nearest are deterministic.
        // Selecting them first (linear) rather than sorting all samples matters: the renewal
        // rule asks for neighbours at every factor age, many times per decision.
        let by = |a: &(f64, usize), b: &(f64, usize)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
        let k = self.options.neighbours.max(1);
        if order.len() > k {
            order.select_nth_unstable_by(k - 1, by);
            order.truncate(k);
        }
        order.sort_by(by);
        order.iter().map(|&(_, i)| &self.samples[i]).collect()
    }

    /// Success rate and iterations (geometric mean over the successful neighbours) of
    /// candidate `c`; for a stale-factor candidate, at factor age `age` (the oldest age the
    /// data has when `age` is beyond it).
    fn iterations(&self, c: usize, features: &[f64], age: Option<usize>) -> (f64, f64) {
        let near = match age {
            None => self.neighbours(features, |_| true),
            Some(a) => {
                let a = a.min(self.oldest[c]);
                self.neighbours(features, |s| s.outcomes[c].2 == a)
            }
        };
        if near.is_empty() {
            return (0.0, f64::INFINITY);
        }
        let ok: Vec<f64> = near
            .iter()
            .filter(|s| s.outcomes[c].0)
            .map(|s| s.outcomes[c].1.ln())
            .collect();
        let rate = ok.len() as f64 / near.len() as f64;
        if ok.is_empty() {
            return (rate, f64::INFINITY);
        }
        let factor = if self.candidates[c].tolerance().is_some() {
            self.iteration_factor
        } else {
            1.0
        };
        (
            rate,
            (factor * (ok.iter().sum::<f64>() / ok.len() as f64).exp()).max(1.0),
        )
    }

    fn setup_work(&self, c: usize, log_n: f64) -> f64 {
        let m = &self.costs[c];
        m.observed_setup
            .or_else(|| m.setup.map(|p| p.at(log_n)))
            .unwrap_or(0.0)
    }

    fn iteration_work(&self, c: usize, log_n: f64) -> f64 {
        let m = &self.costs[c];
        m.observed_iteration
            .or_else(|| m.iteration.map(|p| p.at(log_n)))
            .unwrap_or(f64::INFINITY)
    }

    /// Predicted work of the stale solve at `age` in a cycle whose last observed solve (at
    /// `age - 1`) took `last` iterations: calibrated by the learned growth ratio.
    fn stale_iterations(&self, c: usize, f: &[f64], age: usize, last: Option<f64>) -> (f64, f64) {
        let (rate, its) = self.iterations(c, f, Some(age));
        match last {
            Some(last) if age > 0 => {
                let (_, before) = self.iterations(c, f, Some(age - 1));
                let growth = if before.is_finite() && its.is_finite() {
                    (its / before).max(1.0)
                } else {
                    1.0
                };
                (rate, last * growth)
            }
            _ => (rate, its),
        }
    }

    /// The least predicted average work per solve of a new factor cycle of candidate `c`.
    fn cycle_average(&self, c: usize, f: &[f64], log_n: f64, scale: f64) -> Option<f64> {
        let per = self.iteration_work(c, log_n);
        let (rate, fresh) = self.iterations(c, f, Some(0));
        if rate < self.options.min_success || !fresh.is_finite() {
            return None;
        }
        let mut total = self.setup_work(c, log_n) + fresh * per;
        let mut best = total;
        let cap = max_age(&self.candidates[c]).unwrap_or(0);
        for age in 1..=cap {
            let (rate, its) = self.iterations(c, f, Some(age));
            if rate < self.options.min_success || !its.is_finite() {
                break;
            }
            let cost = its * scale * per;
            let average = total / age as f64;
            if cost > average {
                break;
            }
            total += cost;
            best = total / (age + 1) as f64;
        }
        Some(best)
    }

    /// The same learned model with other forcing terms `(eta_max, gamma)` (for tuning
    /// them), its per-simulation state reset.
    pub fn with_forcing(&self, forcing: Option<(f64, f64)>) -> Self {
        let mut p = self.clone();
        p.options.forcing = forcing;
        p.forcing = forcing.map(|(eta_max, gamma)| {
            EisenstatWalker::with_constants(self.candidates[0].clone(), eta_max, gamma)
        });
        p.cycle = None;
        p.last = None;
        p.calibration = vec![None; self.candidates.len()];
        p.costs.iter_mut().for_each(|c| {
            c.observed_setup = None;
            c.observed_iteration = None;
        });
        p
    }

    /// The choice for a feature vector (in `FEATURES` order): candidate index and whether a
    /// stale factor is recomputed first.
    pub fn choose_index(&self, features: &[f64]) -> (usize, bool) {
        let log_n = features[LOG_DOFS];
        let min = self.options.min_success;
        // (work, candidate, refresh)
        let mut options: Vec<(f64, usize, bool)> = Vec::new();
        for c in 0..self.candidates.len() {
            if max_age(&self.candidates[c]).is_none() {
                let (rate, its) = self.iterations(c, features, None);
                let its = its * self.calibration[c].unwrap_or(1.0);
                if rate >= min && its.is_finite() {
                    let work = self.setup_work(c, log_n) + its * self.iteration_work(c, log_n);
                    options.push((work, c, false));
                }
                continue;
            }
            // A stale-factor candidate: keep the held factor while the renewal rule says so,
            // or start a new cycle, valued at its predicted least average.
            let mut scale = 1.0;
            if let Some(cy) = self.cycle.filter(|cy| cy.candidate == c) {
                let next = cy.age + 1;
                let (rate, its) = self.stale_iterations(c, features, next, cy.last_iterations);
                if let Some(last) = cy.last_iterations {
                    let (_, predicted) = self.iterations(c, features, Some(cy.age));
                    if predicted.is_finite() && predicted > 0.0 {
                        scale = (last / predicted).max(1.0);
                    }
                }
                let within_cap = max_age(&self.candidates[c]).is_some_and(|m| next <= m);
                let work = its * self.iteration_work(c, log_n);
                if within_cap && rate >= min && work <= cy.work / cy.solves.max(1) as f64 {
                    options.push((work, c, false));
                    continue;
                }
            }
            if let Some(average) = self.cycle_average(c, features, log_n, scale) {
                options.push((average, c, true));
            }
        }
        options
            .iter()
            .min_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)))
            .map_or((0, false), |&(_, c, refresh)| (c, refresh))
    }
}

impl SolverPolicy for LearnedPolicy {
    fn name(&self) -> String {
        let names: Vec<String> = self.candidates.iter().map(SolverSpec::name).collect();
        format!(
            "learned(k={}, over [{}])",
            self.options.neighbours,
            names.join(", ")
        )
    }

    fn choose(&mut self, c: &PolicyContext<'_>) -> Decision {
        let features = feature_vector(c, self.options.young);
        // This solve's forcing term, and how much fewer iterations it needs than the
        // configured tolerance the data were logged at.
        let eta = self
            .forcing
            .as_mut()
            .and_then(|ew| ew.choose(c).rel_tolerance);
        self.iteration_factor = 1.0;
        if let Some(eta) = eta {
            let logged = self
                .candidates
                .iter()
                .find_map(|s| s.tolerance())
                .map(|t| t.rel);
            if let Some(rel) = logged.filter(|r| *r > 0.0 && *r < 1.0 && eta > *r) {
                self.iteration_factor = eta.ln() / rel.ln();
            }
        }
        let (chosen, refresh) = self.choose_index(&features);
        if max_age(&self.candidates[chosen]).is_some() {
            // Mirror the kept instance's factor (see `Iterative::factorize`).
            self.cycle = match self.cycle {
                Some(cy) if cy.candidate == chosen && !refresh => Some(Cycle {
                    age: cy.age + 1,
                    ..cy
                }),
                _ => Some(Cycle {
                    candidate: chosen,
                    age: 0,
                    work: 0.0,
                    solves: 0,
                    last_iterations: None,
                }),
            };
        }
        let predicted = if max_age(&self.candidates[chosen]).is_none() {
            self.iterations(chosen, &features, None).1
        } else {
            f64::NAN
        };
        self.last = Some((chosen, predicted));
        Decision {
            solver: self.candidates[chosen].clone(),
            rel_tolerance: eta.filter(|_| self.candidates[chosen].tolerance().is_some()),
            // A new cycle always factorises, whatever the instance holds.
            refresh: self
                .cycle
                .is_some_and(|cy| cy.candidate == chosen && cy.age == 0),
        }
    }

    fn observe(&mut self, _context: &PolicyContext<'_>, outcome: &IterationReport) {
        let Some((last, predicted)) = self.last else {
            return;
        };
        if outcome.fallback {
            // The chosen solver failed; whatever it holds must be recomputed.
            if self.cycle.is_some_and(|cy| cy.candidate == last) {
                self.cycle = None;
            }
            return;
        }
        let setup = outcome.setup.work(self.options.weights);
        let model = &mut self.costs[last];
        if !outcome.setup.reused && outcome.setup.flops > 0 {
            model.observed_setup = Some(setup);
        }
        let iterations = outcome.solve.iterations.max(1) as f64;
        if predicted.is_finite() && predicted > 0.0 {
            let ratio = (iterations / predicted).ln();
            let old = self.calibration[last].map(f64::ln);
            self.calibration[last] = Some(old.map_or(ratio, |o| 0.5 * (o + ratio)).exp());
        }
        let solve = outcome.solve.work(self.options.weights);
        if outcome.solve.flops > 0 {
            model.observed_iteration = Some(solve / iterations);
        }
        if let Some(cy) = self.cycle.as_mut().filter(|cy| cy.candidate == last) {
            cy.work += setup + solve;
            cy.solves += 1;
            cy.last_iterations = Some(iterations);
        }
    }

    fn fork(&self) -> Option<Box<dyn SolverPolicy>> {
        Some(Box::new(self.with_forcing(self.options.forcing)))
    }
}
