//! The output-error loss's adjoint gradient equals finite differences: moduli, damping,
//! ensembles, coefficient fields (per element, smooth, regularised), mass scales, and through
//! the barrier, friction, mesh obstacles and self-contact.

mod common;

use common::*;
use std::path::Path;

use deform_integrator::Scene;
use deform_learn::DatasetSpec;
use deform_learn::dataset::generate;
use deform_learn::{Split, Variations};

#[test]
fn output_error_gradient_equals_finite_differences() {
    let s = scene("", "Beam(1)");
    let data = make(&s, 1, 5);
    let mut sim = s.build(Path::new("test")).unwrap().integrator;
    let trajectories = data.split(Split::Train);
    for rollout in [1, 4] {
        let options = deform_learn::OutputErrorOptions::default()
            .rollout(rollout)
            .velocity_weight(0.5);
        let objective =
            deform_learn::OutputError::new(&mut sim, &trajectories, options, |_, _| {}).unwrap();
        // Away from the truth, so the gradient is not zero.
        let c = [3.0e4, 1.2e5];
        let (loss, grad) = objective.evaluate(&c).unwrap();
        assert!(loss > 0.0);
        for j in 0..2 {
            let h = 1e-4 * c[j];
            let (mut cp, mut cm) = (c, c);
            cp[j] += h;
            cm[j] -= h;
            let fd = (objective.evaluate(&cp).unwrap().0 - objective.evaluate(&cm).unwrap().0)
                / (2.0 * h);
            eprintln!(
                "rollout {rollout}: dL/dc[{j}] = {:.6e}, finite difference {fd:.6e}",
                grad[j]
            );
            assert!(
                (grad[j] - fd).abs() <= 1e-4 * fd.abs(),
                "rollout {rollout}, component {j}: {} vs {fd}",
                grad[j]
            );
        }
        drop(objective);
    }
}

/// A cube on the ground, thrown at random velocities: its output error's gradient through
/// the contact matches differences of the loss over 12-step rollouts through the impacts,
/// and the fit from 1.3x the coefficients (the Lame pair, and with friction its
/// coefficient) comes back within 1 %. `contact` and `gravity` are the scene's fields.
fn output_error_through_contact(contact: &str, gravity: &str) {
    output_error_through_contact_of(CUBE, "[]", contact, gravity);
}

/// [`output_error_through_contact`] with the scene's `mesh` and `constraints` fields.
fn output_error_through_contact_of(mesh: &str, constraints: &str, contact: &str, gravity: &str) {
    let text = format!(
        r#"Scene(
        name: "drop",
        mesh: {mesh},
        material: NeoHookean(Young(e: 1e5, nu: 0.4)),
        density: 1000.0,
        constraints: {constraints},
        contact: Some({contact}),
        integrator: (dt: 0.005, gravity: {gravity}, newton: (rel: 1e-12, abs: 1e-14)),
        steps: 1,
    )"#
    );
    let truth: Scene = ron::from_str(&text).unwrap();
    let data = generate(
        &truth,
        Path::new("test"),
        &DatasetSpec::new(1, 12, 3)
            .variations(
                Variations::default()
                    .speed(0.3)
                    .spin(0.0)
                    .stretch(0.0)
                    .rest(false),
            )
            .split((1.0, 0.0)),
        |_, _| {},
    )
    .unwrap();
    let mut sim = truth.build(Path::new("test")).unwrap().integrator;
    let dhat = sim.contact().unwrap().barrier().dhat;
    let touched = |x: &[f64]| x.chunks(3).any(|p| p[2] < dhat);
    assert!(data.trajectories[0].x.iter().any(|x| touched(x)));
    let trajectories = data.split(Split::Train);
    let options = deform_learn::OutputErrorOptions::default()
        .rollout(12)
        .velocity_weight(0.5);
    // With friction, its coefficients are fitted with the moduli.
    let frictional = sim.contact().unwrap().friction().is_some();
    let objective =
        deform_learn::OutputError::new(&mut sim, &trajectories, options, |_, _| {}).unwrap();
    let objective = match frictional {
        true => objective.with_friction().unwrap(),
        false => objective,
    };
    let c: Vec<f64> = objective.uniform_start().iter().map(|v| 1.3 * v).collect();
    assert_eq!(c.len(), 2 + usize::from(frictional));
    let (loss, grad) = objective.evaluate(&c).unwrap();
    assert!(loss > 0.0);
    for j in 0..c.len() {
        let h = 1e-5 * c[j];
        let (mut cp, mut cm) = (c.clone(), c.clone());
        cp[j] += h;
        cm[j] -= h;
        let fd =
            (objective.evaluate(&cp).unwrap().0 - objective.evaluate(&cm).unwrap().0) / (2.0 * h);
        assert!(
            (grad[j] - fd).abs() <= 1e-4 * fd.abs(),
            "component {j}: {} vs {fd}",
            grad[j]
        );
    }
    let truth_c = objective.uniform_start();
    drop(objective);
    let field = deform_learn::output::Field::default()
        .initial(Some(c))
        .friction(frictional);
    let fit = deform_learn::output::fit_output_error_field(
        &mut sim,
        &trajectories,
        &field,
        options,
        |_, _| {},
    )
    .unwrap();
    assert_eq!(fit.coefficients.len(), truth_c.len());
    for (f, t) in fit.coefficients.iter().zip(&truth_c) {
        assert!(
            relative(*f, *t) < 0.01,
            "{:?} against {truth_c:?}",
            fit.coefficients
        );
    }
}

