//! Experiments run from the library: every task on a tiny scene, its report's figures
//! compared with the CSV files the runner wrote for the same experiments before the
//! experiments moved from xtask into deform-learn (`tests/data/expected/`, recorded with
//! the earlier code). Wall times are not compared. `select_solver` and `tune_solver` were
//! re-recorded on purpose on 2026-12-03, when small systems moved to faer's supernodal
//! Cholesky: the same work figures and choices, errors of about 1e-13 that moved in their
//! fifth digit.

use std::path::{Path, PathBuf};

use deform_learn::rollout::mean_error;
use deform_studies::{Experiment, NoProgress, TaskReport, run};

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

/// Rows of a CSV file by column name (fields may be quoted and hold commas).
fn csv(path: &Path) -> Vec<std::collections::HashMap<String, String>> {
    let text = std::fs::read_to_string(path).unwrap();
    let split = |line: &str| -> Vec<String> {
        let (mut fields, mut field, mut quoted) = (Vec::new(), String::new(), false);
        for c in line.chars() {
            match c {
                '"' => quoted = !quoted,
                ',' if !quoted => fields.push(std::mem::take(&mut field)),
                c => field.push(c),
            }
        }
        fields.push(field);
        fields
    };
    let mut lines = text.lines();
    let header = split(lines.next().unwrap());
    lines
        .map(|l| header.iter().cloned().zip(split(l)).collect())
        .collect()
}

fn expected(experiment: &str, file: &str) -> Vec<std::collections::HashMap<String, String>> {
    csv(&data("expected").join(experiment).join(file))
}

fn num(row: &std::collections::HashMap<String, String>, key: &str) -> f64 {
    row[key]
        .parse()
        .unwrap_or_else(|_| panic!("{key}: {}", row[key]))
}

/// Equal to the recorded figure up to the rounding of a sum taken in another order.
fn same(what: &str, got: f64, want: f64) {
    assert!(
        got == want || (got - want).abs() <= 1e-12 * want.abs(),
        "{what}: {got:e} now, {want:e} before"
    );
}

/// The material-fit report of the bundled experiment `assets/experiments/{name}.ron`.
fn bundled_fit(name: &str) -> deform_studies::fit_material::FitMaterialReport {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../../assets/experiments/{name}.ron"));
    let e = Experiment::load(&path).unwrap();
    let TaskReport::FitMaterial(r) = run(&e, None, &mut NoProgress).unwrap().task else {
        panic!("{name}: not a material fit")
    };
    r
}

fn report(name: &str) -> deform_studies::ExperimentReport {
    let e = Experiment::load(&data(&format!("{name}.ron"))).unwrap();
    run(&e, None, &mut NoProgress).unwrap()
}

#[test]
fn fit_material_reports_the_recorded_figures() {
    let TaskReport::FitMaterial(r) = report("fit_material").task else {
        panic!("task")
    };
    let iterations = &r.output_error.as_ref().unwrap().iterations;
    let want = expected("fit_material", "iterations.csv");
    assert_eq!(iterations.len(), want.len());
    for (it, row) in iterations.iter().zip(&want) {
        same("loss", it.loss, num(row, "loss"));
        same("mu", it.coefficients[0], num(row, "mu"));
        same("lambda", it.coefficients[1], num(row, "lambda"));
    }
    let want = expected("fit_material", "rollout_error.csv");
    for series in &r.rollouts {
        assert_eq!(series.values.len(), want.len());
        for (v, row) in series.values.iter().zip(&want) {
            same(&series.name, *v, num(row, &series.name));
        }
    }
}

/// The bundled contact fit: from clean trajectories of the cube thrown at the ground, the
/// material, the barrier's stiffness and the ground's friction within 1 % (issue 41), and
/// no friction on the frictionless ball.
#[test]
fn the_contact_fit_recovers_material_stiffness_and_friction() {
    let r = bundled_fit("fit_material_contact");
    assert!(
        r.young_error() < Some(0.01) && r.poisson_error() < Some(0.01),
        "{:?}",
        r.rows
    );
    let c = r.contact.expect("the scene has contact");
    let close = |(scene, fit): (f64, Option<f64>)| {
        fit.is_some_and(|f| (f - scene).abs() <= 0.01 * scene.abs().max(1e-3))
    };
    assert!(close(c.kappa), "kappa {:?}", c.kappa);
    assert_eq!(c.friction.len(), 2);
    assert!(
        close(c.friction[0]) && c.friction[0].0 == 0.3,
        "{:?}",
        c.friction
    );
    assert!(
        close(c.friction[1]) && c.friction[1].0 == 0.0,
        "{:?}",
        c.friction
    );
}

