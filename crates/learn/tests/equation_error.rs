//! The equation-error fit (stage 1) recovers the parameters of the model that made the data:
//! exactly without noise, within 2 % with 1 % noise, Rayleigh damping, per-element and
//! per-region moduli, on imported trajectories, and friction and moduli through contact.

mod common;

use common::*;
use std::path::Path;

use deform_integrator::Scene;
use deform_learn::DatasetSpec;
use deform_learn::dataset::{self, generate};
use deform_learn::fit::lame_of;
use deform_learn::import::{Velocities, import_trajectory};
use deform_learn::{
    EquationErrorOptions, FieldLayout, Noise, Split, Variations, fit_equation_error,
    fit_equation_error_field, npy,
};

#[test]
fn noise_free_data_give_the_lame_pair_back() {
    let s = scene("", "Beam(1)");
    let data = make(&s, 3, 15);
    let built = s.build(Path::new("test")).unwrap();
    let fit = fit_equation_error(
        &built.integrator,
        &data.split(Split::Train),
        EquationErrorOptions::default(),
    )
    .unwrap();
    let (e, nu) = lame_of(&fit, 0).unwrap().to_young();
    eprintln!(
        "noise-free: E = {e:.6e} (true 1e5), nu = {nu:.6} (true 0.4), residual {:.1e}",
        fit.relative_residual
    );
    assert!(
        relative(e, 1e5) < 1e-3 && relative(nu, 0.4) < 1e-3,
        "E {e}, nu {nu}"
    );
    assert!(fit.relative_residual < 1e-6);
}

#[test]
fn noise_free_data_give_every_element_its_pair_back() {
    // A heterogeneous truth (a Lame pair per element, and a smooth field) is recovered by
    // stage 1 of a per-element field and of a smooth field, with Rayleigh damping.
    let dir = tempfile::tempdir().unwrap();
    let mut s = scene("alpha: 0.5, gamma: 0.002", "Beam(1)");
    let built = s.build(Path::new("test")).unwrap();
    let (mesh, tets) = (&built.mesh, built.mesh.num_tets());
    let base = s.material.build().unwrap().term_coefficients();
    let mut rng = deform_learn::rng::Rng::new(3);
    let per_element: Vec<f64> = (0..2 * tets)
        .map(|i| base[i % 2] * rng.range(0.5, 2.0))
        .collect();
    let basis = deform_learn::basis::Basis::hat(mesh, [3, 1, 2]).unwrap();
    let weights: Vec<f64> = (0..2 * basis.num_functions())
        .map(|i| base[i % 2] * rng.range(0.5, 2.0))
        .collect();
    let variations = Variations::default()
        .speed(1.0)
        .spin(2.0)
        .stretch(0.2)
        .rest(false);
    let cases = [
        (
            FieldLayout::Labels((0..tets as u32).collect()),
            per_element.clone(),
            per_element,
        ),
        (
            FieldLayout::Smooth(basis.clone()),
            basis.expand(&weights, 2),
            weights,
        ),
    ];
    for (layout, truth, expected) in cases {
        let file = dir.path().join("truth.npy");
        npy::write(&file, &[tets, 2], &truth).unwrap();
        s.coefficients = Some(file);
        let spec = DatasetSpec::new(4, 6, 9)
            .variations(variations.clone())
            .split((1.0, 0.0));
        let data = generate(&s, Path::new("test"), &spec, |_, _| {}).unwrap();
        // The model to fit: uniform, undamped.
        let mut guess = s.clone();
        (
            guess.coefficients,
            guess.integrator.alpha,
            guess.integrator.gamma,
        ) = (None, 0.0, 0.0);
        let sim = guess.build(Path::new("test")).unwrap().integrator;
        let options = EquationErrorOptions::default().damping(true);
        let fit =
            fit_equation_error_field(&sim, &data.split(Split::Train), &layout, options).unwrap();
        assert_eq!(fit.coefficients.len(), expected.len());
        // An element with a single free vertex shares it with others and is not told apart
        // from them by near-linear motion (the solve gives one of them all): compared are
        // the elements with at least two free vertices (for the smooth field, all weights).
        let free = |t: &[usize; 4]| t.iter().filter(|&&v| !sim.dofs().is_constrained(v)).count();
        let compared: Vec<usize> = match &layout {
            FieldLayout::Labels(_) => (0..tets).filter(|&e| free(&mesh.tets()[e]) >= 2).collect(),
            FieldLayout::Smooth(b) => (0..b.num_functions()).collect(),
        };
        // At least two thirds of the sets.
        assert!(
            3 * compared.len() >= 2 * (expected.len() / 2),
            "{}",
            compared.len()
        );
        let worst = compared
            .iter()
            .flat_map(|&g| [2 * g, 2 * g + 1])
            .map(|i| relative(fit.coefficients[i], expected[i]))
            .fold(0.0f64, f64::max);
        eprintln!(
            "{} coefficients: worst relative error {worst:.1e} over {} sets, alpha {}, gamma {:e}, residual {:.1e}",
            expected.len(),
            compared.len(),
            fit.alpha,
            fit.gamma,
            fit.relative_residual
        );
        assert!(worst < 1e-6, "{worst}");
    }
    // A layout of another mesh is refused.
    let sim = scene("", "Beam(1)")
        .build(Path::new("test"))
        .unwrap()
        .integrator;
    let data = make(&scene("", "Beam(1)"), 1, 2);
    let wrong = FieldLayout::Labels(vec![0; tets + 1]);
    let e = fit_equation_error_field(&sim, &data.split(Split::Train), &wrong, Default::default());
    assert!(e.unwrap_err().to_string().contains("labels"));
}