/// Through the barrier alone (a frictionless ground): the adjoint system has the barrier's
/// Hessian (a plane's is exact, nothing is projected). Without it the gradient was 3.5x
/// off.
#[test]
fn output_error_gradient_through_the_barrier_equals_finite_differences() {
    output_error_through_contact(
        "(obstacles: [Plane(point: (0.0, 0.0, 0.0), normal: (0.0, 0.0, 1.0))])",
        "(0.0, 0.0, -9.81)",
    );
}

/// Through friction too (mu 0.3, gravity tilted by 30 degrees, so the cube slides): the
/// adjoint has friction's Hessian and the lag's dependence on each step's start.
#[test]
fn output_error_gradient_through_friction_equals_finite_differences() {
    output_error_through_contact(
        "(obstacles: [Plane(point: (0.0, 0.0, 0.0), normal: (0.0, 0.0, 1.0))], friction: Some((mu: [0.3])))",
        "(4.905, 0.0, -8.4957)",
    );
}

/// Through friction against a triangle mesh (the ground as two triangles, mu 0.3, the cube
/// sliding down the tilted gravity): the lag's closest points' weights move with the
/// step's start too.
#[test]
fn output_error_gradient_through_mesh_friction_equals_finite_differences() {
    let dir = tempfile::tempdir().unwrap();
    let ground = dir.path().join("ground.obj");
    std::fs::write(
        &ground,
        "v -1 -1 0\nv 2 -1 0\nv 2 1 0\nv -1 1 0\nf 1 2 3\nf 1 3 4\n",
    )
    .unwrap();
    let contact = format!(
        "(obstacles: [], meshes: [(file: {:?})], friction: Some((mu: [0.3])))",
        ground.display().to_string()
    );
    output_error_through_contact(&contact, "(4.905, 0.0, -8.4957)");
}

/// Through self-contact and friction between two parts of the body (a cube on a clamped
/// slab of the same mesh, self_mu 0.3, gravity tilted): all four vertices of a pair are
/// the body's, and the barrier's Hessian in the adjoint is the exact one (the projected
/// one Newton takes was 0.2 % off here).
#[test]
fn output_error_gradient_through_self_contact_friction_equals_finite_differences() {
    let dir = tempfile::tempdir().unwrap();
    let slab = ([4, 2, 1], [0.4, 0.2, 0.05], [-0.1, -0.05, -0.05]);
    let file = slab_and_cube(dir.path(), slab, 1e-3);
    output_error_through_contact_of(
        &format!("File({:?})", file.display().to_string()),
        "[(select: Plane(point: (0.0, 0.0, 0.0), normal: (0.0, 0.0, -1.0)))]",
        "(obstacles: [], self_contact: true, friction: Some((mu: [], self_mu: Some(0.3))))",
        "(4.905, 0.0, -8.4957)",
    );
}

