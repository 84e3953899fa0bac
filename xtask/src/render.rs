//! Renders an [`ExperimentReport`] (data) as `report.md`, CSV files and plots. Nothing here
//! computes a figure: every number comes from the report or its methods.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::Result;
use deform_learn::compare::Choice;
use deform_learn::experiment::fit_material::FitMaterialReport;
use deform_learn::experiment::select_model::SelectModelReport;
use deform_learn::experiment::select_solver::{CaseReport, Key, PolicyRow, SelectSolverReport};
use deform_learn::experiment::story::{StoryModel, StoryReport, TIME_REPEATS};
use deform_learn::experiment::tune_solver::TuneSolverReport;
use deform_learn::experiment::{ExperimentReport, Series, TaskReport};
use deform_learn::rollout::mean_error;

use crate::plots::plot;

/// Writes the CSV files and plots of `report` into `out`; returns the markdown.
pub fn render(report: &ExperimentReport, out: &Path) -> Result<String> {
    let d = &report.dataset;
    let mut md = format!(
        "# Experiment `{}`\n\nBase scene: `{}` ({} vertices, {} tets), material `{:?}`.\n\nDataset: {} trajectories x {} steps (seed {}), split {:?} train/validation (rest test), noise {:?}. Saved in `dataset/` (RON + .npy, see docs/experiments.md). The learned model steps with dt = {} s ({}x the base's).\n\n",
        report.name,
        report.scene.display(),
        report.vertices,
        report.tets,
        report.material,
        d.trajectories,
        d.steps,
        d.seed,
        d.split,
        d.noise,
        report.learned_dt,
        d.subsample
    );
    match &report.task {
        TaskReport::FitMaterial(r) => fit_material(r, out, &mut md)?,
        TaskReport::SelectModel(r) => select_model(r, out, &mut md)?,
        TaskReport::SelectSolver(r) => select_solver(r, out, &mut md)?,
        TaskReport::TuneBackwardEuler(r) => story(r, out, &mut md)?,
        TaskReport::TuneSolver(r) => tune_solver(r, &mut md)?,
    }
    writeln!(md, "\nTotal time {:.1} s.", report.seconds)?;
    Ok(md)
}

/// `rollout_error.svg` and `.png`: RMS position error per step of each series.
fn plot_rollouts(out: &Path, series: &[Series]) -> Result<()> {
    plot(
        &out.join("rollout_error"),
        "test rollout RMS position error",
        "step",
        "m",
        series,
        false,
    )
}

fn fit_material(r: &FitMaterialReport, out: &Path, md: &mut String) -> Result<()> {
    if let Some((prior, stage1)) = r.started_from_prior {
        writeln!(
            md,
            "Stage 2 starts from the prior (loss {prior:.3e}) rather than the stage-1 estimate (loss {stage1:.3e}).\n"
        )?;
    }
    let mut losses = Vec::new();
    if let Some(fit) = &r.output_error {
        losses.extend(fit.iterations.iter().map(|it| it.loss));
        writeln!(
            md,
            "Output error: {} iterations, {} loss evaluations, loss {:.4e} -> {:.4e}, termination {:?}.\n",
            fit.iterations.len(),
            fit.evaluations,
            fit.initial_loss,
            fit.loss,
            fit.termination
        )?;
    }
    plot(
        &out.join("loss"),
        "output-error loss per iteration",
        "iteration",
        "loss",
        &[Series::new("loss", losses)],
        true,
    )?;
    md.push_str(
        "| parameters | E (Pa) | nu | E error | nu error | fit time |\n|---|---|---|---|---|---|\n",
    );
    let (e0, nu0) = (r.rows[0].young, r.rows[0].poisson);
    for row in &r.rows {
        writeln!(
            md,
            "| {} | {:.5e} | {:.5} | {:.3} % | {:.3} % | {} |",
            row.estimate.name(),
            row.young,
            row.poisson,
            100.0 * (row.young - e0).abs() / e0,
            100.0 * (row.poisson - nu0).abs() / nu0,
            row.seconds.map_or("-".to_owned(), |s| format!("{s:.2} s"))
        )?;
    }
    plot_rollouts(out, &r.rollouts)?;
    writeln!(
        md,
        "\nRMS position error of free rollouts on the test trajectories, averaged over the predicted states: {}. Fitted / true parameters: {:.3}.\n\nFiles: `iterations.csv`, `loss.svg`/`.png`, `rollout_error.csv`, `rollout_error.svg`/`.png`.",
        r.rollouts
            .iter()
            .map(|s| format!("{} {:.3e} m", s.name, mean_error(&s.values)))
            .collect::<Vec<_>>()
            .join(", "),
        r.rollout_ratio()
    )?;
    Ok(())
}