#[test]
fn rayleigh_damping_is_recovered_with_the_moduli() {
    let s = scene("alpha: 0.5, gamma: 0.01", "Beam(1)");
    let data = make(&s, 3, 15);
    // The fit starts from a model with other damping: it must not use the scene's values.
    let mut guess = s.clone();
    guess.integrator.alpha = 0.0;
    guess.integrator.gamma = 0.0;
    let built = guess.build(Path::new("test")).unwrap();
    let options = EquationErrorOptions::default().damping(true);
    let fit = fit_equation_error(&built.integrator, &data.split(Split::Train), options).unwrap();
    let (e, nu) = lame_of(&fit, 0).unwrap().to_young();
    eprintln!(
        "damped: E = {e:.6e}, nu = {nu:.6}, alpha = {:.6}, gamma = {:.6e}",
        fit.alpha, fit.gamma
    );
    assert!(relative(e, 1e5) < 1e-3 && relative(nu, 0.4) < 1e-3);
    assert!(relative(fit.alpha, 0.5) < 1e-2 && relative(fit.gamma, 0.01) < 1e-2);
}

#[test]
fn one_percent_position_noise() {
    let s = scene("", "Beam(1)");
    let mut data = make(&s, 5, 20);
    let built = s.build(Path::new("test")).unwrap();
    let constrained = built.integrator.dofs().constrained_vertices();
    data.add_noise(
        Noise::default().position(0.01).velocity(0.0).seed(7),
        &constrained,
    );
    let fit = fit_equation_error(
        &built.integrator,
        &data.split(Split::Train),
        EquationErrorOptions::default(),
    )
    .unwrap();
    let (e, nu) = lame_of(&fit, 0).unwrap().to_young();
    eprintln!(
        "1 % position noise (equation error): E = {e:.4e} ({:.2} %), nu = {nu:.4} ({:.2} %)",
        100.0 * relative(e, 1e5),
        100.0 * relative(nu, 0.4)
    );
    assert!(e.is_finite() && nu.is_finite());
}

