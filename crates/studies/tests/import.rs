//! Experiments on imported data: a generated dataset saved by the runner and imported back
//! gives the same data and the same fit; meshes and constraints from `.npy` arrays; bad
//! imports refused naming the file, field, step or vertex.

use std::path::{Path, PathBuf};

use deform_integrator::Scene;
use deform_learn::LearnError;
use deform_learn::npy;
use deform_studies::{Data, Experiment, NoProgress, TaskReport, run, write_report};

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

/// The import of a saved dataset's trajectories (positions and velocities files) with the
/// given extra text (e.g. a split).
fn import_text(dir: &Path, trajectories: usize, velocities: &str, task: &str) -> String {
    let list: Vec<String> = (0..trajectories)
        .map(|k| {
            let folder = dir.join(format!("traj_{k:03}"));
            let v = match velocities {
                "File" => format!("File({:?})", folder.join("v.npy")),
                "Initial" => format!("Initial({:?})", folder.join("v0.npy")),
                _ => "Derived".to_owned(),
            };
            format!("(positions: {:?}, velocities: {v})", folder.join("x.npy"))
        })
        .collect();
    format!(
        "Experiment(name: \"imported\", scene: {:?}, import: (dt: 0.01, gravity: (0, 0, -9.81), mass: Lumped, trajectories: [{}], split: (0.34, 0.33)), task: {task})",
        data("tiny_beam.ron"),
        list.join(", ")
    )
}

fn load(dir: &Path, text: &str) -> Result<Experiment, LearnError> {
    let path = dir.join("experiment.ron");
    std::fs::write(&path, text).unwrap();
    Experiment::load(&path)
}

#[test]
fn a_saved_dataset_imported_back_gives_the_same_data_and_fit() {
    let dir = tempfile::tempdir().unwrap();
    let generated = Experiment::load(&data("fit_material.ron")).unwrap();
    let out = dir.path().join("generated");
    let first = run(&generated, Some(&out), &mut NoProgress).unwrap();
    let saved = out.join("dataset");
    let task = "FitMaterial(output_error: Some((rollout: 3, max_iterations: 5)))";
    let imported = load(dir.path(), &import_text(&saved, 3, "File", task)).unwrap();
    assert!(matches!(imported.data, Data::Import(_)));
    let again_out = dir.path().join("imported");
    let again = run(&imported, Some(&again_out), &mut NoProgress).unwrap();
    // The data are the saved ones, bit for bit (noise was added before saving).
    let a = deform_learn::Dataset::load(&saved).unwrap();
    let b = deform_learn::Dataset::load(&again_out.join("dataset")).unwrap();
    assert_eq!(a.trajectories, b.trajectories);
    assert!(b.meta.trajectories[0].source.is_some());
    let (TaskReport::FitMaterial(r1), TaskReport::FitMaterial(r2)) = (first.task, again.task)
    else {
        panic!("task")
    };
    assert_eq!(r1.rows.len(), 3);
    for (x, y) in r1.rows.iter().zip(&r2.rows) {
        assert_eq!(
            (x.young, x.poisson),
            (y.young, y.poisson),
            "{:?}",
            x.estimate
        );
    }
}

#[test]
fn only_v0_keeps_the_first_frame_and_derives_the_rest() {
    let dir = tempfile::tempdir().unwrap();
    let generated = Experiment::load(&data("select_model.ron")).unwrap();
    let out = dir.path().join("generated");
    run(&generated, Some(&out), &mut NoProgress).unwrap();
    let saved = out.join("dataset");
    let a = deform_learn::Dataset::load(&saved).unwrap();
    for (k, t) in a.trajectories.iter().enumerate() {
        let v0 = saved.join(format!("traj_{k:03}/v0.npy"));
        npy::write(&v0, &[t.v[0].len() / 3, 3], &t.v[0]).unwrap();
    }
    let task = "SelectModel(members: [CorotatedLinear, NeoHookean], output_error: Some((rollout: 2, max_evaluations: 4)))";
    let e = load(dir.path(), &import_text(&saved, 3, "Initial", task)).unwrap();
    let report = run(&e, Some(&dir.path().join("v0")), &mut NoProgress).unwrap();
    let b = deform_learn::Dataset::load(&dir.path().join("v0/dataset")).unwrap();
    for (ta, tb) in a.trajectories.iter().zip(&b.trajectories) {
        assert_eq!(ta.x, tb.x);
        assert_eq!(ta.v[0], tb.v[0]);
        // Backward Euler's own relation: the derived velocities are the data's to rounding.
        for (va, vb) in ta.v.iter().zip(&tb.v).skip(1) {
            let scale = va.iter().fold(1.0f64, |m, v| m.max(v.abs()));
            assert!(
                va.iter()
                    .zip(vb)
                    .all(|(p, q)| (p - q).abs() <= 1e-9 * scale)
            );
        }
    }
    let TaskReport::SelectModel(r) = report.task else {
        panic!("task")
    };
    assert!(!r.models.is_empty() && !r.rollouts.is_empty());
    // Derived velocities drop the first frame.
    let e = load(dir.path(), &import_text(&saved, 3, "Derived", task)).unwrap();
    let Data::Import(spec) = &e.data else {
        panic!("import")
    };
    let scene = Scene::load(&data("tiny_beam.ron")).unwrap();
    let c = deform_learn::import::import(spec, &scene, &data("tiny_beam.ron")).unwrap();
    assert_eq!(c.trajectories[0].x[0], a.trajectories[0].x[1]);
    assert_eq!(
        c.meta.trajectories[0].steps,
        a.meta.trajectories[0].steps - 1
    );
}