/// The bundled coarse-step fit through contact runs its output-error stage (the adjoint
/// through the barrier) on a bouncing cube: it lowers the loss, lands within 5 % of the
/// moduli (the equation error at the coarse step is 15 % off) and rolls out as well as the
/// true moduli do.
#[test]
fn the_coarse_step_fit_goes_through_contact() {
    let r = bundled_fit("coarse_dt_contact");
    let fit = r.output_error.as_ref().expect("the output-error stage ran");
    assert!(
        fit.loss < fit.initial_loss,
        "{} -> {}",
        fit.initial_loss,
        fit.loss
    );
    assert!(
        r.young_error() < Some(0.05) && r.poisson_error() < Some(0.05),
        "{:?}",
        r.rows
    );
    assert!(r.rollout_ratio() <= Some(1.01), "{:?}", r.rollout_ratio());
}

/// The bundled coarse-step fit through friction: stage 2 fits the ground's mu with E and nu
/// over rollouts at 4x the data's step, keeps the frictionless ball at 0, and rolls out
/// better than the true parameters do at that step (0.79x measured; 0.98x when stage 2
/// leaves friction at the scene's) and than stage 1's estimate.
#[test]
fn the_coarse_step_fit_goes_through_friction() {
    let r = bundled_fit("coarse_dt_friction");
    let fit = r.output_error.as_ref().expect("the output-error stage ran");
    assert!(r.unstable.is_none(), "{:?}", r.unstable);
    assert!(
        fit.loss < 0.5 * fit.initial_loss,
        "{} -> {}",
        fit.initial_loss,
        fit.loss
    );
    let c = r.contact.as_ref().expect("the scene has contact");
    let mu = c.output_error.as_ref().expect("stage 2 fitted friction");
    assert_eq!(mu.len(), 2);
    assert_eq!(fit.coefficients[2..], mu[..], "the fit's last coefficients");
    assert!(
        mu[0] > 0.0 && mu[0] < 1.0 && mu[0] != c.friction[0].0,
        "{mu:?}"
    );
    assert_eq!(mu[1], 0.0, "the ball stays frictionless");
    let error = |i: usize| mean_error(&r.rollouts[i].values);
    assert!(r.rollout_ratio() < Some(0.9), "{:?}", r.rollout_ratio());
    assert!(
        error(2) < error(1),
        "fitted {} vs stage 1 {}",
        error(2),
        error(1)
    );
}

#[test]
fn select_model_reports_the_recorded_figures() {
    let TaskReport::SelectModel(r) = report("select_model").task else {
        panic!("task")
    };
    let want = expected("select_model", "members.csv");
    assert_eq!(r.ensemble.members.len(), want.len());
    for (m, row) in r.ensemble.members.iter().zip(&want) {
        assert_eq!(m.model.to_string(), row["model"]);
        same("mu", m.mu, num(row, "mu"));
        same("lambda", m.lambda, num(row, "lambda"));
        same("energy share", m.energy_share, num(row, "energy_share"));
    }
}

