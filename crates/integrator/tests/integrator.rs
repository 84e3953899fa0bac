//! Backward Euler against analytic cases (free fall, momentum, beam theory), dissipation,
//! equilibrium, agreement of every solver policy, kinematic constraints, loads and conditions.

mod beams;

use beams::*;

use deform_integrator::{
    Constraint, Integrator, IntegratorOptions, IterationReport, Motion, NewtonOptions, PolicySpec,
    State,
};
use deform_mesh::generate::BoxGrid;

#[test]
fn free_fall_is_exact() {
    let mesh = beam();
    let mut s = sim(
        &mesh,
        vec![],
        IntegratorOptions::default(),
        "Fixed(Direct())",
    );
    let mut state = s.rest_state();
    let x0 = state.x.clone();
    let dt = s.options().dt;
    for _ in 0..5 {
        s.step(&mut state).unwrap();
    }
    // v_n = n dt g, x_n = x_0 + dt^2 g n(n+1)/2 (backward Euler).
    let g = -9.81;
    for i in 0..state.x.len() {
        let (ev, ex) = if i % 3 == 2 {
            (5.0 * dt * g, x0[i] + dt * dt * g * 15.0)
        } else {
            (0.0, x0[i])
        };
        assert!((state.v[i] - ev).abs() < 1e-9, "v[{i}] = {}", state.v[i]);
        assert!((state.x[i] - ex).abs() < 1e-9, "x[{i}]");
    }
    assert!((state.t - 5.0 * dt).abs() < 1e-15);
}

#[test]
fn scaled_masses_carry_gravity_with_them_and_are_validated() {
    let mesh = beam();
    let mut s = sim(
        &mesh,
        vec![],
        IntegratorOptions::default(),
        "Fixed(Direct())",
    );
    let own = s.assembly().vertex_masses(s.mass());
    let scale: Vec<f64> = (0..mesh.num_vertices())
        .map(|v| 0.5 + (v % 7) as f64 / 4.0)
        .collect();
    s.set_mass_scale(Some(&scale)).unwrap();
    assert_eq!(s.mass_scale(), Some(scale.as_slice()));
    assert_eq!(s.unscaled_vertex_masses(), own);
    let scaled = s.assembly().vertex_masses(s.mass());
    for v in 0..own.len() {
        assert_eq!(scaled[v], own[v] * scale[v]);
        assert_eq!(s.gravity_forces()[3 * v + 2], scaled[v] * -9.81);
    }
    // Free fall stays exact: gravity scales with the mass it pulls.
    let mut state = s.rest_state();
    let x0 = state.x.clone();
    let dt = s.options().dt;
    for _ in 0..3 {
        s.step(&mut state).unwrap();
    }
    for i in (2..state.x.len()).step_by(3) {
        assert!((state.v[i] + 3.0 * dt * 9.81).abs() < 1e-9, "v[{i}]");
        assert!((state.x[i] - x0[i] + 6.0 * dt * dt * 9.81).abs() < 1e-9);
    }
    // Changed gravity is applied to the scaled masses.
    let mut options = s.options().clone();
    options.gravity = [1.0, 0.0, 0.0];
    s.set_options(options.clone()).unwrap();
    assert_eq!(s.gravity_forces()[3], scaled[1]);
    assert_eq!(s.gravity_forces()[5], 0.0);
    // Bad scales are refused naming the vertex and leave the masses as they were.
    let mut bad = scale.clone();
    bad[3] = f64::NAN;
    let e = s.set_mass_scale(Some(&bad)).unwrap_err().to_string();
    assert!(e.contains("mass_scale") && e.contains("vertex 3"), "{e}");
    let e = s.set_mass_scale(Some(&scale[1..])).unwrap_err().to_string();
    assert!(e.contains("vertices"), "{e}");
    assert_eq!(s.mass_scale(), Some(scale.as_slice()));
    // None restores the mesh's own masses exactly.
    s.set_mass_scale(None).unwrap();
    assert_eq!(s.mass_scale(), None);
    assert_eq!(s.assembly().vertex_masses(s.mass()), own);
    // The kind of mass is fixed; a consistent mass has no per-vertex scales.
    options.mass = deform_integrator::MassKind::Consistent;
    assert!(s.set_options(options.clone()).is_err());
    let mut c = sim(&mesh, vec![], options, "Fixed(Direct())");
    let e = c.set_mass_scale(Some(&scale)).unwrap_err().to_string();
    assert!(e.contains("lumped"), "{e}");
}