/// A scene whose mesh and clamped vertex ids are `.npy` arrays builds the same model as
/// the generated beam with a plane selector.
#[test]
fn meshes_and_constraints_from_arrays() {
    let dir = tempfile::tempdir().unwrap();
    let scene = Scene::load(&data("tiny_beam.ron")).unwrap();
    let built = scene.build(&data("tiny_beam.ron")).unwrap();
    let mesh = &built.mesh;
    let vertices: Vec<f64> = mesh.rest_positions_flat();
    let tets: Vec<f64> = mesh.tets().iter().flatten().map(|&i| i as f64).collect();
    npy::write(
        &dir.path().join("vertices.npy"),
        &[mesh.num_vertices(), 3],
        &vertices,
    )
    .unwrap();
    npy::write(&dir.path().join("tets.npy"), &[mesh.num_tets(), 4], &tets).unwrap();
    let clamped = built.integrator.dofs().constrained_vertices();
    let ids: Vec<f64> = clamped.iter().map(|&i| i as f64).collect();
    npy::write(&dir.path().join("clamped.npy"), &[ids.len()], &ids).unwrap();
    let text = std::fs::read_to_string(data("tiny_beam.ron"))
        .unwrap()
        .replace(
            "mesh: Beam(1)",
            "mesh: Arrays(vertices: \"vertices.npy\", tets: \"tets.npy\")",
        )
        .replace(
            "Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0))",
            "File(\"clamped.npy\")",
        );
    let path = dir.path().join("scene.ron");
    std::fs::write(&path, &text).unwrap();
    let from_arrays = Scene::load(&path).unwrap().build(&path).unwrap();
    assert_eq!(from_arrays.mesh.tets(), mesh.tets());
    assert_eq!(from_arrays.mesh.rest_positions(), mesh.rest_positions());
    assert_eq!(
        from_arrays.integrator.dofs().constrained_vertices(),
        clamped
    );
    // Bad arrays are refused naming the file.
    let build_error = || {
        Scene::load(&path)
            .unwrap()
            .build(&path)
            .err()
            .unwrap()
            .to_string()
    };
    npy::write(&dir.path().join("tets.npy"), &[2, 3], &tets[..6]).unwrap();
    let e = build_error();
    assert!(e.contains("tets.npy") && e.contains("shape"), "{e}");
    npy::write(&dir.path().join("tets.npy"), &[mesh.num_tets(), 4], &tets).unwrap();
    npy::write(&dir.path().join("clamped.npy"), &[1], &[1e6]).unwrap();
    let e = build_error();
    assert!(
        e.contains("clamped.npy") && e.contains("out of range"),
        "{e}"
    );
    npy::write(&dir.path().join("clamped.npy"), &[1], &[0.5]).unwrap();
    let e = build_error();
    assert!(e.contains("clamped.npy") && e.contains("integer"), "{e}");
}

