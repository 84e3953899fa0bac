//! Solver optimisation (seed: "given a solver, learn its parameters using data"): black-box
//! tuning of a solver configuration's parameters to minimise the deterministic work of a
//! simulation, subject to its trajectory staying within a tolerance of the reference
//! computed with the direct solver to a tight tolerance.
//!
//! One mechanism, [`tune_policy`]: parameters (in log10) that make a solver policy and may
//! set the integrator's options (the relative tolerance of a fixed iterative solver,
//! Jacobi's omega, stale-factor PCG's refactorisation threshold: [`tune_solver`]; the
//! learned policy's largest forcing term; Newton's
//! tolerance; ...) are tuned by argmin's Nelder-Mead on one or more training simulations.
//! The cost of a parameter vector is the simulations' total work (flops, factorisations
//! and sweeps weighted by `WorkWeights`), multiplied by a penalty
//! `1 + 10 error / accuracy` when the largest trajectory error exceeds `accuracy`, and
//! infinite when a step fails (no retries while tuning).

use std::cell::RefCell;
use std::path::Path;

use argmin::core::{CostFunction, Error as ArgminError, Executor};
use argmin::solver::neldermead::NelderMead;
use deform_integrator::{
    Fixed, IntegratorOptions, OnStep, RunOptions, Scene, SolverPolicy, StaleFactor, State,
    StepReport,
};

use crate::solver_data::Run;
use deform_solvers::{SolverSpec, WorkWeights};
use serde::{Deserialize, Serialize};

use crate::fit::FitError;

/// One evaluated parameter vector.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct TuningSample {
    /// `log10` of each parameter (a relative tolerance, a forcing term, ...), clamped to
    /// its range.
    pub log10_values: Vec<f64>,
    /// Total work of the simulations (flops, factorisations weighted, see [`Tuning`]).
    pub work: f64,
    /// Max position error against the references, relative to the positions' scale.
    pub error: f64,
    /// The penalised cost the optimiser saw.
    pub cost: f64,
}

/// The result of tuning.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct TuningResult {
    /// The best `log10` parameter values.
    pub log10_values: Vec<f64>,
    /// Its sample.
    pub best: TuningSample,
    /// Every evaluation, in order.
    pub samples: Vec<TuningSample>,
}

/// Makes the policy for a parameter vector (log10 values, clamped to their ranges), and
/// may adjust the integrator's options for it (a Newton tolerance, ...); `None`: not a
/// valid value. Called once per simulation.
pub type PolicyOf<'a> =
    dyn Fn(&[f64], &mut IntegratorOptions) -> Option<Box<dyn SolverPolicy>> + 'a;

struct Problem<'a> {
    runs: &'a [Run<'a>],
    make: &'a PolicyOf<'a>,
    range: &'a [(f64, f64)],
    weights: WorkWeights,
    fallback: bool,
    accuracy: f64,
    references: Vec<Reference>,
    samples: RefCell<Vec<TuningSample>>,
}

impl Problem<'_> {
    fn evaluate(&self, log10_values: &[f64]) -> TuningSample {
        let values: Vec<f64> = log10_values
            .iter()
            .zip(self.range)
            .map(|(v, r)| v.clamp(r.0, r.1))
            .collect();
        let sample = |work: f64, error: f64, cost: f64| TuningSample {
            log10_values: values.clone(),
            work,
            error,
            cost,
        };
        let (mut work, mut error) = (0.0, 0.0f64);
        for ((scene, origin, steps), reference) in self.runs.iter().zip(&self.references) {
            let Ok(mut built) = scene.build(origin) else {
                return sample(f64::NAN, f64::NAN, f64::INFINITY);
            };
            let mut options = built.integrator.options().clone();
            let Some(policy) = (self.make)(&values, &mut options) else {
                return sample(f64::NAN, f64::NAN, f64::INFINITY);
            };
            // No retries; no fallback unless the policy relies on it by design (then the
            // failed attempt and the direct solve are both charged): a configuration that
            // fails must show as failing, not as the direct solver's cost.
            options.fallback_to_direct = self.fallback;
            options.max_retries = 0;
            if built.integrator.set_options(options).is_err() {
                return sample(f64::NAN, f64::NAN, f64::INFINITY);
            }
            built.integrator.set_policy(policy);
            let mut n = 0;
            let summary = built.integrator.run(
                &mut built.state,
                &RunOptions::steps(*steps).with_weights(self.weights),
                &mut OnStep(|_: &StepReport, state: &State| {
                    error = error.max(reference.error(n, &state.x));
                    n += 1;
                }),
            );
            if summary.failed() {
                return sample(f64::NAN, f64::INFINITY, f64::INFINITY);
            }
            work += summary.work;
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
        let s = self.evaluate(p);
        let cost = s.cost;
        self.samples.borrow_mut().push(s);
        Ok(if cost.is_finite() { cost } else { f64::MAX })
    }
}

