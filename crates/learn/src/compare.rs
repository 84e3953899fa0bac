//! Solver policies measured on whole simulations: deterministic work and flops, median
//! solver and step times over repeats, Newton and linear iterations, and accuracy against
//! direct solves at a tight Newton tolerance ([`crate::tuning::Reference`]).

use std::path::Path;

use deform_integrator::benchmark::median;
use deform_integrator::{
    IntegratorOptions, OnStep, RunOptions, Scene, SolverPolicy, State, StepReport,
};
use deform_solvers::{SolverSpec, WorkWeights};
use serde::{Deserialize, Serialize};

use crate::error::LearnError;
use crate::tuning::Reference;

/// One or more simulations a policy is measured on together.
#[derive(Debug, Clone)]
pub struct Case<'a> {
    /// Name in reports.
    pub label: String,
    /// Scenes (with their initial conditions) and the folder their paths are relative to.
    pub runs: Vec<(Scene, &'a Path)>,
    /// Steps of each run.
    pub steps: usize,
}

impl Case<'_> {
    /// Positions after every step of each run with the direct solver at a tight tolerance.
    ///
    /// # Errors
    /// The reference simulation's.
    pub fn references(&self) -> Result<Vec<Reference>, LearnError> {
        self.runs
            .iter()
            .map(|(scene, origin)| Ok(Reference::simulate(scene, origin, self.steps)?))
            .collect()
    }
}

/// A policy's totals on a case.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct Measured {
    /// Deterministic flops (set-up plus solves).
    pub flops: f64,
    /// Deterministic work: flops weighted by the `weights` passed in (see `WorkWeights`).
    pub work: f64,
    /// Median over the repeats of the total linear-solver wall time.
    pub seconds: f64,
    /// Median over the repeats of the total step wall time (the whole Newton loop:
    /// assembly, solves, line search).
    pub step_seconds: f64,
    /// Newton iterations.
    pub newton: usize,
    /// Linear (Krylov) iterations.
    pub linear: usize,
    /// Largest position deviation from the reference, relative to the largest coordinate.
    pub error: f64,
    /// Direct fallbacks after a failed iterative solve.
    pub fallbacks: usize,
    /// A step failed.
    pub failed: bool,
    /// Flops were identical in every repeat.
    pub deterministic: bool,
    /// Work and Newton iterations of every step (runs one after the other).
    pub per_step: Vec<(f64, usize)>,
    /// The solver of every Newton iteration, in order.
    pub choices: Vec<Choice>,
}

/// The solver a Newton iteration used.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct Choice {
    /// The solver (the direct one when `fallback`).
    pub solver: SolverSpec,
    /// The chosen solver failed and the direct one was used instead.
    pub fallback: bool,
}

impl std::fmt::Display for Choice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.solver)?;
        if self.fallback {
            f.write_str(" (fallback)")?;
        }
        Ok(())
    }
}

/// A policy and the change it makes to the scenes' Newton options.
pub struct Contestant<'a> {
    /// Makes the policy (once per run).
    pub make: &'a (dyn Fn() -> Box<dyn SolverPolicy> + Sync),
    /// Changes the scenes' integrator options first.
    pub options: &'a (dyn Fn(&mut IntegratorOptions) + Sync),
}

/// Runs `make`'s policy `repeats` times on every run of `case`, with the scenes' Newton
/// options changed by `options` first.
///
/// # Errors
/// A scene that does not build.
pub fn measure(
    case: &Case<'_>,
    references: &[Reference],
    make: &dyn Fn() -> Box<dyn SolverPolicy>,
    options: &dyn Fn(&mut IntegratorOptions),
    weights: WorkWeights,
    repeats: usize,
) -> Result<Measured, LearnError> {
    let passes = (0..repeats.max(1))
        .map(|repeat| pass(case, references, make, options, weights, repeat == 0))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Measured::of_passes(passes))
}