#[test]
fn bad_imports_are_refused_naming_what_is_wrong() {
    let dir = tempfile::tempdir().unwrap();
    let saved = dir.path().join("d");
    let task = "FitMaterial()";
    let good = import_text(&saved, 3, "File", task);
    // Gravity is never assumed.
    let e = load(dir.path(), &good.replace("gravity: (0, 0, -9.81), ", ""))
        .unwrap_err()
        .to_string();
    assert!(e.contains("gravity"), "{e}");
    let e = load(dir.path(), &good.replace("mass: Lumped, ", ""))
        .unwrap_err()
        .to_string();
    assert!(e.contains("mass"), "{e}");
    let both = good.replace(
        "import:",
        "dataset: (trajectories: 3, steps: 3, seed: 1), import:",
    );
    let e = load(dir.path(), &both).unwrap_err().to_string();
    assert!(e.contains("not both"), "{e}");
    let e = load(dir.path(), &good.replace("dt: 0.01", "dt: -1.0"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("import.dt"), "{e}");
    let coarsen = good.replace(
        task,
        "Coarsen(mesh: Beam(1), test: (trajectories: 1, steps: 4, seed: 1), output_error: ())",
    );
    let e = load(dir.path(), &coarsen).unwrap_err().to_string();
    assert!(e.contains("import") && e.contains("base model"), "{e}");
    // Files: missing, wrong vertex count, a constrained vertex that moves.
    let e = load(dir.path(), &good).unwrap();
    let err = run(&e, None, &mut NoProgress).unwrap_err().to_string();
    assert!(err.contains("traj_000") && err.contains("x.npy"), "{err}");
    let scene = Scene::load(&data("tiny_beam.ron")).unwrap();
    let built = scene.build(&data("tiny_beam.ron")).unwrap();
    let n = built.mesh.num_vertices();
    let rest = built.mesh.rest_positions_flat();
    for k in 0..3 {
        let folder = saved.join(format!("traj_{k:03}"));
        std::fs::create_dir_all(&folder).unwrap();
        let frames: Vec<f64> = rest.iter().chain(&rest).chain(&rest).copied().collect();
        npy::write(&folder.join("x.npy"), &[3, n, 3], &frames).unwrap();
        npy::write(&folder.join("v.npy"), &[3, n, 3], &vec![0.0; 9 * n]).unwrap();
    }
    let bad = saved.join("traj_001/x.npy");
    let bad_v = saved.join("traj_001/v.npy");
    npy::write(&bad, &[3, n - 1, 3], &vec![0.0; 9 * (n - 1)]).unwrap();
    npy::write(&bad_v, &[3, n - 1, 3], &vec![0.0; 9 * (n - 1)]).unwrap();
    let err = run(&e, None, &mut NoProgress).unwrap_err().to_string();
    assert!(
        err.contains("traj_001") && err.contains("vertices"),
        "{err}"
    );
    let clamped = built.integrator.dofs().constrained_vertices()[0];
    let mut moved: Vec<f64> = rest.iter().chain(&rest).chain(&rest).copied().collect();
    moved[3 * n + 3 * clamped] += 1e-3;
    npy::write(&bad, &[3, n, 3], &moved).unwrap();
    npy::write(&bad_v, &[3, n, 3], &vec![0.0; 9 * n]).unwrap();
    let err = run(&e, None, &mut NoProgress).unwrap_err().to_string();
    assert!(
        err.contains("traj_001")
            && err.contains("step 1")
            && err.contains(&format!("vertex {clamped}")),
        "{err}"
    );
}

/// `experiment` run on generated data and on those data imported back (saved by the first
/// run, at the base's step, with its subsampling): both reports.
fn generated_and_imported(name: &str) -> (TaskReport, TaskReport) {
    use deform_learn::import::{ImportSpec, ImportedTrajectory, VelocitySource};
    let dir = tempfile::tempdir().unwrap();
    let generated = Experiment::load(&data(&format!("{name}.ron"))).unwrap();
    let out = dir.path().join("generated");
    let first = run(&generated, Some(&out), &mut NoProgress).unwrap();
    let Data::Generate(spec) = &generated.data else {
        panic!("generated")
    };
    let folder = |k: usize| out.join(format!("dataset/traj_{k:03}"));
    let trajectories = (0..spec.trajectories)
        .map(|k| {
            let v = VelocitySource::File(folder(k).join("v.npy"));
            ImportedTrajectory::new(folder(k).join("x.npy"), v)
        })
        .collect();
    let scene = Scene::load(&generated.scene).unwrap();
    let i = &scene.integrator;
    let import = ImportSpec::new(i.dt, i.gravity, i.mass, trajectories)
        .split(spec.split)
        .subsample(spec.subsample);
    let imported = generated.clone().data(Data::Import(import));
    let again = run(&imported, None, &mut NoProgress).unwrap();
    (first.task, again.task)
}

#[test]
fn solver_selection_coarse_dt_and_solver_tuning_run_on_imported_data() {
    let (TaskReport::SelectSolver(a), TaskReport::SelectSolver(b)) =
        generated_and_imported("select_solver")
    else {
        panic!("task")
    };
    assert_eq!((a.logged, a.cases.len()), (b.logged, b.cases.len()));
    let (TaskReport::TuneBackwardEuler(a), TaskReport::TuneBackwardEuler(b)) =
        generated_and_imported("tune_backward_euler")
    else {
        panic!("task")
    };
    assert_eq!(b.subsample, 2);
    assert_eq!(a.fit.coefficients, b.fit.coefficients);
    let (TaskReport::TuneSolver(a), TaskReport::TuneSolver(b)) =
        generated_and_imported("tune_solver")
    else {
        panic!("task")
    };
    // Generated data tune on the scene's own motion, imported ones on their first
    // trajectory's (a scene has no motion for them): both keep the accuracy.
    for r in [a, b] {
        assert!(r.result.samples.len() > 1);
        assert!(r.result.best.error <= r.accuracy, "{:?}", r.result.best);
    }
}

/// The runner alone on positions only with 1 % noise (no velocities: they are differenced
/// from the noisy positions): an experiment file imports them (`Derived`) and fits with
/// estimated rollout starts, as a user with outside data would; E within 0.5 %, nu within
/// 2 %.
#[test]
fn noisy_imported_positions_give_the_moduli_with_estimated_starts() {
    let dir = tempfile::tempdir().unwrap();
    let scene_path = data("tiny_beam.ron");
    let scene = Scene::load(&scene_path).unwrap();
    let spec = deform_learn::DatasetSpec::new(5, 41, 42).split((0.6, 0.2));
    let mut made = deform_learn::dataset::generate(&scene, &scene_path, &spec, |_, _| {}).unwrap();
    let clamped = scene
        .build(&scene_path)
        .unwrap()
        .integrator
        .dofs()
        .constrained_vertices();
    let noise = deform_learn::Noise::default()
        .position(0.01)
        .velocity(0.0)
        .seed(7);
    made.add_noise(noise, &clamped);
    let mut list = Vec::new();
    for (k, t) in made.trajectories.iter().enumerate() {
        let path = dir.path().join(format!("x{k}.npy"));
        let n = t.x[0].len() / 3;
        npy::write(&path, &[t.x.len(), n, 3], &t.x.concat()).unwrap();
        list.push(format!("(positions: \"x{k}.npy\", velocities: Derived)"));
    }
    let text = format!(
        "Experiment(name: \"noisy\", scene: {scene_path:?}, import: (dt: 0.01, gravity: (0, 0, -9.81), mass: Lumped, trajectories: [{}], split: (0.6, 0.2)), task: FitMaterial(start: Some(Young(e: 1.3e5, nu: 0.35)), output_error: Some((rollout: 10, max_iterations: 150, max_evaluations: 300, starts: Some(())))))",
        list.join(", ")
    );
    let e = load(dir.path(), &text).unwrap();
    let report = run(&e, None, &mut NoProgress).unwrap();
    let TaskReport::FitMaterial(r) = report.task else {
        panic!("task")
    };
    let fit = r.output_error.as_ref().unwrap();
    eprintln!(
        "{}, {} iterations, start correction {:?}",
        r.headline(),
        fit.iteration_count(),
        fit.start_correction
    );
    assert!(fit.start_correction.is_some());
    assert!(r.young_error() < Some(0.005) && r.poisson_error() < Some(0.02));
}

/// No text file under `dir` holds a NaN (CSV, markdown, RON).
fn assert_no_nan_written(dir: &Path) {
    for entry in walk(dir) {
        let ext = entry.extension().and_then(|e| e.to_str());
        if matches!(ext, Some("csv" | "md" | "ron")) {
            let text = std::fs::read_to_string(&entry).unwrap();
            assert!(
                !text.to_lowercase().contains("nan"),
                "{}:\n{text}",
                entry.display()
            );
        }
    }
}

/// Every file under `dir`.
fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            files.extend(walk(&path));
        } else {
            files.push(path);
        }
    }
    files
}

