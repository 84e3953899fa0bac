//! The demo's story (`Task::TuneBackwardEuler`): a Backward-Euler model that steps
//! `subsample` times coarser than the base model is tuned with the base's data, and compared
//! with the same coarse model untuned on the test trajectories, accuracy and cost side by
//! side. Tuned means all four of the seed's ideas that apply to one model: the material's
//! Lame pair fitted (equation error, then output error through the coarse steps), a solver
//! policy learned on the tuned model's own Newton systems (counterfactual logs of the
//! candidates), and that policy's largest Eisenstat-Walker forcing term tuned for the least
//! work within the accuracy bound.

use std::fmt::Write as _;
use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result, anyhow};
use deform_integrator::{Integrator, IntegratorOptions, Scene, SolverPolicy};
use deform_learn::dataset::state_at;
use deform_learn::experiment::rollout_error;
use deform_learn::policy::{LearnedPolicy, PolicyOptions};
use deform_learn::tuning::{Tuning, tune_policy};
use deform_learn::{
    Dataset, Split, Trajectory, fit_ensemble, fit_equation_error, fit_output_error, refine_ensemble,
};
use deform_materials::Lame;
use deform_mesh::io::{Pvd, Vtu};
use deform_solvers::SolverSpec;

use crate::experiment::{bar, plot_rollouts, with_lame, write_text};

/// What the story needs besides the dataset.
pub struct Story<'a> {
    /// The coarse scene (the base's with `subsample x dt`) and its folder.
    pub scene: &'a Scene,
    pub origin: &'a Path,
    /// The base scene (fine step) for its cost.
    pub base: &'a Scene,
    /// Steps of the base per coarse step.
    pub subsample: usize,
    /// The data, subsampled to the coarse step.
    pub data: &'a Dataset,
    pub equation_error: deform_learn::EquationErrorOptions,
    pub output_error: deform_learn::OutputErrorOptions,
    pub members: &'a [String],
    pub candidates: &'a [SolverSpec],
    pub factor_weight: f64,
    pub accuracy: f64,
    pub max_iterations: u64,
    pub quiet: bool,
}

/// Totals of one model over the test trajectories.
struct Totals {
    /// RMS position error against the data per coarse step, averaged over trajectories.
    errors: Vec<f64>,
    work: f64,
    flops: f64,
    seconds: f64,
    newton: usize,
    fallbacks: usize,
}

/// Runs of each model whose whole-step times are reduced to their median (tiny problems:
/// one run's time varies by tens of percent here).
const TIME_REPEATS: usize = 3;

/// [`run_model`], with the step time the median of [`TIME_REPEATS`] runs (frames from the
/// first).
fn run_model_timed(
    make: &dyn Fn() -> Result<(Integrator, deform_mesh::TetMesh)>,
    tests: &[&Trajectory],
    refine: usize,
    factor_weight: f64,
    frames: Option<&Path>,
) -> Result<Totals> {
    let mut totals = run_model(make, tests, refine, factor_weight, frames)?;
    let mut seconds = vec![totals.seconds];
    for _ in 1..TIME_REPEATS {
        seconds.push(run_model(make, tests, refine, factor_weight, None)?.seconds);
    }
    seconds.sort_by(f64::total_cmp);
    totals.seconds = seconds[seconds.len() / 2];
    Ok(totals)
}

