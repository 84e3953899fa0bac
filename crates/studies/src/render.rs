//! Renders an [`ExperimentReport`] (data) as `report.md` and draws the plots it describes.
//! Nothing here computes a figure: every number comes from the report or its methods.

use std::fmt::Write as _;
use std::path::Path;

use crate::coarsen::{CoarseModel, CoarsenReport};
use crate::fit_material::{ContactParameters, FitMaterialReport};
use crate::select_model::{ROUNDING_LEVEL, SelectModelReport};
use crate::select_solver::{CaseReport, Key, SelectSolverReport};
use crate::story::{StoryModel, StoryReport, TIME_REPEATS};
use crate::tune_solver::TuneSolverReport;
use crate::{Data, ExperimentReport, TaskReport};
use deform_learn::output::{OutputErrorFit, Termination};
use deform_learn::rollout::mean_error;

use crate::error::Result;
use crate::plot::plot;

/// Renders `report` into `out` (its plots as SVG and PNG, its markdown as `report.md` and
/// the same as a self-contained `report.html` with the plots inline, each written
/// atomically); returns the markdown. The runner and the Python module both write
/// reports through it, so they write the same files.
///
/// # Errors
/// A plot that cannot be drawn, or a file that cannot be written.
pub fn write_report(report: &ExperimentReport, out: &Path) -> Result<String> {
    let markdown = render(report, out)?;
    deform_fs::write_text(&out.join("report.md"), &markdown)?;
    let title = format!("Experiment {}", report.name);
    let page = crate::html::page(&title, &markdown, out)?;
    deform_fs::write_text(&out.join("report.html"), &page)?;
    Ok(markdown)
}

/// Draws the plots of `report` into `out`; returns its markdown.
///
/// # Errors
/// A plot that cannot be drawn or written.
pub fn render(report: &ExperimentReport, out: &Path) -> Result<String> {
    let data = match &report.data {
        Data::Generate(d) => format!(
            "Dataset: {} trajectories x {} steps (seed {}), split {:?} train/validation (rest test), {}.",
            d.trajectories,
            d.steps,
            d.seed,
            d.split,
            noise(d.noise)
        ),
        Data::Import(i) => format!(
            "Dataset: {} trajectories imported (dt {} s, gravity {:?}, {:?} mass; first `{}`), split {:?} train/validation (rest test), {}. The scene is the model to learn: its own parameters (rows named truth or true) are the truth only if the data were made with them.",
            i.trajectories.len(),
            i.dt,
            i.gravity,
            i.mass,
            i.trajectories[0].positions.display(),
            i.split,
            noise(i.noise)
        ),
    };
    // Coarsening learns a model per coarse step, each in its own section.
    let steps = match &report.task {
        TaskReport::Coarsen(_) => {
            "The coarse models step with the multiples of the data's dt their sections name."
                .to_owned()
        }
        _ => format!(
            "The learned model steps with dt = {} s ({}x the data's).",
            report.learned_dt,
            report.data.subsample()
        ),
    };
    let mut md = format!(
        "# Experiment `{}`\n\nBase scene: `{}` ({} vertices, {} tets), material `{}`.\n\n{data} Saved in `dataset/` (RON + .npy, see docs/experiments.md). {steps}\n\n",
        report.name,
        report.scene.display(),
        report.vertices,
        report.tets,
        ron::to_string(&report.material).unwrap_or_else(|_| format!("{:?}", report.material)),
    );
    match &report.task {
        TaskReport::FitMaterial(r) => fit_material(r, &mut md)?,
        TaskReport::SelectModel(r) => select_model(r, &mut md)?,
        TaskReport::SelectSolver(r) => select_solver(r, &mut md)?,
        TaskReport::TuneBackwardEuler(r) => story(r, &mut md)?,
        TaskReport::TuneSolver(r) => tune_solver(r, &mut md)?,
        TaskReport::Coarsen(r) => coarsen(r, matches!(report.data, Data::Import(_)), &mut md)?,
    }
    files(report, out, &mut md)?;
    writeln!(md, "\nTotal time {:.1} s.", report.seconds)?;
    Ok(md)
}