/// `data` of `shape` as a little-endian float32 `.npy` (numpy's `astype(np.float32)`).
fn write_f32(path: &Path, shape: &[usize], data: &[f64]) {
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let mut header = format!(
        "{{'descr': '<f4', 'fortran_order': False, 'shape': ({},), }}",
        dims.join(", ")
    );
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend((header.len() as u16).to_le_bytes());
    bytes.extend(header.as_bytes());
    for v in data {
        bytes.extend((*v as f32).to_le_bytes());
    }
    std::fs::write(path, bytes).unwrap();
}

/// What a user with two float32 trajectories of another simulator meets: the runner takes
/// two (one to fit, one to test), single-precision clamps pass (a clamp that moves is
/// still refused, naming the dtype), the scene's moduli are reported as its guess (not as
/// the truth), and a run refused on its data leaves no results folder behind.
#[test]
fn two_float32_trajectories_fit_and_a_refused_run_leaves_no_folder() {
    let dir = tempfile::tempdir().unwrap();
    let scene_path = data("tiny_beam.ron");
    let scene = Scene::load(&scene_path).unwrap();
    let made = deform_learn::dataset::generate(
        &scene,
        &scene_path,
        &deform_learn::DatasetSpec::new(2, 6, 3),
        |_, _| {},
    )
    .unwrap();
    let n = made.meta.vertices;
    let mut list = Vec::new();
    for (k, t) in made.trajectories.iter().enumerate() {
        let x = dir.path().join(format!("x{k}.npy"));
        write_f32(&x, &[t.x.len(), n, 3], &t.x.concat());
        let v0 = dir.path().join(format!("v{k}.npy"));
        write_f32(&v0, &[n, 3], &t.v[0]);
        list.push(format!(
            "(positions: \"x{k}.npy\", velocities: Initial(\"v{k}.npy\"))"
        ));
    }
    let text = format!(
        "Experiment(name: \"two\", scene: {scene_path:?}, import: (dt: 0.01, gravity: (0, 0, -9.81), mass: Lumped, trajectories: [{}], split: (0.5, 0.0)), task: FitMaterial(output_error: Some((rollout: 3, max_evaluations: 20))))",
        list.join(", ")
    );
    let e = load(dir.path(), &text).unwrap();
    let Data::Import(spec) = &e.data else {
        panic!("import")
    };
    let imported = deform_learn::import::import(spec, &scene, &scene_path).unwrap();
    // Given initial velocities make the first frame exact.
    assert!(imported.trajectories.iter().all(|t| t.exact_start));
    assert!(imported.meta.trajectories.iter().all(|m| m.exact_start));
    let report = run(&e, None, &mut NoProgress).unwrap();
    let TaskReport::FitMaterial(r) = &report.task else {
        panic!("task")
    };
    assert!(!r.truth_known());
    assert_eq!(r.rows[0].estimate.name(), "scene's guess");
    assert_eq!(r.rollouts[0].name, "scene's parameters");
    assert!(
        report.headline().contains("scene's guess"),
        "{}",
        report.headline()
    );
    // The start prior's type is where a user looks for it.
    let _: deform_learn::StartPrior = Default::default();
    // A clamped vertex that moves by 1 mm in float32 is refused, naming the dtype.
    let built = scene.build(&scene_path).unwrap();
    let clamped = built.integrator.dofs().constrained_vertices()[0];
    let mut x = made.trajectories[1].x.concat();
    x[3 * n + 3 * clamped] += 1e-3;
    write_f32(
        &dir.path().join("x1.npy"),
        &[made.trajectories[1].x.len(), n, 3],
        &x,
    );
    let out = dir.path().join("results");
    let err = run(&e, Some(&out), &mut NoProgress)
        .unwrap_err()
        .to_string();
    assert!(err.contains("x1.npy") && err.contains("float32"), "{err}");
    assert!(!out.exists(), "a refused run left {}", out.display());
}