/// Runs `sim` from the first state of each trajectory for its length (times `refine` finer
/// steps), comparing with the data at the coarse times; writes frames of the first one.
fn run_model(
    make: &dyn Fn() -> Result<(Integrator, deform_mesh::TetMesh)>,
    tests: &[&Trajectory],
    refine: usize,
    factor_weight: f64,
    frames: Option<&Path>,
) -> Result<Totals> {
    let len = tests.first().map_or(0, |t| t.x.len());
    let mut totals = Totals {
        errors: vec![0.0; len],
        work: 0.0,
        flops: 0.0,
        seconds: 0.0,
        newton: 0,
        fallbacks: 0,
    };
    for (k, t) in tests.iter().enumerate() {
        let (mut sim, mesh) = make()?;
        let dt = sim.options().dt;
        let mut state = state_at(t, 0, dt);
        let mut pvd = match frames.filter(|_| k == 0) {
            Some(dir) => {
                std::fs::create_dir_all(dir)
                    .with_context(|| format!("creating {}", dir.display()))?;
                Some((dir.to_path_buf(), Pvd::new(dir.join("series.pvd"))))
            }
            None => None,
        };
        let mut frame = |n: usize, x: &[f64], time: f64| -> Result<()> {
            if let Some((dir, pvd)) = pvd.as_mut() {
                let file = dir.join(format!("frame_{n:05}.vtu"));
                Vtu::deformed(&mesh, x).write(&file)?;
                pvd.push(time, &file)?;
            }
            Ok(())
        };
        frame(0, &state.x, state.t)?;
        for n in 1..t.x.len() {
            for _ in 0..refine {
                let started = Instant::now();
                let r = sim
                    .step(&mut state)
                    .map_err(|e| anyhow!("test trajectory {k}, step {n}: {e}"))?;
                totals.seconds += started.elapsed().as_secs_f64();
                totals.work += r.work(factor_weight);
                totals.flops += r.flops() as f64;
                totals.newton += r.newton_iterations();
                totals.fallbacks += r.iterations.iter().filter(|i| i.fallback).count();
            }
            let sq: f64 = state
                .x
                .iter()
                .zip(&t.x[n])
                .map(|(a, b)| (a - b).powi(2))
                .sum();
            totals.errors[n] += (sq / (state.x.len() / 3) as f64).sqrt() / tests.len() as f64;
            frame(n, &state.x, state.t)?;
        }
    }
    Ok(totals)
}

