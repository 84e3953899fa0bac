//! `cargo xtask experiment EXPERIMENT.ron [--out DIR]`: makes the dataset of an experiment,
//! learns from it, and writes a results folder: `report.md`, CSV files, SVG plots and the
//! dataset itself.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, anyhow};
use clap::Args;
use deform_integrator::Scene;
use deform_learn::experiment::{Experiment, Task, rollout_error};
use deform_learn::{
    Dataset, Split, Trajectory, dataset, fit_ensemble, fit_equation_error, fit_output_error,
};
use deform_materials::{Lame, MaterialSpec, Moduli};
use deform_mesh::io::write_atomic;
use indicatif::{ProgressBar, ProgressStyle};

/// Makes a fresh policy for each test trajectory.
use crate::plots::plot;
use crate::policies::{self, PolicyMaker};

/// Arguments of `experiment`.
#[derive(Debug, Args)]
pub struct ExperimentArgs {
    /// The experiment file (RON).
    pub experiment: PathBuf,
    /// Results folder (default `target/deform/experiments/<name>`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// No progress bars.
    #[arg(long)]
    pub quiet: bool,
}

pub(crate) fn bar(quiet: bool, len: u64, what: &str) -> ProgressBar {
    let b = if quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(len)
    };
    b.set_style(
        ProgressStyle::with_template(&format!(
            "{what:>10} {{bar:30}} {{pos}}/{{len}} {{msg}} [{{elapsed_precise}}]"
        ))
        .expect("a valid template"),
    );
    b
}

pub(crate) fn write_text(path: &Path, text: &str) -> Result<()> {
    write_atomic(path, |w| w.write_all(text.as_bytes()))
        .with_context(|| format!("writing {}", path.display()))
}

/// `rollout_error.svg` and `.png`: RMS position error per step of each series.
pub(crate) fn plot_rollouts(out: &Path, series: &[(String, Vec<f64>)]) -> Result<()> {
    plot(
        &out.join("rollout_error"),
        "test rollout RMS position error",
        "step",
        "m",
        series,
        false,
    )
}

/// The scene with its material's moduli replaced by a Lame pair.
pub(crate) fn with_lame(scene: &Scene, mu: f64, lambda: f64) -> Result<Scene> {
    let moduli = Moduli::Lame { mu, lambda };
    let material = match &scene.material {
        MaterialSpec::LinearElastic(_) => MaterialSpec::LinearElastic(moduli),
        MaterialSpec::CorotatedLinear {
            lagged_rotation, ..
        } => MaterialSpec::CorotatedLinear {
            moduli,
            lagged_rotation: *lagged_rotation,
        },
        MaterialSpec::FixedCorotated(_) => MaterialSpec::FixedCorotated(moduli),
        MaterialSpec::StVenantKirchhoff(_) => MaterialSpec::StVenantKirchhoff(moduli),
        MaterialSpec::NeoHookean(_) => MaterialSpec::NeoHookean(moduli),
        MaterialSpec::StableNeoHookean(_) => MaterialSpec::StableNeoHookean(moduli),
        other => {
            return Err(anyhow!(
                "fitting a material needs a single model, the scene has {other:?}"
            ));
        }
    };
    let mut s = scene.clone();
    s.material = material;
    Ok(s)
}

/// Mean over test trajectories of the rollout error per step, for a scene variant.
fn test_rollout(scene: &Scene, origin: &Path, data: &Dataset) -> Result<Vec<f64>> {
    split_rollout(scene, origin, data, Split::Test)
}

/// Mean over a split's trajectories of the rollout error per step.
fn split_rollout(scene: &Scene, origin: &Path, data: &Dataset, split: Split) -> Result<Vec<f64>> {
    let mut sim = scene.build(origin)?.integrator;
    let tests = data.split(split);
    let mut mean = vec![0.0; tests.first().map_or(0, |t| t.x.len())];
    for t in &tests {
        let e = rollout_error(&mut sim, t).map_err(anyhow::Error::msg)?;
        for (m, v) in mean.iter_mut().zip(e) {
            *m += v / tests.len() as f64;
        }
    }
    Ok(mean)
}