/// The documented noisy path with default options: on noisy states (2 % position, 300 %
/// velocity noise) stage 1 is
/// unusable, and stage 2 starts from the scene's guess and fits, accepting rollout steps
/// that converge only in halves (here every step: Newton is capped at 3 iterations). With
/// such steps refused, the error says why stage 2 could not start and names the step,
/// never "mu = 0".
#[test]
fn noisy_data_fit_with_default_options_or_say_which_step_failed() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(data("tiny_beam.ron"))
        .unwrap()
        .replace(
            "newton: (rel: 1e-10, abs: 1e-12)",
            "newton: (rel: 1e-10, abs: 1e-12, max_iterations: 3), max_retries: 6",
        );
    let scene_path = dir.path().join("capped.ron");
    std::fs::write(&scene_path, text).unwrap();
    let experiment = |options: &str| {
        format!(
            "Experiment(name: \"noisy\", scene: {scene_path:?}, dataset: (trajectories: 4, steps: 12, seed: 4, split: (0.5, 0.25), noise: Some((position: 0.02, velocity: 3.0, seed: 1))), task: FitMaterial(output_error: Some(({options}))))"
        )
    };
    let e = load(dir.path(), &experiment("max_evaluations: 30")).unwrap();
    let report = run(&e, None, &mut NoProgress).unwrap();
    let TaskReport::FitMaterial(r) = &report.task else {
        panic!("task")
    };
    assert!(
        r.stage1_unusable.is_some(),
        "stage 1 was usable: {:?}",
        r.rows
    );
    let fit = r.output_error.as_ref().unwrap();
    assert!(r.started_from_prior.is_some() && fit.loss <= fit.initial_loss);
    assert!(r.rows[2].young.is_finite(), "{:?}", r.rows);
    let e = load(dir.path(), &experiment("allow_retries: false")).unwrap();
    let err = run(&e, None, &mut NoProgress).unwrap_err().to_string();
    assert!(
        err.contains("stage 1 is unusable") && err.contains("step") && err.contains("halvings"),
        "{err}"
    );
    assert!(!err.contains("mu = 0"), "{err}");
}

