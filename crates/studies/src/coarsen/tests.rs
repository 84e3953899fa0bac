//! Unit tests of the parent module.

use super::*;

/// A fitted model whose free rollout fails (here one far too soft: its elements
/// invert under gravity) is rejected for the model the fit started from, and the reason
/// names the trajectory and step; a model that runs is kept.
#[test]
fn a_fitted_model_that_fails_its_free_rollout_is_rejected() {
    let text = r#"Scene(name: "t", mesh: Beam(1), material: NeoHookean(Young(e: 1e5, nu: 0.4)),
        density: 1000.0, constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
        integrator: (dt: 0.01, max_retries: 2), steps: 3)"#;
    let origin = Path::new("t.ron");
    let scene = Scene::parse(text, origin).unwrap();
    let spec = deform_learn::dataset::DatasetSpec::new(2, 60, 5);
    let data = generate(&scene, origin, &spec, |_, _| ()).unwrap();
    let train: Vec<&Trajectory> = data.trajectories.iter().collect();
    let mut sim = scene.build(origin).unwrap().integrator;
    let good = fitted_model(&sim);
    let soft = deform_materials::MaterialSpec::NeoHookean(deform_materials::Moduli::Young {
        e: 1e-4,
        nu: 0.4,
    });
    let bad = (
        MaterialField::Uniform(soft.build().unwrap()),
        good.1.clone(),
        None,
    );
    let settings = CoarseSettings {
        damping: false,
        ..CoarseSettings::new(good.1.newton.max_iterations, OutputErrorOptions::default())
    };
    let mut summary = FitSummary {
        coefficients: 2,
        losses: (1.0, 0.5),
        evaluations: 1,
        seconds: 0.0,
        termination: Termination::Converged,
        unstable: None,
    };
    let sets = [train.as_slice()];
    let kept = settings
        .keep_stable(&mut sim, &sets, bad, &good, &mut summary)
        .unwrap();
    let why = summary.unstable.clone().expect("rejected");
    assert!(
        why.contains("training trajectory 0") && why.contains("step"),
        "{why}"
    );
    assert_eq!(kept.0, good.0);
    assert_eq!(sim.assembly().materials(), &good.0);
    summary.unstable = None;
    let kept = settings
        .keep_stable(&mut sim, &sets, good.clone(), &good, &mut summary)
        .unwrap();
    assert!(summary.unstable.is_none());
    assert_eq!(kept.0, good.0);
}
