//! Solver optimisation (seed: "given a solver, learn its parameters using data"): black-box
//! tuning of a solver configuration's parameters to minimise the deterministic work of a
//! simulation, subject to its trajectory staying within a tolerance of the reference
//! computed with the direct solver to a tight tolerance.
//!
//! One mechanism, [`tune_policy`]: a scalar parameter (in log10) that makes a solver policy
//! (the relative tolerance of a fixed iterative solver, [`tune_relative_tolerance`]; the
//! largest forcing term of the learned policy; ...) is tuned by argmin's Nelder-Mead. The
//! cost of a parameter value is the simulation's total work (flops, factorisations weighted
//! by `factor_weight`, see `SetupStats::work`), multiplied by a penalty
//! `1 + 10 error / accuracy` when the trajectory error exceeds `accuracy`, and infinite when
//! a step fails (no direct fallback, no retries while tuning).

use std::cell::RefCell;
use std::path::Path;

use argmin::core::{CostFunction, Error as ArgminError, Executor};
use argmin::solver::neldermead::NelderMead;
use deform_integrator::{Fixed, IntegratorOptions, Scene, SolverPolicy};
use deform_solvers::{SolverSpec, Tolerance};
use serde::{Deserialize, Serialize};

use crate::fit::FitError;

/// One evaluated parameter value.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TuningSample {
    /// `log10` of the parameter (a relative tolerance, a forcing term, ...).
    pub log10_value: f64,
    /// Total work of the simulation (flops, factorisations weighted, see [`Tuning`]).
    pub work: f64,
    /// Max position error against the reference, relative to the positions' scale.
    pub error: f64,
    /// The penalised cost the optimiser saw.
    pub cost: f64,
}

/// The result of tuning.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TuningResult {
    /// The best `log10` parameter value.
    pub log10_value: f64,
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
        SolverSpec::MatrixFree(inner) => {
            SolverSpec::MatrixFree(Box::new(with_relative_tolerance(inner, rel)?))
        }
    })
}

/// Makes the policy for a parameter value, and may adjust the integrator's options for it
/// (a Newton tolerance, ...); `None`: not a valid value.
pub type PolicyOf<'a> = dyn Fn(f64, &mut IntegratorOptions) -> Option<Box<dyn SolverPolicy>> + 'a;

struct Problem<'a> {
    scene: &'a Scene,
    origin: &'a Path,
    make: &'a PolicyOf<'a>,
    range: (f64, f64),
    factor_weight: f64,
    fallback: bool,
    steps: usize,
    accuracy: f64,
    reference: Reference,
    samples: RefCell<Vec<TuningSample>>,
}

impl Problem<'_> {
    fn evaluate(&self, log10_value: f64) -> TuningSample {
        let sample = |work: f64, error: f64, cost: f64| TuningSample {
            log10_value,
            work,
            error,
            cost,
        };
        let Ok(mut built) = self.scene.build(self.origin) else {
            return sample(f64::NAN, f64::NAN, f64::INFINITY);
        };
        let mut options = built.integrator.options().clone();
        let value = log10_value.clamp(self.range.0, self.range.1);
        let Some(policy) = (self.make)(value, &mut options) else {
            return sample(f64::NAN, f64::NAN, f64::INFINITY);
        };
        // No retries; no fallback unless the policy relies on it by design (then the failed
        // attempt and the direct solve are both charged): a configuration that fails must show
        // as failing, not as the direct solver's cost.
        options.fallback_to_direct = self.fallback;
        options.max_retries = 0;
        if built.integrator.set_options(options).is_err() {
            return sample(f64::NAN, f64::NAN, f64::INFINITY);
        }
        built.integrator.set_policy(policy);
        let (mut work, mut error) = (0.0, 0.0f64);
        for n in 0..self.steps {
            match built.integrator.step(&mut built.state) {
                Ok(r) => work += r.work(self.factor_weight),
                Err(_) => return sample(f64::NAN, f64::INFINITY, f64::INFINITY),
            }
            error = error.max(self.reference.error(n, &built.state.x));
        }
        let penalty = if error > self.accuracy {
            1.0 + 10.0 * error / self.accuracy
        } else {
            1.0
        };
        sample(work, error, work * penalty)
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

/// Tunes the relative tolerance of the iterative `solver` (the same at every Newton
/// iteration) for the least flops on `steps` steps of `scene`, keeping the trajectory within
/// `accuracy` (relative max-norm) of the direct solver's ([`reference_scene`]).
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
    let make = |log10_value: f64, _: &mut IntegratorOptions| -> Option<Box<dyn SolverPolicy>> {
        let spec = with_relative_tolerance(solver, 10f64.powf(log10_value))?;
        Some(Box::new(Fixed(spec)))
    };
    tune_policy(
        scene,
        origin,
        &make,
        Tuning {
            start: (-3.0, -8.0),
            range: (-14.0, -0.5),
            factor_weight: 1.0,
            fallback: false,
            steps,
            accuracy,
            max_iterations,
        },
    )
}