/// A capture through the runner: each motion seen twice, through 4 free vertices and
/// through 2 points inside elements (`markers`), the scene's moduli a guess 30 % off. The first
/// state is estimated with the guess, stage 1 is skipped (it needs whole states) and stage 2
/// refines the starts with the material: E and nu within 1 % of the model that made the data.
#[test]
fn a_capture_of_markers_fits_the_moduli_from_the_runner() {
    let dir = tempfile::tempdir().unwrap();
    let scene_path = data("tiny_beam.ron");
    let scene = Scene::load(&scene_path).unwrap();
    let spec = deform_learn::DatasetSpec::new(4, 20, 3);
    let made = deform_learn::dataset::generate(&scene, &scene_path, &spec, |_, _| {}).unwrap();
    let built = scene.build(&scene_path).unwrap();
    let free: Vec<usize> = (0..built.mesh.num_vertices())
        .filter(|&v| !built.integrator.dofs().is_constrained(v))
        .collect();
    let vertices: Vec<usize> = free.iter().copied().step_by(3).take(4).collect();
    let (elements, weights) = ([7.0, 19.0], [0.1, 0.2, 0.3, 0.4, 0.25, 0.25, 0.25, 0.25]);
    let mut markers: Vec<deform_learn::observe::Marker> = vertices
        .iter()
        .map(|&v| deform_learn::observe::Marker::Vertex(v))
        .collect();
    for (e, w) in elements.iter().zip(weights.chunks(4)) {
        let w = [w[0], w[1], w[2], w[3]];
        markers
            .push(deform_learn::observe::Marker::in_element(&built.mesh, *e as usize, w).unwrap());
    }
    let ids: Vec<f64> = vertices.iter().map(|&v| v as f64).collect();
    npy::write(&dir.path().join("ids.npy"), &[4], &ids).unwrap();
    npy::write(&dir.path().join("elements.npy"), &[2], &elements).unwrap();
    npy::write(&dir.path().join("weights.npy"), &[2, 4], &weights).unwrap();
    let mut list = Vec::new();
    for (k, t) in made.trajectories.iter().enumerate() {
        // Each motion twice: seen through the vertices, and through the inside points.
        let (a, b) = (format!("v{k}.npy"), format!("i{k}.npy"));
        let (seen, inside): (Vec<f64>, Vec<f64>) = (
            t.x.iter()
                .flat_map(|x| {
                    markers[..4]
                        .iter()
                        .flat_map(|m| m.position(x))
                        .collect::<Vec<_>>()
                })
                .collect(),
            t.x.iter()
                .flat_map(|x| {
                    markers[4..]
                        .iter()
                        .flat_map(|m| m.position(x))
                        .collect::<Vec<_>>()
                })
                .collect(),
        );
        npy::write(&dir.path().join(&a), &[t.x.len(), 4, 3], &seen).unwrap();
        npy::write(&dir.path().join(&b), &[t.x.len(), 2, 3], &inside).unwrap();
        list.push(format!(
            "(positions: \"{a}\", velocities: Derived, markers: Some(Vertices(\"ids.npy\")))"
        ));
        list.push(format!("(positions: \"{b}\", velocities: Derived, markers: Some(Inside(elements: \"elements.npy\", weights: \"weights.npy\")))"));
    }
    let guess = std::fs::read_to_string(&scene_path)
        .unwrap()
        .replace("Young(e: 1e5, nu: 0.4)", "Young(e: 1.3e5, nu: 0.35)");
    std::fs::write(dir.path().join("guess.ron"), guess).unwrap();
    let text = format!(
        "Experiment(name: \"capture\", scene: \"guess.ron\", import: (dt: 0.01, gravity: (0, 0, -9.81), mass: Lumped, trajectories: [{}], split: (0.5, 0.25)), task: FitMaterial(output_error: Some((rollout: 20, max_iterations: 150, max_evaluations: 150, starts: Some(())))))",
        list.join(", ")
    );
    // Without output error there is nothing to fit from markers: refused, saying why.
    let stage1_only = text.replace(
        "FitMaterial(output_error: Some((rollout: 20, max_iterations: 150, max_evaluations: 150, starts: Some(()))))",
        "FitMaterial()",
    );
    let err = run(
        &load(dir.path(), &stage1_only).unwrap(),
        None,
        &mut NoProgress,
    )
    .unwrap_err();
    assert!(
        err.to_string().contains("needs `output_error`")
            && err.to_string().contains("markers only"),
        "{err}"
    );
    let e = load(dir.path(), &text).unwrap();
    let out = dir.path().join("out");
    let report = run(&e, Some(&out), &mut NoProgress).unwrap();
    let markdown = write_report(&report, &out).unwrap();
    // Stage 1 did not run: no row, no rollout, no NaN written anywhere.
    assert!(!markdown.contains("| equation error |"), "{markdown}");
    assert_no_nan_written(&out);
    let TaskReport::FitMaterial(r) = report.task else {
        panic!("task")
    };
    assert_eq!(r.rows.len(), 2, "{:?}", r.rows);
    let names: Vec<&str> = r.rollouts.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(names, ["scene's parameters", "fitted"]);
    let fit = r.output_error.as_ref().unwrap();
    assert_eq!(
        (fit.iterations[0].iteration, fit.iterations[0].loss),
        (0, fit.initial_loss),
        "iterations.csv starts at the start"
    );
    assert!(
        matches!(
            r.stage1_unusable,
            Some(deform_learn::Unusable::MarkersOnly { .. })
        ),
        "{:?}",
        r.stage1_unusable
    );
    assert!(r.unstable.is_none(), "{:?}", r.unstable);
    let fitted = r.rows.last().unwrap();
    let (de, dnu) = (
        (fitted.young - 1e5).abs() / 1e5,
        (fitted.poisson - 0.4).abs() / 0.4,
    );
    eprintln!("E {:.3} %, nu {:.3} %", 100.0 * de, 100.0 * dnu);
    assert!(
        de < 0.01 && dnu < 0.01,
        "E {}, nu {}",
        fitted.young,
        fitted.poisson
    );
}