fn select_model(r: &SelectModelReport, out: &Path, md: &mut String) -> Result<()> {
    md.push_str(
        "| member | effective mu | effective lambda | energy share (test) |\n|---|---|---|---|\n",
    );
    for m in &r.ensemble.members {
        writeln!(
            md,
            "| {} | {:.5e} | {:.5e} | {:.2} % |",
            m.model,
            m.mu,
            m.lambda,
            100.0 * m.energy_share
        )?;
    }
    writeln!(
        md,
        "\nEquation-error residual {:.3e}.",
        r.ensemble.relative_residual
    )?;
    if let Some(st) = &r.stage2 {
        writeln!(
            md,
            "Stage 2 (output error, the pairs above are its result): loss {:.3e} -> {:.3e} in {} iterations, {} evaluations ({:?}).",
            st.initial_loss,
            st.loss,
            st.iterations.len(),
            st.evaluations,
            st.termination
        )?;
    }
    md.push_str(
        "\n| model | validation rollout error (m) | test rollout error (m) |\n|---|---|---|\n",
    );
    for m in &r.models {
        let name = m
            .member
            .map_or("ensemble".to_owned(), |m| format!("{m} alone"));
        writeln!(md, "| {name} | {:.4e} | {:.4e} |", m.validation, m.test)?;
    }
    if let (Some(best), Some(ens)) = (r.best_single(), r.ensemble_errors()) {
        // Below a nanometre both are rounding noise; a ratio of two would mislead.
        let verdict = if ens.test.max(best.test) < 1e-9 {
            "both at rounding level (below 1e-9 m): equal".to_owned()
        } else {
            format!("{:.3}", ens.test / best.test.max(f64::MIN_POSITIVE))
        };
        writeln!(
            md,
            "\nBest single model by validation error: {} (test {:.4e} m). Ensemble test error / best single model's: {verdict}.",
            best.member.map_or("-".to_owned(), |m| m.to_string()),
            best.test
        )?;
    }
    plot_rollouts(out, &r.rollouts)
}

fn select_solver(r: &SelectSolverReport, out: &Path, md: &mut String) -> Result<()> {
    if let Some(t) = &r.tuning {
        writeln!(
            md,
            "Tuned for the learned policy: {} ({} evaluations on the first training trajectory{}, work {:.4e}, error {:.1e} within {:e}; every evaluation in `tuning.csv`).",
            t.settings.label(),
            t.evaluations,
            t.scenes
                .iter()
                .map(|s| format!(" and `{}`", s.display()))
                .collect::<String>(),
            t.best.work,
            t.best.error,
            t.accuracy
        )?;
    }
    for (ci, case) in r.cases.iter().enumerate() {
        policy_case(r, ci, case, out, md)?;
    }
    writeln!(
        md,
        "\n{} logged Newton iterations from {} training trajectories and {} more training scenes; data in `solver_data/`.",
        r.logged, r.training_trajectories, r.also_train
    )?;
    Ok(())
}

/// One case of the policy comparison: its table, CSV rows, plots and ratios.
fn policy_case(
    r: &SelectSolverReport,
    ci: usize,
    case: &CaseReport,
    out: &Path,
    md: &mut String,
) -> Result<()> {
    writeln!(
        md,
        "\n### {}\n\nWork = solve flops + {} x factorisation flops; solver s / step s: median linear-solver / whole Newton-loop time over {} run(s); error: max position deviation from direct solves at Newton rel 1e-10, relative to the largest coordinate.\n\n| policy | flops | work | solver s | step s | Newton its | linear its | error | fallbacks |\n|---|---|---|---|---|---|---|---|---|",
        case.label, r.factor_weight, r.repeats
    )?;
    for row in &case.rows {
        let (name, m) = (row.contender.name(), &row.measured);
        let error = if m.failed {
            "failed".to_owned()
        } else {
            format!("{:.1e}", m.error)
        };
        writeln!(
            md,
            "| {name} | {:.4e} | {:.4e} | {:.3} | {:.3} | {} | {} | {error} | {} |",
            m.flops, m.work, m.seconds, m.step_seconds, m.newton, m.linear, m.fallbacks
        )?;
        if !m.deterministic {
            writeln!(md, "(flops of `{name}` differed between repeats)")?;
        }
    }
    policy_plots(r, ci, case, out)?;
    writeln!(
        md,
        "\nPlots: `case{ci}_work.svg`/`.png` (work per step), `case{ci}_newton.svg`/`.png` (Newton iterations per step), `case{ci}_choices.svg`/`.png` and `.csv` (the learned policy's solver at every Newton iteration)."
    )?;
    ratios(case, md)
}