#[test]
fn select_solver_reports_the_recorded_figures() {
    let full = report("select_solver");
    let headline = full.headline();
    let TaskReport::SelectSolver(r) = full.task else {
        panic!("task")
    };
    // The summary credits the gain as the last case's table does: the learned policy's
    // work over the best fixed solver's, and its solver choice alone over the direct solver
    // with the same tuned Newton settings.
    let case = r.cases.last().unwrap();
    let work = |pick: &dyn Fn(&deform_studies::select_solver::PolicyRow) -> bool| {
        let rows = case.rows.iter().filter(|row| pick(row));
        rows.map(|row| row.measured.work)
            .fold(f64::INFINITY, f64::min)
    };
    let learned = case.learned().unwrap().measured.work;
    let best_fixed = work(&|row| {
        row.contender.is_fixed() && row.within_accuracy() && !row.contender.reuses_factor()
    });
    let same_settings = work(&|row| {
        matches!(
            row.contender,
            deform_studies::select_solver::Contender::FixedTunedNewton(..)
        )
    });
    for figure in [
        format!("best fixed without reuse {:.2}x work", learned / best_fixed),
        format!(
            "the solver choice alone {:.2}x the work",
            learned / same_settings
        ),
    ] {
        assert!(headline.contains(&figure), "{headline:?} lacks {figure:?}");
    }
    let want = expected("select_solver", "policies.csv");
    let rows: Vec<_> = r
        .cases
        .iter()
        .flat_map(|c| c.rows.iter().map(move |row| (c, row)))
        .collect();
    assert_eq!(rows.len(), want.len());
    for ((case, row), w) in rows.iter().zip(&want) {
        let name = row.contender.name();
        assert_eq!(
            (case.label.as_str(), name.as_str()),
            (w["case"].as_str(), w["policy"].as_str())
        );
        let m = &row.measured;
        same(&format!("{name} flops"), m.flops, num(w, "flops"));
        same(&format!("{name} work"), m.work, num(w, "work"));
        same(&format!("{name} error"), m.error, num(w, "error"));
        assert_eq!(m.newton as f64, num(w, "newton"), "{name}");
        assert_eq!(m.linear as f64, num(w, "linear"), "{name}");
        assert_eq!(m.fallbacks as f64, num(w, "fallbacks"), "{name}");
        assert_eq!(m.failed.to_string(), w["failed"], "{name}");
    }
    let tuning = r.tuning.unwrap();
    let want = expected("select_solver", "tuning.csv");
    assert_eq!(tuning.samples.len(), want.len());
    for ((_, s), w) in tuning.samples.iter().zip(&want) {
        same("tuning work", s.work, num(w, "work"));
        same("tuning cost", s.cost, num(w, "cost"));
    }
}

#[test]
fn select_solver_plots_every_case_from_its_rows() {
    let report = report("select_solver");
    let plots = report.plots();
    let TaskReport::SelectSolver(r) = &report.task else {
        panic!("task")
    };
    let stems: Vec<&str> = plots.iter().map(|p| p.stem.as_str()).collect();
    let what = ["work", "newton", "choices"];
    let want: Vec<String> = (0..r.cases.len())
        .flat_map(|c| what.map(|w| format!("case{c}_{w}")))
        .collect();
    assert_eq!(stems, want);
    for (case, plots) in r.cases.iter().zip(plots.chunks(3)) {
        let [work, newton, choices] = plots else {
            panic!("three plots per case")
        };
        assert!(work.log && !newton.log);
        assert_eq!(work.series.len(), case.rows.len());
        for ((row, w), n) in case.rows.iter().zip(&work.series).zip(&newton.series) {
            let m = &row.measured;
            same("work per step sums to work", w.values.iter().sum(), m.work);
            assert_eq!(n.values.iter().sum::<f64>(), m.newton as f64);
        }
        let learned = case.learned().unwrap();
        let values = &choices.series[0].values;
        assert_eq!(values.len(), learned.measured.newton);
        assert!(
            values
                .iter()
                .all(|&i| i >= -1.0 && i < r.candidates.len() as f64)
        );
    }
}

#[test]
fn the_story_reports_the_recorded_figures() {
    let TaskReport::TuneBackwardEuler(r) = report("tune_backward_euler").task else {
        panic!("task")
    };
    let want = expected("tune_backward_euler", "comparison.csv");
    assert_eq!(r.rows.len(), want.len());
    for (row, w) in r.rows.iter().zip(&want) {
        same("mean error", row.mean_error(), num(w, "mean_error"));
        same("final error", row.final_error(), num(w, "final_error"));
        same("work", row.work, num(w, "work"));
        same("flops", row.flops, num(w, "flops"));
        assert_eq!(row.newton as f64, num(w, "newton"));
        assert_eq!(row.fallbacks as f64, num(w, "fallbacks"));
    }
    let want = expected("tune_backward_euler", "tuning.csv");
    for (s, w) in r.tuning.samples.iter().zip(&want) {
        same("tuning work", s.work, num(w, "work"));
        same("tuning error", s.error, num(w, "error"));
    }
}

#[test]
fn tune_solver_reports_the_recorded_figures() {
    let TaskReport::TuneSolver(r) = report("tune_solver").task else {
        panic!("task")
    };
    let want = expected("tune_solver", "tuning.csv");
    assert_eq!(r.result.samples.len(), want.len());
    for (s, w) in r.result.samples.iter().zip(&want) {
        same(
            "log10 tolerance",
            s.log10_values[0],
            num(w, "log10_RelativeTolerance"),
        );
        same("work", s.work, num(w, "work"));
        same("error", s.error, num(w, "error"));
    }
}