#[test]
fn momentum_is_conserved_and_energy_is_dissipated_without_external_forces() {
    let mesh = beam();
    let options = IntegratorOptions::default().gravity([0.0; 3]);
    let mut s = sim(&mesh, vec![], options, "Fixed(Direct())");
    let mut state = s.rest_state();
    // A stretched, spinning, drifting start.
    for (i, p) in mesh.rest_positions().iter().enumerate() {
        state.x[3 * i] = 1.1 * p.x;
        state.v[3 * i] = 0.3 - p.y;
        state.v[3 * i + 1] = p.x;
        state.v[3 * i + 2] = 0.1;
    }
    let p0 = momentum(&s, &state.v);
    let total = |s: &mut Integrator, st: &State| {
        let m = s.assembly().vertex_masses(s.mass());
        let kinetic: f64 =
            st.v.iter()
                .enumerate()
                .map(|(i, v)| 0.5 * m[i / 3] * v * v)
                .sum();
        kinetic + s.assembly_mut().energy(&st.x).unwrap()
    };
    let mut energy = total(&mut s, &state);
    for _ in 0..10 {
        s.step(&mut state).unwrap();
        let p = momentum(&s, &state.v);
        for c in 0..3 {
            assert!(
                (p[c] - p0[c]).abs() < 1e-9 * (1.0 + p0[c].abs()),
                "momentum {c}: {} vs {}",
                p[c],
                p0[c]
            );
        }
        let e = total(&mut s, &state);
        assert!(e <= energy * (1.0 + 1e-9), "energy grew: {e} > {energy}");
        energy = e;
    }
}

#[test]
fn static_equilibrium_balances_gravity_and_damped_dynamics_reach_it() {
    let mesh = beam();
    // E = 1e6: the tip sags a few centimetres; alpha = 16 is about critical for the first mode.
    let options = IntegratorOptions::default().alpha(16.0).dt(0.02);
    let mut s = Integrator::builder(&mesh, material("NeoHookean(Young(e: 1e6, nu: 0.4))"))
        .density(1000.0)
        .constraints(clamp(&mesh))
        .options(options)
        .policy(policy("Fixed(Direct())"))
        .build()
        .unwrap();
    let mut equilibrium = s.rest_state();
    let report = s.solve_static(&mut equilibrium).unwrap();
    assert!(report.converged);
    // f_e + M g = 0 on the free DOFs.
    let mut f = vec![0.0; equilibrium.x.len()];
    s.assembly_mut().forces(&equilibrium.x, &mut f).unwrap();
    let g = s.gravity_forces().to_vec();
    let scale = g.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    for &d in s.dofs().free_dofs() {
        assert!(
            (f[d] + g[d]).abs() <= 1e-5 * scale,
            "dof {d}: {}",
            f[d] + g[d]
        );
    }
    // The tip sags.
    let tip = (0..mesh.num_vertices())
        .find(|&v| mesh.rest_positions()[v].x > 1.0 - 1e-9)
        .unwrap();
    assert!(equilibrium.x[3 * tip + 2] < mesh.rest_positions()[tip].z - 1e-3);
    let mut state = s.rest_state();
    for _ in 0..150 {
        s.step(&mut state).unwrap();
    }
    let diff = state
        .x
        .iter()
        .zip(&equilibrium.x)
        .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
    assert!(diff < 1e-4, "damped dynamics end {diff} m from equilibrium");
}