fn policy_plots(r: &SelectSolverReport, ci: usize, case: &CaseReport, out: &Path) -> Result<()> {
    let stem = |what: &str| out.join(format!("case{ci}_{what}"));
    let per_step = |f: &dyn Fn(&(f64, usize)) -> f64| -> Vec<Series> {
        case.rows
            .iter()
            .map(|row| {
                Series::new(
                    row.contender.name(),
                    row.measured.per_step.iter().map(f).collect(),
                )
            })
            .collect()
    };
    plot(
        &stem("work"),
        &format!("work per step: {}", case.label),
        "step",
        "work",
        &per_step(&|p| p.0),
        true,
    )?;
    plot(
        &stem("newton"),
        &format!("Newton iterations per step: {}", case.label),
        "step",
        "iterations",
        &per_step(&|p| p.1 as f64),
        false,
    )?;
    if let Some(learned) = case.learned() {
        let index = |c: &Choice| {
            r.candidates
                .iter()
                .position(|s| !c.fallback && *s == c.solver)
                .map_or(-1.0, |i| i as f64)
        };
        let choices = &learned.measured.choices;
        plot(
            &stem("choices"),
            &format!(
                "learned policy's solver per Newton iteration: {}",
                case.label
            ),
            "Newton iteration (all steps)",
            "candidate index (-1: fallback)",
            &[Series::new("learned", choices.iter().map(index).collect())],
            false,
        )?;
    }
    Ok(())
}

/// The best fixed solver in hindsight, by work and by time, against the others: among
/// every fixed candidate, and among those that set up afresh for every solve.
fn ratios(case: &CaseReport, md: &mut String) -> Result<()> {
    writeln!(
        md,
        "\nRatios to the best fixed solver in hindsight (within 1e-6), by work, by linear-solver time and by whole-step time, each picked separately; \"without reuse\": among the fixed solvers that set up afresh for every solve (a fresh factorisation, IC(0), ...), stale-factor PCG being a schedule:\n"
    )?;
    let keys = [Key::Work, Key::SolverSeconds, Key::StepSeconds];
    let refs = [("best fixed", false), ("best fixed without reuse", true)];
    let mut header = String::from("| policy |");
    let mut rule = String::from("|---|");
    for (label, without_reuse) in refs {
        let name = |k| {
            case.best_fixed(without_reuse, k)
                .map_or("-".to_owned(), |r| r.contender.name())
        };
        header += &format!(
            " work / {label} (`{}`) | solver s / {label} (`{}`) | step s / {label} (`{}`) |",
            name(Key::Work),
            name(Key::SolverSeconds),
            name(Key::StepSeconds)
        );
        rule += "---|---|---|";
    }
    writeln!(md, "{header}\n{rule}")?;
    for row in case.rows.iter().filter(|r| !r.contender.is_fixed()) {
        let mut line = format!("| {} |", row.contender.name());
        for (_, without_reuse) in refs {
            for key in keys {
                let ratio = case
                    .best_fixed(without_reuse, key)
                    .map_or("-".to_owned(), |b| {
                        format!(
                            "{:.3}",
                            key.of(&row.measured) / key.of(&b.measured).max(f64::MIN_POSITIVE)
                        )
                    });
                line += &format!(" {ratio} |");
            }
        }
        if !row.within_accuracy() {
            line += " (outside the 1e-6 accuracy bound)";
        }
        writeln!(md, "{line}")?;
    }
    // What the solver choice adds on top of the tuned Newton settings.
    if let (Some(l), Some(d)) = (case.learned(), case.tuned_direct())
        && l.contender.settings().is_some()
    {
        let ratio = |k: Key, a: &PolicyRow, b: &PolicyRow| {
            k.of(&a.measured) / k.of(&b.measured).max(f64::MIN_POSITIVE)
        };
        writeln!(
            md,
            "\nSolver choice alone: `{}` / `{}` (the same Newton settings): {:.3} work, {:.3} solver time, {:.3} step time.",
            l.contender.name(),
            d.contender.name(),
            l.measured.work / d.measured.work,
            ratio(Key::SolverSeconds, l, d),
            ratio(Key::StepSeconds, l, d)
        )?;
    }
    Ok(())
}