#[test]
fn bad_experiments_name_the_file_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.ron");
    std::fs::write(
        &path,
        r#"Experiment(name: "x", scene: "s.ron", dataset: (trajectories: 5, steps: 3, seed: 1, split: (0.9, 0.2)), task: SelectModel(members: [NeoHookean]))"#,
    )
    .unwrap();
    let e = Experiment::load(&path).unwrap_err();
    assert!(
        matches!(&e, deform_learn::LearnError::Config { field, .. } if field == "dataset.split"),
        "{e}"
    );
    // An unknown ensemble member is rejected, not silently replaced.
    std::fs::write(
        &path,
        r#"Experiment(name: "x", scene: "s.ron", dataset: (trajectories: 5, steps: 3, seed: 1), task: SelectModel(members: [Rubber]))"#,
    )
    .unwrap();
    let e = Experiment::load(&path).unwrap_err().to_string();
    assert!(e.contains("bad.ron") && e.contains("Rubber"), "{e}");
}

#[test]
fn every_bad_setting_is_refused_at_load_naming_its_field() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.ron");
    let solver = r#"SelectSolver(candidates: [Direct()])"#;
    let story = r#"TuneBackwardEuler(output_error: (), candidates: [Direct()])"#;
    let coarsen = r#"Coarsen(mesh: Beam(1), test: (trajectories: 1, steps: 8, seed: 2), regions: 2, output_error: ())"#.to_owned();
    let cases = [
        (
            "trajectories: 3, steps: 3, seed: 1",
            solver.replace("[Direct()]", "[]"),
            "task.candidates",
        ),
        (
            "trajectories: 3, steps: 3, seed: 1",
            story.replace("[Direct()]", "[]"),
            "task.candidates",
        ),
        (
            "trajectories: 3, steps: 3, seed: 1",
            solver.replace("])", "], forcing: Some((NaN, 0.9)))"),
            "task.forcing",
        ),
        (
            "trajectories: 3, steps: 3, seed: 1",
            solver.replace("])", "], factor_weight: NaN)"),
            "task.factor_weight",
        ),
        (
            "trajectories: 3, steps: 3, seed: 1",
            solver.replace("])", "], sweep_weight: 0.0)"),
            "task.sweep_weight",
        ),
        (
            "trajectories: 3, steps: 3, seed: 1",
            solver.replace("])", "], neighbours: 0)"),
            "task.neighbours",
        ),
        (
            "trajectories: 3, steps: 3, seed: 1",
            solver.replace("])", "], min_success: 2.0)"),
            "task.min_success",
        ),
        (
            "trajectories: 3, steps: 3, seed: 1",
            solver.replace("])", "], repeats: 0)"),
            "task.repeats",
        ),
        (
            "trajectories: 3, steps: 3, seed: 1",
            "FitMaterial(output_error: Some((rollout: 0)))".into(),
            "task.output_error",
        ),
        (
            "trajectories: 3, steps: 3, seed: 1",
            story.replace("])", "], accuracy: -1.0)"),
            "task.accuracy",
        ),
        (
            "trajectories: 3, steps: 3, seed: 1",
            "TuneSolver(solver: Pcg(preconditioner: Jacobi), parameters: [Omega, Omega])".into(),
            "task.parameters",
        ),
        (
            "trajectories: 3, steps: 3, seed: 1",
            "TuneSolver(solver: Pcg(preconditioner: Jacobi), accuracy: NaN)".into(),
            "task.accuracy",
        ),
        (
            "trajectories: 3, steps: 3, seed: 1, split: (0.6, 0.2)",
            "FitMaterial()".into(),
            "dataset.split",
        ),
        (
            "trajectories: 3, steps: 3, seed: 1, noise: Some((position: -0.1, velocity: 0.0, seed: 1))",
            "FitMaterial()".into(),
            "dataset.noise",
        ),
        (
            "trajectories: 3, steps: 3, seed: 1",
            "SelectModel(members: [])".into(),
            "task.members",
        ),
        (
            "trajectories: 3, steps: 8, seed: 1",
            coarsen.replace("regions: 2", "dt_factors: [0]"),
            "task.dt_factors",
        ),
        (
            "trajectories: 3, steps: 8, seed: 1",
            coarsen.replace("regions: 2", "dt_factors: [5]"),
            "task.dt_factors",
        ),
        (
            "trajectories: 3, steps: 8, seed: 1",
            coarsen.replace("regions: 2", "regions: 0"),
            "task.regions",
        ),
        (
            "trajectories: 3, steps: 8, seed: 1",
            coarsen.replace("regions: 2", "regularisation: [-1.0]"),
            "task.regularisation",
        ),
        (
            "trajectories: 3, steps: 8, seed: 1",
            coarsen.replace("regions: 2", "regions: 2, newton_rel: [1e-3, 1.0]"),
            "task.newton_rel",
        ),
        (
            "trajectories: 3, steps: 8, seed: 1",
            coarsen.replace("regions: 2", "regions: 2, fit_newton_iterations: Some(0)"),
            "task.fit_newton_iterations",
        ),
        (
            "trajectories: 3, steps: 8, seed: 1",
            coarsen.replace("steps: 8, seed: 2", "steps: 0, seed: 2"),
            "task.test",
        ),
        (
            "trajectories: 3, steps: 8, seed: 1, subsample: 2",
            coarsen.clone(),
            "dataset.subsample",
        ),
        (
            "trajectories: 3, steps: 8, seed: 1, split: (0.9, 0.0)",
            coarsen.clone(),
            "dataset.split",
        ),
    ];
    for (dataset, task, field) in cases {
        let text = format!(
            r#"Experiment(name: "x", scene: "s.ron", dataset: ({dataset}, split: (0.34, 0.33)), task: {task})"#
        )
        .replace(", split: (0.6, 0.2), split: (0.34, 0.33)", ", split: (0.6, 0.2)")
        .replace(", split: (0.9, 0.0), split: (0.34, 0.33)", ", split: (0.9, 0.0)");
        std::fs::write(&path, &text).unwrap();
        match Experiment::load(&path) {
            Err(deform_learn::LearnError::Config {
                field: f, path: p, ..
            }) => {
                assert_eq!((f.as_str(), p.as_path()), (field, path.as_path()), "{text}")
            }
            other => panic!("{text}: expected a Config error naming {field}, got {other:?}"),
        }
    }
    // Solver tuning uses no test trajectory: three trajectories split 0.6 / 0.2 are fine.
    std::fs::write(
        &path,
        r#"Experiment(name: "x", scene: "s.ron", dataset: (trajectories: 3, steps: 3, seed: 1), task: TuneSolver(solver: Pcg(preconditioner: Jacobi)))"#,
    )
    .unwrap();
    Experiment::load(&path).unwrap();
}

