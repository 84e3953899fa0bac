//! Observations of part of the body, as a capture gives them: the positions of a few surface
//! vertices. The output error compares only those; the rest of the state is the model's own
//! (rolled out from the complete first state).

use std::path::Path;

use deform_integrator::Scene;
use deform_learn::dataset::generate;
use deform_learn::{DatasetSpec, FitError, OutputErrorOptions, fit_output_error};
use deform_mesh::select::Selector;

fn scene() -> Scene {
    let text = r#"Scene(
        name: "observed",
        mesh: Beam(2),
        material: NeoHookean(Young(e: 1e5, nu: 0.4)),
        density: 1000.0,
        constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
        integrator: (dt: 0.01, newton: (rel: 1e-10, abs: 1e-12)),
        steps: 1,
    )"#;
    Scene::parse(text, Path::new("observed.ron")).unwrap()
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
        for frame in t.x.iter_mut().skip(1) {
            for v in (0..total).filter(|v| !observed.contains(v)) {
                frame[3 * v..3 * v + 3].copy_from_slice(&[0.0; 3]);
            }
        }
        t.observed = Some(observed.clone());
    }
    let train: Vec<_> = data.trajectories.iter().collect();
    let mut sim = built.integrator;
    let start = deform_materials::Lame::from_young(1.3e5, 0.35).unwrap();
    let options = OutputErrorOptions {
        rollout: 30,
        ..Default::default()
    };
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
    let short = OutputErrorOptions {
        rollout: 5,
        ..Default::default()
    };
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
