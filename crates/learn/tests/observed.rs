//! Observations of part of the body, as a capture gives them: the positions of a few surface
//! vertices and points inside elements. The output error compares only those; the rest of the
//! state is the model's own, rolled out from the first state, known or estimated.

use std::path::Path;

use deform_integrator::Scene;
use deform_learn::dataset::generate;
use deform_learn::observe::{Marker, Observed};
use deform_learn::{
    DatasetSpec, FitError, OutputErrorOptions, StartPrior, Trajectory, fit_output_error,
};
use deform_mesh::select::Selector;

fn scene() -> Scene {
    scene_of(1e5, 0.4)
}

fn scene_of(e: f64, nu: f64) -> Scene {
    let text = format!(
        r#"Scene(
        name: "observed",
        mesh: Beam(2),
        material: NeoHookean(Young(e: {e:e}, nu: {nu})),
        density: 1000.0,
        constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
        integrator: (dt: 0.01, newton: (rel: 1e-10, abs: 1e-12)),
        steps: 1,
    )"#
    );
    Scene::parse(&text, Path::new("observed.ron")).unwrap()
}

/// E and nu from 10 % of the surface vertices of a beam, on clean data: within 1 %. The
/// other vertices' positions after the first frame are overwritten with garbage, which the
/// fit must not read.
#[test]
fn the_moduli_from_ten_percent_of_the_surface_vertices() {
    let s = scene();
    let origin = Path::new("observed.ron");
    let mut data = generate(&s, origin, &DatasetSpec::new(3, 30, 11), |_, _| {}).unwrap();
    let built = s.build(origin).unwrap();
    let surface = Selector::Surface.select(&built.mesh).unwrap();
    let free = surface
        .iter()
        .copied()
        .filter(|&v| !built.integrator.dofs().is_constrained(v));
    let observed: Vec<usize> = free.step_by(10).collect();
    let total = built.mesh.num_vertices();
    assert!(
        10 * observed.len() <= surface.len() + 10,
        "{} of {}",
        observed.len(),
        surface.len()
    );
    for t in &mut data.trajectories {
        t.observed = Some(Observed::vertices(&t.x, &observed));
        for frame in t.x.iter_mut().skip(1) {
            for v in (0..total).filter(|v| !observed.contains(v)) {
                frame[3 * v..3 * v + 3].copy_from_slice(&[0.0; 3]);
            }
        }
    }
    // The markers and their positions go through the dataset folder.
    let dir = tempfile::tempdir().unwrap();
    data.save(dir.path()).unwrap();
    let loaded = deform_learn::Dataset::load(dir.path()).unwrap();
    assert_eq!(loaded.trajectories, data.trajectories);
    let train: Vec<_> = data.trajectories.iter().collect();
    let mut sim = built.integrator;
    let start = deform_materials::Lame::from_young(1.3e5, 0.35).unwrap();
    let options = OutputErrorOptions::default().rollout(30);
    let fit = fit_output_error(
        &mut sim,
        &train,
        &[start.mu, start.lambda],
        options,
        |_, _| {},
    )
    .unwrap();
    let lame = deform_materials::Lame::try_new(fit.coefficients[0], fit.coefficients[1]).unwrap();
    let (e, nu) = lame.to_young();
    eprintln!(
        "{} of {total} vertices observed: E {e:.6e}, nu {nu:.6}, loss {:.2e} -> {:.2e}",
        observed.len(),
        fit.initial_loss,
        fit.loss
    );
    assert!(
        (e - 1e5).abs() < 0.01 * 1e5 && (nu - 0.4).abs() < 0.01 * 0.4,
        "E {e}, nu {nu}"
    );
    // The rollout error compares the observed vertices only: zero-ish at the fit.
    let errors = deform_learn::rollout::rollout_error(&mut sim, train[0]).unwrap();
    assert!(errors.iter().all(|e| *e < 1e-3), "{errors:?}");
    // Rollouts that would start from unobserved states, and the equation error, refuse.
    let short = OutputErrorOptions::default().rollout(5);
    let e = fit_output_error(
        &mut sim,
        &train,
        &[start.mu, start.lambda],
        short,
        |_, _| {},
    )
    .unwrap_err();
    assert!(
        matches!(e, FitError::Data { .. }) && e.to_string().contains("whole length"),
        "{e}"
    );
    let e = deform_learn::fit_equation_error(&sim, &train, Default::default()).unwrap_err();
    assert!(e.to_string().contains("whole states"), "{e}");
}