#[test]
fn a_rerun_replaces_the_previous_runs_files_and_keeps_the_users() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let mut e = Experiment::load(&data("select_solver.ron")).unwrap();
    let first = run(&e, Some(&out), &mut NoProgress).unwrap();
    // What a renderer adds: report.md and the plots the report describes.
    std::fs::write(out.join("report.md"), "# old").unwrap();
    for p in first.plots() {
        std::fs::write(out.join(format!("{}.svg", p.stem)), "<svg/>").unwrap();
    }
    std::fs::write(out.join("notes.csv"), "mine").unwrap();
    assert!(out.join("case1_work.svg").exists() && out.join("solver_data").is_dir());
    // The rerun has one case fewer: the held-out case's plots must not linger.
    let deform_studies::Task::SelectSolver { held_out, .. } = &mut e.task else {
        panic!("task")
    };
    held_out.clear();
    let second = run(&e, Some(&out), &mut NoProgress).unwrap();
    assert!(!out.join("case1_work.svg").exists());
    assert!(!out.join("report.md").exists());
    assert_eq!(
        std::fs::read_to_string(out.join("notes.csv")).unwrap(),
        "mine"
    );
    for f in &second.files {
        assert!(out.join(f).exists(), "{}", f.display());
    }
}

#[test]
fn coarsening_fits_every_field_from_the_homogeneous_one_and_saves_the_model() {
    use deform_studies::coarsen::CoarseModel;
    let dir = tempfile::tempdir().unwrap();
    let e = Experiment::load(&data("coarsen.ron")).unwrap();
    let report = run(&e, Some(dir.path()), &mut NoProgress).unwrap();
    let TaskReport::Coarsen(r) = &report.task else {
        panic!("task")
    };
    assert_eq!((r.mapping.ratio, r.mapping.outside), (8.0, 0));
    assert_eq!(r.cases.len(), 2);
    // The report does not claim one learned step for models of several: each section names
    // its own, as the cases have them.
    let markdown = deform_studies::write_report(&report, dir.path()).unwrap();
    assert!(
        !markdown.contains("The learned model steps with"),
        "{markdown}"
    );
    for c in &r.cases {
        let section = format!("## Coarse step {}x (dt = {} s)", c.dt_factor, c.dt);
        assert!(markdown.contains(&section), "{section}");
        // The field is drawn at the elements' positions with the slabs' boundaries marked.
        assert!(c.field.iter().all(|s| s.x.is_some()));
        assert_eq!(c.region_bounds.len(), 1, "2 slabs meet once");
    }
    // report.md embeds every plot, and report.html holds each one inline: one page that
    // needs no file beside it.
    let html = std::fs::read_to_string(dir.path().join("report.html")).unwrap();
    for p in report.plots() {
        assert!(
            markdown.contains(&format!("]({}.svg)", p.stem)),
            "{}",
            p.stem
        );
    }
    let figures = html.matches("<figure><svg").count();
    assert_eq!(figures, report.plots().len(), "one inline SVG per plot");
    assert!(!html.contains(".svg\""), "no SVG left as a link");
    for c in &r.cases {
        let models: Vec<CoarseModel> = c.rows.iter().map(|row| row.model).collect();
        use CoarseModel::*;
        assert_eq!(
            models,
            [Fine, Untuned, Homogeneous, PerRegion, Smooth, PerElement]
        );
        // The test motions: 8 fine steps, so 8 / k coarse steps and the initial state.
        assert!(
            c.rows
                .iter()
                .all(|row| row.errors.len() == 8 / c.dt_factor + 1)
        );
        assert!(c.rows[0].errors.iter().all(|&e| e == 0.0));
        assert!(c.rows[1].mean_error() > 0.0);
        // Every field starts from the homogeneous fit, where its penalty vanishes, so its
        // loss starts at the homogeneous fit's final loss and only goes down.
        let homogeneous = c.row(Homogeneous).unwrap().fit.as_ref().unwrap();
        assert!(homogeneous.losses.1 < homogeneous.losses.0);
        for model in [PerRegion, Smooth, PerElement] {
            let fit = c.row(model).unwrap().fit.as_ref().unwrap();
            let (start, end) = fit.losses;
            assert!(
                (start - homogeneous.losses.1).abs() <= 1e-9 * start,
                "{model:?}"
            );
            assert!(end <= start, "{model:?}");
        }
        // 24 coarse tets x (mu, lambda), and alpha, gamma.
        let per_element = c.row(PerElement).unwrap();
        assert_eq!(per_element.fit.as_ref().unwrap().coefficients, 50);
        assert!(per_element.damping.1 > -0.5 * c.dt);
        assert_eq!(c.regularisation.len(), 2);
        // Fitted models keep the scene's Newton tolerance or take a looser one tried on the
        // validation trajectories; the fine and untuned ones keep the scene's.
        let scene_rel = c.rows[0].newton_rel;
        assert_eq!(c.rows[1].newton_rel, scene_rel);
        assert!(
            c.rows[2..]
                .iter()
                .all(|row| [scene_rel, 1e-3, 1e-1].contains(&row.newton_rel))
        );
        // The model is a scene to keep: it loads, with the fitted damping and its field.
        let saved = deform_integrator::Scene::load(&dir.path().join(&c.files[0])).unwrap();
        assert_eq!(
            (saved.integrator.alpha, saved.integrator.gamma),
            per_element.damping
        );
        assert_eq!(saved.integrator.newton.rel, per_element.newton_rel);
        // The fits' Newton iteration cap (27) is not the model's: it runs with the scene's.
        assert_eq!(saved.integrator.newton.max_iterations, 30);
        assert_eq!(saved.integrator.dt, c.dt);
        let built = saved.build(&dir.path().join(&c.files[0])).unwrap();
        assert!(matches!(
            built.integrator.assembly().materials(),
            deform_assembly::MaterialField::PerElement { .. }
        ));
        for f in &c.files {
            assert!(
                report.files.contains(f) && dir.path().join(f).is_file(),
                "{f:?}"
            );
        }
    }
    let names: Vec<String> = report.plots().into_iter().map(|p| p.stem).collect();
    assert_eq!(
        names,
        [
            "rollout_error_1x_dt",
            "field_1x_dt",
            "rollout_error_2x_dt",
            "field_2x_dt"
        ]
    );
    // The field plot holds every element's pair, the same values as the saved field.
    for c in &r.cases {
        assert_eq!(c.field.len(), 2);
        assert!(c.field.iter().all(|s| s.values.len() == 24));
        let saved = deform_fs::npy::read(&dir.path().join(&c.files[1])).unwrap();
        let mut mu: Vec<f64> = saved.data.iter().step_by(2).copied().collect();
        let mut plotted = c.field[0].values.clone();
        mu.sort_by(f64::total_cmp);
        plotted.sort_by(f64::total_cmp);
        assert_eq!(mu, plotted);
    }
    // Each fit says how its optimiser stopped: 3 iterations are too few to converge here.
    for c in &r.cases {
        let fit = c
            .row(CoarseModel::Homogeneous)
            .unwrap()
            .fit
            .as_ref()
            .unwrap();
        assert_eq!(
            fit.termination,
            deform_learn::output::Termination::MaxIterations
        );
    }
    let csv = std::fs::read_to_string(dir.path().join("models.csv")).unwrap();
    assert!(csv.lines().next().unwrap().ends_with(",termination"));
    assert!(csv.contains(",\"iteration cap\""), "{csv}");
}