/// [`measure`] for every contestant. On problems below
/// `lanes::SIDE_BY_SIDE_MAX_DOFS` (20,000) free DOFs the runs (every contestant's repeats)
/// go side by side, one per thread on a pool of one thread, so their times are one core's
/// as on one thread; the work, flops and accuracy are the same bits either way. `progress`
/// sees each finished repeat.
///
/// # Errors
/// A scene that does not build.
pub fn measure_all(
    case: &Case<'_>,
    references: &[Reference],
    contestants: &[Contestant<'_>],
    weights: WorkWeights,
    repeats: usize,
    progress: &mut dyn FnMut(),
) -> Result<Vec<Measured>, LearnError> {
    let repeats = repeats.max(1);
    let jobs = contestants.len() * repeats;
    let run = |_: &mut (), k: usize, done: &mut dyn FnMut(())| {
        let (c, repeat) = (&contestants[k / repeats], k % repeats);
        let ran = pass(case, references, c.make, c.options, weights, repeat == 0);
        done(());
        ran
    };
    let mut free = 0;
    for (scene, origin) in &case.runs {
        free = free.max(scene.build(origin)?.integrator.dofs().num_free());
    }
    let mut passes = if crate::lanes::worth_it(jobs, free) {
        let mut lanes = vec![(); rayon::current_num_threads().min(jobs)];
        crate::lanes::side_by_side(&mut lanes, jobs, &run, &mut |_, ()| progress())?
    } else {
        (0..jobs)
            .map(|k| run(&mut (), k, &mut |()| progress()))
            .collect::<Result<Vec<_>, _>>()?
    }
    .into_iter();
    Ok((0..contestants.len())
        .map(|_| Measured::of_passes(passes.by_ref().take(repeats).collect()))
        .collect())
}

/// One run of a policy over every run of a case.
struct Pass {
    flops: f64,
    work: f64,
    seconds: f64,
    step_seconds: f64,
    newton: usize,
    linear: usize,
    fallbacks: usize,
    error: f64,
    failed: bool,
    /// Per step and per Newton iteration, when kept.
    per_step: Vec<(f64, usize)>,
    choices: Vec<Choice>,
}

/// `make`'s policy once over every run of `case`; `keep` keeps the per-step figures and
/// choices.
fn pass(
    case: &Case<'_>,
    references: &[Reference],
    make: &dyn Fn() -> Box<dyn SolverPolicy>,
    options: &dyn Fn(&mut IntegratorOptions),
    weights: WorkWeights,
    keep: bool,
) -> Result<Pass, LearnError> {
    let mut out = Pass {
        flops: 0.0,
        work: 0.0,
        seconds: 0.0,
        step_seconds: 0.0,
        newton: 0,
        linear: 0,
        fallbacks: 0,
        error: 0.0,
        failed: false,
        per_step: Vec::new(),
        choices: Vec::new(),
    };
    for ((scene, origin), reference) in case.runs.iter().zip(references) {
        let mut scene = scene.clone();
        options(&mut scene.integrator);
        let mut built = scene.build(origin)?;
        built.integrator.set_policy(make());
        let mut n = 0;
        let mut error = 0.0f64;
        let run = RunOptions::steps(reference.steps()).with_weights(weights);
        let summary = built.integrator.run(
            &mut built.state,
            &if keep { run.keeping_reports() } else { run },
            &mut OnStep(|_: &StepReport, s: &State| {
                error = error.max(reference.error(n, &s.x));
                n += 1;
            }),
        );
        out.failed |= summary.failed();
        out.flops += summary.flops as f64;
        out.seconds += summary.solver_seconds;
        out.step_seconds += summary.step_seconds;
        out.work += summary.work;
        out.newton += summary.newton_iterations;
        out.linear += summary.linear_iterations;
        out.fallbacks += summary.fallbacks;
        out.error = out.error.max(error);
        for r in &summary.reports {
            out.per_step.push((r.work(weights), r.newton_iterations()));
            out.choices.extend(r.iterations.iter().map(|i| Choice {
                solver: i.solver.clone(),
                fallback: i.fallback,
            }));
        }
    }
    Ok(out)
}

impl Measured {
    /// The first pass's counts and accuracy, the median times over all passes, and whether
    /// every pass did the first one's flops.
    fn of_passes(passes: Vec<Pass>) -> Self {
        let times = passes.iter().map(|p| p.seconds).collect();
        let step_times = passes.iter().map(|p| p.step_seconds).collect();
        let deterministic = passes.iter().all(|p| p.flops == passes[0].flops);
        let failed = passes.iter().any(|p| p.failed);
        let first = passes.into_iter().next().expect("at least one repeat");
        Measured {
            flops: first.flops,
            work: first.work,
            seconds: median(times),
            step_seconds: median(step_times),
            newton: first.newton,
            linear: first.linear,
            error: first.error,
            fallbacks: first.fallbacks,
            failed,
            deterministic,
            per_step: first.per_step,
            choices: first.choices,
        }
    }
}