/// Runs the experiment; returns a one-line summary of its headline figure.
pub fn run(args: ExperimentArgs) -> Result<String> {
    let experiment = Experiment::load(&args.experiment).map_err(anyhow::Error::msg)?;
    let scene = Scene::load(&experiment.scene)?;
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| Path::new("target/deform/experiments").join(&experiment.name));
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let spec = &experiment.dataset;
    let started = Instant::now();

    // The dataset.
    let total = (spec.trajectories * spec.steps) as u64;
    let b = bar(args.quiet, total, "dataset");
    let mut data = dataset::generate(
        &scene,
        &experiment.scene,
        spec.trajectories,
        spec.steps,
        spec.seed,
        &spec.variations,
        spec.split,
        |_, _| b.inc(1),
    )?;
    b.finish_and_clear();
    let base = scene.build(&experiment.scene)?;
    if let Some(noise) = spec.noise {
        data.add_noise(noise, &base.integrator.dofs().constrained_vertices());
    }
    data.save(&out.join("dataset"))?;
    // The learned model may step coarser than the base (seed: cheap model, accurate data).
    let k = spec.subsample;
    let data = if k > 1 { data.subsample(k) } else { data };
    let mut scene = scene;
    scene.integrator.dt *= k as f64;
    let base = if k > 1 {
        scene.build(&experiment.scene)?
    } else {
        base
    };
    let train = data.split(Split::Train);
    let mut report = format!(
        "# Experiment `{}`\n\nBase scene: `{}` ({} vertices, {} tets), material `{:?}`.\n\nDataset: {} trajectories x {} steps (seed {}), split {:?} train/validation (rest test), noise {:?}. Saved in `dataset/` (RON + .npy, see docs/experiments.md). The learned model steps with dt = {} s ({}x the base's).\n\n",
        experiment.name,
        experiment.scene.display(),
        base.mesh.num_vertices(),
        base.mesh.num_tets(),
        scene.material,
        spec.trajectories,
        spec.steps,
        spec.seed,
        spec.split,
        spec.noise,
        scene.integrator.dt,
        k
    );

    let mut summary = String::new();
    match &experiment.task {
        Task::FitMaterial {
            equation_error,
            output_error,
            start,
        } => {
            let t1 = Instant::now();
            let stage1 = fit_equation_error(&base.integrator, &train, *equation_error)?;
            let stage1_seconds = t1.elapsed().as_secs_f64();
            let (mu1, lambda1) = (stage1.coefficients[0], stage1.coefficients[1]);
            let truth = scene.material.build()?;
            let true_lame = truth
                .lame()
                .ok_or_else(|| anyhow!("the scene's model has no single Lame pair"))?;
            let young = |mu: f64, lambda: f64| {
                Lame::try_new(mu, lambda)
                    .map(|l| l.to_young())
                    .unwrap_or((f64::NAN, f64::NAN))
            };
            let (e0, nu0) = true_lame.to_young();
            let (e1, nu1) = young(mu1, lambda1);
            let mut rows = vec![
                ("truth".to_owned(), e0, nu0, f64::NAN),
                ("equation error".to_owned(), e1, nu1, stage1_seconds),
            ];
            let mut fitted = (mu1, lambda1);
            let mut csv = String::from("iteration,loss,mu,lambda\n");
            let mut losses = Vec::new();
            if let Some(options) = output_error {
                let mut sim = base.integrator;
                let b = bar(args.quiet, options.max_iterations, "fit");
                let t2 = Instant::now();
                // Start from the stage-1 estimate, or from the prior when it fits better (or
                // the estimate cannot even be simulated).
                let mut initial = stage1.coefficients.clone();
                if let Some(prior) = start {
                    let lame = prior.to_lame()?;
                    let prior = vec![lame.mu, lame.lambda];
                    let mut loss_at = |c: &[f64]| {
                        deform_learn::OutputError::new(&mut sim, &train, *options, |_, _| {})
                            .and_then(|o| o.evaluate(c))
                            .map_or(f64::INFINITY, |(l, _)| l)
                    };
                    let (l1, l0) = (loss_at(&initial), loss_at(&prior));
                    if l0 < l1 {
                        writeln!(
                            report,
                            "Stage 2 starts from the prior (loss {l0:.3e}) rather than the stage-1 estimate (loss {l1:.3e}).\n"
                        )?;
                        initial = prior;
                    }
                }
                let fit = fit_output_error(&mut sim, &train, &initial, *options, |k, loss| {
                    b.set_message(format!("evaluation {k}, loss {loss:.3e}"));
                })?;
                b.finish_and_clear();
                let (e2, nu2) = young(fit.coefficients[0], fit.coefficients[1]);
                rows.push((
                    "output error".to_owned(),
                    e2,
                    nu2,
                    t2.elapsed().as_secs_f64(),
                ));
                fitted = (fit.coefficients[0], fit.coefficients[1]);
                for it in &fit.iterations {
                    writeln!(
                        csv,
                        "{},{:e},{:e},{:e}",
                        it.iteration,
                        it.loss,
                        it.coefficients.first().copied().unwrap_or(f64::NAN),
                        it.coefficients.get(1).copied().unwrap_or(f64::NAN)
                    )?;
                    losses.push(it.loss);
                }
                writeln!(
                    report,
                    "Output error: {} iterations, {} loss evaluations, loss {:.4e} -> {:.4e}, termination {:?}.\n",
                    fit.iterations.len(),
                    fit.evaluations,
                    fit.initial_loss,
                    fit.loss,
                    fit.termination
                )?;
            }
            write_text(&out.join("iterations.csv"), &csv)?;
            plot(
                &out.join("loss"),
                "output-error loss per iteration",
                "iteration",
                "loss",
                &[("loss".into(), losses)],
                true,
            )?;
            report.push_str("| parameters | E (Pa) | nu | E error | nu error | fit time |\n|---|---|---|---|---|---|\n");
            for (name, e, nu, s) in &rows {
                writeln!(
                    report,
                    "| {name} | {e:.5e} | {nu:.5} | {:.3} % | {:.3} % | {} |",
                    100.0 * (e - e0).abs() / e0,
                    100.0 * (nu - nu0).abs() / nu0,
                    if s.is_nan() {
                        "-".to_owned()
                    } else {
                        format!("{s:.2} s")
                    }
                )?;
            }
            // Rollouts on the test trajectories with each parameter set.
            let b = bar(args.quiet, 3, "rollouts");
            let mut series = Vec::new();
            for (name, (mu, lambda)) in [
                ("true parameters", (true_lame.mu, true_lame.lambda)),
                ("equation error", (mu1, lambda1)),
                ("fitted", fitted),
            ] {
                let errors =
                    test_rollout(&with_lame(&scene, mu, lambda)?, &experiment.scene, &data)?;
                series.push((name.to_owned(), errors));
                b.inc(1);
            }
            b.finish_and_clear();
            let mut rcsv = String::from("step");
            for (name, _) in &series {
                write!(rcsv, ",{name}")?;
            }
            rcsv.push('\n');
            for n in 0..series[0].1.len() {
                write!(rcsv, "{n}")?;
                for (_, e) in &series {
                    write!(rcsv, ",{:e}", e[n])?;
                }
                rcsv.push('\n');
            }
            write_text(&out.join("rollout_error.csv"), &rcsv)?;
            plot_rollouts(&out, &series)?;
            let mean = |e: &[f64]| e.iter().sum::<f64>() / e.len().max(1) as f64;
            let (last_e, last_nu) = (rows[rows.len() - 1].1, rows[rows.len() - 1].2);
            summary = format!(
                "E off by {:.3} %, nu by {:.3} %; rollout error fitted / true {:.3}",
                100.0 * (last_e - e0).abs() / e0,
                100.0 * (last_nu - nu0).abs() / nu0,
                mean(&series[2].1) / mean(&series[0].1).max(f64::MIN_POSITIVE)
            );
            writeln!(
                report,
                "\nRMS position error of free rollouts on the test trajectories, averaged over the rollout: {}. Fitted / true parameters: {:.3}.\n\nFiles: `iterations.csv`, `loss.svg`/`.png`, `rollout_error.csv`, `rollout_error.svg`/`.png`.",
                series
                    .iter()
                    .map(|(n, e)| format!("{n} {:.3e} m", mean(e)))
                    .collect::<Vec<_>>()
                    .join(", "),
                mean(&series[2].1) / mean(&series[0].1).max(f64::MIN_POSITIVE)
            )?;
        }
        Task::SelectModel {
            members,
            output_error,
        } => {
            let names: Vec<&str> = members.iter().map(String::as_str).collect();
            // Stage 1, then (optionally) stage 2 on the kept members.
            let fit_models = |names: &[&str], evaluate: &[&Trajectory], label: &str| {
                let fit = fit_ensemble(&scene, &experiment.scene, names, &train, evaluate)?;
                let Some(options) = output_error else {
                    return Ok::<_, anyhow::Error>((fit, None));
                };
                let b = bar(args.quiet, options.max_evaluations as u64, label);
                let (refined, stage2) = deform_learn::refine_ensemble(
                    &fit,
                    &scene,
                    &experiment.scene,
                    &train,
                    evaluate,
                    *options,
                    |_, loss| {
                        b.inc(1);
                        b.set_message(format!("loss {loss:.3e}"));
                    },
                )?;
                b.finish_and_clear();
                Ok((refined, Some(stage2)))
            };
            let (fit, stage2) = fit_models(&names, &data.split(Split::Test), "ensemble")?;
            report.push_str("| member | effective mu | effective lambda | energy share (test) |\n|---|---|---|---|\n");
            let mut csv = String::from("model,mu,lambda,energy_share\n");
            for m in &fit.members {
                writeln!(
                    report,
                    "| {} | {:.5e} | {:.5e} | {:.2} % |",
                    m.model,
                    m.mu,
                    m.lambda,
                    100.0 * m.energy_share
                )?;
                writeln!(
                    csv,
                    "{},{:e},{:e},{:e}",
                    m.model, m.mu, m.lambda, m.energy_share
                )?;
            }
            writeln!(
                report,
                "\nEquation-error residual {:.3e}.",
                fit.relative_residual
            )?;
            if let Some(st) = &stage2 {
                writeln!(
                    report,
                    "Stage 2 (output error, the pairs above are its result): loss {:.3e} -> {:.3e} in {} iterations, {} evaluations ({:?}).",
                    st.initial_loss,
                    st.loss,
                    st.iterations.len(),
                    st.evaluations,
                    st.termination
                )?;
            }
            // Each model alone against the ensemble, by rollout error on validation (to
            // select) and test (to report), averaged over the rollouts.
            let mean = |e: &[f64]| e.iter().sum::<f64>() / e.len().max(1) as f64;
            let evaluate = |spec: Option<MaterialSpec>| -> (f64, f64) {
                let Some(spec) = spec else {
                    return (f64::INFINITY, f64::INFINITY);
                };
                let mut s = scene.clone();
                s.material = spec;
                let run = |split| {
                    split_rollout(&s, &experiment.scene, &data, split)
                        .map_or(f64::INFINITY, |e| mean(&e))
                };
                (run(Split::Validation), run(Split::Test))
            };
            report.push_str("\n| model | validation rollout error (m) | test rollout error (m) |\n|---|---|---|\n");
            let mut best: Option<(String, f64, f64)> = None;
            for name in &names {
                let (single, _) = fit_models(&[name], &data.split(Split::Validation), name)?;
                let (val, test) = evaluate(single.spec());
                writeln!(report, "| {name} alone | {val:.4e} | {test:.4e} |")?;
                if best.as_ref().is_none_or(|b| val < b.1) {
                    best = Some(((*name).to_owned(), val, test));
                }
            }
            let (val, test) = evaluate(fit.spec());
            writeln!(report, "| ensemble | {val:.4e} | {test:.4e} |")?;
            if let Some((name, _, btest)) = best {
                // Below a nanometre both are rounding noise; a ratio of two would mislead.
                let verdict = if test.max(btest) < 1e-9 {
                    "both at rounding level (below 1e-9 m): equal".to_owned()
                } else {
                    format!("{:.3}", test / btest.max(f64::MIN_POSITIVE))
                };
                writeln!(
                    report,
                    "\nBest single model by validation error: {name} (test {btest:.4e} m). Ensemble test error / best single model's: {verdict}."
                )?;
                let top = fit
                    .members
                    .iter()
                    .max_by(|a, b| a.energy_share.total_cmp(&b.energy_share));
                summary = format!(
                    "{} carries {:.1} % of the energy; best single model {name}",
                    top.map_or("-", |m| m.model.as_str()),
                    100.0 * top.map_or(0.0, |m| m.energy_share)
                );
            }
            write_text(&out.join("members.csv"), &csv)?;
            // Test rollouts of the ensemble and of the base scene.
            let mut series = vec![(
                "base model".to_owned(),
                test_rollout(&scene, &experiment.scene, &data)?,
            )];
            if let Some(spec) = fit.spec() {
                let mut s = scene.clone();
                s.material = spec;
                series.push((
                    "fitted ensemble".to_owned(),
                    test_rollout(&s, &experiment.scene, &data)?,
                ));
            }
            plot_rollouts(&out, &series)?;
        }
        Task::SelectSolver {
            candidates,
            neighbours,
            min_success,
            factor_weight,
            held_out,
            also_train,
            repeats,
            forcing,
            tune,
            refactor_above,
        } => {
            let steps = data.meta.trajectories.first().map_or(0, |t| t.steps);
            let variant = |initial: &deform_integrator::scene::Initial| {
                let mut s = scene.clone();
                s.initial = initial.clone();
                s
            };
            // Counterfactual logs from the training trajectories' initial conditions.
            let b = bar(args.quiet, (train.len() * steps) as u64, "logging");
            let also: Vec<(Scene, &Path, usize)> = also_train
                .iter()
                .map(|r| Ok((Scene::load(&r.scene)?, r.scene.as_path(), r.steps)))
                .collect::<Result<_>>()?;
            let runs: Vec<(Scene, &Path, usize)> = data
                .meta
                .trajectories
                .iter()
                .filter(|m| m.split == Split::Train)
                .map(|m| (variant(&m.initial), experiment.scene.as_path(), steps))
                .chain(also)
                .collect();
            let logged = deform_learn::solver_data::collect_runs(&runs, candidates, |_| b.inc(1))?;
            b.finish_and_clear();
            logged.save(&out.join("solver_data"))?;
            let young = scene
                .material
                .build()?
                .lame()
                .map_or(1.0, |l| l.to_young().0);
            // Policies compared on the test trajectories and the held-out scenes.
            let mut policies: Vec<(String, PolicyMaker)> = Vec::new();
            for c in candidates {
                let c = c.clone();
                policies.push((
                    format!("fixed {}", deform_integrator::spec_name(&c)),
                    Box::new(move || Box::new(deform_integrator::Fixed(c.clone()))),
                ));
            }
            let fixed = policies.len();
            if let Some(iterative) = candidates.iter().find(|c| {
                !matches!(c, deform_solvers::SolverSpec::Direct { .. })
                    && !deform_integrator::is_stale_cholesky(c)
            }) {
                let c = iterative.clone();
                policies.push((
                    format!("Eisenstat-Walker {}", deform_integrator::spec_name(&c)),
                    Box::new(move || Box::new(deform_integrator::EisenstatWalker::new(c.clone()))),
                ));
            }
            if let Some(stale) = candidates
                .iter()
                .find(|c| deform_integrator::is_stale_cholesky(c))
            {
                let (c, above) = (stale.clone(), *refactor_above);
                policies.push((
                    format!("hand schedule: refactorise above {above} iterations"),
                    Box::new(move || {
                        Box::new(deform_integrator::StaleFactor::new(c.clone(), above))
                    }),
                ));
            }
            let learned = deform_learn::policy::LearnedPolicy::train(
                &logged,
                deform_learn::policy::PolicyOptions {
                    neighbours: *neighbours,
                    min_success: *min_success,
                    factor_weight: *factor_weight,
                    young,
                    forcing: *forcing,
                },
            );
            // The learned policy with its Newton options and forcing tuned on the first
            // training run (and the tuning's own scenes).
            let mut tuned_settings = None;
            if let (Some(t), Some(m)) = (
                tune,
                data.meta
                    .trajectories
                    .iter()
                    .find(|m| m.split == Split::Train),
            ) {
                let mut runs: Vec<(Scene, &Path, usize)> =
                    vec![(variant(&m.initial), experiment.scene.as_path(), steps)];
                for r in &t.scenes {
                    runs.push((Scene::load(&r.scene)?, r.scene.as_path(), r.steps));
                }
                // Newton rel, and the largest forcing term when the policy has one.
                let (mut start, mut range) = (vec![vec![-6.0], vec![-9.0]], vec![(-12.0, -3.0)]);
                if let Some((eta_max, _)) = forcing {
                    let e = eta_max.log10();
                    start = vec![vec![-6.0, e], vec![-9.0, e], vec![-6.0, e - 1.0]];
                    range.push((-8.0, -0.3));
                }
                let tuning = deform_learn::tuning::Tuning {
                    start,
                    range,
                    factor_weight: *factor_weight,
                    fallback: true,
                    accuracy: t.accuracy,
                    max_iterations: t.max_iterations,
                };
                let projections: Vec<Option<deform_integrator::Projection>> = std::iter::once(None)
                    .chain(t.projections.iter().copied().map(Some))
                    .collect();
                let b = bar(
                    args.quiet,
                    projections.len() as u64 * (t.max_iterations + 3) * runs.len() as u64,
                    "tune",
                );
                let mut best: Option<(TunedLearned, deform_learn::tuning::TuningResult)> = None;
                let mut tcsv =
                    String::from("projection,log10_newton_rel,log10_eta_max,work,error,cost\n");
                for projection in projections {
                    let make = |p: &[f64], o: &mut deform_integrator::IntegratorOptions| {
                        b.inc(1);
                        let settings = TunedLearned::from_values(p, *forcing, projection);
                        settings.apply(o);
                        Some(Box::new(learned.with_forcing(settings.forcing))
                            as Box<dyn deform_integrator::SolverPolicy>)
                    };
                    let tuned = deform_learn::tuning::tune_policy(&runs, &make, &tuning)?;
                    for x in &tuned.samples {
                        writeln!(
                            tcsv,
                            "{},{},{},{:e},{:e},{:e}",
                            projection.map_or("scene's".to_owned(), |p| format!("{p:?}")),
                            x.log10_values[0],
                            x.log10_values.get(1).map_or(String::new(), f64::to_string),
                            x.work,
                            x.error,
                            x.cost
                        )?;
                    }
                    if best
                        .as_ref()
                        .is_none_or(|(_, b)| tuned.best.cost < b.best.cost)
                    {
                        best = Some((
                            TunedLearned::from_values(&tuned.log10_values, *forcing, projection),
                            tuned,
                        ));
                    }
                }
                b.finish_and_clear();
                write_text(&out.join("tuning.csv"), &tcsv)?;
                if let Some((settings, tuned)) = best {
                    writeln!(
                        report,
                        "Tuned for the learned policy: {} ({} evaluations on the first training trajectory{}, work {:.4e}, error {:.1e} within {:e}; every evaluation in `tuning.csv`).",
                        settings.label(),
                        tuned.samples.len(),
                        t.scenes
                            .iter()
                            .map(|r| format!(" and `{}`", r.scene.display()))
                            .collect::<String>(),
                        tuned.best.work,
                        tuned.best.error,
                        t.accuracy
                    )?;
                    tuned_settings = Some(settings);
                }
            }
            let mut policies: Vec<(String, PolicyMaker, Option<TunedLearned>)> = policies
                .into_iter()
                .map(|(name, make)| (name, make, None))
                .collect();
            let plain = learned.clone();
            policies.push((
                "learned".to_owned(),
                Box::new(move || Box::new(plain.clone())),
                None,
            ));
            if let Some(settings) = tuned_settings {
                let tuned = learned.with_forcing(settings.forcing);
                policies.push((
                    format!("learned, tuned ({})", settings.label()),
                    Box::new(move || Box::new(tuned.clone())),
                    Some(settings),
                ));
                // The same Newton settings with the direct solver: what tuning Newton alone gives.
                if let Some(direct) = candidates
                    .iter()
                    .find(|c| matches!(c, deform_solvers::SolverSpec::Direct { .. }))
                {
                    let c = direct.clone();
                    policies.push((
                        format!("fixed {}{TUNED_DIRECT}", deform_integrator::spec_name(&c)),
                        Box::new(move || Box::new(deform_integrator::Fixed(c.clone()))),
                        Some(settings),
                    ));
                }
            }
            let held: Vec<(String, Scene)> = held_out
                .iter()
                .map(|h| {
                    let s = Scene::load(&h.scene)?;
                    Ok((s.name.clone(), s))
                })
                .collect::<Result<_>>()?;
            let mut cases = vec![policies::Case {
                label: format!("test trajectories of `{}`", scene.name),
                runs: data
                    .meta
                    .trajectories
                    .iter()
                    .filter(|m| m.split == Split::Test)
                    .map(|m| (variant(&m.initial), experiment.scene.as_path()))
                    .collect(),
                steps,
            }];
            for (h, (name, s)) in held_out.iter().zip(&held) {
                cases.push(policies::Case {
                    label: format!("held-out `{name}` ({} steps)", h.steps),
                    runs: vec![(s.clone(), h.scene.as_path())],
                    steps: h.steps,
                });
            }
            let mut csv = String::from(
                "case,policy,flops,work,solver_seconds,step_seconds,newton,linear,error,fallbacks,failed\n",
            );
            let b = bar(
                args.quiet,
                (cases.len() * (policies.len() * repeats.max(&1) + 1)) as u64,
                "policies",
            );
            for (ci, case) in cases.iter().enumerate() {
                writeln!(
                    report,
                    "\n### {}\n\nWork = solve flops + {factor_weight} x factorisation flops; solver s / step s: median linear-solver / whole Newton-loop time over {} run(s); error: max position deviation from direct solves at Newton rel 1e-10, relative to the largest coordinate.\n\n| policy | flops | work | solver s | step s | Newton its | linear its | error | fallbacks |\n|---|---|---|---|---|---|---|---|---|",
                    case.label,
                    repeats.max(&1)
                )?;
                let references = policies::references(case)?;
                b.inc(1);
                let mut rows = Vec::new();
                for (name, make, settings) in &policies {
                    // Tuned Newton options run the same scenes with those options.
                    let tuned_case;
                    let run_case = match settings {
                        Some(settings) => {
                            tuned_case = policies::Case {
                                label: case.label.clone(),
                                runs: case
                                    .runs
                                    .iter()
                                    .map(|(s, o)| {
                                        let mut s = s.clone();
                                        settings.apply(&mut s.integrator);
                                        (s, *o)
                                    })
                                    .collect(),
                                steps: case.steps,
                            };
                            &tuned_case
                        }
                        None => case,
                    };
                    let row = policies::measure(
                        run_case,
                        &references,
                        name,
                        make,
                        *factor_weight,
                        *repeats,
                    )?;
                    b.inc(repeats.max(&1).to_owned() as u64);
                    let error = if row.failed {
                        "failed".to_owned()
                    } else {
                        format!("{:.1e}", row.error)
                    };
                    writeln!(
                        report,
                        "| {name} | {:.4e} | {:.4e} | {:.3} | {:.3} | {} | {} | {error} | {} |",
                        row.flops,
                        row.work,
                        row.seconds,
                        row.step_seconds,
                        row.newton,
                        row.linear,
                        row.fallbacks
                    )?;
                    writeln!(
                        csv,
                        "\"{}\",\"{name}\",{:e},{:e},{},{},{},{},{:e},{},{}",
                        case.label,
                        row.flops,
                        row.work,
                        row.seconds,
                        row.step_seconds,
                        row.newton,
                        row.linear,
                        row.error,
                        row.fallbacks,
                        row.failed
                    )?;
                    if !row.deterministic {
                        writeln!(report, "(flops of `{name}` differed between repeats)")?;
                    }
                    rows.push(row);
                }
                // Plots: work and Newton iterations per step, and the learned policy's choices.
                let stem = |what: &str| out.join(format!("case{ci}_{what}"));
                plot(
                    &stem("work"),
                    &format!("work per step: {}", case.label),
                    "step",
                    "work",
                    &rows
                        .iter()
                        .map(|r| (r.policy.clone(), r.per_step.iter().map(|p| p.0).collect()))
                        .collect::<Vec<_>>(),
                    true,
                )?;
                plot(
                    &stem("newton"),
                    &format!("Newton iterations per step: {}", case.label),
                    "step",
                    "iterations",
                    &rows
                        .iter()
                        .map(|r| {
                            (
                                r.policy.clone(),
                                r.per_step.iter().map(|p| p.1 as f64).collect(),
                            )
                        })
                        .collect::<Vec<_>>(),
                    false,
                )?;
                if let Some(learned) = rows.iter().rev().find(|r| r.policy.starts_with("learned")) {
                    let index = |name: &str| {
                        candidates
                            .iter()
                            .position(|c| name.starts_with(&deform_integrator::spec_name(c)))
                            .map_or(-1.0, |i| i as f64)
                    };
                    plot(
                        &stem("choices"),
                        &format!(
                            "learned policy's solver per Newton iteration: {}",
                            case.label
                        ),
                        "Newton iteration (all steps)",
                        "candidate index (-1: fallback)",
                        &[(
                            "learned".to_owned(),
                            learned.choices.iter().map(|c| index(c)).collect(),
                        )],
                        false,
                    )?;
                    let mut ccsv = String::from("iteration,solver\n");
                    for (i, c) in learned.choices.iter().enumerate() {
                        writeln!(ccsv, "{i},\"{c}\"")?;
                    }
                    write_text(&stem("choices.csv"), &ccsv)?;
                }
                writeln!(
                    report,
                    "\nPlots: `case{ci}_work.svg`/`.png` (work per step), `case{ci}_newton.svg`/`.png` (Newton iterations per step), `case{ci}_choices.svg`/`.png` and `.csv` (the learned policy's solver at every Newton iteration)."
                )?;
                // The best fixed solver in hindsight, by work and by time, against the others:
                // among every fixed candidate, and among those that set up afresh for every
                // solve (the "best fixed solver"; a stale factor is a schedule).
                let ok = |r: &&policies::Row| !r.failed && r.error <= 1e-6;
                let fresh = |r: &&policies::Row| !r.policy.contains("StaleCholesky");
                let best = |pick: &dyn Fn(&&policies::Row) -> bool,
                            key: &dyn Fn(&policies::Row) -> f64| {
                    rows[..fixed]
                        .iter()
                        .filter(ok)
                        .filter(|r| pick(r))
                        .min_by(|a, b| key(a).total_cmp(&key(b)))
                };
                let any = |_: &&policies::Row| true;
                let refs = [
                    ("best fixed", &any as &dyn Fn(&&policies::Row) -> bool),
                    ("best fixed without reuse", &fresh),
                ];
                writeln!(
                    report,
                    "\nRatios to the best fixed solver in hindsight (within 1e-6), by work, by linear-solver time and by whole-step time, each picked separately; \"without reuse\": among the fixed solvers that set up afresh for every solve (a fresh factorisation, IC(0), ...), stale-factor PCG being a schedule:\n"
                )?;
                let mut header = String::from("| policy |");
                let mut rule = String::from("|---|");
                for (label, pick) in &refs {
                    let (w, s, t) = (
                        best(*pick, &|r| r.work),
                        best(*pick, &|r| r.seconds),
                        best(*pick, &|r| r.step_seconds),
                    );
                    let name =
                        |r: Option<&policies::Row>| r.map_or("-", |r| r.policy.as_str()).to_owned();
                    header += &format!(
                        " work / {label} (`{}`) | solver s / {label} (`{}`) | step s / {label} (`{}`) |",
                        name(w),
                        name(s),
                        name(t)
                    );
                    rule += "---|---|---|";
                }
                writeln!(report, "{header}\n{rule}")?;
                for r in &rows[fixed..] {
                    let mut line = format!("| {} |", r.policy);
                    for (_, pick) in &refs {
                        let ratio = |key: &dyn Fn(&policies::Row) -> f64| {
                            best(*pick, key).map_or("-".to_owned(), |b| {
                                format!("{:.3}", key(r) / key(b).max(f64::MIN_POSITIVE))
                            })
                        };
                        line += &format!(
                            " {} | {} | {} |",
                            ratio(&|r| r.work),
                            ratio(&|r| r.seconds),
                            ratio(&|r| r.step_seconds)
                        );
                    }
                    if !ok(&r) {
                        line += " (outside the 1e-6 accuracy bound)";
                    }
                    writeln!(report, "{line}")?;
                }
                let learned = rows[fixed..]
                    .iter()
                    .rev()
                    .find(|r| r.policy.starts_with("learned"));
                if let (Some(l), Some(bw), Some(bs)) = (
                    learned,
                    best(&fresh, &|r| r.work),
                    best(&fresh, &|r| r.seconds),
                ) {
                    summary = format!(
                        "{}: {} / best fixed without reuse {:.2}x work, {:.2}x solver time",
                        case.label,
                        l.policy,
                        l.work / bw.work,
                        l.seconds / bs.seconds.max(f64::MIN_POSITIVE)
                    );
                }
                // What the solver choice adds on top of the tuned Newton settings.
                if let (Some(l), Some(d)) = (
                    learned,
                    rows.iter().find(|r| r.policy.ends_with(TUNED_DIRECT)),
                ) && l.policy.contains("tuned")
                {
                    writeln!(
                        report,
                        "\nSolver choice alone: `{}` / `{}` (the same Newton settings): {:.3} work, {:.3} solver time, {:.3} step time.",
                        l.policy,
                        d.policy,
                        l.work / d.work,
                        l.seconds / d.seconds.max(f64::MIN_POSITIVE),
                        l.step_seconds / d.step_seconds.max(f64::MIN_POSITIVE)
                    )?;
                }
            }
            b.finish_and_clear();
            write_text(&out.join("policies.csv"), &csv)?;
            writeln!(
                report,
                "\n{} logged Newton iterations from {} training trajectories and {} more training scenes; data in `solver_data/`.",
                logged.len(),
                train.len(),
                also_train.len()
            )?;
        }
        Task::TuneBackwardEuler {
            equation_error,
            output_error,
            members,
            candidates,
            factor_weight,
            accuracy,
            max_iterations,
        } => {
            let mut base_scene = scene.clone();
            base_scene.integrator.dt /= k as f64;
            summary = crate::story::run(
                &crate::story::Story {
                    scene: &scene,
                    origin: &experiment.scene,
                    base: &base_scene,
                    subsample: k,
                    data: &data,
                    equation_error: *equation_error,
                    output_error: *output_error,
                    members,
                    candidates,
                    factor_weight: *factor_weight,
                    accuracy: *accuracy,
                    max_iterations: *max_iterations,
                    quiet: args.quiet,
                },
                &out,
                &mut report,
            )?;
        }
        Task::TuneSolver {
            solver,
            parameters,
            factor_weight,
            accuracy,
            max_iterations,
        } => {
            let steps = data.meta.trajectories.first().map_or(0, |t| t.steps);
            let tuned = deform_learn::tuning::tune_solver(
                &scene,
                &experiment.scene,
                solver,
                parameters,
                steps,
                *accuracy,
                *factor_weight,
                *max_iterations,
            )?;
            let names: Vec<String> = parameters.iter().map(|p| format!("{p:?}")).collect();
            let mut csv = names
                .iter()
                .map(|n| format!("log10_{n}"))
                .collect::<Vec<_>>()
                .join(",");
            csv += ",work,error,cost\n";
            for sample in &tuned.samples {
                for v in &sample.log10_values {
                    write!(csv, "{v},")?;
                }
                writeln!(
                    csv,
                    "{:e},{:e},{:e}",
                    sample.work, sample.error, sample.cost
                )?;
            }
            write_text(&out.join("tuning.csv"), &csv)?;
            let values = |v: &[f64]| {
                names
                    .iter()
                    .zip(v)
                    .map(|(n, x)| format!("{n} {:.3e}", 10f64.powf(*x)))
                    .collect::<Vec<_>>()
                    .join(", ")
            };
            let configured = &tuned.samples[0];
            writeln!(
                report,
                "Tuned `{}` ({}): {}, work {:.4e} over {steps} steps (factorisation flops x {factor_weight}), trajectory error {:.1e} (bound {accuracy:e}); {} evaluations (`tuning.csv`).\n\nAs configured ({}): work {:.4e}, error {:.1e}; tuned / configured: {:.3}.",
                deform_integrator::spec_name(solver),
                names.join(", "),
                values(&tuned.log10_values),
                tuned.best.work,
                tuned.best.error,
                tuned.samples.len(),
                values(&configured.log10_values),
                configured.work,
                configured.error,
                tuned.best.work / configured.work
            )?;
            summary = format!(
                "{}: {:.2}x the work as configured",
                values(&tuned.log10_values),
                tuned.best.work / configured.work
            );
        }
    }
    writeln!(
        report,
        "\nTotal time {:.1} s.",
        started.elapsed().as_secs_f64()
    )?;
    write_text(&out.join("report.md"), &report)?;
    println!("{report}");
    println!("results: {}", out.display());
    Ok(summary)
}