#[test]
fn output_error_gradient_of_an_ensemble_equals_finite_differences() {
    // Stage 2 of model selection: the coefficients are every member's effective pair,
    // including a negative lambda (allowed while 3 lambda + 2 mu > 0).
    let mut s = scene("", "Beam(1)");
    let data = make(&s, 1, 4);
    s.material = ron::from_str(
        "Ensemble([(weight: 1.0, model: StVenantKirchhoff(Lame(mu: 1e4, lambda: -2e3))), \
         (weight: 2.0, model: NeoHookean(Lame(mu: 1e4, lambda: 4e4)))])",
    )
    .unwrap();
    let mut sim = s.build(Path::new("test")).unwrap().integrator;
    let deform_assembly::MaterialField::Uniform(model) = sim.assembly().materials() else {
        panic!("uniform");
    };
    let c0 = deform_learn::term_coefficients(model);
    assert_eq!(c0, vec![1e4, -2e3, 2e4, 8e4]);
    let trajectories = data.split(Split::Train);
    let options = deform_learn::OutputErrorOptions::default()
        .rollout(2)
        .velocity_weight(0.5);
    let objective =
        deform_learn::OutputError::new(&mut sim, &trajectories, options, |_, _| {}).unwrap();
    let (loss, grad) = objective.evaluate(&c0).unwrap();
    assert!(loss > 0.0);
    for j in 0..c0.len() {
        let h = 1e-4 * c0[j].abs();
        let (mut cp, mut cm) = (c0.clone(), c0.clone());
        cp[j] += h;
        cm[j] -= h;
        let fd =
            (objective.evaluate(&cp).unwrap().0 - objective.evaluate(&cm).unwrap().0) / (2.0 * h);
        eprintln!("dL/dc[{j}] = {:.6e}, finite difference {fd:.6e}", grad[j]);
        assert!(
            (grad[j] - fd).abs()
                <= 1e-4
                    * fd.abs()
                        .max(1e-3 * grad.iter().map(|g| g.abs()).fold(0.0, f64::max)),
            "component {j}: {} vs {fd}",
            grad[j]
        );
    }
}

#[test]
fn output_error_gradient_of_coefficient_fields_equals_finite_differences() {
    // A coefficient pair per element and per label, at random values around the truth.
    let s = scene("", "Beam(1)");
    let data = make(&s, 1, 4);
    let mut sim = s.build(Path::new("test")).unwrap().integrator;
    let tets = sim.assembly().num_elements();
    let trajectories = data.split(Split::Train);
    let options = deform_learn::OutputErrorOptions::default()
        .rollout(2)
        .velocity_weight(0.5);
    let per_element: Vec<u32> = (0..tets as u32).collect();
    let by_label: Vec<u32> = (0..tets as u32).map(|e| 10 + e % 3).collect();
    for labels in [per_element, by_label] {
        let objective = deform_learn::OutputError::new(&mut sim, &trajectories, options, |_, _| {})
            .unwrap()
            .with_field(&labels)
            .unwrap();
        let groups = labels
            .iter()
            .collect::<std::collections::BTreeSet<_>>()
            .len();
        assert_eq!(objective.num_coefficients(), 2 * groups);
        let mut rng = deform_learn::rng::Rng::new(5);
        let c: Vec<f64> = objective
            .uniform_start()
            .iter()
            .map(|c| c * rng.range(0.5, 1.5))
            .collect();
        let (loss, grad) = objective.evaluate(&c).unwrap();
        assert!(loss > 0.0 && grad.len() == c.len());
        for j in [0, 1, c.len() / 2, c.len() - 1] {
            let h = 1e-4 * c[j];
            let (mut cp, mut cm) = (c.clone(), c.clone());
            cp[j] += h;
            cm[j] -= h;
            let fd = (objective.evaluate(&cp).unwrap().0 - objective.evaluate(&cm).unwrap().0)
                / (2.0 * h);
            assert!(
                (grad[j] - fd).abs()
                    <= 1e-4
                        * fd.abs()
                            .max(1e-6 * grad.iter().fold(0.0f64, |m, g| m.max(g.abs()))),
                "{groups} groups, coefficient {j}: {} vs {fd}",
                grad[j]
            );
        }
        // The field's gradient sums, per term, to the uniform fit's at uniform coefficients.
        let start = objective.uniform_start();
        let (_, field_grad) = objective.evaluate(&start).unwrap();
        drop(objective);
        let truth = deform_assembly::MaterialField::Uniform(s.material.build().unwrap());
        sim.assembly_mut().set_materials(truth.clone()).unwrap();
        let uniform =
            deform_learn::OutputError::new(&mut sim, &trajectories, options, |_, _| {}).unwrap();
        let (_, g) = uniform.evaluate(&start[..2]).unwrap();
        for k in 0..2 {
            let sum: f64 = field_grad.iter().skip(k).step_by(2).sum();
            assert!(
                (sum - g[k]).abs() <= 1e-8 * g[k].abs().max(1e-12),
                "term {k}: {sum} vs {}",
                g[k]
            );
        }
        drop(uniform);
        sim.assembly_mut().set_materials(truth).unwrap();
    }
}

