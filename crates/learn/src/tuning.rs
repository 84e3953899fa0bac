//! Solver optimisation (seed: "given a solver, learn its parameters using data"): black-box
//! tuning of a solver configuration's parameters to minimise the deterministic work of a
//! simulation, subject to its trajectory staying within a tolerance of the reference
//! computed with the direct solver to a tight tolerance.
//!
//! The parameters are the base-10 logarithm of the relative tolerance of an iterative
//! solver used at every Newton iteration; the optimiser is argmin's Nelder-Mead. The cost of
//! a parameter value is the total flop count of the simulation, multiplied by a penalty
//! `1 + 10 error / accuracy` when the trajectory error exceeds `accuracy`, and infinite when
//! a step fails.

use std::cell::RefCell;
use std::path::Path;

use argmin::core::{CostFunction, Error as ArgminError, Executor};
use argmin::solver::neldermead::NelderMead;
use deform_integrator::{Fixed, Scene};
use deform_solvers::{SolverSpec, Tolerance};
use serde::{Deserialize, Serialize};

use crate::fit::FitError;

/// One evaluated parameter value.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TuningSample {
    /// `log10` of the relative tolerance.
    pub log10_rel: f64,
    /// Total flops of the simulation.
    pub flops: f64,
    /// Max position error against the reference, relative to the positions' scale.
    pub error: f64,
    /// The penalised cost the optimiser saw.
    pub cost: f64,
}

/// The result of tuning.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TuningResult {
    /// The best `log10` relative tolerance.
    pub log10_rel: f64,
    /// Its sample.
    pub best: TuningSample,
    /// Every evaluation, in order.
    pub samples: Vec<TuningSample>,
}

/// `solver` with its relative tolerance replaced (iterative solvers only).
pub fn with_relative_tolerance(solver: &SolverSpec, rel: f64) -> Option<SolverSpec> {
    let set = |t: &Tolerance| Tolerance { rel, ..*t };
    Some(match solver {
        SolverSpec::Jacobi { omega, tolerance } => SolverSpec::Jacobi {
            omega: *omega,
            tolerance: set(tolerance),
        },
        SolverSpec::Cg { tolerance } => SolverSpec::Cg {
            tolerance: set(tolerance),
        },
        SolverSpec::Pcg {
            preconditioner,
            tolerance,
        } => SolverSpec::Pcg {
            preconditioner: *preconditioner,
            tolerance: set(tolerance),
        },
        SolverSpec::Direct { .. } => return None,
    })
}

struct Problem<'a> {
    scene: &'a Scene,
    origin: &'a Path,
    solver: &'a SolverSpec,
    steps: usize,
    accuracy: f64,
    reference: Vec<Vec<f64>>,
    scale: f64,
    samples: RefCell<Vec<TuningSample>>,
}

impl Problem<'_> {
    fn evaluate(&self, log10_rel: f64) -> TuningSample {
        let rel = 10f64.powf(log10_rel.clamp(-14.0, -0.5));
        let sample = |flops: f64, error: f64, cost: f64| TuningSample {
            log10_rel,
            flops,
            error,
            cost,
        };
        let Some(spec) = with_relative_tolerance(self.solver, rel) else {
            return sample(f64::NAN, f64::NAN, f64::INFINITY);
        };
        let Ok(mut built) = self.scene.build(self.origin) else {
            return sample(f64::NAN, f64::NAN, f64::INFINITY);
        };
        // No fallback: a configuration that fails must show as failing, not as the direct
        // solver's cost.
        let mut options = built.integrator.options().clone();
        options.fallback_to_direct = false;
        options.max_retries = 0;
        if built.integrator.set_options(options).is_err() {
            return sample(f64::NAN, f64::NAN, f64::INFINITY);
        }
        built.integrator.set_policy(Box::new(Fixed(spec)));
        let (mut flops, mut error) = (0.0, 0.0f64);
        for n in 0..self.steps {
            match built.integrator.step(&mut built.state) {
                Ok(r) => flops += r.flops() as f64,
                Err(_) => return sample(f64::NAN, f64::INFINITY, f64::INFINITY),
            }
            let e = built
                .state
                .x
                .iter()
                .zip(&self.reference[n])
                .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
            error = error.max(e / self.scale);
        }
        let penalty = if error > self.accuracy {
            1.0 + 10.0 * error / self.accuracy
        } else {
            1.0
        };
        sample(flops, error, flops * penalty)
    }
}

impl CostFunction for Problem<'_> {
    type Param = Vec<f64>;
    type Output = f64;

    fn cost(&self, p: &Vec<f64>) -> Result<f64, ArgminError> {
        let s = self.evaluate(p[0]);
        let cost = s.cost;
        self.samples.borrow_mut().push(s);
        Ok(if cost.is_finite() { cost } else { f64::MAX })
    }
}

/// Tunes the relative tolerance of `solver` (an iterative configuration used at every
/// Newton iteration) on `steps` steps of `scene`, keeping the trajectory within `accuracy`
/// (relative max-norm) of the direct solver's at Newton tolerance 1e-12.
///
/// # Errors
/// [`FitError`] when the reference simulation fails or the solver is not iterative.
pub fn tune_relative_tolerance(
    scene: &Scene,
    origin: &Path,
    solver: &SolverSpec,
    steps: usize,
    accuracy: f64,
    max_iterations: u64,
) -> Result<TuningResult, FitError> {
    if with_relative_tolerance(solver, 1e-8).is_none() {
        return Err(FitError::Data {
            index: 0,
            reason: "tolerance tuning needs an iterative solver".into(),
        });
    }
    let fail = |e: String| FitError::Data {
        index: 0,
        reason: e,
    };
    // The reference: direct solves, tight Newton tolerance.
    let mut reference_scene = scene.clone();
    reference_scene.integrator.newton.rel = 1e-12;
    reference_scene.integrator.newton.abs = 0.0;
    let mut built = reference_scene
        .build(origin)
        .map_err(|e| fail(e.to_string()))?;
    let mut reference = Vec::with_capacity(steps);
    for _ in 0..steps {
        built
            .integrator
            .step(&mut built.state)
            .map_err(|e| fail(e.to_string()))?;
        reference.push(built.state.x.clone());
    }
    let scale = reference
        .iter()
        .flatten()
        .fold(0.0f64, |m, v| m.max(v.abs()))
        .max(f64::MIN_POSITIVE);
    let problem = Problem {
        scene,
        origin,
        solver,
        steps,
        accuracy,
        reference,
        scale,
        samples: RefCell::new(Vec::new()),
    };
    let simplex = NelderMead::new(vec![vec![-3.0], vec![-8.0]])
        .with_sd_tolerance(1e-3)
        .map_err(|e| fail(e.to_string()))?;
    let result = Executor::new(&problem, simplex)
        .configure(|s| s.max_iters(max_iterations))
        .run();
    let samples = problem.samples.borrow().clone();
    let best = samples
        .iter()
        .filter(|s| s.cost.is_finite())
        .min_by(|a, b| a.cost.total_cmp(&b.cost))
        .cloned()
        .ok_or_else(|| fail(format!("no tolerance worked ({:?})", result.err())))?;
    Ok(TuningResult {
        log10_rel: best.log10_rel,
        best,
        samples,
    })
}

impl CostFunction for &Problem<'_> {
    type Param = Vec<f64>;
    type Output = f64;

    fn cost(&self, p: &Vec<f64>) -> Result<f64, ArgminError> {
        (*self).cost(p)
    }
}
