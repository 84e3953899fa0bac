//! Solver policies measured on whole simulations: deterministic work and flops, median
//! solver and step times over repeats, Newton and linear iterations, and accuracy against
//! direct solves at a tight Newton tolerance ([`crate::tuning::Reference`]).

use std::path::Path;

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
    let mut row = Measured {
        flops: 0.0,
        work: 0.0,
        seconds: 0.0,
        step_seconds: 0.0,
        newton: 0,
        linear: 0,
        error: 0.0,
        fallbacks: 0,
        failed: false,
        deterministic: true,
        per_step: Vec::new(),
        choices: Vec::new(),
    };
    let (mut times, mut step_times) = (Vec::new(), Vec::new());
    for repeat in 0..repeats.max(1) {
        let (mut flops, mut seconds, mut step_seconds) = (0.0, 0.0, 0.0);
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
                &if repeat == 0 {
                    run.keeping_reports()
                } else {
                    run
                },
                &mut OnStep(|_: &StepReport, s: &State| {
                    error = error.max(reference.error(n, &s.x));
                    n += 1;
                }),
            );
            row.failed |= summary.failed();
            flops += summary.flops as f64;
            seconds += summary.solver_seconds;
            step_seconds += summary.step_seconds;
            if repeat == 0 {
                row.work += summary.work;
                row.newton += summary.newton_iterations;
                row.linear += summary.linear_iterations;
                row.fallbacks += summary.fallbacks;
                row.error = row.error.max(error);
                for r in &summary.reports {
                    row.per_step.push((r.work(weights), r.newton_iterations()));
                    row.choices.extend(r.iterations.iter().map(|i| Choice {
                        solver: i.solver.clone(),
                        fallback: i.fallback,
                    }));
                }
            }
        }
        if repeat == 0 {
            row.flops = flops;
        } else if flops != row.flops {
            row.deterministic = false;
        }
        times.push(seconds);
        step_times.push(step_seconds);
    }
    row.seconds = median(times);
    row.step_seconds = median(step_times);
    Ok(row)
}

/// The median of `v` (the upper one of an even count); `v` is not empty.
pub(crate) fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}