/// The noise a dataset was given, in words.
fn noise(noise: Option<deform_learn::Noise>) -> String {
    match noise {
        None => "no noise added".into(),
        Some(n) => format!(
            "Gaussian noise added (positions {} x their RMS displacement, velocities {} x their RMS, seed {})",
            n.position, n.velocity, n.seed
        ),
    }
}

/// Draws the report's plots, embeds each one drawn (a plot without a point is not drawn)
/// and lists the files: the tables' CSV and the plots, each of which exists.
fn files(report: &ExperimentReport, out: &Path, md: &mut String) -> Result<()> {
    let mut names: Vec<String> = report.csv_files().into_iter().map(|(n, _)| n).collect();
    let mut embedded = Vec::new();
    for p in report.plots() {
        if plot(&out.join(&p.stem), &p)? {
            embedded.push(format!("![{}]({}.svg)", p.title, p.stem));
            names.push(format!("{}.svg", p.stem));
            names.push(format!("{}.png", p.stem));
        }
    }
    if !embedded.is_empty() {
        writeln!(md, "\n## Plots\n\n{}", embedded.join("\n\n"))?;
    }
    let names: Vec<String> = names.iter().map(|n| format!("`{n}`")).collect();
    writeln!(md, "\nFiles: {}.", names.join(", "))?;
    Ok(())
}

/// Contact's parameters in a material fit: the scene's, stage 1's and (friction, when it
/// fitted them) stage 2's, with their relative differences from the scene's.
fn contact_parameters(c: &ContactParameters, md: &mut String) -> Result<()> {
    let stage2 = c.output_error.as_ref();
    md.push_str(match stage2 {
        None => "\nContact's parameters (stage 1 fits them with the material):\n\n| parameter | scene | equation error | difference |\n|---|---|---|---|\n",
        Some(_) => "\nContact's parameters (stage 1 fits them with the material, stage 2 fits friction again):\n\n| parameter | scene | equation error | difference | output error | difference |\n|---|---|---|---|---|---|\n",
    });
    let cell = |scene: f64, fit: Option<f64>| match fit {
        Some(f) if scene != 0.0 => format!("{f:.5e} | {:.3} %", 100.0 * (f - scene).abs() / scene),
        Some(f) => format!("{f:.5e} | -"),
        None => "not fitted | -".into(),
    };
    let row = |md: &mut String, name: String, (scene, fit): (f64, Option<f64>), two| {
        let last = match stage2 {
            Some(_) => format!(" {} |", cell(scene, two)),
            None => String::new(),
        };
        writeln!(md, "| {name} | {scene:.5e} | {} |{last}", cell(scene, fit))
    };
    row(md, "kappa (N/m)".into(), c.kappa, None)?;
    let own = c.self_contact.then(|| c.friction.len() - 1);
    for (i, mu) in c.friction.iter().enumerate() {
        let name = match own == Some(i) {
            true => "mu, self-contact".to_owned(),
            false => format!("mu, obstacle {i}"),
        };
        row(md, name, *mu, stage2.map(|m| m[i]))?;
    }
    md.push('\n');
    Ok(())
}

