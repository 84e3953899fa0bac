//! Every bundled scene parses, builds and takes a few steps; bad scenes give errors that name
//! the file and the field.

use std::path::Path;

use deform_integrator::{Scene, SceneError};
use deform_tests::asset;

#[test]
fn bundled_scenes_build_and_step() {
    let dir = asset("scenes");
    let mut count = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().and_then(|e| e.to_str()) != Some("ron") {
            continue;
        }
        let scene = Scene::load(&path).unwrap_or_else(|e| panic!("{e}"));
        let mut built = scene.build(&path).unwrap_or_else(|e| panic!("{e}"));
        for _ in 0..3 {
            let report = built
                .integrator
                .step(&mut built.state)
                .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            assert!(report.converged);
        }
        assert!(built.state.x.iter().all(|v| v.is_finite()));
        count += 1;
    }
    assert!(count >= 3, "found {count} scenes");
}

fn load_str(text: &str) -> Result<Scene, SceneError> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.ron");
    std::fs::write(&path, text).unwrap();
    let scene = Scene::load(&path)?;
    scene.build(&path).map(|_| scene)
}

#[test]
fn bad_scenes_name_the_file_and_field() {
    let base = r#"Scene(name: "t", mesh: Beam(1), material: NeoHookean(Young(e: 1e6, nu: 0.4)), density: 1000.0, steps: 1"#;
    // Unknown field.
    let e = load_str(&format!("{base}, colour: 3)"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("bad.ron") && e.contains("colour"), "{e}");
    // Bad values, each naming its field.
    for (extra, field) in [
        (", density: -1.0", "density"),
        (", integrator: (dt: 0.0)", "dt"),
        (
            ", constraints: [(select: Indices([100000]))]",
            "constraints[0].select",
        ),
        (
            ", constraints: [(select: Box(min: (5.0, 5.0, 5.0), max: (6.0, 6.0, 6.0)))]",
            "selects no vertex",
        ),
        (", policy: EisenstatWalker(solver: Direct())", "policy"),
    ] {
        let text = format!(
            "{}{extra})",
            base.replace(
                ", density: 1000.0",
                if field == "density" {
                    ""
                } else {
                    ", density: 1000.0"
                }
            )
        );
        let e = load_str(&text).map(|_| ()).unwrap_err().to_string();
        assert!(e.contains(field), "{extra}: {e}");
    }
    let e = load_str(
        &base
            .replace("nu: 0.4", "nu: 0.5")
            .replace("steps: 1", "steps: 1)"),
    )
    .map(|_| ())
    .unwrap_err()
    .to_string();
    assert!(e.contains("material") && e.contains("nu"), "{e}");
    let e = load_str(r#"Scene(name: "t", mesh: File("missing.msh"), material: NeoHookean(Young(e: 1e6, nu: 0.4)), density: 1.0, steps: 1)"#)
        .map(|_| ())
        .unwrap_err()
        .to_string();
    assert!(e.contains("missing.msh"), "{e}");
    assert!(Scene::load(Path::new("/nonexistent/scene.ron")).is_err());
}

#[test]
fn every_value_is_refused_at_load_before_any_mesh_is_made() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.ron");
    let base = r#"Scene(name: "t", mesh: Beam(1), material: NeoHookean(Young(e: 1e6, nu: 0.4)), density: 1000.0, steps: 1"#;
    for (extra, field) in [
        (", integrator: (dt: NaN)", "integrator"),
        (", integrator: (max_retries: 1000)", "integrator"),
        (
            ", policy: Fixed(Pcg(preconditioner: Jacobi, tolerance: (rel: -1.0)))",
            "policy",
        ),
        (
            ", constraints: [(select: Indices([0]), motion: Translate(velocity: (NaN, 0.0, 0.0)))]",
            "constraints[0].motion",
        ),
        (", initial: (velocity: (inf, 0.0, 0.0))", "initial"),
        (", initial: (scale: Some((0.0, 1.0, 1.0)))", "initial.scale"),
        (", output: (track: Some((NaN, 0.0, 0.0)))", "output.track"),
    ] {
        std::fs::write(&path, format!("{base}{extra})")).unwrap();
        match Scene::load(&path) {
            Err(SceneError::Invalid {
                field: f, path: p, ..
            }) => {
                assert_eq!(
                    (f.as_str(), p.as_path()),
                    (field, path.as_path()),
                    "{extra}"
                )
            }
            other => panic!("{extra}: expected an Invalid error naming {field}, got {other:?}"),
        }
    }
    // A generated mesh too large for any machine is refused at load, before it is built.
    std::fs::write(&path, format!("{})", base.replace("Beam(1)", "Beam(560)"))).unwrap();
    let e = Scene::load(&path).unwrap_err();
    assert!(
        matches!(&e, SceneError::Invalid { field, .. } if field == "mesh"),
        "{e}"
    );
}