#[test]
fn every_policy_gives_the_same_trajectory() {
    let mesh = beam();
    let run = |p: &str| {
        let options = IntegratorOptions::default()
            .newton(NewtonOptions::default().rel(1e-9).abs(1e-12))
            .max_retries(0);
        let mut s = sim(&mesh, clamp(&mesh), options, p);
        let mut state = s.rest_state();
        let mut reports = Vec::new();
        for _ in 0..5 {
            reports.push(s.step(&mut state).unwrap());
        }
        (state, reports)
    };
    let (reference, _) = run("Fixed(Direct())");
    for p in [
        "Fixed(Pcg(preconditioner: Ic0, tolerance: (rel: 1e-12)))",
        "Fixed(Cg(tolerance: (rel: 1e-12, max_iterations: 5000)))",
        "Fixed(Pcg(preconditioner: BlockJacobi, tolerance: (rel: 1e-12)))",
        "Schedule(iterations: [Direct()], otherwise: Pcg(preconditioner: StaleCholesky(max_age: 10), tolerance: (rel: 1e-12)))",
        "EisenstatWalker(solver: Pcg(preconditioner: Jacobi, tolerance: (rel: 1e-8)))",
        "StaleFactor(solver: Pcg(preconditioner: StaleCholesky(max_age: 1000), tolerance: (rel: 1e-12)), refactor_above: 6)",
        "StaleFactor(solver: Pcg(preconditioner: Amg(max_age: 1000), tolerance: (rel: 1e-12)), refactor_above: 6)",
        "Fixed(MatrixFree(Pcg(preconditioner: BlockJacobi, tolerance: (rel: 1e-12))))",
    ] {
        let (state, reports) = run(p);
        let diff = state
            .x
            .iter()
            .zip(&reference.x)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        assert!(diff < 1e-7, "{p}: {diff}");
        assert!(
            reports
                .iter()
                .all(|r| r.converged && r.iterations.iter().all(|i| !i.fallback)),
            "{p}"
        );
        if p.starts_with("Schedule") {
            // Later Newton iterations and later steps reuse the factor of the first.
            let solvers: Vec<&deform_solvers::SolverSpec> = reports
                .iter()
                .flat_map(|r| r.iterations.iter().map(|i| &i.solver))
                .collect();
            assert!(solvers.iter().any(|s| s.is_stale_cholesky()), "{solvers:?}");
            let reused = reports
                .iter()
                .flat_map(|r| &r.iterations)
                .filter(|i| i.setup.reused)
                .count();
            assert!(reused > 0);
        }
        if p.starts_with("StaleFactor") {
            // A fresh factor (or AMG hierarchy) exactly when the previous solve took more
            // than 6 iterations.
            let its: Vec<&IterationReport> = reports.iter().flat_map(|r| &r.iterations).collect();
            assert!(!its[0].setup.reused);
            for w in its.windows(2) {
                assert_eq!(
                    w[1].setup.reused,
                    w[0].solve.iterations <= 6,
                    "{} then reused = {}",
                    w[0].solve.iterations,
                    w[1].setup.reused
                );
            }
            let reused = its.iter().filter(|i| i.setup.reused).count();
            assert!(
                reused > its.len() / 2,
                "{reused} of {}: {:?}",
                its.len(),
                its.iter().map(|i| i.solve.iterations).collect::<Vec<_>>()
            );
        }
        if p.starts_with("EisenstatWalker") {
            let tolerances: Vec<f64> = reports[0]
                .iterations
                .iter()
                .map(|i| i.solve.relative_residual())
                .collect();
            assert!(
                tolerances[0] <= 0.1 && tolerances[0] > 1e-6,
                "the first solve is loose: {tolerances:?}"
            );
        }
    }
}

#[test]
fn kinematic_vertices_follow_their_path() {
    let mesh = beam();
    let end: Vec<usize> = (0..mesh.num_vertices())
        .filter(|&v| mesh.rest_positions()[v].x > 1.0 - 1e-9)
        .collect();
    let mut constraints = clamp(&mesh);
    let motion = Motion::Rotate {
        center: [1.0, 0.125, 0.125],
        axis: [1.0, 0.0, 0.0],
        angular_velocity: 3.0,
        until: None,
    };
    constraints.push(Constraint {
        vertices: end.clone(),
        motion: motion.clone(),
    });
    let options = IntegratorOptions::default().gravity([0.0; 3]);
    let mut s = sim(&mesh, constraints, options, "Fixed(Direct())");
    let mut state = s.rest_state();
    for _ in 0..10 {
        s.step(&mut state).unwrap();
    }
    for &v in &end {
        let target = motion.position(&mesh.rest_positions()[v], state.t);
        for d in 0..3 {
            assert!((state.x[3 * v + d] - target[d]).abs() < 1e-12);
        }
    }
    // The middle of the bar twists too.
    assert!(s.assembly_mut().energy(&state.x).unwrap() > 0.0);
}

#[test]
fn bundled_scenes_dissipate_energy_with_and_without_damping() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/scenes");
    // The cantilever and the torus have fixed constraints only, so nothing does work.
    for name in ["cantilever.ron", "torus.ron"] {
        let path = root.join(name);
        for damped in [true, false] {
            let mut scene = deform_integrator::Scene::load(&path).unwrap();
            if !damped {
                scene.integrator.alpha = 0.0;
                scene.integrator.gamma = 0.0;
            }
            scene.integrator.newton.rel = 1e-9;
            // Dissipation is the integrator's property; solve exactly.
            scene.policy = PolicySpec::Fixed(deform_solvers::SolverSpec::Direct {
                ordering: Default::default(),
                indefinite: Default::default(),
                parallel: false,
                precision: Default::default(),
            });
            let mut built = scene.build(&path).unwrap();
            let mut previous = total_energy(&mut built.integrator, &built.state);
            let scale = previous.abs().max(1.0);
            for step in 0..15 {
                built.integrator.step(&mut built.state).unwrap();
                let e = total_energy(&mut built.integrator, &built.state);
                assert!(
                    e <= previous + 1e-7 * scale,
                    "{name} damped={damped} step {step}: {e} > {previous}"
                );
                previous = e;
            }
        }
    }
}