#[test]
fn the_smooth_field_gradient_equals_finite_differences() {
    // The third kind of field: weights of trilinear hat functions over the rest shape.
    let s = scene("", "Beam(1)");
    let data = make(&s, 1, 4);
    let built = s.build(Path::new("test")).unwrap();
    let (mesh, mut sim) = (built.mesh, built.integrator);
    let basis = deform_learn::basis::Basis::hat(&mesh, [3, 2, 1]).unwrap();
    let trajectories = data.split(Split::Train);
    let options = deform_learn::OutputErrorOptions::default()
        .rollout(2)
        .velocity_weight(0.5);
    let objective = deform_learn::OutputError::new(&mut sim, &trajectories, options, |_, _| {})
        .unwrap()
        .with_basis(basis.clone())
        .unwrap();
    assert_eq!(objective.num_coefficients(), 2 * 6);
    let mut rng = deform_learn::rng::Rng::new(7);
    let w: Vec<f64> = objective
        .uniform_start()
        .iter()
        .map(|c| c * rng.range(0.5, 1.5))
        .collect();
    let (loss, grad) = objective.evaluate(&w).unwrap();
    assert!(loss > 0.0);
    for j in 0..w.len() {
        let h = 1e-5 * w[j];
        let (mut wp, mut wm) = (w.clone(), w.clone());
        wp[j] += h;
        wm[j] -= h;
        let fd =
            (objective.evaluate(&wp).unwrap().0 - objective.evaluate(&wm).unwrap().0) / (2.0 * h);
        assert!(
            (grad[j] - fd).abs() <= 1e-4 * fd.abs(),
            "weight {j}: {} vs {fd}",
            grad[j]
        );
    }
    // It is the per-element gradient at the expanded field, contracted with the basis.
    let per_element = basis.expand(&w, 2);
    drop(objective);
    let uniform = deform_assembly::MaterialField::Uniform(s.material.build().unwrap());
    sim.assembly_mut().set_materials(uniform).unwrap();
    let labels: Vec<u32> = (0..mesh.num_tets() as u32).collect();
    let elements = deform_learn::OutputError::new(&mut sim, &trajectories, options, |_, _| {})
        .unwrap()
        .with_field(&labels)
        .unwrap();
    let (element_loss, g) = elements.evaluate(&per_element).unwrap();
    assert!((element_loss - loss).abs() <= 1e-12 * loss);
    for (a, b) in basis.contract(&g, 2).iter().zip(&grad) {
        assert!((a - b).abs() <= 1e-10 * b.abs().max(1e-12), "{a} vs {b}");
    }
}

