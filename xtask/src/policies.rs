//! Solver policies compared on whole simulations: work, time and accuracy against direct
//! solves at a tight Newton tolerance (`deform_learn::tuning::reference_scene`).

use std::path::Path;

use anyhow::Result;
use deform_integrator::{Scene, SolverPolicy};
use deform_learn::tuning::Reference;

/// Makes a fresh policy for each run.
pub type PolicyMaker = Box<dyn Fn() -> Box<dyn SolverPolicy>>;

/// One or more simulations a policy is measured on together.
pub struct Case<'a> {
    /// Name in reports.
    pub label: String,
    /// Scenes (with their initial conditions) and the folder their paths are relative to.
    pub runs: Vec<(Scene, &'a Path)>,
    /// Steps of each run.
    pub steps: usize,
}

/// A policy's totals on a case.
#[derive(Debug, Clone)]
pub struct Row {
    /// Policy name.
    pub policy: String,
    /// Deterministic flops (set-up plus solves).
    pub flops: f64,
    /// Deterministic work: solve flops plus `factor_weight` times factorisation flops.
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
    /// The solver of every Newton iteration (with the fallback marked), in order.
    pub choices: Vec<String>,
}

/// Positions after every step of each run with the direct solver at a tight tolerance.
pub fn references(case: &Case<'_>) -> Result<Vec<Reference>> {
    case.runs
        .iter()
        .map(|(scene, origin)| Ok(Reference::simulate(scene, origin, case.steps)?))
        .collect()
}

/// Runs `make`'s policy `repeats` times on every run of `case`.
pub fn measure(
    case: &Case<'_>,
    references: &[Reference],
    name: &str,
    make: &PolicyMaker,
    factor_weight: f64,
    repeats: usize,
) -> Result<Row> {
    let mut row = Row {
        policy: name.to_owned(),
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
            let mut built = scene.build(origin)?;
            built.integrator.set_policy(make());
            for n in 0..reference.steps() {
                let started = std::time::Instant::now();
                let result = built.integrator.step(&mut built.state);
                step_seconds += started.elapsed().as_secs_f64();
                let Ok(r) = result else {
                    row.failed = true;
                    break;
                };
                flops += r.flops() as f64;
                seconds += r.solver_seconds();
                if repeat == 0 {
                    row.work += r.work(factor_weight);
                    row.per_step
                        .push((r.work(factor_weight), r.newton_iterations()));
                    row.choices.extend(r.iterations.iter().map(|i| {
                        if i.fallback {
                            format!("{} (fallback)", i.solver)
                        } else {
                            i.solver.clone()
                        }
                    }));
                    row.newton += r.newton_iterations();
                    row.linear += r.linear_iterations();
                    row.fallbacks += r.iterations.iter().filter(|i| i.fallback).count();
                    row.error = row.error.max(reference.error(n, &built.state.x));
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
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    row.seconds = median(times);
    row.step_seconds = median(step_times);
    Ok(row)
}