/// The small coarsening experiment at 2x the step only, without the smooth field, with
/// these per-element regularisation weights.
fn small_coarsen(weights: Vec<f64>) -> Experiment {
    let mut e = Experiment::load(&data("coarsen.ron")).unwrap();
    let deform_studies::Task::Coarsen {
        dt_factors,
        smooth,
        regularisation,
        ..
    } = &mut e.task
    else {
        panic!("task")
    };
    (*dt_factors, *smooth, *regularisation) = (vec![2], None, weights);
    e
}

/// The fits' Newton iteration cap reaches their rollouts: in one iteration no step reaches
/// the tight tolerance, and the fit fails naming the step.
#[test]
fn the_fits_newton_cap_is_the_one_their_rollouts_run_with() {
    let with_cap = |cap| {
        let mut e = small_coarsen(vec![0.0]);
        let deform_studies::Task::Coarsen {
            fit_newton_iterations,
            ..
        } = &mut e.task
        else {
            panic!("task")
        };
        *fit_newton_iterations = Some(cap);
        run(&e, None, &mut NoProgress)
    };
    let error = with_cap(1).unwrap_err().to_string();
    assert!(error.contains("Newton did not converge"), "{error}");
    with_cap(30).unwrap();
}

#[test]
fn each_regularisation_weight_fits_the_same_alone_or_beside_others() {
    // The first weight is fitted in the experiment's integrator, the others concurrently in
    // integrators of their own: a weight's result must not depend on which.
    let tried = |weights: Vec<f64>| {
        let report = run(&small_coarsen(weights), None, &mut NoProgress).unwrap();
        let TaskReport::Coarsen(r) = report.task else {
            panic!("task")
        };
        r.cases[0].regularisation.clone()
    };
    let together = tried(vec![0.0, 1e-2, 1e-1]);
    assert_eq!(together.len(), 3);
    for (w, error) in &together {
        assert_eq!(tried(vec![*w]), [(*w, *error)]);
    }
    assert!(together[0].1 != together[2].1, "the weights change the fit");
}