/// A parameter of a solver configuration that [`tune_solver`] can tune (each in log10).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum SolverParameter {
    /// The relative residual tolerance of an iterative solver (the same at every Newton
    /// iteration), in `[1e-14, 10^-0.5]`.
    RelativeTolerance,
    /// The relaxation `omega` of the Jacobi iteration, in `[0.1, 1.99]`.
    Omega,
    /// The refactorisation threshold of stale-factor PCG (the `StaleFactor` hand schedule:
    /// refactorise after a solve above this many iterations), in `[1, 1000]`; the solver
    /// must be PCG with a `StaleCholesky` preconditioner.
    RefactorAbove,
}

impl SolverParameter {
    /// `(lower, upper)` bounds in log10.
    fn range(self) -> (f64, f64) {
        match self {
            Self::RelativeTolerance => (-14.0, -0.5),
            Self::Omega => (-1.0, 1.99f64.log10()),
            Self::RefactorAbove => (0.0, 3.0),
        }
    }

    /// The configured value (log10) and the second vertex of the initial simplex.
    fn start(self, solver: &SolverSpec) -> Option<(f64, f64)> {
        Some(match (self, solver) {
            (Self::RelativeTolerance, _) => {
                let rel = solver.tolerance()?.rel.log10();
                (rel, if rel < -4.0 { -3.0 } else { rel - 3.0 })
            }
            (Self::Omega, SolverSpec::Jacobi { omega, .. }) => (omega.log10(), 0.0),
            (
                Self::RefactorAbove,
                SolverSpec::Pcg {
                    preconditioner: deform_solvers::PreconditionerSpec::StaleCholesky { .. },
                    ..
                },
            ) => (20f64.log10(), 5f64.log10()),
            _ => return None,
        })
    }
}

/// `solver` with `parameters` set to `10^values` (none of them `RefactorAbove`).
fn with_parameters(
    solver: &SolverSpec,
    parameters: &[SolverParameter],
    values: &[f64],
) -> Option<SolverSpec> {
    let mut spec = solver.clone();
    for (p, v) in parameters.iter().zip(values) {
        let value = 10f64.powf(*v);
        spec = match p {
            SolverParameter::RelativeTolerance => spec.with_relative_tolerance(value)?,
            SolverParameter::Omega => match spec {
                SolverSpec::Jacobi { tolerance, .. } => SolverSpec::Jacobi {
                    omega: value,
                    tolerance,
                },
                _ => return None,
            },
            SolverParameter::RefactorAbove => spec,
        };
    }
    Some(spec)
}

/// What [`tune_solver`] tunes, and how.
#[derive(Debug, Clone, Copy)]
pub struct SolverTuning<'a> {
    /// The iterative configuration, its values the starting point.
    pub solver: &'a SolverSpec,
    /// The parameters tuned jointly.
    pub parameters: &'a [SolverParameter],
    /// Steps of the training simulation.
    pub steps: usize,
    /// Relative max-norm position accuracy to keep against the direct reference.
    pub accuracy: f64,
    /// How the work weighs factorisation and sweep flops.
    pub weights: WorkWeights,
    /// Nelder-Mead iterations.
    pub max_iterations: u64,
}

