//! `simulate` runs a scene file into a folder: frames, the per-step CSV and the summary;
//! a failed step is a typed error naming the scene and step, with the steps before it kept.

use std::path::Path;

use deform_integrator::{NoObserver, SimulateError, simulate};

fn scene(dir: &Path, newton: &str) -> std::path::PathBuf {
    let path = dir.join("scene.ron");
    std::fs::write(
        &path,
        format!(
            r#"Scene(
                name: "tiny",
                mesh: Beam(1),
                material: NeoHookean(Young(e: 1e5, nu: 0.4)),
                density: 1000.0,
                constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
                integrator: (dt: 0.01, max_retries: 0, newton: {newton}),
                steps: 4,
                output: (every: 2),
            )"#
        ),
    )
    .unwrap();
    path
}

#[test]
fn a_scene_runs_into_its_folder() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let sim = simulate(
        &scene(dir.path(), "(rel: 1e-8)"),
        None,
        Some(&out),
        &mut NoObserver,
    )
    .unwrap();
    assert_eq!(sim.run.steps, 4);
    assert!((sim.state.t - 0.04).abs() < 1e-12);
    let csv = std::fs::read_to_string(out.join("steps.csv")).unwrap();
    assert_eq!(csv.lines().count(), 5);
    for frame in [
        "frame_00000.vtu",
        "frame_00002.vtu",
        "frame_00004.vtu",
        "series.pvd",
    ] {
        assert!(out.join(frame).exists(), "{frame}");
    }
    assert!(!out.join("frame_00001.vtu").exists());
    let summary = std::fs::read_to_string(out.join("summary.txt")).unwrap();
    assert!(summary.contains("steps: 4"), "{summary}");
    // The measured peak memory, at least the mesh's own estimate where it can be read.
    let line = summary
        .lines()
        .find(|l| l.starts_with("peak memory"))
        .expect("summary has the peak memory");
    if let Some(peak) = deform_mesh::memory::peak_rss_bytes() {
        assert!(line.ends_with(" MB"), "{line}");
        let mesh = deform_mesh::memory::mesh_bytes(20, 24);
        assert!(peak > mesh, "{peak} vs {mesh}");
    } else {
        assert!(line.ends_with("unknown"), "{line}");
    }
}

#[test]
fn a_failed_step_names_the_scene_and_keeps_the_steps_before_it() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let path = scene(dir.path(), "(rel: 1e-14, abs: 0.0, max_iterations: 1)");
    let err = simulate(&path, None, Some(&out), &mut NoObserver).unwrap_err();
    assert!(matches!(err, SimulateError::Step { step: 1, .. }), "{err}");
    assert!(err.to_string().contains("scene.ron"), "{err}");
    let csv = std::fs::read_to_string(out.join("steps.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1, "the header, no step");
    let missing = simulate(
        &dir.path().join("none.ron"),
        None,
        Some(&out),
        &mut NoObserver,
    );
    assert!(matches!(missing, Err(SimulateError::Scene(_))));
}

#[test]
fn zero_steps_and_path_like_names_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let path = scene(dir.path(), "(rel: 1e-8)");
    let e = simulate(&path, Some(0), Some(&out), &mut NoObserver).unwrap_err();
    assert!(e.to_string().contains("steps"), "{e}");
    assert!(!out.join("summary.txt").exists());
    for name in ["", "..", "../../x", "/abs", "a/b"] {
        let text = std::fs::read_to_string(&path)
            .unwrap()
            .replace("name: \"tiny\"", &format!("name: {name:?}"));
        std::fs::write(&path, text).unwrap();
        let e = simulate(&path, None, None, &mut NoObserver).unwrap_err();
        assert!(
            matches!(&e, SimulateError::Scene(deform_integrator::SceneError::Invalid { field, .. }) if field == "name"),
            "{name:?}: {e}"
        );
        std::fs::write(
            &path,
            std::fs::read_to_string(&path)
                .unwrap()
                .replace(&format!("name: {name:?}"), "name: \"tiny\""),
        )
        .unwrap();
    }
}

