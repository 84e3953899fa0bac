//! The bundled experiments parse and point at scenes that build; bad experiment files name
//! the file and the problem.

use deform_integrator::Scene;
use deform_studies::Experiment;
use deform_tests::asset;

#[test]
fn bundled_experiments_load_and_their_scenes_build() {
    let mut count = 0;
    for entry in std::fs::read_dir(asset("experiments")).unwrap() {
        let path = entry.unwrap().path();
        let e = Experiment::load(&path).unwrap_or_else(|e| panic!("{e}"));
        let scene = Scene::load(&e.scene).unwrap_or_else(|err| panic!("{}: {err}", path.display()));
        scene.build(&e.scene).unwrap();
        count += 1;
    }
    assert!(count >= 2);
}

#[test]
fn bad_experiments_are_reported() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.ron");
    let base = r#"Experiment(name: "x", scene: "s.ron", dataset: (trajectories: 5, steps: 3, seed: 1), task: SelectModel(members: []))"#;
    std::fs::write(&path, base.replace("seed: 1", "seed: 1, colour: 2")).unwrap();
    let e = Experiment::load(&path).unwrap_err().to_string();
    assert!(e.contains("bad.ron") && e.contains("colour"), "{e}");
    std::fs::write(&path, base.replace("trajectories: 5", "trajectories: 2")).unwrap();
    assert!(
        Experiment::load(&path)
            .unwrap_err()
            .to_string()
            .contains("trajectories")
    );
    std::fs::write(&path, base.replace("seed: 1", "seed: 1, split: (0.9, 0.2)")).unwrap();
    assert!(
        Experiment::load(&path)
            .unwrap_err()
            .to_string()
            .contains("split")
    );
}