fn fit_material(r: &FitMaterialReport, md: &mut String) -> Result<()> {
    if let Some(why) = &r.stage1_unusable {
        writeln!(md, "The stage-1 estimate is unusable: {why}.\n")?;
    }
    if let Some((prior, stage1)) = r.started_from_prior {
        writeln!(
            md,
            "Stage 2 starts from the prior (loss {prior:.3e}) rather than the stage-1 estimate (loss {stage1:.3e}).\n"
        )?;
    }
    if let Some(why) = &r.unstable {
        writeln!(
            md,
            "Stage 2's model failed a free rollout of a training trajectory ({why}): rejected, the output-error row holds its start.\n"
        )?;
    }
    if let Some(fit) = &r.output_error {
        let (its, n, l0, loss, t) = summary(fit);
        writeln!(
            md,
            "Output error: {its} iterations, {n} loss evaluations, loss {l0:.4e} -> {loss:.4e}, termination {t:?}.\n"
        )?;
        if let Some(c) = fit.start_correction {
            writeln!(
                md,
                "Rollout starts estimated with the parameters: RMS correction of the data's start positions {c:.3e} m.\n"
            )?;
        }
    }
    md.push_str(if r.truth_known() {
        "| parameters | E (Pa) | nu | E error | nu error | fit time |\n|---|---|---|---|---|---|\n"
    } else {
        "| parameters | E (Pa) | nu | E change from the scene's guess | nu change | fit time |\n|---|---|---|---|---|---|\n"
    });
    for (i, row) in r.rows.iter().enumerate() {
        let (name, young, poisson, seconds) =
            (row.estimate.name(), row.young, row.poisson, row.seconds);
        let (de, dnu) = r.errors(i);
        let time = seconds.map_or("-".to_owned(), |s| format!("{s:.2} s"));
        writeln!(
            md,
            "| {name} | {young:.5e} | {poisson:.5} | {:.3} % | {:.3} % | {time} |",
            100.0 * de,
            100.0 * dnu
        )?;
    }
    if let Some(c) = &r.contact {
        contact_parameters(c, md)?;
    }
    let errors: Vec<String> = r
        .rollouts
        .iter()
        .map(|s| format!("{} {:.3e} m", s.name, mean_error(&s.values)))
        .collect();
    writeln!(
        md,
        "\nRMS position error of free rollouts on the test trajectories, averaged over the predicted states: {}; {}.",
        errors.join(", "),
        r.rollout_phrase()
    )?;
    Ok(())
}

/// Iterations, evaluations, initial and final loss and termination of an output-error fit.
fn summary(fit: &OutputErrorFit) -> (u64, usize, f64, f64, &Termination) {
    let f = fit;
    (
        f.iteration_count(),
        f.evaluations,
        f.initial_loss,
        f.loss,
        &f.termination,
    )
}

fn select_model(r: &SelectModelReport, md: &mut String) -> Result<()> {
    for m in r.models.iter().filter(|m| m.unstable.is_some()) {
        let name = m
            .member
            .map_or("The ensemble".to_owned(), |n| n.to_string());
        let why = m.unstable.as_deref().unwrap_or_default();
        writeln!(
            md,
            "{name}'s stage-2 fit failed a free rollout ({why}): rejected, its stage-1 fit stands.\n"
        )?;
    }
    for e in &r.ensemble.excluded {
        writeln!(
            md,
            "{} is left out: the data leave its domain (trajectory {}, step {}, element {}: det F = {:.3e}), so it cannot have made them.\n",
            e.model, e.trajectory, e.step, e.element, e.det
        )?;
    }
    md.push_str(
        "| member | effective mu | effective lambda | energy share (test) |\n|---|---|---|---|\n",
    );
    for m in &r.ensemble.members {
        let (model, mu, lambda, energy_share) = (m.model, m.mu, m.lambda, m.energy_share);
        writeln!(
            md,
            "| {model} | {mu:.5e} | {lambda:.5e} | {:.2} % |",
            100.0 * energy_share
        )?;
    }
    writeln!(
        md,
        "\nEquation-error residual {:.3e}.",
        r.ensemble.relative_residual
    )?;
    if let Some(st) = &r.stage2 {
        let (its, n, l0, loss, t) = summary(st);
        writeln!(
            md,
            "Stage 2 (output error, the pairs above are its result): loss {l0:.3e} -> {loss:.3e} in {its} iterations, {n} evaluations ({t:?})."
        )?;
    }
    md.push_str(
        "\n| model | validation rollout error (m) | test rollout error (m) |\n|---|---|---|\n",
    );
    for m in &r.models {
        let (member, validation, test) = (m.member, m.validation, m.test);
        let name = member.map_or("ensemble".to_owned(), |m| format!("{m} alone"));
        writeln!(md, "| {name} | {validation:.4e} | {test:.4e} |")?;
    }
    if r.best_single().is_none() {
        writeln!(
            md,
            "\nNo single model could be fitted and rolled out on the validation trajectories."
        )?;
    }
    if let (Some(best), Some(ratio)) = (r.best_single(), r.ensemble_over_best()) {
        let verdict = ratio.map_or_else(
            || format!("both at rounding level (below {ROUNDING_LEVEL:e} m): equal"),
            |x| format!("{x:.3}"),
        );
        let name = best.member.map_or("-".to_owned(), |m| m.to_string());
        writeln!(
            md,
            "\nBest single model by validation error: {name} (test {:.4e} m). Ensemble test error / best single model's: {verdict}.",
            best.test
        )?;
    }
    Ok(())
}