#[test]
fn a_coarse_ensemble_fits_every_members_pair_per_element_and_keeps_the_base_untuned() {
    use deform_studies::coarsen::CoarseModel;
    let dir = tempfile::tempdir().unwrap();
    let mut e = small_coarsen(vec![1e-2]);
    let plain = run(&e, None, &mut NoProgress).unwrap();
    let deform_studies::Task::Coarsen { material, .. } = &mut e.task else {
        panic!("task")
    };
    use deform_materials::{EnsembleMember, MaterialSpec, Moduli};
    let moduli = Moduli::Young { e: 1e5, nu: 0.4 };
    let ensemble = MaterialSpec::Ensemble(vec![
        EnsembleMember::new(
            0.5,
            MaterialSpec::CorotatedLinear {
                moduli,
                lagged_rotation: false,
            },
        ),
        EnsembleMember::new(0.5, MaterialSpec::NeoHookean(moduli)),
    ]);
    *material = Some(ensemble.clone());
    let report = run(&e, Some(dir.path()), &mut NoProgress).unwrap();
    let (TaskReport::Coarsen(plain), TaskReport::Coarsen(r)) = (&plain.task, &report.task) else {
        panic!("task")
    };
    assert_eq!(r.material.as_ref(), Some(&ensemble));
    let (before, c) = (&plain.cases[0], &r.cases[0]);
    // The untuned row is the base's material on the coarse mesh, whatever is fitted.
    let untuned = |c: &deform_studies::coarsen::CoarsenCase| {
        c.row(CoarseModel::Untuned).unwrap().errors.clone()
    };
    assert_eq!(untuned(c), untuned(before));
    // 24 coarse tets x 2 members x (mu, lambda), and alpha, gamma; the homogeneous fit
    // starts from the ensemble, not from the base's single model.
    let fit = |c: &deform_studies::coarsen::CoarsenCase, m| c.row(m).unwrap().fit.clone().unwrap();
    assert_eq!(fit(c, CoarseModel::PerElement).coefficients, 98);
    assert_eq!(fit(c, CoarseModel::Homogeneous).coefficients, 6);
    assert_ne!(
        fit(c, CoarseModel::Homogeneous).losses.0,
        fit(before, CoarseModel::Homogeneous).losses.0
    );
    assert_eq!(c.field.len(), 4);
    // The saved model is the ensemble with four coefficients per element.
    let path = dir.path().join(&c.files[0]);
    let saved = deform_integrator::Scene::load(&path).unwrap();
    assert_eq!(saved.material, ensemble);
    let field = deform_fs::npy::read(&dir.path().join(&c.files[1])).unwrap();
    assert_eq!(field.shape, [24, 4]);
    saved.build(&path).unwrap();
}