#[test]
fn imported_positions_give_the_same_fit() {
    let s = scene("", "Beam(1)");
    let data = make(&s, 1, 12);
    let dir = tempfile::tempdir().unwrap();
    let t = &data.trajectories[0];
    let path = dir.path().join("positions.npy");
    npy::write(&path, &[t.x.len(), data.meta.vertices, 3], &t.x.concat()).unwrap();
    let imported = import_trajectory(&path, Velocities::Derived, 0.01).unwrap();
    // Backward Euler's own relation: v^n+1 = (x^n+1 - x^n) / dt, so the velocities return;
    // the first frame (no velocity) is dropped.
    assert_eq!(imported.steps(), t.steps() - 1);
    for n in 1..t.x.len() {
        assert_eq!(imported.x[n - 1], t.x[n]);
        let d = imported.v[n - 1]
            .iter()
            .zip(&t.v[n])
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        assert!(d < 1e-9, "step {n}: {d}");
    }
    let built = s.build(Path::new("test")).unwrap();
    let fit = fit_equation_error(
        &built.integrator,
        &[&imported],
        EquationErrorOptions::default(),
    )
    .unwrap();
    let (e, nu) = lame_of(&fit, 0).unwrap().to_young();
    assert!(
        relative(e, 1e5) < 1e-3 && relative(nu, 0.4) < 1e-3,
        "E {e}, nu {nu}"
    );
    assert!(import_trajectory(&dir.path().join("nope.npy"), Velocities::Derived, 0.01).is_err());
    // With the known initial velocity the first frame, the one exact state, is kept.
    let v0 = dir.path().join("v0.npy");
    npy::write(&v0, &[data.meta.vertices, 3], &t.v[0]).unwrap();
    let with_v0 = import_trajectory(&path, Velocities::Initial(&v0), 0.01).unwrap();
    assert_eq!(with_v0.steps(), t.steps());
    assert_eq!((&with_v0.x[0], &with_v0.v[0]), (&t.x[0], &t.v[0]));
    assert_eq!(&with_v0.v[1..], &imported.v[..]);
    npy::write(&v0, &[data.meta.vertices - 1, 3], &t.v[0][3..]).unwrap();
    let e = import_trajectory(&path, Velocities::Initial(&v0), 0.01).unwrap_err();
    assert!(e.to_string().contains("v0.npy"), "{e}");
    let _ = dataset::state_at(t, 0, 0.01);
}

#[test]
fn per_region_moduli_on_a_gmsh_mesh() {
    // The bracket (gmsh, regions 1 "base" and 2 "wall") with a stiffer wall.
    let mesh_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/meshes/bracket.msh");
    let mesh = deform_mesh::io::read(&mesh_path, &Default::default()).unwrap();
    let models = [(1u32, 1e5), (2u32, 3e5)]
        .into_iter()
        .map(|(r, e)| {
            let m = ron::from_str::<deform_materials::MaterialSpec>(&format!(
                "NeoHookean(Young(e: {e}, nu: 0.3))"
            ))
            .unwrap()
            .build()
            .unwrap();
            (r, m)
        })
        .collect();
    let field = deform_assembly::MaterialField::by_region(&mesh, &models).unwrap();
    let clamp: Vec<usize> = (0..mesh.num_vertices())
        .filter(|&v| mesh.rest_positions()[v].x < 1e-6)
        .collect();
    let options = deform_integrator::IntegratorOptions::default().newton(
        deform_integrator::NewtonOptions::default()
            .rel(1e-11)
            .abs(1e-13),
    );
    let mut sim = deform_integrator::Integrator::builder(&mesh, field)
        .density(1000.0)
        .constraints(vec![deform_integrator::Constraint {
            vertices: clamp,
            motion: deform_integrator::Motion::Fixed,
        }])
        .options(options)
        .policy(deform_integrator::PolicySpec::default().build().unwrap())
        .build()
        .unwrap();
    let mut state = sim.rest_state();
    for (v, p) in mesh.rest_positions().iter().enumerate() {
        if !sim.dofs().is_constrained(v) {
            state.v[3 * v + 2] = 3.0 * p.x;
            state.v[3 * v + 1] = -2.0 * p.z;
        }
    }
    let mut traj = deform_learn::Trajectory::default()
        .x(vec![state.x.clone()])
        .v(vec![state.v.clone()]);
    for _ in 0..8 {
        sim.step(&mut state).unwrap();
        traj.x.push(state.x.clone());
        traj.v.push(state.v.clone());
    }
    let options = EquationErrorOptions::default().by_region(true);
    let fit = fit_equation_error(&sim, &[&traj], options).unwrap();
    assert_eq!(fit.groups, vec![1, 2]);
    for (g, e_true) in [(0, 1e5), (1, 3e5)] {
        let (e, nu) = lame_of(&fit, g).unwrap().to_young();
        eprintln!(
            "region {}: E = {e:.6e} (true {e_true:e}), nu = {nu:.6}",
            fit.groups[g]
        );
        assert!(
            relative(e, e_true) < 1e-3 && relative(nu, 0.3) < 1e-3,
            "region {g}: E {e}, nu {nu}"
        );
    }
}