/// A capture shows only its markers, from the first frame on: 10 % of the surface vertices
/// and three points inside elements. The first state (stretched, moving, spinning) is
/// estimated from the first frames with the fit's starting material and refined with the
/// material: E and nu within 1 % on clean data.
#[test]
fn the_moduli_and_the_first_state_from_markers_alone() {
    let s = scene();
    let origin = Path::new("observed.ron");
    let data = generate(&s, origin, &DatasetSpec::new(2, 20, 11), |_, _| {}).unwrap();
    let built = s.build(origin).unwrap();
    let surface = Selector::Surface.select(&built.mesh).unwrap();
    let vertices: Vec<usize> = surface
        .iter()
        .copied()
        .filter(|&v| !built.integrator.dofs().is_constrained(v))
        .step_by(10)
        .collect();
    let inside = [
        (5, [0.1, 0.2, 0.3, 0.4]),
        (40, [0.25; 4]),
        (77, [0.7, 0.1, 0.1, 0.1]),
    ];
    let mut markers: Vec<Marker> = vertices.iter().map(|&v| Marker::Vertex(v)).collect();
    for (element, weights) in inside {
        markers.push(Marker::in_element(&built.mesh, element, weights).unwrap());
    }
    let start = deform_materials::Lame::from_young(1.3e5, 0.35).unwrap();
    let mut sim = built.integrator;
    let mut estimator = scene_of(1.3e5, 0.35).build(origin).unwrap().integrator;
    let mut captured = Vec::new();
    let mut first_error = 0.0f64;
    for t in &data.trajectories {
        let positions =
            t.x.iter()
                .map(|x| markers.iter().flat_map(|m| m.position(x)).collect())
                .collect();
        let observed = Observed {
            markers: markers.clone(),
            positions,
        };
        let c = Trajectory::from_markers(&mut estimator, observed, t.conditions.clone()).unwrap();
        first_error = first_error.max(deform_learn::rollout::rms_distance(&c.x[0], &t.x[0]));
        captured.push(c);
    }
    // Markers inside elements go through the dataset folder too.
    let dir = tempfile::tempdir().unwrap();
    let mut saved = data.clone();
    saved.trajectories.clone_from(&captured);
    saved.save(dir.path()).unwrap();
    let loaded = deform_learn::Dataset::load(dir.path()).unwrap();
    assert_eq!(loaded.trajectories, captured);
    let train: Vec<_> = captured.iter().collect();
    let options = OutputErrorOptions::default()
        .rollout(20)
        .starts(Some(StartPrior::default()))
        .max_evaluations(150)
        .max_iterations(150);
    let fit = fit_output_error(
        &mut sim,
        &train,
        &[start.mu, start.lambda],
        options,
        |_, _| {},
    )
    .unwrap();
    let lame = deform_materials::Lame::try_new(fit.coefficients[0], fit.coefficients[1]).unwrap();
    let (e, nu) = lame.to_young();
    eprintln!(
        "{} markers: first state estimated to {first_error:.3e} m RMS; E {e:.6e}, nu {nu:.6}, loss {:.2e} -> {:.2e} in {} evaluations",
        markers.len(),
        fit.initial_loss,
        fit.loss,
        fit.evaluations
    );
    assert!(
        (e - 1e5).abs() < 0.01 * 1e5 && (nu - 0.4).abs() < 0.01 * 0.4,
        "E {e}, nu {nu}"
    );
}