#[test]
fn a_regularised_field_gradient_equals_finite_differences() {
    let s = scene("", "Beam(1)");
    let data = make(&s, 1, 3);
    let built = s.build(Path::new("test")).unwrap();
    let (mesh, mut sim) = (built.mesh, built.integrator);
    let labels: Vec<u32> = (0..mesh.num_tets() as u32).collect();
    let neighbours = deform_learn::face_neighbours(&mesh, &labels);
    assert_eq!(
        neighbours.len(),
        deform_mesh::topology::faces(&mesh).interior.len()
    );
    let trajectories = data.split(Split::Train);
    let options = deform_learn::OutputErrorOptions::default().rollout(3);
    let regularisation = deform_learn::Regularisation::default()
        .towards(0.3)
        .smooth(0.2)
        .neighbours(neighbours);
    let objective = deform_learn::OutputError::new(&mut sim, &trajectories, options, |_, _| {})
        .unwrap()
        .with_field(&labels)
        .unwrap()
        .with_regularisation(regularisation);
    let mut rng = deform_learn::rng::Rng::new(8);
    let c: Vec<f64> = objective
        .uniform_start()
        .iter()
        .map(|c| c * rng.range(0.5, 2.0))
        .collect();
    let (_, grad) = objective.evaluate(&c).unwrap();
    for j in [0, 3, 17, c.len() - 2] {
        let h = 1e-5 * c[j];
        let (mut cp, mut cm) = (c.clone(), c.clone());
        cp[j] += h;
        cm[j] -= h;
        let fd =
            (objective.evaluate(&cp).unwrap().0 - objective.evaluate(&cm).unwrap().0) / (2.0 * h);
        assert!(
            (grad[j] - fd).abs() <= 1e-4 * fd.abs(),
            "coefficient {j}: {} vs {fd}",
            grad[j]
        );
    }
    // At the base material everywhere the penalty and its gradient vanish.
    let start = objective.uniform_start();
    let (plain, _) = objective.evaluate(&start).unwrap();
    drop(objective);
    let uniform = deform_assembly::MaterialField::Uniform(s.material.build().unwrap());
    sim.assembly_mut().set_materials(uniform).unwrap();
    let unregularised = deform_learn::OutputError::new(&mut sim, &trajectories, options, |_, _| {})
        .unwrap()
        .with_field(&labels)
        .unwrap();
    assert_eq!(unregularised.evaluate(&start).unwrap().0, plain);
}

#[test]
fn the_damping_gradient_equals_finite_differences() {
    // Rayleigh alpha and gamma fitted through the same adjoint, with a two-group field. The
    // damping force's derivative in x (gamma D_v K, by a forward difference) is in the
    // adjoint: without it the gradient is 8e-5 relative off at gamma = 1e-4 (see the module docs).
    let s = scene("alpha: 0.3, gamma: 2e-4", "Beam(1)");
    let data = make(&s, 1, 4);
    let mut sim = s.build(Path::new("test")).unwrap().integrator;
    let labels: Vec<u32> = (0..sim.assembly().num_elements() as u32)
        .map(|e| e % 2)
        .collect();
    let trajectories = data.split(Split::Train);
    let options = deform_learn::OutputErrorOptions::default().rollout(4);
    let objective = deform_learn::OutputError::new(&mut sim, &trajectories, options, |_, _| {})
        .unwrap()
        .with_field(&labels)
        .unwrap()
        .with_damping();
    assert_eq!(objective.num_coefficients(), 2 * 2 + 2);
    let start = objective.uniform_start();
    assert_eq!(&start[4..], &[0.3, 2e-4]);
    // Away from the truth in every coefficient; then with a negative gamma (a coarse step's
    // correction of its own dissipation, above -dt / 2).
    let away: Vec<f64> = start
        .iter()
        .zip([0.7, 1.3, 1.2, 0.8, 2.0, 0.5])
        .map(|(a, b)| a * b)
        .collect();
    let mut negative = away.clone();
    negative[5] = -2e-4;
    // Near the stability bound, where the fits of a 4x coarser step end.
    let mut bound = away.clone();
    bound[5] = -0.45 * 0.01;
    for c in [away, negative, bound] {
        let (_, grad) = objective.evaluate(&c).unwrap();
        for j in 0..c.len() {
            let h = 1e-5 * c[j].abs();
            let (mut cp, mut cm) = (c.clone(), c.clone());
            cp[j] += h;
            cm[j] -= h;
            let fd = (objective.evaluate(&cp).unwrap().0 - objective.evaluate(&cm).unwrap().0)
                / (2.0 * h);
            eprintln!("coefficient {j}: {:.6e} vs {fd:.6e}", grad[j]);
            assert!(
                (grad[j] - fd).abs() <= 1e-5 * fd.abs(),
                "gamma {}, coefficient {j}: {} vs {fd}",
                c[5],
                grad[j]
            );
        }
    }
}