/// Positions only of a body whose clamped end moves: the first frame, which has no velocity,
/// is dropped, so the trajectory starts at `dt`, and the moving constraint is checked and
/// simulated at `dt + n dt` (at `n dt` the import refused the data, its clamped vertices a
/// step ahead of where the scene put them). Stage 1 and the rollout error then match the
/// model that made the data; the start time survives the dataset folder.
#[test]
fn derived_velocities_keep_the_time_of_a_moving_constraint() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(data("tiny_beam.ron"))
        .unwrap()
        .replace(
            "motion: Fixed",
            "motion: Translate(velocity: (0.0, 0.0, 0.5))",
        );
    let scene_path = dir.path().join("pulled.ron");
    std::fs::write(&scene_path, text).unwrap();
    let scene = Scene::load(&scene_path).unwrap();
    let made = deform_learn::dataset::generate(
        &scene,
        &scene_path,
        &deform_learn::DatasetSpec::new(3, 12, 9),
        |_, _| {},
    )
    .unwrap();
    let mut read = Vec::new();
    for (k, t) in made.trajectories.iter().enumerate() {
        let n = t.x[0].len() / 3;
        let a = npy::Array::new(vec![t.x.len(), n, 3], t.x.concat());
        let name = format!("x{k}");
        let v = deform_learn::import::ArrayVelocities::Derived;
        let imported = deform_learn::import::trajectory_from_arrays((&name, None), &a, v, 0.01);
        let imported = imported.unwrap();
        assert_eq!(imported.start_time, 0.01);
        read.push((imported, deform_learn::import::Source::float64(name)));
    }
    let data =
        deform_learn::import::from_trajectories(&scene, &scene_path, read, (0.6, 0.2)).unwrap();
    let sim = scene.build(&scene_path).unwrap().integrator;
    let train: Vec<_> = data.trajectories.iter().collect();
    let fit = deform_learn::fit_equation_error(&sim, &train, Default::default()).unwrap();
    let truth = deform_materials::Lame::from_young(1e5, 0.4).unwrap();
    let off = (fit.coefficients[0] / truth.mu - 1.0).abs();
    assert!(off < 1e-6, "mu off by {off:.3e}");
    let mut sim = sim;
    let errors = deform_learn::rollout::rollout_error(&mut sim, train[0]).unwrap();
    assert!(errors.iter().all(|e| *e < 1e-8), "{errors:?}");
    data.save(&dir.path().join("saved")).unwrap();
    let loaded = deform_learn::Dataset::load(&dir.path().join("saved")).unwrap();
    assert_eq!(loaded.trajectories[0].start_time, 0.01);
}

