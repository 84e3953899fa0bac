//! The runner's commands on tiny inputs, as a user types them: `mesh`, `simulate`,
//! `experiment` and `demo` succeed and write what they promise; bad input fails with a
//! message naming the file.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn tiny(name: &str) -> PathBuf {
    root().join("crates/studies/tests/data").join(name)
}

fn xtask(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_xtask"))
        .args(args)
        .current_dir(root())
        .output()
        .expect("the runner starts")
}

fn ok(args: &[&str]) -> String {
    let out = xtask(args);
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    );
    assert!(out.status.success(), "{args:?} failed:\n{stdout}\n{stderr}");
    stdout
}

fn lines(path: &Path) -> usize {
    std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .lines()
        .count()
}

#[test]
fn mesh_info_convert_and_generate() {
    let dir = tempfile::tempdir().unwrap();
    let info = ok(&["mesh", "info", "assets/meshes/bracket.msh"]);
    assert!(info.contains("tets"), "{info}");
    let vtu = dir.path().join("bracket.vtu");
    ok(&[
        "mesh",
        "convert",
        "assets/meshes/bracket.msh",
        vtu.to_str().unwrap(),
    ]);
    assert!(std::fs::read_to_string(&vtu).unwrap().contains("<VTKFile"));
    let msh = dir.path().join("beam.msh");
    ok(&[
        "mesh",
        "generate",
        "beam",
        "--cells",
        "4x1x1",
        "--out",
        msh.to_str().unwrap(),
    ]);
    let again = ok(&["mesh", "info", msh.to_str().unwrap()]);
    assert!(again.contains("24"), "4 x 1 x 1 cubes are 24 tets: {again}");
}

#[test]
fn simulate_writes_frames_steps_and_summary() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("sim");
    let text = ok(&[
        "simulate",
        tiny("tiny_beam.ron").to_str().unwrap(),
        "--steps",
        "3",
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ]);
    assert!(text.contains("3 steps"), "{text}");
    assert_eq!(
        lines(&out.join("steps.csv")),
        4,
        "a header and one row per step"
    );
    assert!(out.join("series.pvd").exists());
    assert!(out.join("frame_00003.vtu").exists());
    assert!(
        std::fs::read_to_string(out.join("summary.txt"))
            .unwrap()
            .contains("steps: 3")
    );
}

#[test]
fn experiment_writes_its_report_tables_and_plots() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("exp");
    ok(&[
        "experiment",
        tiny("fit_material.ron").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ]);
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(report.contains("| output error |"), "{report}");
    assert_eq!(
        lines(&out.join("rollout_error.csv")),
        1 + 7,
        "header + 7 states"
    );
    assert!(out.join("rollout_error.svg").exists());
    assert!(out.join("dataset").is_dir());
    // The dataset it wrote, imported back through the runner: the same fit.
    let list: Vec<String> = (0..3)
        .map(|k| {
            let f = format!("exp/dataset/traj_{k:03}");
            format!("(positions: \"{f}/x.npy\", velocities: File(\"{f}/v.npy\"))")
        })
        .collect();
    let experiment = dir.path().join("import.ron");
    let text = format!(
        "Experiment(name: \"imported\", scene: {:?}, import: (dt: 0.01, gravity: (0, 0, -9.81), mass: Lumped, trajectories: [{}], split: (0.34, 0.33)), task: FitMaterial(output_error: Some((rollout: 3, max_iterations: 5))))",
        tiny("tiny_beam.ron"),
        list.join(", ")
    );
    std::fs::write(&experiment, text).unwrap();
    let again = dir.path().join("again");
    ok(&[
        "experiment",
        experiment.to_str().unwrap(),
        "--out",
        again.to_str().unwrap(),
        "--quiet",
    ]);
    let imported = std::fs::read_to_string(again.join("report.md")).unwrap();
    assert!(imported.contains("3 trajectories imported"), "{imported}");
    let table = |md: &str| -> Vec<String> {
        let rows = md
            .lines()
            .filter(|l| l.starts_with("| equation error |") || l.starts_with("| output error |"));
        // The fit time column differs run to run.
        rows.map(|l| {
            l.rsplit_once('|')
                .unwrap()
                .0
                .rsplit_once('|')
                .unwrap()
                .0
                .to_owned()
        })
        .collect()
    };
    assert_eq!(table(&report).len(), 2, "{report}");
    assert_eq!(table(&report), table(&imported));
}

#[test]
fn demo_composes_the_reports_of_a_folder_of_experiments() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("demo");
    ok(&[
        "demo",
        "--out",
        out.to_str().unwrap(),
        "--quiet",
        "--demo",
        tiny("demo.ron").to_str().unwrap(),
    ]);
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    for name in [
        "coarsen",
        "fit_material",
        "select_model",
        "select_solver",
        "tune_backward_euler",
        "tune_solver",
    ] {
        assert!(report.contains(&format!("| {name} |")), "{name}: {report}");
        assert!(out.join(name).join("report.md").exists(), "{name}");
    }
    assert!(report.contains("tuned / untuned: error"), "{report}");
    assert!(report.contains("8x fewer tets, 2x the step"), "{report}");
    // The learned coarse model is a scene the runner simulates, its field beside it.
    let model = out.join("coarsen/coarse_2x_dt.ron");
    assert!(out.join("coarsen/coarse_2x_dt_field.vtu").exists());
    let text = ok(&[
        "simulate",
        model.to_str().unwrap(),
        "--steps",
        "2",
        "--out",
        dir.path().join("coarse_run").to_str().unwrap(),
        "--quiet",
    ]);
    assert!(text.contains("2 steps"), "{text}");
    assert!(out.join("tiny_beam/series.pvd").exists());
    assert!(
        out.join("tune_backward_euler/frames/tuned/series.pvd")
            .exists()
    );
}

#[test]
fn bad_input_fails_naming_the_file() {
    let out = xtask(&["simulate", "no/such/scene.ron", "--quiet"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no/such/scene.ron"), "{err}");
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.ron");
    std::fs::write(
        &bad,
        r#"Experiment(name: "x", scene: "s.ron", dataset: (trajectories: 5, steps: 3, seed: 1), task: SelectModel(members: [Rubber]))"#,
    )
    .unwrap();
    let out = xtask(&["experiment", bad.to_str().unwrap(), "--quiet"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("bad.ron") && err.contains("Rubber"), "{err}");
}

#[test]
fn bench_prints_one_json_object_per_measurement() {
    let out = ok(&["bench", "step", "--n", "1"]);
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(
        lines.len(),
        deform_integrator::benchmark::STEP_POLICIES.len(),
        "one line per policy: {out}"
    );
    assert!(
        lines
            .iter()
            .all(|l| l.starts_with("{\"what\": \"step\"") && l.ends_with('}'))
    );
    let out = ok(&["bench", "assembly", "--n", "1", "--repeats", "2"]);
    assert!(out.contains("\"tets\": 24"), "{out}");
    let out = ok(&["bench", "solvers", "--n", "1", "--repeats", "1"]);
    assert!(
        out.contains("\"solver\": \"direct\"")
            && out.contains("pcg_ic0_1e-6")
            && out.contains("pcg_amg_1e-6"),
        "{out}"
    );
    let out = ok(&["bench", "step", "--n", "1", "--policies", "pcg_amg,direct"]);
    assert_eq!(out.lines().count(), 2, "{out}");
    let out = xtask(&["bench", "step", "--n", "1", "--policies", "pcg_mystery"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("pcg_mystery") && err.contains("pcg_amg_refresh"),
        "{err}"
    );
}