fn select_solver(r: &SelectSolverReport, md: &mut String) -> Result<()> {
    if let Some(t) = &r.tuning {
        let (label, n, accuracy) = (t.settings.label(), t.evaluations, t.accuracy);
        let also: String = t
            .scenes
            .iter()
            .map(|s| format!(" and `{}`", s.display()))
            .collect();
        writeln!(
            md,
            "Tuned for the learned policy: {label} ({n} evaluations on the first training trajectory{also}, work {:.4e}, error {:.1e} within {accuracy:e}; every evaluation in `tuning.csv`).",
            t.best.work, t.best.error
        )?;
    }
    for case in &r.cases {
        policy_case(r, case, md)?;
    }
    let (n, trajectories, scenes) = (r.logged, r.training_trajectories, r.also_train);
    writeln!(
        md,
        "\n{n} logged Newton iterations from {trajectories} training trajectories and {scenes} more training scenes; data in `solver_data/`."
    )?;
    Ok(())
}

/// One case of the policy comparison: its table, CSV rows, plots and ratios.
fn policy_case(r: &SelectSolverReport, case: &CaseReport, md: &mut String) -> Result<()> {
    let (label, weight, repeats) = (&case.label, r.weights, r.repeats);
    writeln!(
        md,
        "\n### {label}\n\nWork = {weight}; solver s / step s: median linear-solver / whole Newton-loop time over {repeats} run(s); error: max position deviation from direct solves at Newton rel 1e-10, relative to the largest coordinate.\n\n| policy | flops | work | solver s | step s | Newton its | linear its | error | fallbacks |\n|---|---|---|---|---|---|---|---|---|"
    )?;
    for row in &case.rows {
        let name = row.contender.name();
        let m = &row.measured;
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
    ratios(case, md)
}

/// The best fixed solver in hindsight, by work and by time, against the others: among
/// every fixed candidate, and among those that set up afresh for every solve.
fn ratios(case: &CaseReport, md: &mut String) -> Result<()> {
    md.push_str("\nRatios to the best fixed solver in hindsight (within 1e-6), by work, by linear-solver time and by whole-step time, each picked separately; \"without reuse\": among the fixed solvers that set up afresh for every solve (a fresh factorisation, IC(0), ...), stale-factor PCG being a schedule:\n\n| policy |");
    let refs = [("best fixed", false), ("best fixed without reuse", true)];
    for (label, without_reuse) in refs {
        let name = |k| {
            case.best_fixed(without_reuse, k)
                .map_or("-".to_owned(), |r| r.contender.name())
        };
        let [w, s, t] = Key::ALL.map(name);
        write!(
            md,
            " work / {label} (`{w}`) | solver s / {label} (`{s}`) | step s / {label} (`{t}`) |"
        )?;
    }
    md.push_str("\n|---|---|---|---|---|---|---|\n");
    for row in case.rows.iter().filter(|r| !r.contender.is_fixed()) {
        write!(md, "| {} |", row.contender.name())?;
        for (key, (_, without_reuse)) in refs.iter().flat_map(|r| Key::ALL.map(|k| (k, *r))) {
            let ratio = case.ratio_to_best(row, without_reuse, key);
            write!(
                md,
                " {} |",
                ratio.map_or("-".to_owned(), |x| format!("{x:.3}"))
            )?;
        }
        let outside = if row.within_accuracy() {
            ""
        } else {
            " (outside the 1e-6 accuracy bound)"
        };
        writeln!(md, "{outside}")?;
    }
    // What the solver choice adds on top of the tuned Newton settings.
    if let Some((l, d, [w, s, t])) = case.solver_choice_alone() {
        let (l, d) = (l.contender.name(), d.contender.name());
        writeln!(
            md,
            "\nSolver choice alone: `{l}` / `{d}` (the same Newton settings): {w:.3} work, {s:.3} solver time, {t:.3} step time."
        )?;
    }
    Ok(())
}

fn story(r: &StoryReport, md: &mut String) -> Result<()> {
    let (base, coarse) = (&r.rows[0], &r.rows[1]);
    let selection = r.selection.as_ref().map_or(String::new(), |s| {
        let shares: Vec<String> = s.members.iter().map(|m| format!("{} {:.1} %", m.model, 100.0 * m.energy_share)).collect();
        let names: Vec<String> = s.members.iter().map(|m| m.model.to_string()).collect();
        let kept = if s.ensemble_kept { "the ensemble" } else { "the single model" };
        let unstable = s.ensemble_unstable.as_ref().map_or(String::new(), |why| format!(" (the ensemble failed a free rollout: {why})"));
        format!(" Model selection: an ensemble of {} fitted by both stages (energy shares {}) has validation rollout error {:.3e} m against {:.3e} m for the single model: {kept} is kept{unstable}.", names.join(", "), shares.join(", "), s.ensemble_error, s.single_error)
    });
    if let Some(why) = &r.unstable {
        writeln!(
            md,
            "Stage 2's Lame pair failed a free rollout ({why}): rejected, stage 1's pair stands.\n"
        )?;
    }
    let ((a0, g0), (a1, g1), fit, tuning) =
        (r.damping_before, r.damping_after, &r.fit, &r.tuning.best);
    let (k, logged, n, accuracy) = (r.subsample, r.logged, r.tuning.samples.len(), r.accuracy);
    writeln!(
        md,
        "The cheap model steps {k}x coarser (dt = {} s) than the base (dt = {} s). Tuned: Rayleigh alpha {a0:.4} -> {a1:.4}, gamma {g0:.4} -> {g1:.4} (stage 1), Lame pair fitted through the coarse steps (stage 1, then stage 2: loss {:.3e} -> {:.3e}, {} evaluations).{selection} A solver policy learned from {logged} logged Newton systems of the tuned model, its largest forcing term tuned by Nelder-Mead ({n} evaluations, work {:.3e}, error {:.1e} within {accuracy:e}).\n",
        coarse.dt, base.dt, fit.initial_loss, fit.loss, fit.evaluations, tuning.work, tuning.error
    )?;
    let (tests, steps, weight) = (r.tests, r.steps, r.weights);
    writeln!(
        md,
        "On the {tests} test trajectories ({steps} coarse steps each; work = {weight}; time = whole steps, median of {TIME_REPEATS} runs):\n"
    )?;
    md.push_str("| model | dt | E (Pa) | nu | solver | mean RMS error vs base (m) | final RMS error (m) | work | flops | step time (s) | Newton its | fallbacks |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    let kept = r.selection.as_ref().is_some_and(|s| s.ensemble_kept);
    for row in &r.rows {
        let name = match row.model {
            StoryModel::Base => "base (the data)",
            StoryModel::Tuned if kept => "tuned (ensemble; E, nu of the single fit)",
            model => model.name(),
        };
        let (mean, last) = (row.mean_error(), row.final_error());
        writeln!(
            md,
            "| {name} | {} | {:.4e} | {:.4} | {} | {mean:.3e} | {last:.3e} | {:.3e} | {:.3e} | {:.3} | {} | {} |",
            row.dt,
            row.young,
            row.poisson,
            row.solver,
            row.work,
            row.flops,
            row.seconds,
            row.newton,
            row.fallbacks
        )?;
    }
    let ((e, w, t), against_base) = (r.ratios(), r.time_against_base());
    writeln!(
        md,
        "\n**tuned / untuned: error {e:.2}x, work {w:.2}x, time {t:.2}x**; against the base model the tuned one takes {against_base:.2}x the time.\n\nParaView: `frames/base/series.pvd`, `frames/untuned/series.pvd`, `frames/tuned/series.pvd` (the first test trajectory; open together); the solver's training data in `solver_data/`."
    )?;
    Ok(())
}

fn tune_solver(r: &TuneSolverReport, md: &mut String) -> Result<()> {
    let names: Vec<String> = r.parameters.iter().map(|p| format!("{p:?}")).collect();
    let (best, configured) = (&r.result.best, &r.result.samples[0]);
    let (solver, tuned, steps, weight, accuracy, n) = (
        r.solver.name(),
        r.tuned_values(),
        r.steps,
        r.weights,
        r.accuracy,
        r.result.samples.len(),
    );
    writeln!(
        md,
        "Tuned `{solver}` ({}): {tuned}, work {:.4e} over {steps} steps ({weight}), trajectory error {:.1e} (bound {accuracy:e}); {n} evaluations (`tuning.csv`).\n\nAs configured ({}): work {:.4e}, error {:.1e}; tuned / configured: {:.3}.",
        names.join(", "),
        best.work,
        best.error,
        r.values(&configured.log10_values),
        configured.work,
        configured.error,
        r.work_ratio()
    )?;
    Ok(())
}

fn coarsen(r: &CoarsenReport, imported: bool, md: &mut String) -> Result<()> {
    let m = &r.mapping;
    let held_out = if imported {
        "the data's test split (the truth); the fine cost is deform's fine model (the experiment's scene) on them"
    } else {
        "simulated by the fine model (the truth)"
    };
    writeln!(
        md,
        "The fine model's trajectories are carried onto a coarse mesh of {} vertices and {} tets ({:.1}x fewer; {} coarse vertices outside the fine mesh, at most {:.2e} m away). Held-out motions: {:.2} s in all, {held_out}. Cost = wall time per simulated second of those motions.\n",
        m.vertices, m.tets, m.ratio, m.outside, m.max_distance, r.test_seconds
    )?;
    if let Some(material) = &r.material {
        let spec = ron::ser::to_string(material)?;
        writeln!(
            md,
            "The fitted models' material (the untuned one keeps the base's): `{spec}`; every field fits its term coefficients.\n"
        )?;
    }
    for c in &r.cases {
        let tried: Vec<String> = c
            .regularisation
            .iter()
            .map(|(w, e)| format!("{w:e}: {e:.3e} m"))
            .collect();
        writeln!(
            md,
            "## Coarse step {}x (dt = {} s)\n\nPer-element regularisation weights tried (validation error): {}; chosen {:e}.\n",
            c.dt_factor,
            c.dt,
            tried.join(", "),
            c.chosen
        )?;
        md.push_str("| model | mean RMS error (m) | final RMS error (m) | error / untuned | cost (s/s) | cost / fine | alpha | gamma | Newton rel | coefficients | loss | fit time (s) | optimiser |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
        for row in &c.rows {
            let vs_untuned = c
                .error_ratio(row.model, CoarseModel::Untuned)
                .unwrap_or(f64::NAN);
            let vs_fine = c
                .cost_ratio(row.model, CoarseModel::Fine)
                .unwrap_or(f64::NAN);
            let (alpha, gamma) = row.damping;
            let fit = row.fit.as_ref().map_or("| - | - | - | -".to_owned(), |f| {
                format!(
                    "| {} | {:.3e} -> {:.3e} | {:.1} | {}",
                    f.coefficients,
                    f.losses.0,
                    f.losses.1,
                    f.seconds,
                    f.termination.describe()
                )
            });
            writeln!(
                md,
                "| {} | {:.4e} | {:.4e} | {vs_untuned:.3} | {:.4} | {vs_fine:.3} | {alpha:.4} | {gamma:.3e} | {:.0e} {fit} |",
                row.model.name(),
                row.mean_error(),
                row.final_error(),
                row.cost,
                row.newton_rel
            )?;
        }
        let unstable = c
            .rows
            .iter()
            .filter_map(|r| Some((r.model, r.fit.as_ref()?.unstable.as_ref()?)));
        for (model, why) in unstable {
            let start = match model {
                CoarseModel::Homogeneous => "the untuned model",
                _ => "the homogeneous fit",
            };
            writeln!(
                md,
                "\nThe {} failed a free rollout ({why}): the row is {start}, which the fit started from.",
                model.name()
            )?;
        }
        if !c.files.is_empty() {
            let files: Vec<String> = c
                .files
                .iter()
                .map(|f| format!("`{}`", f.display()))
                .collect();
            writeln!(
                md,
                "\nThe per-element model: {} (`cargo xtask simulate` runs the scene; ParaView opens the field).",
                files.join(", ")
            )?;
        }
        md.push('\n');
    }
    Ok(())
}