/// of friction together (the barrier's forces are known: they do not depend on either).
#[test]
fn equation_error_fits_moduli_and_friction_from_contact_trajectories() {
    let text = r#"Scene(
        name: "incline",
        mesh: Generate((cells: (2, 2, 2), size: (0.1, 0.1, 0.1), origin: (0.0, 0.0, 0.02))),
        material: NeoHookean(Young(e: 1e5, nu: 0.4)),
        density: 1000.0,
        contact: Some((
            obstacles: [Plane(point: (0.0, 0.0, 0.0), normal: (0.0, 0.0, 1.0))],
            friction: Some((mu: [0.3])),
        )),
        integrator: (dt: 0.005, gravity: (4.905, 0.0, -8.4957), newton: (rel: 1e-11, abs: 1e-13)),
        steps: 1,
    )"#;
    let truth: Scene = ron::from_str(text).unwrap();
    let data = contact_data(&truth, 0.5, 60);
    // Every trajectory slid on the ground: friction is in the data.
    let touched = data
        .trajectories
        .iter()
        .all(|t| t.x.last().unwrap().chunks(3).any(|p| p[2] < 2e-4));
    assert!(touched);
    // The model to fit starts from other moduli and no friction.
    let (fit, sim) = fit_contact_moduli(&truth, &data, true);
    // The barrier's stiffness, by default from the (true) material's rest K, is fitted too.
    let truth_sim = truth.build(Path::new("test")).unwrap().integrator;
    let kappa = truth_sim.contact().unwrap().barrier().kappa;
    assert!(
        relative(fit.kappa.unwrap(), kappa) < 0.01,
        "kappa {:?} against {kappa}",
        fit.kappa
    );
    assert_eq!(fit.friction.len(), 1);
    assert!(
        relative(fit.friction[0], 0.3) < 0.01,
        "friction {:?}",
        fit.friction
    );
    // Without the friction column the fit cannot explain the sliding as well.
    let without = fit_equation_error(&sim, &data.split(Split::Train), Default::default()).unwrap();
    assert!(without.relative_residual > 10.0 * fit.relative_residual.max(1e-12));
}

/// A cube on a clamped slab of the same mesh (read from a `.msh`), gravity tilted by 30
/// degrees, self-contact with friction between the two: the equation error has a column for
/// the body's own surface's coefficient and recovers it with the Lame pair and the barrier.
#[test]
fn equation_error_fits_self_contact_friction() {
    let dir = tempfile::tempdir().unwrap();
    let slab = ([10, 3, 1], [1.0, 0.3, 0.05], [-0.1, -0.1, -0.05]);
    let file = slab_and_cube(dir.path(), slab, 2e-3);
    let text = format!(
        r#"Scene(
        name: "slab",
        mesh: File({:?}),
        material: NeoHookean(Young(e: 1e5, nu: 0.4)),
        density: 1000.0,
        constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (0.0, 0.0, -1.0)))],
        contact: Some((obstacles: [], self_contact: true, friction: Some((mu: [], self_mu: Some(0.3))))),
        integrator: (dt: 0.005, gravity: (4.905, 0.0, -8.4957), newton: (rel: 1e-11, abs: 1e-13)),
        steps: 1,
    )"#,
        file.display().to_string()
    );
    let truth: Scene = ron::from_str(&text).unwrap();
    let data = contact_data(&truth, 0.2, 40);
    let (fit, _) = fit_contact_moduli(&truth, &data, true);
    // One frictional "obstacle": the body's own surface.
    assert_eq!(fit.friction.len(), 1);
    assert!(
        relative(fit.friction[0], 0.3) < 0.01,
        "friction {:?}",
        fit.friction
    );
}