/// Name suffix of the direct solver run with the learned policy's tuned Newton settings.
const TUNED_DIRECT: &str = ", the tuned Newton settings";

/// The learned policy's tuned settings in a solver-selection experiment.
#[derive(Debug, Clone, Copy)]
struct TunedLearned {
    newton_rel: f64,
    /// Its forcing terms `(eta_max, gamma)`, when it has them.
    forcing: Option<(f64, f64)>,
    /// Newton's tangent projection, when it replaces the scenes' own.
    projection: Option<deform_integrator::Projection>,
}

impl TunedLearned {
    /// From the tuned log10 values: Newton rel, then eta_max when there is forcing.
    fn from_values(
        p: &[f64],
        forcing: Option<(f64, f64)>,
        projection: Option<deform_integrator::Projection>,
    ) -> Self {
        Self {
            newton_rel: 10f64.powf(p[0]),
            forcing: forcing.map(|(eta, gamma)| (p.get(1).map_or(eta, |e| 10f64.powf(*e)), gamma)),
            projection,
        }
    }

    /// Sets the tuned Newton options.
    fn apply(&self, o: &mut deform_integrator::IntegratorOptions) {
        o.newton.rel = self.newton_rel;
        if let Some(p) = self.projection {
            o.newton.project = p;
        }
    }

    fn label(&self) -> String {
        let mut s = format!("Newton rel {:.1e}", self.newton_rel);
        if let Some((eta, _)) = self.forcing {
            s += &format!(", eta_max {eta:.1e}");
        }
        if let Some(p) = self.projection {
            s += &format!(", projection {p:?}");
        }
        s
    }
}