fn story(r: &StoryReport, out: &Path, md: &mut String) -> Result<()> {
    let (base, coarse) = (&r.rows[0], &r.rows[1]);
    let selection = r.selection.as_ref().map_or(String::new(), |s| {
        let shares: Vec<String> = s
            .members
            .iter()
            .map(|m| format!("{} {:.1} %", m.model, 100.0 * m.energy_share))
            .collect();
        let names: Vec<String> = s.members.iter().map(|m| m.model.to_string()).collect();
        format!(
            " Model selection: an ensemble of {} fitted by both stages (energy shares {}) has validation rollout error {:.3e} m against {:.3e} m for the single model: {} is kept.",
            names.join(", "),
            shares.join(", "),
            s.ensemble_error,
            s.single_error,
            if s.ensemble_kept { "the ensemble" } else { "the single model" }
        )
    });
    writeln!(
        md,
        "The cheap model steps {k}x coarser (dt = {} s) than the base (dt = {} s). Tuned: Rayleigh alpha {:.4} -> {:.4}, gamma {:.4} -> {:.4} (stage 1), Lame pair fitted through the coarse steps (stage 1, then stage 2: loss {:.3e} -> {:.3e}, {} evaluations).{selection} A solver policy learned from {} logged Newton systems of the tuned model, its largest forcing term tuned by Nelder-Mead ({} evaluations, work {:.3e}, error {:.1e} within {:e}).\n",
        coarse.dt,
        base.dt,
        r.damping_before.0,
        r.damping_after.0,
        r.damping_before.1,
        r.damping_after.1,
        r.fit.initial_loss,
        r.fit.loss,
        r.fit.evaluations,
        r.logged,
        r.tuning.samples.len(),
        r.tuning.best.work,
        r.tuning.best.error,
        r.accuracy,
        k = r.subsample,
    )?;
    writeln!(
        md,
        "On the {} test trajectories ({} coarse steps each; work = solve flops + {} x factorisation flops; time = whole steps, median of {TIME_REPEATS} runs):\n",
        r.tests, r.steps, r.factor_weight
    )?;
    md.push_str("| model | dt | E (Pa) | nu | solver | mean RMS error vs base (m) | final RMS error (m) | work | flops | step time (s) | Newton its | fallbacks |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    let kept = r.selection.as_ref().is_some_and(|s| s.ensemble_kept);
    for t in &r.rows {
        let name = match t.model {
            StoryModel::Base => "base (the data)",
            StoryModel::Tuned if kept => "tuned (ensemble; E, nu of the single fit)",
            model => model.name(),
        };
        let (mean, last) = (t.mean_error(), t.final_error());
        writeln!(
            md,
            "| {name} | {} | {:.4e} | {:.4} | {} | {mean:.3e} | {last:.3e} | {:.3e} | {:.3e} | {:.3} | {} | {} |",
            t.dt, t.young, t.poisson, t.solver, t.work, t.flops, t.seconds, t.newton, t.fallbacks
        )?;
    }
    let (e, w, t) = r.ratios();
    writeln!(
        md,
        "\n**tuned / untuned: error {e:.2}x, work {w:.2}x, time {t:.2}x**; against the base model the tuned one takes {:.2}x the time.\n\nParaView: `frames/base/series.pvd`, `frames/untuned/series.pvd`, `frames/tuned/series.pvd` (the first test trajectory; open together). Files: `comparison.csv`, `rollout_error.svg`/`.png`, `solver_data/`, `tuning.csv`.",
        r.time_against_base()
    )?;
    plot_rollouts(
        out,
        &[
            Series::new("untuned", r.rows[1].errors.clone()),
            Series::new("tuned", r.rows[2].errors.clone()),
        ],
    )
}

fn tune_solver(r: &TuneSolverReport, md: &mut String) -> Result<()> {
    let names: Vec<String> = r.parameters.iter().map(|p| format!("{p:?}")).collect();
    let (best, configured) = (&r.result.best, &r.result.samples[0]);
    writeln!(
        md,
        "Tuned `{}` ({}): {}, work {:.4e} over {} steps (factorisation flops x {}), trajectory error {:.1e} (bound {:e}); {} evaluations (`tuning.csv`).\n\nAs configured ({}): work {:.4e}, error {:.1e}; tuned / configured: {:.3}.",
        r.solver.name(),
        names.join(", "),
        r.tuned_values(),
        best.work,
        r.steps,
        r.factor_weight,
        best.error,
        r.accuracy,
        r.result.samples.len(),
        r.values(&configured.log10_values),
        configured.work,
        configured.error,
        r.work_ratio()
    )?;
    Ok(())
}
