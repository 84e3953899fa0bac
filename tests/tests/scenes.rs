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