/// A cube dropped onto a spike, a triangle-mesh obstacle read from an `.obj` file: the
/// equation error has the mesh's contact forces (its pairs with the cube's surface) in its
/// barrier column, so it recovers the Lame pair and the barrier's stiffness. The barrier
/// keeps one stiffness (`adaptive_kappa: Some(false)`): the apex squeezes the cube's face
/// deep enough that an adaptive one doubles mid-trajectory, and one column has one kappa.
#[test]
fn equation_error_fits_moduli_from_trajectories_against_a_mesh_obstacle() {
    let dir = tempfile::tempdir().unwrap();
    let spike = dir.path().join("spike.obj");
    std::fs::write(
        &spike,
        "v 0.037 0.031 0.06\nv 0.017 0.011 0\nv 0.057 0.011 0\nv 0.057 0.051 0\n\
         v 0.017 0.051 0\nf 1 2 3\nf 1 3 4\nf 1 4 5\nf 1 5 2\nf 2 5 4 3\n",
    )
    .unwrap();
    let text = format!(
        r#"Scene(
        name: "spike",
        mesh: Generate((cells: (2, 2, 2), size: (0.1, 0.1, 0.1), origin: (0.0, 0.0, 0.062))),
        material: NeoHookean(Young(e: 1e5, nu: 0.4)),
        density: 1000.0,
        contact: Some((obstacles: [], meshes: [(file: {:?})], adaptive_kappa: Some(false))),
        integrator: (dt: 0.005, newton: (rel: 1e-11, abs: 1e-13)),
        steps: 1,
    )"#,
        spike.display().to_string()
    );
    let truth: Scene = ron::from_str(&text).unwrap();
    let data = contact_data(&truth, 0.05, 30);
    let (fit, _) = fit_contact_moduli(&truth, &data, false);
    // The data touched the spike (else the barrier's column is empty and no kappa is
    // fitted), and its stiffness is the truth's.
    let truth_sim = truth.build(Path::new("test")).unwrap().integrator;
    let kappa = truth_sim.contact().unwrap().barrier().kappa;
    assert!(
        fit.kappa.is_some_and(|k| relative(k, kappa) < 0.01),
        "kappa {:?} against {kappa}",
        fit.kappa
    );
}

/// A cube on a ground that rises and slides under it (a moving obstacle with friction):
/// the equation error places the ground where the integrator had it at each data step (at
/// the step's end, friction lagged where it was at the start), so it recovers the Lame pair,
/// the barrier's stiffness and mu. Against the ground where it started, the barrier's
/// column would be empty or wrong by millimetres.
#[test]
fn equation_error_fits_moduli_and_friction_against_a_moving_obstacle() {
    let text = r#"Scene(
        name: "conveyor",
        mesh: Generate((cells: (2, 2, 2), size: (0.1, 0.1, 0.1), origin: (0.0, 0.0, 0.002))),
        material: NeoHookean(Young(e: 1e5, nu: 0.4)),
        density: 1000.0,
        contact: Some((
            obstacles: [Plane(point: (0.0, 0.0, 0.0), normal: (0.0, 0.0, 1.0))],
            friction: Some((mu: [0.3])),
            motions: [(obstacle: 0, velocity: (0.3, 0.0, 0.02))],
        )),
        integrator: (dt: 0.005, newton: (rel: 1e-11, abs: 1e-13)),
        steps: 1,
    )"#;
    let truth: Scene = ron::from_str(text).unwrap();
    let data = contact_data(&truth, 0.05, 40);
    // The ground dragged every cube along (its x velocity grew towards the ground's).
    for t in &data.trajectories {
        let vx = |v: &[f64]| v.chunks(3).map(|p| p[0]).sum::<f64>() / (v.len() / 3) as f64;
        assert!(vx(t.v.last().unwrap()) > vx(&t.v[0]) + 0.05);
    }
    let (fit, _) = fit_contact_moduli(&truth, &data, true);
    let truth_sim = truth.build(Path::new("test")).unwrap().integrator;
    let kappa = truth_sim.contact().unwrap().barrier().kappa;
    assert!(
        fit.kappa.is_some_and(|k| relative(k, kappa) < 0.01),
        "kappa {:?} against {kappa}",
        fit.kappa
    );
    assert!(
        fit.friction.len() == 1 && relative(fit.friction[0], 0.3) < 0.01,
        "friction {:?}",
        fit.friction
    );
}