#[test]
fn the_mass_scale_gradient_equals_finite_differences() {
    // A scale per vertex's lumped mass, through the same adjoint, with a per-element field,
    // mass damping and gravity (both of which enter dr/ds), and the pull of ln s towards 0.
    let s = scene("alpha: 0.4", "Beam(1)");
    let data = make(&s, 1, 4);
    let mut sim = s.build(Path::new("test")).unwrap().integrator;
    let (tets, vertices) = (sim.assembly().num_elements(), sim.assembly().num_vertices());
    let labels: Vec<u32> = (0..tets as u32).collect();
    let (free, fixed): (Vec<usize>, Vec<usize>) =
        (0..vertices).partition(|&v| !sim.dofs().is_constrained(v));
    let trajectories = data.split(Split::Train);
    let options = deform_learn::OutputErrorOptions::default()
        .rollout(4)
        .velocity_weight(0.5);
    let regularisation = deform_learn::Regularisation::default().towards(0.2);
    let objective = deform_learn::OutputError::new(&mut sim, &trajectories, options, |_, _| {})
        .unwrap()
        .with_field(&labels)
        .unwrap()
        .with_regularisation(regularisation)
        .with_mass_scale()
        .with_damping();
    let m = 2 * tets;
    assert_eq!(objective.num_coefficients(), m + vertices + 2);
    let start = objective.uniform_start();
    assert!(start[m..m + vertices].iter().all(|&s| s == 1.0));
    let mut rng = deform_learn::rng::Rng::new(11);
    let c: Vec<f64> = start.iter().map(|c| c * rng.range(0.7, 1.4)).collect();
    let (_, grad) = objective.evaluate(&c).unwrap();
    // An element, free vertices and alpha.
    assert!(!fixed.is_empty() && free.len() > fixed.len());
    let mut checked = vec![
        0,
        m + free[0],
        m + free[free.len() / 2],
        m + free[free.len() - 1],
    ];
    checked.push(m + vertices);
    for j in checked {
        let h = 1e-5 * c[j].abs();
        let (mut cp, mut cm) = (c.clone(), c.clone());
        cp[j] += h;
        cm[j] -= h;
        let fd =
            (objective.evaluate(&cp).unwrap().0 - objective.evaluate(&cm).unwrap().0) / (2.0 * h);
        assert!(
            (grad[j] - fd).abs() <= 1e-4 * fd.abs(),
            "coefficient {j}: {} vs {fd}",
            grad[j]
        );
    }
    // A constrained vertex's scale changes nothing but the penalty.
    let fixed = fixed[0];
    let mut cp = c.clone();
    cp[m + fixed] *= 1.5;
    let penalty = |s: f64| 0.2 / vertices as f64 * s.ln().powi(2);
    let moved = objective.evaluate(&cp).unwrap().0 - objective.evaluate(&c).unwrap().0;
    let expected = penalty(cp[m + fixed]) - penalty(c[m + fixed]);
    assert!((moved - expected).abs() <= 1e-12, "{moved} vs {expected}");
    drop(objective);
    // The fitted scales are left in the integrator.
    assert_eq!(sim.mass_scale(), Some(&c[m..m + vertices]));
}