#[test]
fn cantilever_tip_deflection_approaches_beam_theory_under_refinement() {
    // Linear elasticity with nu = 0 (no Poisson coupling), small load: the static tip
    // deflection against Euler-Bernoulli w = q L^4 / (8 E I) plus Timoshenko's shear term
    // q L^2 / (2 kappa G A), kappa = 5/6 (L/h = 4, so shear adds about 5 %).
    let (e, rho, g) = (1e7, 1000.0, 0.01);
    let (l, h) = (1.0f64, 0.25f64);
    let (area, inertia, shear) = (h * h, h.powi(4) / 12.0, e / 2.0);
    let q = rho * g * area;
    let euler_bernoulli = q * l.powi(4) / (8.0 * e * inertia);
    let timoshenko = euler_bernoulli + q * l * l / (2.0 * 5.0 / 6.0 * shear * area);
    let mut errors = Vec::new();
    for n in [1, 2, 4, 8] {
        let mesh = BoxGrid::beam(n).build().unwrap();
        let options = IntegratorOptions::default().gravity([0.0, 0.0, -g]);
        let mut s = Integrator::builder(
            &mesh,
            material(&format!("LinearElastic(Young(e: {e}, nu: 0.0))")),
        )
        .density(rho)
        .constraints(clamp(&mesh))
        .options(options)
        .policy(policy("Fixed(Direct())"))
        .build()
        .unwrap();
        let mut state = s.rest_state();
        s.solve_static(&mut state).unwrap();
        let tip: Vec<usize> = (0..mesh.num_vertices())
            .filter(|&v| mesh.rest_positions()[v].x > l - 1e-9)
            .collect();
        let w = -tip
            .iter()
            .map(|&v| state.x[3 * v + 2] - mesh.rest_positions()[v].z)
            .sum::<f64>()
            / tip.len() as f64;
        let error = (w - timoshenko).abs() / timoshenko;
        eprintln!(
            "n = {n}: {} tets, tip {w:.4e} m, Timoshenko {timoshenko:.4e}, Euler-Bernoulli {euler_bernoulli:.4e}, error {:.2} %",
            mesh.num_tets(),
            100.0 * error
        );
        errors.push(error);
    }
    for w in errors.windows(2) {
        assert!(
            w[1] < w[0],
            "the error must decrease with refinement: {errors:?}"
        );
    }
    assert!(errors[3] < 0.1, "finest error {:.3}", errors[3]);
}

#[test]
fn a_negative_gamma_gives_back_some_of_a_coarse_steps_dissipation_and_stays_stable() {
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/scenes/cantilever.ron");
    let mut scene = deform_integrator::Scene::load(&path).unwrap();
    scene.integrator.dt = 0.04;
    scene.integrator.alpha = 0.0;
    scene.integrator.newton.rel = 1e-9;
    // At gamma = -dt / 2 the highest modes stop decaying: refused, naming the field.
    scene.integrator.gamma = -0.02;
    let err = scene
        .build(&path)
        .err()
        .expect("gamma = -dt / 2 is refused");
    assert!(err.to_string().contains("gamma"), "{err}");
    // The swing's energy is what lies above the static equilibrium's.
    let mut at_rest = scene.clone();
    at_rest.integrator.gamma = 0.0;
    at_rest.initial.equilibrium = true;
    let mut eq = at_rest.build(&path).unwrap();
    let equilibrium = total_energy(&mut eq.integrator, &eq.state);
    let mut energies = Vec::new();
    for gamma in [0.0, -0.018] {
        scene.integrator.gamma = gamma;
        let mut built = scene.build(&path).unwrap();
        // Substeps keep the fraction of the step.
        assert_eq!(
            built.integrator.options().stiffness_damping(0.02),
            gamma / 2.0
        );
        let initial = total_energy(&mut built.integrator, &built.state);
        let mut e = initial;
        for step in 0..15 {
            built.integrator.step(&mut built.state).unwrap();
            e = total_energy(&mut built.integrator, &built.state);
            assert!(
                e <= initial + 1e-9 * initial.abs(),
                "gamma {gamma}, step {step}: {e} > {initial}"
            );
        }
        // Released at rest under gravity, it sags and swings: energy goes, from the start.
        assert!(e < initial);
        energies.push((e - equilibrium) / (initial - equilibrium));
    }
    // More of the swing is left with the negative gamma.
    assert!(
        energies[1] > 1.2 * energies[0],
        "swing energy left {energies:?}"
    );
}