/// The scene that accuracy is measured against: the direct solver, and a Newton tolerance
/// tighter than any policy run (relative 1e-10, or the scene's if tighter), above the
/// rounding floor of stiff systems.
pub fn reference_scene(scene: &Scene) -> Scene {
    let mut s = scene.clone();
    s.integrator.newton.rel = s.integrator.newton.rel.min(1e-10);
    s.policy = deform_integrator::PolicySpec::default();
    s
}

/// The positions after every step of [`reference_scene`], against which trajectories are
/// measured: the max-norm deviation relative to the largest reference coordinate.
#[derive(Debug, Clone, PartialEq)]
pub struct Reference {
    positions: Vec<Vec<f64>>,
    scale: f64,
}

impl Reference {
    /// Simulates `steps` steps of `scene`'s reference.
    ///
    /// # Errors
    /// [`FitError::Data`] naming the failure.
    pub fn simulate(scene: &Scene, origin: &Path, steps: usize) -> Result<Self, FitError> {
        let fail = |e: String| FitError::Data {
            index: 0,
            reason: format!("reference simulation: {e}"),
        };
        let mut built = reference_scene(scene)
            .build(origin)
            .map_err(|e| fail(e.to_string()))?;
        let mut positions = Vec::with_capacity(steps);
        for _ in 0..steps {
            built
                .integrator
                .step(&mut built.state)
                .map_err(|e| fail(e.to_string()))?;
            positions.push(built.state.x.clone());
        }
        let scale = positions
            .iter()
            .flatten()
            .fold(0.0f64, |m, v| m.max(v.abs()))
            .max(f64::MIN_POSITIVE);
        Ok(Self { positions, scale })
    }

    /// Steps simulated.
    pub fn steps(&self) -> usize {
        self.positions.len()
    }

    /// Max-norm deviation of positions `x` after step `n` (0-based) from the reference's,
    /// relative to its largest coordinate.
    pub fn error(&self, n: usize, x: &[f64]) -> f64 {
        let e = x
            .iter()
            .zip(&self.positions[n])
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        e / self.scale
    }
}

/// What [`tune_policy`] searches and how it scores.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tuning {
    /// The two vertices of the initial simplex (log10 of the parameter).
    pub start: (f64, f64),
    /// Values are clamped to this range (log10).
    pub range: (f64, f64),
    /// Factorisation flops count this much (1: plain flops).
    pub factor_weight: f64,
    /// Let the integrator fall back to the direct solver when a solve fails (for policies
    /// that rely on it, such as the learned one); the failed attempt is charged too.
    pub fallback: bool,
    /// Steps simulated per evaluation.
    pub steps: usize,
    /// Relative max-norm position error allowed against the reference.
    pub accuracy: f64,
    /// Nelder-Mead iterations.
    pub max_iterations: u64,
}

/// Tunes the log10 of a scalar parameter of the policy `make` builds, for the least work
/// on `tuning.steps` steps of `scene` within `tuning.accuracy` of the direct solver's
/// trajectory (see [`reference_scene`]). Every evaluation is returned in `samples`.
///
/// # Errors
/// [`FitError`] when the reference simulation fails or no value works.
pub fn tune_policy(
    scene: &Scene,
    origin: &Path,
    make: &PolicyOf<'_>,
    tuning: Tuning,
) -> Result<TuningResult, FitError> {
    let fail = |e: String| FitError::Data {
        index: 0,
        reason: e,
    };
    let steps = tuning.steps;
    let reference = Reference::simulate(scene, origin, steps)?;
    let problem = Problem {
        scene,
        origin,
        make,
        range: tuning.range,
        factor_weight: tuning.factor_weight,
        fallback: tuning.fallback,
        steps,
        accuracy: tuning.accuracy,
        reference,
        samples: RefCell::new(Vec::new()),
    };
    let simplex = NelderMead::new(vec![vec![tuning.start.0], vec![tuning.start.1]])
        .with_sd_tolerance(1e-3)
        .map_err(|e| fail(e.to_string()))?;
    let result = Executor::new(&problem, simplex)
        .configure(|s| s.max_iters(tuning.max_iterations))
        .run();
    let samples = problem.samples.borrow().clone();
    let best = samples
        .iter()
        .filter(|s| s.cost.is_finite())
        .min_by(|a, b| a.cost.total_cmp(&b.cost))
        .cloned()
        .ok_or_else(|| fail(format!("no value worked ({:?})", result.err())))?;
    Ok(TuningResult {
        log10_value: best.log10_value,
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