/// Each marker file is blamed for its own faults, saying what it holds: a vertex id out of
/// range names the ids file (it named the positions), an element out of range the elements
/// file and a wrong weights shape the weights file (the two were swapped).
#[test]
fn bad_marker_files_are_named_for_their_own_faults() {
    let dir = tempfile::tempdir().unwrap();
    let scene_path = data("tiny_beam.ron");
    let scene = Scene::load(&scene_path).unwrap();
    npy::write(&dir.path().join("x.npy"), &[3, 2, 3], &[0.5; 18]).unwrap();
    let fail = |markers: &str, files: &[(&str, &[usize], &[f64])]| {
        for (name, shape, values) in files {
            npy::write(&dir.path().join(name), shape, values).unwrap();
        }
        let t = format!("(positions: \"x.npy\", velocities: Derived, markers: Some({markers}))");
        let text = format!(
            "Experiment(name: \"m\", scene: {scene_path:?}, import: (dt: 0.01, gravity: (0, 0, -9.81), mass: Lumped, trajectories: [{t}, {t}], split: (0.5, 0.0)), task: FitMaterial(output_error: Some(())))"
        );
        let e = load(dir.path(), &text).unwrap();
        let Data::Import(spec) = &e.data else {
            panic!("import")
        };
        match deform_learn::import::import(spec, &scene, &scene_path) {
            Ok(_) => panic!("{markers}: accepted"),
            Err(err) => err.to_string(),
        }
    };
    let weights: &[f64] = &[0.25; 8];
    let cases = [
        (
            "Vertices(\"ids.npy\")",
            vec![("ids.npy", &[2][..], &[0.0, 9999.0][..])],
            ["ids.npy", "vertex 9999 is out of range"],
        ),
        (
            "Inside(elements: \"el.npy\", weights: \"w.npy\")",
            vec![
                ("el.npy", &[2][..], &[0.0, 9999.0][..]),
                ("w.npy", &[2, 4], weights),
            ],
            ["el.npy", "element 9999 is out of range"],
        ),
        (
            "Inside(elements: \"el.npy\", weights: \"w.npy\")",
            vec![
                ("el.npy", &[2][..], &[0.0, 1.0][..]),
                ("w.npy", &[2, 3], &weights[..6]),
            ],
            ["w.npy", "shape [2, 3], expected [2, 4]"],
        ),
        (
            "Inside(elements: \"el.npy\", weights: \"w.npy\")",
            vec![
                ("el.npy", &[3][..], &[0.0, 1.0, 2.0][..]),
                ("w.npy", &[2, 4], weights),
            ],
            ["el.npy", "shape [3], expected [2]"],
        ),
    ];
    for (markers, files, names) in cases {
        let message = fail(markers, &files);
        for name in names {
            assert!(
                message.contains(name),
                "{markers}: {message:?} lacks {name:?}"
            );
        }
    }
}

/// Positions with their first two axes swapped are blamed on the positions file, saying
/// so, not on the velocities file whose shape then did not match them.
#[test]
fn transposed_positions_are_blamed_on_the_positions_file() {
    let dir = tempfile::tempdir().unwrap();
    let scene_path = data("tiny_beam.ron");
    let scene = Scene::load(&scene_path).unwrap();
    let n = scene.build_mesh(&scene_path).unwrap().num_vertices();
    npy::write(&dir.path().join("x.npy"), &[n, 4, 3], &vec![0.5; 12 * n]).unwrap();
    npy::write(&dir.path().join("v.npy"), &[4, n, 3], &vec![0.0; 12 * n]).unwrap();
    let t = "(positions: \"x.npy\", velocities: File(\"v.npy\"))";
    let text = format!(
        "Experiment(name: \"t\", scene: {scene_path:?}, import: (dt: 0.01, gravity: (0, 0, -9.81), mass: Lumped, trajectories: [{t}, {t}], split: (0.5, 0.0)), task: FitMaterial(output_error: Some(())))"
    );
    let e = load(dir.path(), &text).unwrap();
    let Data::Import(spec) = &e.data else {
        panic!("import")
    };
    let err = deform_learn::import::import(spec, &scene, &scene_path).unwrap_err();
    let message = err.to_string();
    assert!(
        message.contains("x.npy") && message.contains("transposed") && !message.contains("v.npy"),
        "{message}"
    );
}

/// A trajectory whose conditions make its steps blow up (gravity of 1e300, finite but no
/// body survives it) is named by its place in the dataset and its file, not by its place in
/// its split (issue 58: "trajectory 0, step 0" for imported trajectory 4).
#[test]
fn a_failing_trajectory_is_named_by_its_dataset_index_and_file() {
    let dir = tempfile::tempdir().unwrap();
    let generated = Experiment::load(&data("fit_material.ron")).unwrap();
    let out = dir.path().join("generated");
    run(&generated, Some(&out), &mut NoProgress).unwrap();
    let saved = out.join("dataset");
    let task = "FitMaterial(output_error: Some((rollout: 3, max_iterations: 5)))";
    // Trajectory 2 is the test split's only one, trajectory 0 the training split's.
    for k in [2, 0] {
        let text = import_text(&saved, 3, "File", task);
        let name = format!("traj_{k:03}");
        let this = format!("{:?}, velocities: File", saved.join(&name).join("x.npy"));
        assert!(text.contains(&this));
        let blown = ", conditions: (gravity: Some((0, 0, 1e300))), velocities:";
        let text = text.replace(&this, &this.replace(", velocities:", blown));
        let e = load(dir.path(), &text).unwrap();
        let err = run(&e, None, &mut NoProgress).unwrap_err().to_string();
        let named = format!("trajectory {k}");
        assert!(err.contains(&named) && err.contains(&name), "{err}");
    }
}