#[test]
fn an_unusable_stage_one_falls_back_to_the_scenes_moduli_and_says_so() {
    // Positions so noisy that the equation error explains nothing of the data.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("noisy.ron");
    let text = std::fs::read_to_string(data("fit_material.ron"))
        .unwrap()
        .replace("position: 0.001", "position: 3.0")
        .replace("\"tiny_beam.ron\"", &format!("{:?}", data("tiny_beam.ron")));
    std::fs::write(&path, text).unwrap();
    let report = run(&Experiment::load(&path).unwrap(), None, &mut NoProgress).unwrap();
    let TaskReport::FitMaterial(r) = &report.task else {
        panic!("task")
    };
    let why = r.stage1_unusable.as_ref().expect("stage 1 is unusable");
    eprintln!("{why}; rows {:?}", r.rows);
    assert!(r.output_error.is_some() && r.started_from_prior.is_some());
    assert!(r.rows[2].young.is_finite() && r.rows[2].poisson.is_finite());
}

/// On noise-free large-deformation data (stretch 30 %, spin 4 rad/s) of each of deform's
/// models, model selection among all of them, run as an experiment, names the generating
/// model as the best single model (least validation rollout error).
#[test]
fn model_selection_identifies_the_generating_model_among_all() {
    use deform_learn::Member;
    let dir = tempfile::tempdir().unwrap();
    let all: Vec<String> = Member::ALL.iter().map(|m| m.to_string()).collect();
    for base in Member::ALL {
        let material =
            ron::to_string(&base.spec(deform_materials::Moduli::Young { e: 1e5, nu: 0.3 }))
                .unwrap();
        let scene = std::fs::read_to_string(data("tiny_beam.ron"))
            .unwrap()
            .replace("NeoHookean(Young(e: 1e5, nu: 0.4))", &material);
        std::fs::write(dir.path().join("scene.ron"), scene).unwrap();
        let text = format!(
            r#"Experiment(name: "x", scene: "scene.ron", dataset: (trajectories: 5, steps: 12, seed: 3, variations: (speed: 2.0, spin: 4.0, stretch: 0.3), split: (0.4, 0.2)), task: SelectModel(members: [{}]))"#,
            all.join(", ")
        );
        let path = dir.path().join("select.ron");
        std::fs::write(&path, text).unwrap();
        let e = Experiment::load(&path).unwrap();
        let TaskReport::SelectModel(r) = run(&e, None, &mut NoProgress).unwrap().task else {
            panic!("task")
        };
        let errors: Vec<String> = r
            .models
            .iter()
            .map(|m| format!("{:?} {:.2e}", m.member, m.validation))
            .collect();
        eprintln!("data of {base}: {}", errors.join(", "));
        let best = r.best_single().unwrap();
        assert_eq!(best.member, Some(base), "{errors:?}");
        // By a wide margin: every other model misses by a million times more.
        let singles = r.models.iter().filter(|m| m.member.is_some());
        let mut others = singles.filter(|m| m.member != Some(base));
        assert!(
            others.all(|m| m.validation > 1e6 * best.validation),
            "{errors:?}"
        );
    }
}
