//! The coarsening experiment through the library: on imported trajectories of mixed
//! conditions with a given embedding, and its fits called as a library function.

use std::path::Path;

use deform_integrator::Scene;
use deform_integrator::scene::MeshSource;
use deform_learn::coarsen::{Constraints, coarsen};
use deform_learn::dataset::generate;
use deform_learn::npy;

/// `Coarsen` on data another simulator made, from the experiment file alone: the fine
/// body's trajectories under three conditions (released under gravity, kicked at its end
/// without gravity, and under sideways gravity), a given embedding, region tags, and the
/// data's own test split held out (no base model to simulate other motions).
#[test]
fn coarsen_runs_on_imported_trajectories_of_mixed_conditions_with_a_given_embedding() {
    use deform_studies::coarsen::CoarseModel;
    use deform_studies::{Experiment, NoProgress, TaskReport, run};
    let dir = tempfile::tempdir().unwrap();
    let data = |name: &str| {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/data")
            .join(name)
    };
    let fine_path = data("small_beam.ron");
    let mut fine = Scene::load(&fine_path).unwrap();
    fine.loads = vec![deform_integrator::LoadSpec::new(
        deform_mesh::select::Selector::Plane {
            point: [1.0, 0.0, 0.0],
            normal: [1.0, 0.0, 0.0],
        },
        [0.0; 3],
    )];
    let conditions = [
        "()",
        "(gravity: Some((0.0, 0.0, 0.0)), loads: Some([(force: (0.0, 30.0, 10.0), until: Some(0.03))]))",
        "(gravity: Some((0.0, 5.0, -5.0)))",
    ];
    let spec = deform_learn::DatasetSpec::new(6, 8, 3).conditions(
        conditions
            .iter()
            .map(|c| ron::from_str(c).unwrap())
            .collect(),
    );
    let made = deform_learn::dataset::generate(&fine, &fine_path, &spec, |_, _| {}).unwrap();
    let mut list = Vec::new();
    for (k, t) in made.trajectories.iter().enumerate() {
        let n = t.x[0].len() / 3;
        let x = dir.path().join(format!("x{k}.npy"));
        npy::write(&x, &[t.x.len(), n, 3], &t.x.concat()).unwrap();
        let v = dir.path().join(format!("v{k}.npy"));
        npy::write(&v, &[t.v.len(), n, 3], &t.v.concat()).unwrap();
        list.push(format!(
            "(positions: \"x{k}.npy\", velocities: File(\"v{k}.npy\"), conditions: {})",
            conditions[k % 3]
        ));
    }
    // The fine scene as the user states it (the same mesh, the load's vertex set).
    let scene_text = std::fs::read_to_string(&fine_path).unwrap().replace(
        "integrator:",
        "loads: [(select: Plane(point: (1.0, 0.0, 0.0), normal: (1.0, 0.0, 0.0)), force: (0.0, 0.0, 0.0))],\n    integrator:",
    );
    std::fs::write(dir.path().join("fine.ron"), scene_text).unwrap();
    // The embedding the user's mesher gives (nested grids: located exactly), and 3 tags.
    let fine_mesh = fine.build_mesh(&fine_path).unwrap();
    let coarse_mesh = deform_mesh::generate::BoxGrid::beam(1).build().unwrap();
    let e = deform_mesh::embed::Embedding::locate(&fine_mesh, coarse_mesh.rest_positions());
    let ids: Vec<f64> = e.element.iter().map(|&t| t as f64).collect();
    npy::write(&dir.path().join("elements.npy"), &[ids.len()], &ids).unwrap();
    let w: Vec<f64> = e.weights.iter().flatten().copied().collect();
    npy::write(&dir.path().join("weights.npy"), &[ids.len(), 4], &w).unwrap();
    let tags: Vec<f64> = (0..coarse_mesh.num_tets())
        .map(|t| (t % 3) as f64)
        .collect();
    npy::write(&dir.path().join("tags.npy"), &[tags.len()], &tags).unwrap();
    let text = format!(
        "Experiment(name: \"outside\", scene: \"fine.ron\",
            import: (dt: 0.01, gravity: (0, 0, -9.81), mass: Lumped, trajectories: [{}], split: (0.5, 0.17)),
            task: Coarsen(mesh: Beam(1), embedding: (elements: \"elements.npy\", weights: \"weights.npy\"),
                region_tags: \"tags.npy\", regularisation: [0.0], output_error: (rollout: 4, max_iterations: 4)))",
        list.join(", ")
    );
    let path = dir.path().join("outside.ron");
    std::fs::write(&path, text).unwrap();
    let experiment = Experiment::load(&path).unwrap();
    let out = dir.path().join("results");
    let report = run(&experiment, Some(&out), &mut NoProgress).unwrap();
    let TaskReport::Coarsen(r) = &report.task else {
        panic!("task")
    };
    let case = &r.cases[0];
    // Held out: the data's two test trajectories (8 steps of 0.01 s each).
    assert!((r.test_seconds - 0.16).abs() < 1e-12, "{}", r.test_seconds);
    assert_eq!(case.row(CoarseModel::Untuned).unwrap().errors.len(), 9);
    // Three tags: three pairs and the damping.
    let per_region = case.row(CoarseModel::PerRegion).unwrap();
    assert_eq!(per_region.fit.as_ref().unwrap().coefficients, 8);
    let per_element = case.row(CoarseModel::PerElement).unwrap();
    let (before, after) = per_element.fit.as_ref().unwrap().losses;
    assert!(after < before, "{before} -> {after}");
    assert!(
        case.rows
            .iter()
            .all(|r| r.mean_error().is_finite() && r.cost > 0.0)
    );
    assert!(out.join(&case.files[0]).is_file());
    // Generated held-out motions need a base model, which imported data do not have.
    let text = std::fs::read_to_string(&path).unwrap().replace(
        "mesh: Beam(1),",
        "mesh: Beam(1), test: (trajectories: 1, steps: 4, seed: 1),",
    );
    std::fs::write(&path, text).unwrap();
    let error = Experiment::load(&path).unwrap_err().to_string();
    assert!(
        error.contains("task.test") && error.contains("imported"),
        "{error}"
    );
    // A given embedding that does not fit is refused, naming the file.
    npy::write(
        &dir.path().join("weights.npy"),
        &[ids.len(), 4],
        &vec![0.5; 4 * ids.len()],
    )
    .unwrap();
    let broken = std::fs::read_to_string(&path)
        .unwrap()
        .replace("test: (trajectories: 1, steps: 4, seed: 1),", "");
    std::fs::write(&path, broken).unwrap();
    let error = run(&Experiment::load(&path).unwrap(), None, &mut NoProgress)
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("weights.npy") && error.contains("sum to 1"),
        "{error}"
    );
}

/// The coarsening study's fits as a library call, without the runner: the same models and
/// figures as the experiment, and the per-element model saved as a scene that builds.
#[test]
fn the_coarse_fits_are_a_library_function_with_the_experiments_figures() {
    use deform_studies::coarsen::{CoarseModel, CoarseSettings, fit_coarse_models};
    use deform_studies::{Experiment, NoProgress, Task, TaskReport, run};
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/coarsen.ron");
    let mut experiment = Experiment::load(&path).unwrap();
    let Task::Coarsen {
        dt_factors,
        smooth,
        regularisation,
        regions,
        newton_rel,
        fit_newton_iterations,
        output_error,
        ..
    } = &mut experiment.task
    else {
        panic!("task")
    };
    *dt_factors = vec![1];
    let settings = CoarseSettings::new(30, *output_error)
        .regions(*regions)
        .smooth(*smooth)
        .regularisation(regularisation.clone())
        .newton_rel(newton_rel.clone())
        .fit_newton_iterations(*fit_newton_iterations);
    let report = run(&experiment, None, &mut NoProgress).unwrap();
    let TaskReport::Coarsen(r) = &report.task else {
        panic!("task")
    };
    // The same data and coarse scene as the experiment's, by the library alone.
    let fine = Scene::load(&experiment.scene).unwrap();
    let deform_studies::Data::Generate(spec) = &experiment.data else {
        panic!("generated data")
    };
    let data = generate(&fine, &experiment.scene, spec, |_, _| {}).unwrap();
    let coarse = fine.clone().name("coarse".into()).mesh(MeshSource::Beam(1));
    let (coarse_data, _) =
        coarsen(&data, &coarse, &experiment.scene, Constraints::FromFine).unwrap();
    let fits =
        fit_coarse_models(&coarse_data, &experiment.scene, &settings, &mut NoProgress).unwrap();
    let kinds: Vec<CoarseModel> = fits.models.iter().map(|m| m.model).collect();
    let rows: Vec<CoarseModel> = r.cases[0]
        .rows
        .iter()
        .skip(1)
        .map(|row| row.model)
        .collect();
    assert_eq!(kinds, rows);
    for (m, row) in fits.models.iter().zip(r.cases[0].rows.iter().skip(1)) {
        assert_eq!(
            m.fit.as_ref().map(|f| f.losses),
            row.fit.as_ref().map(|f| f.losses)
        );
        assert_eq!((m.options.alpha, m.options.gamma), row.damping);
    }
    assert_eq!(fits.regularisation, r.cases[0].regularisation);
    // The weights' fits run side by side or, on one thread, one after another: the same
    // bits either way.
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| fit_coarse_models(&coarse_data, &experiment.scene, &settings, &mut NoProgress))
        .unwrap();
    assert_eq!(one.regularisation, fits.regularisation);
    for (a, b) in one.models.iter().zip(&fits.models) {
        assert_eq!(
            a.fit.as_ref().map(|f| f.losses),
            b.fit.as_ref().map(|f| f.losses)
        );
    }
    let dir = tempfile::tempdir().unwrap();
    let files = fits
        .save(&coarse_data.meta.scene, "mine", dir.path())
        .unwrap();
    let saved = Scene::load(&dir.path().join(&files[0])).unwrap();
    let built = saved.build(&dir.path().join(&files[0])).unwrap();
    assert!(matches!(
        built.integrator.assembly().materials(),
        deform_assembly::MaterialField::PerElement { .. }
    ));
}

/// The coarse-fit benchmark, at its smallest: the fine data carried onto the coarse beam and
/// every coarse model fitted, with the timings `cargo xtask bench coarsen` prints.
#[test]
fn the_coarse_fit_benchmark_fits_every_model_on_a_tiny_beam() {
    use deform_studies::coarsen::bench::{CoarsenBench, bench_coarse_fits};
    let mut b = CoarsenBench::default();
    (b.fine, b.coarse, b.trajectories, b.steps, b.rollout) = (2, 1, 1, 4, 2);
    let t = bench_coarse_fits(&b).unwrap();
    assert_eq!(
        t.coarse_tets,
        deform_mesh::generate::BoxGrid::beam(1).num_tets()
    );
    assert!(t.fits.models.iter().filter(|m| m.fit.is_some()).count() >= 3);
    assert!(t.generate_seconds > 0.0 && t.fit_seconds > 0.0);
}