/// Tunes `parameters` of the iterative `solver` jointly (Nelder-Mead in log10 from the
/// configured values) for the least work (flops weighted by `weights`) on
/// `steps` steps of `scene`, within `accuracy` of the direct solver's trajectory. With
/// `RefactorAbove` the solver runs as the `StaleFactor` hand schedule. The first sample is
/// the configuration as given.
///
/// # Errors
/// [`FitError`] when a parameter does not apply to the solver, or the reference fails.
pub fn tune_solver(
    scene: &Scene,
    origin: &Path,
    tuning: &SolverTuning<'_>,
) -> Result<TuningResult, FitError> {
    let SolverTuning {
        solver,
        parameters,
        steps,
        accuracy,
        weights,
        max_iterations,
    } = *tuning;
    let starts = parameters
        .iter()
        .map(|p| {
            p.start(solver).ok_or_else(|| {
                FitError::Invalid(format!("{p:?} does not apply to {}", solver.name()))
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    if parameters.is_empty() {
        return Err(FitError::Invalid("no parameter to tune".into()));
    }
    let first: Vec<f64> = starts.iter().map(|s| s.0).collect();
    let mut start = vec![first.clone()];
    for (i, s) in starts.iter().enumerate() {
        let mut v = first.clone();
        v[i] = s.1;
        start.push(v);
    }
    let refactor = parameters
        .iter()
        .position(|p| *p == SolverParameter::RefactorAbove);
    let make = |p: &[f64], _: &mut IntegratorOptions| -> Option<Box<dyn SolverPolicy>> {
        let spec = with_parameters(solver, parameters, p)?;
        Some(match refactor {
            Some(i) => Box::new(StaleFactor::new(spec, 10f64.powf(p[i]).round() as usize)),
            None => Box::new(Fixed(spec)),
        })
    };
    tune_policy(
        &[(scene.clone(), origin, steps)],
        &make,
        &Tuning {
            start,
            range: parameters.iter().map(|p| p.range()).collect(),
            weights,
            fallback: false,
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
    /// [`FitError::Scene`] or [`FitError::Reference`] naming the failed step.
    pub fn simulate(scene: &Scene, origin: &Path, steps: usize) -> Result<Self, FitError> {
        let mut built = reference_scene(scene).build(origin)?;
        let mut positions = Vec::with_capacity(steps);
        built
            .integrator
            .run(
                &mut built.state,
                &RunOptions::steps(steps),
                &mut OnStep(|_: &StepReport, state: &State| positions.push(state.x.clone())),
            )
            .into_result()
            .map_err(|e| FitError::Reference {
                step: e.step,
                source: e.source,
            })?;
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
#[derive(Debug, Clone, PartialEq)]
pub struct Tuning {
    /// The `n + 1` vertices of the initial simplex (log10 of the `n` parameters).
    pub start: Vec<Vec<f64>>,
    /// Each parameter is clamped to its range (log10).
    pub range: Vec<(f64, f64)>,
    /// How the work weighs factorisation and sweep flops (default: plain flops).
    pub weights: WorkWeights,
    /// Let the integrator fall back to the direct solver when a solve fails (for policies
    /// that rely on it, such as the learned one); the failed attempt is charged too.
    pub fallback: bool,
    /// Relative max-norm position error allowed against the reference.
    pub accuracy: f64,
    /// Nelder-Mead iterations.
    pub max_iterations: u64,
}

impl Tuning {
    /// The most cost evaluations it can make: the simplex's vertices, then per Nelder-Mead
    /// iteration a reflection, an expansion or a contraction, and a shrink of the other
    /// vertices. Progress bars count against it.
    pub fn max_evaluations(&self) -> u64 {
        let n = self.range.len() as u64;
        n + 1 + self.max_iterations * (n + 2)
    }
}

/// Tunes the log10 of the parameters of the policy `make` builds, for the least total work
/// on `runs` (scene, folder of its paths, steps) within `tuning.accuracy` of the direct
/// solver's trajectories (see [`reference_scene`]). Every evaluation is returned in
/// `samples`.
///
/// # Errors
/// [`FitError`] when a reference simulation fails, the simplex does not match the ranges,
/// or no value works.
pub fn tune_policy(
    runs: &[Run<'_>],
    make: &PolicyOf<'_>,
    tuning: &Tuning,
) -> Result<TuningResult, FitError> {
    let fail = FitError::Invalid;
    let n = tuning.range.len();
    if tuning.start.len() != n + 1 || tuning.start.iter().any(|v| v.len() != n) {
        return Err(fail(format!(
            "the initial simplex needs {} vertices of {n} values",
            n + 1
        )));
    }
    let references = runs
        .iter()
        .map(|(scene, origin, steps)| Reference::simulate(scene, origin, *steps))
        .collect::<Result<Vec<_>, _>>()?;
    let problem = Problem {
        runs,
        make,
        range: &tuning.range,
        weights: tuning.weights,
        fallback: tuning.fallback,
        accuracy: tuning.accuracy,
        references,
        samples: RefCell::new(Vec::new()),
    };
    let simplex = NelderMead::new(tuning.start.clone())
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
        log10_values: best.log10_values.clone(),
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