#[test]
fn a_scene_too_large_for_the_machine_is_refused_before_allocating() {
    let dir = tempfile::tempdir().unwrap();
    let path = scene(dir.path(), "(rel: 1e-8)");
    // Beam(300): 648 million tets, 80 GB for the mesh alone; Beam(560), 1.4 TB, fits on no machine.
    for huge in [
        "Beam(2000)",
        "Generate((cells: (100000, 100000, 100000), size: (1.0, 1.0, 1.0)))",
    ] {
        let text = std::fs::read_to_string(&path)
            .unwrap()
            .replace("Beam(1)", huge);
        std::fs::write(&path, text).unwrap();
        let e = simulate(&path, None, Some(&dir.path().join("out")), &mut NoObserver).unwrap_err();
        let text = e.to_string();
        assert!(
            matches!(&e, SimulateError::Scene(deform_integrator::SceneError::Invalid { field, .. }) if field == "mesh"),
            "{huge}: {e}"
        );
        assert!(
            text.contains("needs at least") && text.contains("GB available"),
            "{text}"
        );
        std::fs::write(
            &path,
            std::fs::read_to_string(&path)
                .unwrap()
                .replace(huge, "Beam(1)"),
        )
        .unwrap();
    }
    // A generator called directly refuses too.
    let e = deform_mesh::generate::BoxGrid::beam(560)
        .build()
        .unwrap_err();
    assert!(e.to_string().contains("needs at least"), "{e}");
}

#[test]
fn a_second_run_into_a_busy_folder_is_refused_and_touches_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let path = scene(dir.path(), "(rel: 1e-8)");
    simulate(&path, Some(2), Some(&out), &mut NoObserver).unwrap();
    let before = std::fs::read_to_string(out.join("steps.csv")).unwrap();
    let first = deform_fs::lock_folder(&out).unwrap();
    let e = simulate(&path, Some(1), Some(&out), &mut NoObserver).unwrap_err();
    assert!(
        matches!(e, SimulateError::Locked(deform_fs::LockError::Busy { .. })),
        "{e}"
    );
    assert_eq!(
        std::fs::read_to_string(out.join("steps.csv")).unwrap(),
        before
    );
    drop(first);
    simulate(&path, Some(1), Some(&out), &mut NoObserver).unwrap();
}

#[test]
fn a_rerun_leaves_only_its_own_files() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let path = scene(dir.path(), "(rel: 1e-8)");
    simulate(&path, None, Some(&out), &mut NoObserver).unwrap();
    assert!(out.join("frame_00004.vtu").exists());
    // A temporary a killed run left behind, and a file of the user's.
    std::fs::write(out.join(".steps.csv.tmp12345"), "half").unwrap();
    std::fs::write(out.join("notes.txt"), "mine").unwrap();
    simulate(&path, Some(2), Some(&out), &mut NoObserver).unwrap();
    assert!(
        !out.join("frame_00004.vtu").exists(),
        "a frame of the earlier run"
    );
    assert!(out.join("frame_00002.vtu").exists());
    assert!(!out.join(".steps.csv.tmp12345").exists());
    assert!(out.join("notes.txt").exists(), "other files are left alone");
    let csv = std::fs::read_to_string(out.join("steps.csv")).unwrap();
    assert_eq!(csv.lines().count(), 3);
}

/// Moving obstacles get frames of their own beside the body's (`obstacles_*.vtu` in
/// `obstacles.pvd`, where they are at each frame's time); still ones only `obstacles.vtu`.
#[test]
fn moving_obstacles_are_written_where_they_are_at_each_frame() {
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, motions: &str| {
        let path = dir.path().join(format!("{name}.ron"));
        std::fs::write(
            &path,
            format!(
                r#"Scene(
                    name: "{name}",
                    mesh: Beam(1),
                    material: NeoHookean(Young(e: 1e5, nu: 0.4)),
                    density: 1000.0,
                    constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
                    contact: Some((
                        obstacles: [Sphere(center: (0.8, 0.125, -0.3), radius: 0.1)],
                        motions: [{motions}],
                    )),
                    integrator: (dt: 0.01),
                    steps: 4,
                    output: (every: 2),
                )"#
            ),
        )
        .unwrap();
        path
    };
    let out = dir.path().join("moving");
    let moving = write("moving", "(obstacle: 0, velocity: (0.0, 0.0, 0.5))");
    simulate(&moving, None, Some(&out), &mut NoObserver).unwrap();
    let pvd = std::fs::read_to_string(out.join("obstacles.pvd")).unwrap();
    for frame in [
        "obstacles_00000.vtu",
        "obstacles_00002.vtu",
        "obstacles_00004.vtu",
    ] {
        assert!(pvd.contains(frame), "{pvd}");
    }
    let read = |f: &str| std::fs::read(out.join(f)).unwrap();
    assert_ne!(read("obstacles_00000.vtu"), read("obstacles_00004.vtu"));
    assert_eq!(read("obstacles_00000.vtu"), read("obstacles.vtu"));
    let still_out = dir.path().join("still");
    simulate(&write("still", ""), None, Some(&still_out), &mut NoObserver).unwrap();
    assert!(still_out.join("obstacles.vtu").exists());
    assert!(!still_out.join("obstacles.pvd").exists());
}