/// Runs the story, appending to `report`; returns the one-line summary.
pub fn run(s: &Story<'_>, out: &Path, report: &mut String) -> Result<String> {
    let train = s.data.split(Split::Train);
    let tests = s.data.split(Split::Test);
    let built = s.scene.build(s.origin)?;
    let truth = s
        .scene
        .material
        .build()?
        .lame()
        .ok_or_else(|| anyhow!("the scene's model has no single Lame pair"))?;

    // 1. Force-model optimisation through the coarse steps.
    let b = bar(s.quiet, s.output_error.max_evaluations as u64, "fit");
    let stage1 = fit_equation_error(&built.integrator, &train, s.equation_error)?;
    let mut sim = built.integrator;
    // Stage 2 refines the Lame pair with stage 1's damping.
    let mut options = sim.options().clone();
    (options.alpha, options.gamma) = (stage1.alpha, stage1.gamma);
    sim.set_options(options)?;
    let fit = fit_output_error(
        &mut sim,
        &train,
        &stage1.coefficients,
        s.output_error,
        |_, loss| {
            b.inc(1);
            b.set_message(format!("loss {loss:.3e}"));
        },
    )?;
    b.finish_and_clear();
    let fitted = Lame::try_new(fit.coefficients[0], fit.coefficients[1])?;
    let mut tuned_scene = with_lame(s.scene, fitted.mu, fitted.lambda)?;
    tuned_scene.integrator.alpha = stage1.alpha;
    tuned_scene.integrator.gamma = stage1.gamma;

    // 2. Model selection: an ensemble fitted the same two ways (with the fitted damping)
    // replaces the single model when it predicts the validation trajectories better.
    let validation = s.data.split(Split::Validation);
    let mut selection = String::new();
    let mut tuned_name = "tuned";
    if !s.members.is_empty() {
        let names: Vec<&str> = s.members.iter().map(String::as_str).collect();
        let b = bar(s.quiet, s.output_error.max_evaluations as u64, "ensemble");
        let ensemble = fit_ensemble(&tuned_scene, s.origin, &names, &train, &validation)?;
        let (ensemble, _) = refine_ensemble(
            &ensemble,
            &tuned_scene,
            s.origin,
            &train,
            &validation,
            s.output_error,
            |_, _| b.inc(1),
        )?;
        b.finish_and_clear();
        let rollout = |scene: &Scene| -> Result<f64> {
            let mut sim = scene.build(s.origin)?.integrator;
            let mut total = 0.0;
            for t in &validation {
                let e = rollout_error(&mut sim, t).map_err(anyhow::Error::msg)?;
                total += e.iter().sum::<f64>() / e.len().max(1) as f64;
            }
            Ok(total / validation.len().max(1) as f64)
        };
        let single_error = rollout(&tuned_scene)?;
        let mut ensemble_scene = tuned_scene.clone();
        let shares: Vec<String> = ensemble
            .members
            .iter()
            .map(|m| format!("{} {:.1} %", m.model, 100.0 * m.energy_share))
            .collect();
        let ensemble_error = match ensemble.spec() {
            Some(spec) => {
                ensemble_scene.material = spec;
                rollout(&ensemble_scene).unwrap_or(f64::INFINITY)
            }
            None => f64::INFINITY,
        };
        let chosen = if ensemble_error < single_error {
            tuned_scene = ensemble_scene;
            tuned_name = "tuned (ensemble; E, nu of the single fit)";
            "the ensemble"
        } else {
            "the single model"
        };
        selection = format!(
            " Model selection: an ensemble of {} fitted by both stages (energy shares {}) has validation rollout error {ensemble_error:.3e} m against {single_error:.3e} m for the single model: {chosen} is kept.",
            names.join(", "),
            shares.join(", ")
        );
    }

    // 3. Solver selection on the tuned model's own Newton systems.
    let steps = train.first().map_or(0, |t| t.steps());
    let b = bar(s.quiet, (train.len() * steps) as u64, "solver data");
    let runs: Vec<(Scene, &Path, usize)> = s
        .data
        .meta
        .trajectories
        .iter()
        .filter(|m| m.split == Split::Train)
        .map(|m| {
            let mut variant = tuned_scene.clone();
            variant.initial = m.initial.clone();
            (variant, s.origin, steps)
        })
        .collect();
    let logged = deform_learn::solver_data::collect_runs(&runs, s.candidates, |_| b.inc(1))?;
    b.finish_and_clear();
    let policy = LearnedPolicy::train(
        &logged,
        PolicyOptions {
            neighbours: 5,
            min_success: 0.9,
            factor_weight: s.factor_weight,
            young: fitted.to_young().0,
            forcing: Some((0.1, 0.9)),
        },
    );

    // 4. Solver optimisation: the largest forcing term, on the first training trajectory.
    let b = bar(s.quiet, s.max_iterations, "tune");
    let mut tune_scene = tuned_scene.clone();
    if let Some(m) = s
        .data
        .meta
        .trajectories
        .iter()
        .find(|m| m.split == Split::Train)
    {
        tune_scene.initial = m.initial.clone();
    }
    let make = |p: &[f64], _: &mut IntegratorOptions| -> Option<Box<dyn SolverPolicy>> {
        b.inc(1);
        Some(Box::new(policy.with_forcing(Some((10f64.powf(p[0]), 0.9)))))
    };
    let tuned = tune_policy(
        &[(tune_scene, s.origin, steps)],
        &make,
        &Tuning {
            start: vec![vec![-1.0], vec![-3.0]],
            range: vec![(-8.0, -0.3)],
            factor_weight: s.factor_weight,
            fallback: true,
            accuracy: s.accuracy,
            max_iterations: s.max_iterations,
        },
    )?;
    b.finish_and_clear();
    let eta_max = 10f64.powf(tuned.log10_values[0]);
    let tuned_policy = policy.with_forcing(Some((eta_max, 0.9)));

    // 5. Side by side on the test trajectories; frames of the first.
    let b = bar(s.quiet, 3, "compare");
    let build = |scene: &Scene, policy: Option<LearnedPolicy>| -> Result<(Integrator, _)> {
        let built = scene.build(s.origin)?;
        let mut sim = built.integrator;
        if let Some(p) = policy {
            sim.set_policy(Box::new(p));
        }
        Ok((sim, built.mesh))
    };
    let frames = out.join("frames");
    let base = run_model_timed(
        &|| build(s.base, None),
        &tests,
        s.subsample,
        s.factor_weight,
        Some(&frames.join("base")),
    )?;
    b.inc(1);
    let untuned = run_model_timed(
        &|| build(s.scene, None),
        &tests,
        1,
        s.factor_weight,
        Some(&frames.join("untuned")),
    )?;
    b.inc(1);
    let tuned_run = run_model_timed(
        &|| build(&tuned_scene, Some(tuned_policy.clone())),
        &tests,
        1,
        s.factor_weight,
        Some(&frames.join("tuned")),
    )?;
    b.finish_and_clear();

    let mean = |e: &[f64]| e.iter().skip(1).sum::<f64>() / (e.len().max(2) - 1) as f64;
    let (e_untuned, e_tuned) = (mean(&untuned.errors), mean(&tuned_run.errors));
    let (e0, nu0) = truth.to_young();
    let (e2, nu2) = fitted.to_young();
    let policy_name = format!(
        "learned over {} candidates, eta_max {eta_max:.2e}",
        s.candidates.len()
    );
    writeln!(
        report,
        "The cheap model steps {k}x coarser (dt = {} s) than the base (dt = {} s). Tuned: Rayleigh alpha {:.4} -> {:.4}, gamma {:.4} -> {:.4} (stage 1), Lame pair fitted through the coarse steps (stage 1, then stage 2: loss {:.3e} -> {:.3e}, {} evaluations).{selection} A solver policy learned from {} logged Newton systems of the tuned model, its largest forcing term tuned by Nelder-Mead ({} evaluations, work {:.3e}, error {:.1e} within {:e}).\n",
        s.scene.integrator.dt,
        s.base.integrator.dt,
        s.scene.integrator.alpha,
        stage1.alpha,
        s.scene.integrator.gamma,
        stage1.gamma,
        fit.initial_loss,
        fit.loss,
        fit.evaluations,
        logged.len(),
        tuned.samples.len(),
        tuned.best.work,
        tuned.best.error,
        s.accuracy,
        k = s.subsample,
    )?;
    writeln!(
        report,
        "On the {} test trajectories ({} coarse steps each; work = solve flops + {} x factorisation flops; time = whole steps, median of {TIME_REPEATS} runs):\n",
        tests.len(),
        steps,
        s.factor_weight
    )?;
    report.push_str("| model | dt | E (Pa) | nu | solver | mean RMS error vs base (m) | final RMS error (m) | work | flops | step time (s) | Newton its | fallbacks |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    // The scene's own policy (base and untuned run with it).
    let base_policy = s.base.policy.build().map_err(anyhow::Error::msg)?.name();
    // One row per model, in the report's table and in comparison.csv.
    let mut csv =
        String::from("model,mean_error,final_error,work,flops,seconds,newton,fallbacks\n");
    for (key, name, dt, (e, nu), solver, t) in [
        (
            "base",
            "base (the data)",
            s.base.integrator.dt,
            (e0, nu0),
            base_policy.clone(),
            &base,
        ),
        (
            "untuned",
            "untuned",
            s.scene.integrator.dt,
            (e0, nu0),
            base_policy.clone(),
            &untuned,
        ),
        (
            "tuned",
            tuned_name,
            s.scene.integrator.dt,
            (e2, nu2),
            policy_name.clone(),
            &tuned_run,
        ),
    ] {
        let (mean_error, final_error) = (mean(&t.errors), t.errors.last().copied().unwrap_or(0.0));
        writeln!(
            report,
            "| {name} | {dt} | {e:.4e} | {nu:.4} | {solver} | {mean_error:.3e} | {final_error:.3e} | {:.3e} | {:.3e} | {:.3} | {} | {} |",
            t.work, t.flops, t.seconds, t.newton, t.fallbacks
        )?;
        writeln!(
            csv,
            "{key},{mean_error:e},{final_error:e},{:e},{:e},{},{},{}",
            t.work, t.flops, t.seconds, t.newton, t.fallbacks
        )?;
    }
    let summary = format!(
        "tuned / untuned: error {:.2}x, work {:.2}x, time {:.2}x",
        e_tuned / e_untuned.max(f64::MIN_POSITIVE),
        tuned_run.work / untuned.work.max(f64::MIN_POSITIVE),
        tuned_run.seconds / untuned.seconds.max(f64::MIN_POSITIVE)
    );
    writeln!(
        report,
        "\n**{summary}**; against the base model the tuned one takes {:.2}x the time.\n\nParaView: `frames/base/series.pvd`, `frames/untuned/series.pvd`, `frames/tuned/series.pvd` (the first test trajectory; open together). Files: `comparison.csv`, `rollout_error.svg`/`.png`, `solver_data/`, `tuning.csv`.",
        tuned_run.seconds / base.seconds.max(f64::MIN_POSITIVE)
    )?;
    write_text(&out.join("comparison.csv"), &csv)?;
    let mut tcsv = String::from("log10_eta_max,work,error,cost\n");
    for x in &tuned.samples {
        writeln!(
            tcsv,
            "{},{:e},{:e},{:e}",
            x.log10_values[0], x.work, x.error, x.cost
        )?;
    }
    write_text(&out.join("tuning.csv"), &tcsv)?;
    logged.save(&out.join("solver_data"))?;
    plot_rollouts(
        out,
        &[
            ("untuned".to_owned(), untuned.errors.clone()),
            ("tuned".to_owned(), tuned_run.errors.clone()),
        ],
    )?;
    Ok(summary)
}