/// A free body under a load on some of its vertices gains exactly `F dt` of momentum per step
/// while the load acts (Backward Euler's momentum balance) and none after `until`.
#[test]
fn loads_change_momentum_by_their_impulse_until_they_stop() {
    let mesh = beam();
    let end: Vec<usize> = (0..mesh.num_vertices())
        .filter(|&v| mesh.rest_positions()[v].x > 1.0 - 1e-9)
        .collect();
    let options = IntegratorOptions::default().gravity([0.0; 3]);
    let dt = options.dt;
    let force = [3.0, -2.0, 5.0];
    let load = deform_integrator::Load {
        vertices: end,
        force: deform_integrator::LoadForce::new(force).until(Some(3.0 * dt)),
    };
    let mut s = Integrator::builder(&mesh, material(NH))
        .options(options)
        .loads(vec![load])
        .build()
        .unwrap();
    assert_eq!(s.num_loads(), 1);
    let mut state = s.rest_state();
    for n in 1..=6 {
        s.step(&mut state).unwrap();
        let p = momentum(&s, &state.v);
        let active = n.min(3) as f64;
        for d in 0..3 {
            let expected = active * dt * force[d];
            assert!((p[d] - expected).abs() < 1e-9, "step {n}: {p:?}");
        }
    }
    // The external forces name the load while it acts and only gravity after.
    let sum = |f: Vec<f64>| {
        (0..3)
            .map(|d| f.iter().skip(d).step_by(3).sum::<f64>())
            .collect::<Vec<_>>()
    };
    let during = sum(s.external_forces(dt));
    assert!((during[2] - 5.0).abs() < 1e-12, "{during:?}");
    assert!(
        sum(s.external_forces(4.0 * dt))
            .iter()
            .all(|f| f.abs() < 1e-12)
    );
}

/// Conditions set on an integrator step exactly like a model built with them, and the
/// default conditions restore the model's own.
#[test]
fn conditions_step_like_a_model_built_with_them() {
    let mesh = beam();
    let end: Vec<usize> = (0..mesh.num_vertices())
        .filter(|&v| mesh.rest_positions()[v].x > 1.0 - 1e-9)
        .collect();
    let pull = Motion::Translate {
        velocity: [0.5, 0.0, 0.0],
        until: None,
    };
    let constraints = |motion: Motion| {
        let mut c = clamp(&mesh);
        c.push(Constraint {
            vertices: end.clone(),
            motion,
        });
        c
    };
    let other = IntegratorOptions::default().gravity([0.0, 4.0, 0.0]);
    let run = |s: &mut Integrator| {
        let mut state = s.rest_state();
        for _ in 0..4 {
            s.step(&mut state).unwrap();
        }
        state
    };
    let mut built = sim(&mesh, constraints(pull.clone()), other, "Fixed(Direct())");
    let expected = run(&mut built);
    let own = IntegratorOptions::default();
    let mut s = sim(&mesh, constraints(Motion::Fixed), own, "Fixed(Direct())");
    let alone = run(&mut s);
    let conditions = deform_integrator::Conditions::default()
        .gravity(Some([0.0, 4.0, 0.0]))
        .motions(Some(vec![Motion::Fixed, pull]))
        .loads(None);
    s.set_conditions(&conditions).unwrap();
    assert_eq!(s.gravity(), [0.0, 4.0, 0.0]);
    assert_eq!(run(&mut s), expected);
    s.set_conditions(&deform_integrator::Conditions::default())
        .unwrap();
    assert_eq!(run(&mut s), alone);
    // Conditions that do not fit the model are refused, naming the field.
    let wrong = deform_integrator::Conditions::default().motions(Some(vec![Motion::Fixed]));
    let err = s.set_conditions(&wrong).unwrap_err().to_string();
    assert!(
        err.contains("motions") && err.contains("2 constraints"),
        "{err}"
    );
    let nan = deform_integrator::Conditions::default().gravity(Some([f64::NAN, 0.0, 0.0]));
    assert!(
        s.set_conditions(&nan)
            .unwrap_err()
            .to_string()
            .contains("gravity")
    );
    assert_eq!(s.conditions(), &deform_integrator::Conditions::default());
}
