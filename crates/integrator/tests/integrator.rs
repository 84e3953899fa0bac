//! Backward Euler against analytic cases (free fall, momentum), dissipation, equilibrium,
//! agreement of every solver policy, kinematic constraints, typed failures and reports.

use deform_solvers::WorkWeights;
use std::ops::ControlFlow;

use deform_assembly::MaterialField;
use deform_integrator::{
    Constraint, Integrator, IntegratorError, IntegratorOptions, IterationReport, Motion,
    NewtonOptions, NoObserver, Observer, PolicySpec, RunOptions, State, StepError, StepReport,
    Termination, Until,
};
use deform_materials::MaterialSpec;
use deform_mesh::TetMesh;
use deform_mesh::generate::BoxGrid;

fn material(spec: &str) -> MaterialField {
    MaterialField::Uniform(
        ron::from_str::<MaterialSpec>(spec)
            .unwrap()
            .build()
            .unwrap(),
    )
}

const NH: &str = "NeoHookean(Young(e: 1e5, nu: 0.4))";

fn beam() -> TetMesh {
    BoxGrid::beam(1).build().unwrap()
}

fn clamp(mesh: &TetMesh) -> Vec<Constraint> {
    vec![Constraint {
        vertices: (0..mesh.num_vertices())
            .filter(|&v| mesh.rest_positions()[v].x < 1e-9)
            .collect(),
        motion: Motion::Fixed,
    }]
}

fn policy(ron_text: &str) -> Box<dyn deform_integrator::SolverPolicy> {
    ron::from_str::<PolicySpec>(ron_text)
        .unwrap()
        .build()
        .unwrap()
}

fn sim(
    mesh: &TetMesh,
    constraints: Vec<Constraint>,
    options: IntegratorOptions,
    p: &str,
) -> Integrator {
    Integrator::builder(mesh, material(NH))
        .density(1000.0)
        .constraints(constraints)
        .options(options)
        .policy(policy(p))
        .build()
        .unwrap()
}

fn momentum(sim: &Integrator, v: &[f64]) -> [f64; 3] {
    let m = sim.assembly().vertex_masses(sim.mass());
    let mut p = [0.0; 3];
    for (i, vi) in v.iter().enumerate() {
        p[i % 3] += m[i / 3] * vi;
    }
    p
}

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
    let options = IntegratorOptions {
        gravity: [0.0; 3],
        ..IntegratorOptions::default()
    };
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
    let options = IntegratorOptions {
        alpha: 16.0,
        dt: 0.02,
        ..IntegratorOptions::default()
    };
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
        let options = IntegratorOptions {
            newton: NewtonOptions {
                rel: 1e-9,
                abs: 1e-12,
                ..NewtonOptions::default()
            },
            max_retries: 0,
            ..IntegratorOptions::default()
        };
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
    let options = IntegratorOptions {
        gravity: [0.0; 3],
        ..IntegratorOptions::default()
    };
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
fn failures_are_typed_carry_reports_and_leave_the_state_alone() {
    let mesh = beam();
    // A one-iteration cap with tight tolerances cannot converge.
    let options = IntegratorOptions {
        newton: NewtonOptions {
            max_iterations: 1,
            rel: 1e-12,
            abs: 0.0,
            ..NewtonOptions::default()
        },
        max_retries: 0,
        ..IntegratorOptions::default()
    };
    let mut s = sim(&mesh, clamp(&mesh), options, "Fixed(Direct())");
    let mut state = s.rest_state();
    state.v.iter_mut().step_by(3).for_each(|v| *v = 5.0);
    let before = state.clone();
    match s.step(&mut state) {
        Err(StepError::NotConverged { report }) => assert_eq!(report.iterations.len(), 1),
        other => panic!("expected NotConverged, got {other:?}"),
    }
    assert_eq!(state, before);

    // An inverted element for Neo-Hookean: a typed assembly error naming it.
    let mut s = sim(
        &mesh,
        clamp(&mesh),
        IntegratorOptions::default(),
        "Fixed(Direct())",
    );
    let mut state = s.rest_state();
    let tip = (0..mesh.num_vertices())
        .rev()
        .find(|&v| !s.dofs().is_constrained(v))
        .unwrap();
    state.x[3 * tip] -= 0.5;
    let before = state.clone();
    match s.step(&mut state) {
        Err(StepError::Assembly { source, .. }) => {
            assert!(source.to_string().contains("element"), "{source}")
        }
        other => panic!("expected an assembly error, got {other:?}"),
    }
    assert_eq!(state, before);

    // Options are validated with the field named.
    let bad = IntegratorOptions {
        dt: -1.0,
        ..IntegratorOptions::default()
    };
    match Integrator::builder(&mesh, material(NH))
        .density(1000.0)
        .constraints(vec![])
        .options(bad)
        .policy(policy("Fixed(Direct())"))
        .build()
    {
        Err(IntegratorError::Invalid { field: "dt", .. }) => {}
        other => panic!("expected invalid dt, got {other:?}"),
    }
    for floor in [1.0, -0.1, f64::NAN] {
        let mut bad = IntegratorOptions::default();
        bad.newton.linear_floor = floor;
        assert!(matches!(
            bad.validate(),
            Err(IntegratorError::Invalid {
                field: "newton.linear_floor",
                ..
            })
        ));
    }
    assert!(ron::from_str::<IntegratorOptions>("(dt: 0.01, damping: 3.0)").is_err());
    assert!(
        ron::from_str::<PolicySpec>("EisenstatWalker(solver: Direct())")
            .unwrap()
            .build()
            .is_err()
    );
    // A matrix-free solve cannot use a preconditioner that needs the matrix's entries.
    assert!(
        ron::from_str::<PolicySpec>("Fixed(MatrixFree(Pcg(preconditioner: Ic0)))")
            .unwrap()
            .build()
            .is_err()
    );
}

#[test]
fn halved_retries_recover_from_a_hard_step() {
    let mesh = beam();
    let options = IntegratorOptions {
        dt: 0.05,
        newton: NewtonOptions {
            max_iterations: 3,
            ..NewtonOptions::default()
        },
        max_retries: 4,
        ..IntegratorOptions::default()
    };
    let mut s = sim(&mesh, clamp(&mesh), options, "Fixed(Direct())");
    let mut state = s.rest_state();
    state
        .v
        .iter_mut()
        .skip(2)
        .step_by(3)
        .for_each(|v| *v = -8.0);
    let report = s.step(&mut state).unwrap();
    assert!(
        report.retries > 0 && report.dt < 0.05,
        "{} retries",
        report.retries
    );
    assert!(
        (state.t - 0.05).abs() < 1e-12,
        "the whole step is covered: t = {}",
        state.t
    );
}

#[derive(Default)]
struct Recorder {
    iterations: Vec<IterationReport>,
    steps: Vec<StepReport>,
    times: Vec<f64>,
}

impl Observer for Recorder {
    fn iteration(&mut self, r: &IterationReport) {
        self.iterations.push(r.clone());
    }
    fn step(&mut self, r: &StepReport, state: &State) -> ControlFlow<()> {
        self.steps.push(r.clone());
        self.times.push(state.t);
        ControlFlow::Continue(())
    }
}

#[test]
fn observers_see_every_iteration_and_newton_converges_fast() {
    let mesh = beam();
    let mut s = sim(
        &mesh,
        clamp(&mesh),
        IntegratorOptions::default(),
        "Fixed(Direct())",
    );
    let mut recorder = Recorder::default();
    let mut state = s.rest_state();
    let summary = s.run(
        &mut state,
        &RunOptions::steps(3).keeping_reports(),
        &mut recorder,
    );
    assert!(matches!(summary.termination, Termination::Completed));
    assert_eq!(summary.steps, 3);
    for r in &summary.reports {
        assert!(
            r.newton_iterations() <= 6,
            "{} Newton iterations",
            r.newton_iterations()
        );
        assert!(
            r.final_residual <= 1e-6 * r.initial_residual.max(1e-300) || r.final_residual <= 1e-10
        );
        assert!(r.flops() > 0);
    }
    // The summary's totals are the sums of the steps' figures.
    let total: usize = summary.reports.iter().map(|r| r.newton_iterations()).sum();
    assert_eq!(summary.newton_iterations, total);
    assert_eq!(
        summary.flops,
        summary.reports.iter().map(|r| r.flops()).sum::<u64>()
    );
    assert_eq!(recorder.iterations.len(), total);
    // Every iteration times its stages; they lie within the iteration's own time.
    for it in &recorder.iterations {
        let s = it.stages;
        assert!(
            s.residual > 0.0 && s.matrix > 0.0 && s.direction > 0.0,
            "{s:?}"
        );
        let sum = s.residual + s.matrix + s.direction + s.line_search;
        assert!(sum <= it.seconds, "{s:?} over {}", it.seconds);
    }
    assert_eq!(recorder.steps.len(), 3);
    assert_eq!(recorder.steps[2].step, 2);
    for (k, t) in recorder.times.iter().enumerate() {
        assert!(
            (t - 0.01 * (k + 1) as f64).abs() < 1e-15,
            "t = {t} after step {k}"
        );
    }
}

#[test]
fn runs_end_at_a_time_when_the_observer_stops_or_when_a_step_fails() {
    let mesh = beam();
    let mut s = sim(
        &mesh,
        clamp(&mesh),
        IntegratorOptions::default(),
        "Fixed(Direct())",
    );
    // Until a time: 0.025 s at dt 0.01 is three whole steps, 0.03 is three too (rounding).
    let mut state = s.rest_state();
    let summary = s.run(
        &mut state,
        &RunOptions {
            until: Until::Time(0.025),
            weights: WorkWeights::default(),
            keep_reports: false,
        },
        &mut NoObserver,
    );
    assert_eq!(summary.steps, 3);
    let mut state = s.rest_state();
    let summary = s.run(
        &mut state,
        &RunOptions {
            until: Until::Time(0.03),
            weights: WorkWeights::default(),
            keep_reports: false,
        },
        &mut NoObserver,
    );
    assert_eq!(summary.steps, 3);
    // The observer stops after the second step.
    struct StopAt(usize);
    impl Observer for StopAt {
        fn step(&mut self, r: &StepReport, _: &State) -> ControlFlow<()> {
            if r.step + 1 >= self.0 {
                ControlFlow::Break(())
            } else {
                ControlFlow::Continue(())
            }
        }
    }
    let mut s = sim(
        &mesh,
        clamp(&mesh),
        IntegratorOptions::default(),
        "Fixed(Direct())",
    );
    let mut state = s.rest_state();
    let summary = s.run(&mut state, &RunOptions::steps(10), &mut StopAt(2));
    assert!(matches!(
        summary.termination,
        Termination::Stopped { after: 1 }
    ));
    assert_eq!(summary.steps, 2);
    // A step that cannot converge: the state before it is kept, the error is typed.
    let mut opts = IntegratorOptions::default();
    opts.newton.max_iterations = 1;
    opts.newton.rel = 1e-14;
    opts.newton.abs = 0.0;
    opts.max_retries = 0;
    let mut s = sim(&mesh, clamp(&mesh), opts, "Fixed(Direct())");
    let mut state = s.rest_state();
    let before = state.clone();
    let summary = s.run(&mut state, &RunOptions::steps(4), &mut NoObserver);
    assert!(summary.failed());
    assert_eq!(summary.steps, 0);
    assert_eq!(state.x, before.x);
    let err = summary.into_result().unwrap_err();
    assert_eq!(err.step, 0);
    assert!(matches!(*err.source, StepError::NotConverged { .. }));
}

/// Total energy: kinetic + elastic + gravitational (`-x . M g`).
fn total_energy(s: &mut Integrator, st: &State) -> f64 {
    let m = s.assembly().vertex_masses(s.mass());
    let kinetic: f64 =
        st.v.iter()
            .enumerate()
            .map(|(i, v)| 0.5 * m[i / 3] * v * v)
            .sum();
    let gravity: f64 = -st
        .x
        .iter()
        .zip(s.gravity_forces())
        .map(|(x, g)| x * g)
        .sum::<f64>();
    kinetic + s.assembly_mut().energy(&st.x).unwrap() + gravity
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
fn newton_with_the_direct_solver_converges_quadratically() {
    // Also with Rayleigh stiffness damping: Newton's matrix then carries the damping force's
    // derivative in x (dt^2 gamma D_u K); without it the rate is linear (negative gamma
    // keeps the positive definite matrix without it, see `Integrator::newton_matrix`).
    let mesh = beam();
    for gamma in [0.0, 0.02] {
        let options = IntegratorOptions {
            gamma,
            newton: NewtonOptions {
                rel: 1e-13,
                abs: 1e-13,
                line_search: false,
                ..NewtonOptions::default()
            },
            max_retries: 0,
            ..IntegratorOptions::default()
        };
        let mut s = sim(&mesh, clamp(&mesh), options, "Fixed(Direct())");
        let mut state = s.rest_state();
        // A sharp kick: Newton starts far enough away to show its rate.
        for (v, p) in mesh.rest_positions().iter().enumerate() {
            state.v[3 * v + 2] = -3.0 * p.x;
        }
        let report = match s.step(&mut state) {
            Ok(r) => r,
            Err(StepError::NotConverged { report }) => *report,
            Err(e) => panic!("{e}"),
        };
        let r: Vec<f64> = report
            .iterations
            .iter()
            .map(|i| i.residual / report.initial_residual)
            .collect();
        // In the quadratic regime (relative residual below 1e-2, above the rounding floor),
        // each residual is bounded by a constant times the square of the previous one.
        let mut checked = 0;
        for w in r.windows(2) {
            if w[0] < 1e-2 && w[1] > 1e-12 {
                assert!(
                    w[1] <= 50.0 * w[0] * w[0],
                    "gamma {gamma}: not quadratic: {r:?}"
                );
                checked += 1;
            }
        }
        assert!(
            checked >= 1,
            "gamma {gamma}: no iteration in the quadratic regime: {r:?}"
        );
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
        let options = IntegratorOptions {
            gravity: [0.0, 0.0, -g],
            ..IntegratorOptions::default()
        };
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
fn matrix_free_force_differentials_drive_cg_like_the_assembled_matrix() {
    use deform_assembly::Tangent;
    use deform_solvers::{LinearOperator, SolverSpec};
    let mesh = beam();
    let mut s = sim(
        &mesh,
        vec![],
        IntegratorOptions::default(),
        "Fixed(Direct())",
    );
    let x: Vec<f64> = mesh
        .rest_positions()
        .iter()
        .flat_map(|p| [p.x, p.y + 0.05 * p.x * p.x, p.z])
        .collect();
    let (c_m, c_k) = (1.0, 1e-4);
    let mass = s.mass().clone();
    let asm = s.assembly_mut();
    let mut k = asm.stiffness_matrix();
    asm.stiffness(&x, Tangent::Projected, &mut k).unwrap();
    let mut a = asm.stiffness_matrix();
    asm.combine(c_m, &mass, c_k, &k, &mut a).unwrap();
    let asm = s.assembly();
    let op = deform_integrator::MatrixFreeNewton::new(
        asm,
        asm.tangents(&x, Tangent::Projected).unwrap(),
        &mass,
        c_m,
        c_k,
    );
    let b: Vec<f64> = (0..x.len()).map(|i| (i as f64 * 0.7).sin()).collect();
    // Same products, then the same CG solution.
    let (mut y1, mut y2) = (vec![0.0; b.len()], vec![0.0; b.len()]);
    a.apply(&b, &mut y1);
    op.apply(&b, &mut y2);
    let scale = y1.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(
        y1.iter()
            .zip(&y2)
            .all(|(p, q)| (p - q).abs() <= 1e-10 * scale)
    );
    let solve = |operator: &dyn LinearOperator| {
        let mut solver = ron::from_str::<SolverSpec>(
            "Pcg(preconditioner: BlockJacobi, tolerance: (rel: 1e-10))",
        )
        .unwrap()
        .build()
        .unwrap();
        solver.factorize(operator).unwrap();
        let mut sol = vec![0.0; b.len()];
        solver.solve(operator, &b, &mut sol).unwrap();
        sol
    };
    let (s1, s2) = (solve(a.csr()), solve(&op));
    let norm = s1.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(
        s1.iter()
            .zip(&s2)
            .all(|(p, q)| (p - q).abs() <= 1e-8 * norm)
    );
}

#[test]
fn counterfactual_candidates_are_logged_without_changing_the_trajectory() {
    use deform_solvers::SolverSpec;
    let mesh = beam();
    let run = |candidates: bool| {
        let mut s = sim(
            &mesh,
            clamp(&mesh),
            IntegratorOptions::default(),
            "Fixed(Direct())",
        );
        if candidates {
            let specs: Vec<SolverSpec> = [
                "Direct()",
                "Cg(tolerance: (rel: 1e-8))",
                "Pcg(preconditioner: Jacobi, tolerance: (rel: 1e-8))",
                "Pcg(preconditioner: StaleCholesky(max_age: 5), tolerance: (rel: 1e-8))",
                "Jacobi(tolerance: (rel: 1e-8, max_iterations: 3))",
                // On element-by-element force differentials instead of the assembled K.
                "MatrixFree(Pcg(preconditioner: BlockJacobi, tolerance: (rel: 1e-8)))",
            ]
            .iter()
            .map(|t| ron::from_str(t).unwrap())
            .collect();
            s.set_candidates(&specs).unwrap();
        }
        let mut state = s.rest_state();
        let reports: Vec<StepReport> = (0..3).map(|_| s.step(&mut state).unwrap()).collect();
        (state, reports)
    };
    let (plain, _) = run(false);
    let (logged, reports) = run(true);
    assert_eq!(plain, logged, "candidates must not change the trajectory");
    for (r, it) in reports
        .iter()
        .flat_map(|r| r.iterations.iter().map(move |it| (r, it)))
    {
        assert_eq!(it.candidates.len(), 6);
        // Candidates stop where the chosen solver would: at 1e-8 relative, or at a tenth
        // of Newton's tolerance (`NewtonOptions::linear_floor`), whichever comes first.
        let floor = 0.1 * 1e-10_f64.max(1e-6 * r.initial_residual);
        let direct = &it.candidates[0];
        assert!(
            direct.distance < 1e-12,
            "direct vs the chosen direct solve: {}",
            direct.distance
        );
        for c in it.candidates[1..4].iter().chain(&it.candidates[5..]) {
            let stats = c
                .solve
                .as_ref()
                .unwrap_or_else(|| panic!("{}: {:?}", c.solver, c.error));
            let last = stats.residuals.last().copied().unwrap_or(f64::INFINITY);
            // Stopped by the floor, a direction is as accurate as the last Newton update
            // needs: its residual a tenth of Newton's tolerance, not 1e-8 of its own.
            let tight = stats.relative_residual() <= 1e-8 && c.distance < 1e-5;
            assert!(
                tight || (last <= floor && c.distance < 0.05),
                "{}: {} (residual {last:e}, floor {floor:e})",
                c.solver,
                c.distance
            );
        }
        // Three Jacobi sweeps cannot reach 1e-8: the failure is recorded, not raised.
        let jacobi = &it.candidates[4];
        assert!(jacobi.error.is_some() && jacobi.distance.is_infinite());
    }
    // The stale factor is reused in later iterations and steps.
    let reused = reports
        .iter()
        .flat_map(|r| &r.iterations)
        .filter(|i| i.candidates[3].setup.is_some_and(|s| s.reused))
        .count();
    assert!(reused > 0);
}

#[test]
fn projection_when_needed_switches_once_the_exact_tangent_fails_and_charges_the_attempt() {
    use deform_integrator::Projection;
    let mesh = beam();
    // A beam squashed along its axis, released with a small or a huge time step.
    let run = |project: Projection, dt: f64| {
        let options = IntegratorOptions {
            dt,
            newton: NewtonOptions {
                project,
                ..NewtonOptions::default()
            },
            max_retries: 0,
            ..IntegratorOptions::default()
        };
        let mut s = sim(&mesh, clamp(&mesh), options, "Fixed(Direct())");
        let mut state = s.rest_state();
        state.x.iter_mut().step_by(3).for_each(|x| *x *= 0.9);
        s.step(&mut state).map(|r| (r, state))
    };
    // Small step: the exact tangent stays positive definite; nothing changes.
    let (never, x_never) = run(Projection::Never, 0.01).unwrap();
    let (when, x_when) = run(Projection::WhenNeeded, 0.01).unwrap();
    assert_eq!(x_never.x, x_when.x);
    assert_eq!(never.iterations.len(), when.iterations.len());
    assert!(when.iterations.iter().all(|i| i.discarded.is_empty()));
    // Huge step: the exact tangent is indefinite; Newton on it inverts an element.
    assert!(run(Projection::Never, 1.0).is_err());
    let (when, x_when) = run(Projection::WhenNeeded, 1.0).unwrap();
    let (always, x_always) = run(Projection::Always, 1.0).unwrap();
    let discarded: Vec<_> = when.iterations.iter().flat_map(|i| &i.discarded).collect();
    assert_eq!(discarded.len(), 1, "one switch per step");
    assert!(
        discarded[0]
            .error
            .as_deref()
            .is_some_and(|e| e.contains("not positive definite")),
        "{:?}",
        discarded[0].error
    );
    // The failed attempt is charged: its analysis at least.
    let used: u64 = when
        .iterations
        .iter()
        .map(|i| i.setup.flops + i.solve.flops)
        .sum();
    assert!(when.flops() > used, "{} vs {used}", when.flops());
    assert!(when.work(WorkWeights::default()) > used as f64);
    // After the switch it is Newton on the projected tangent: the same iterations and
    // solution as `Always`.
    assert_eq!(when.iterations.len(), always.iterations.len());
    let scale = x_always.x.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let diff = x_when
        .x
        .iter()
        .zip(&x_always.x)
        .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
    assert!(diff <= 1e-6 * scale, "{diff:e}");
}

#[test]
fn a_failed_choice_falls_back_to_the_direct_solver_and_is_charged() {
    let mesh = beam();
    let capped = "Fixed(Jacobi(tolerance: (rel: 1e-10, max_iterations: 2)))";
    let mut s = sim(&mesh, clamp(&mesh), IntegratorOptions::default(), capped);
    let mut state = s.rest_state();
    let report = s.step(&mut state).unwrap();
    assert!(report.converged);
    for it in &report.iterations {
        assert!(it.fallback, "the capped Jacobi cannot converge");
        assert_eq!(it.discarded.len(), 1);
        let failed = &it.discarded[0];
        let solve = failed
            .solve
            .as_ref()
            .expect("the failed solve's statistics");
        assert_eq!(solve.iterations, 2);
        assert!(solve.flops > 0 && failed.error.is_some());
        assert!(
            it.work(WorkWeights::default())
                > it.setup.work(WorkWeights::default()) + it.solve.flops as f64
        );
    }
    let used: u64 = report
        .iterations
        .iter()
        .map(|i| i.setup.flops + i.solve.flops)
        .sum();
    assert!(report.flops() > used);
    // The same trajectory as the direct solver's, which did the work.
    let mut d = sim(
        &mesh,
        clamp(&mesh),
        IntegratorOptions::default(),
        "Fixed(Direct())",
    );
    let mut direct = d.rest_state();
    d.step(&mut direct).unwrap();
    let diff = state
        .x
        .iter()
        .zip(&direct.x)
        .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
    assert!(diff < 1e-12, "{diff:e}");
    // Without the fallback the failure is the step's error.
    let options = IntegratorOptions {
        fallback_to_direct: false,
        max_retries: 0,
        ..IntegratorOptions::default()
    };
    let mut s = sim(&mesh, clamp(&mesh), options, capped);
    let mut state = s.rest_state();
    assert!(matches!(s.step(&mut state), Err(StepError::Solver { .. })));
}

#[test]
fn a_hopeless_step_fails_after_max_retries_solves_and_big_retry_counts_are_refused() {
    let mesh = beam();
    let mut opts = IntegratorOptions::default();
    opts.newton.max_iterations = 1;
    opts.newton.rel = 1e-15;
    opts.newton.abs = 0.0;
    opts.max_retries = 20;
    let mut s = sim(&mesh, clamp(&mesh), opts.clone(), "Fixed(Direct())");
    let mut state = s.rest_state();
    let started = std::time::Instant::now();
    let err = s.step(&mut state).unwrap_err();
    // Twenty failed solves end it; the substeps that converged on the way are few (a
    // binary tree of retries would take up to 2^20 solves).
    assert_eq!(err.report().retries, 20, "{err}");
    assert!(err.report().newton_iterations() <= 64, "{err}");
    assert!(started.elapsed().as_secs_f64() < 30.0);
    assert_eq!(state.t, 0.0, "the state is unchanged");
    opts.max_retries = 1000;
    assert!(matches!(
        Integrator::builder(&mesh, material(NH))
            .options(opts)
            .build(),
        Err(IntegratorError::Invalid {
            field: "max_retries",
            ..
        })
    ));
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

#[test]
fn newton_stops_at_the_rounding_floor_when_the_tolerance_is_out_of_reach() {
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/scenes/cantilever.ron");
    let mut scene = deform_integrator::Scene::load(&path).unwrap();
    // No residual reaches 1e-30 relative, nor 1e-300 absolute.
    (scene.integrator.newton.rel, scene.integrator.newton.abs) = (1e-30, 1e-300);
    scene.integrator.max_retries = 0;
    let mut built = scene.build(&path).unwrap();
    for _ in 0..3 {
        let report = built.integrator.step(&mut built.state).unwrap();
        assert!(report.converged && report.rounding_floor && report.retries == 0);
        assert!(report.newton_iterations() < scene.integrator.newton.max_iterations);
        assert!(
            report.final_residual <= 1e-10 * report.initial_residual,
            "{report:?}"
        );
    }
    // A reachable tolerance is met as before, not at the floor.
    scene.integrator.newton.rel = 1e-8;
    let mut built = scene.build(&path).unwrap();
    let report = built.integrator.step(&mut built.state).unwrap();
    assert!(report.converged && !report.rounding_floor);
}

/// The residual of Backward Euler at `(x1, v1)` from `(x0, v0)`, assembled from scratch.
fn residual_norm(s: &mut Integrator, start: &State, end: &State) -> f64 {
    let o = s.options().clone();
    let n = end.x.len();
    let mut k = s.assembly().stiffness_matrix();
    let mut f = vec![0.0; n];
    let asm = s.assembly_mut();
    asm.forces(&end.x, &mut f).unwrap();
    asm.stiffness(&end.x, deform_assembly::Tangent::Exact, &mut k)
        .unwrap();
    let (mut fd, mut r) = (vec![0.0; n], vec![0.0; n]);
    let dv: Vec<f64> = end.v.iter().zip(&start.v).map(|(a, b)| a - b).collect();
    let asm = s.assembly();
    asm.damping_forces(o.alpha, o.gamma, s.mass(), &k, &end.v, &mut fd)
        .unwrap();
    asm.mass_apply(s.mass(), &dv, &mut r).unwrap();
    let g = s.gravity_forces();
    for i in 0..n {
        r[i] -= o.dt * (f[i] + fd[i] + g[i]);
    }
    let mut free = vec![0.0; s.dofs().num_free()];
    s.dofs().restrict(&r, &mut free).unwrap();
    free.iter().map(|v| v * v).sum::<f64>().sqrt()
}

#[test]
fn the_reported_residual_is_that_of_the_end_state_with_and_without_stiffness_damping() {
    // Without stiffness damping the converged check reuses the line search's energy and
    // forces (no K); with it, it assembles K for the damping force. Either way the residual
    // reported must be the end state's.
    let mesh = beam();
    for gamma in [0.0, 0.01] {
        let options = IntegratorOptions {
            alpha: 0.5,
            gamma,
            ..IntegratorOptions::default()
        };
        let mut s = sim(&mesh, clamp(&mesh), options, "Fixed(Direct())");
        let mut state = s.rest_state();
        for (v, p) in mesh.rest_positions().iter().enumerate() {
            state.v[3 * v + 2] = -2.0 * p.x;
        }
        for _ in 0..3 {
            let start = state.clone();
            let report = s.step(&mut state).unwrap();
            assert!(report.iterations.len() >= 2, "{report:?}");
            assert!(report.iterations.iter().all(|it| it.step_length > 0.0));
            let independent = residual_norm(&mut s, &start, &state);
            let reported = report.final_residual;
            assert!(
                (independent - reported).abs() <= 1e-6 * reported + 1e-14 * report.initial_residual,
                "gamma {gamma}: reported {reported:e}, recomputed {independent:e}"
            );
        }
    }
}

/// A free body under a load on some of its vertices gains exactly `F dt` of momentum per step
/// while the load acts (Backward Euler's momentum balance) and none after `until`.
#[test]
fn loads_change_momentum_by_their_impulse_until_they_stop() {
    let mesh = beam();
    let end: Vec<usize> = (0..mesh.num_vertices())
        .filter(|&v| mesh.rest_positions()[v].x > 1.0 - 1e-9)
        .collect();
    let options = IntegratorOptions {
        gravity: [0.0; 3],
        ..IntegratorOptions::default()
    };
    let dt = options.dt;
    let force = [3.0, -2.0, 5.0];
    let load = deform_integrator::Load {
        vertices: end,
        force: deform_integrator::LoadForce {
            force,
            until: Some(3.0 * dt),
        },
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
    let other = IntegratorOptions {
        gravity: [0.0, 4.0, 0.0],
        ..IntegratorOptions::default()
    };
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
    let conditions = deform_integrator::Conditions {
        gravity: Some([0.0, 4.0, 0.0]),
        motions: Some(vec![Motion::Fixed, pull]),
        loads: None,
    };
    s.set_conditions(&conditions).unwrap();
    assert_eq!(s.gravity(), [0.0, 4.0, 0.0]);
    assert_eq!(run(&mut s), expected);
    s.set_conditions(&deform_integrator::Conditions::default())
        .unwrap();
    assert_eq!(run(&mut s), alone);
    // Conditions that do not fit the model are refused, naming the field.
    let wrong = deform_integrator::Conditions {
        motions: Some(vec![Motion::Fixed]),
        ..Default::default()
    };
    let err = s.set_conditions(&wrong).unwrap_err().to_string();
    assert!(
        err.contains("motions") && err.contains("2 constraints"),
        "{err}"
    );
    let nan = deform_integrator::Conditions {
        gravity: Some([f64::NAN, 0.0, 0.0]),
        ..Default::default()
    };
    assert!(
        s.set_conditions(&nan)
            .unwrap_err()
            .to_string()
            .contains("gravity")
    );
    assert_eq!(s.conditions(), &deform_integrator::Conditions::default());
}

/// A run after `restart`, or on a fork, gives the bits of a new integrator's run, whatever
/// ran before: with a stale factor, adaptive tolerances and a schedule by iteration (all
/// history the policy or the kept solvers carry), so that a fit's rollouts can run on any
/// copy, in any order, on any thread.
#[test]
fn a_restarted_or_forked_integrator_runs_as_a_new_one() {
    let mesh = beam();
    let options = IntegratorOptions {
        max_retries: 0,
        ..IntegratorOptions::default()
    };
    let run = |s: &mut Integrator, from: &State| {
        let mut state = from.clone();
        let its: Vec<usize> = (0..3)
            .map(|_| s.step(&mut state).unwrap().linear_iterations())
            .collect();
        (state, its)
    };
    let mut history_mattered = Vec::new();
    for p in [
        "StaleFactor(solver: Pcg(preconditioner: StaleCholesky(max_age: 1000), tolerance: (rel: 1e-6)), refactor_above: 1000)",
        "EisenstatWalker(solver: Pcg(preconditioner: Jacobi, tolerance: (rel: 1e-8)))",
        "Schedule(iterations: [Direct()], otherwise: Pcg(preconditioner: StaleCholesky(max_age: 10), tolerance: (rel: 1e-6)))",
    ] {
        let new = || sim(&mesh, clamp(&mesh), options.clone(), p);
        let rest = new().rest_state();
        let mut bent = rest.clone();
        for (i, v) in bent.v.iter_mut().enumerate() {
            *v = if i % 3 == 2 { 0.3 } else { 0.0 };
        }
        for v in &clamp(&mesh)[0].vertices {
            bent.v[3 * v..3 * v + 3].fill(0.0);
        }
        let fresh = run(&mut new(), &rest);
        // A run from the bent state first leaves its history behind (a stale factor of a
        // bent state, the step count, the last forcing term).
        let mut s = new();
        run(&mut s, &bent);
        let mut fork = s.fork().expect("built-in policies fork");
        let without = run(&mut s, &rest);
        assert_eq!(run(&mut fork, &rest), fresh, "{p}: the fork");
        assert!(s.restart());
        assert_eq!(run(&mut s, &rest), fresh, "{p}: after restart");
        if without != fresh {
            history_mattered.push(p);
        }
    }
    // Without a restart the same run differs (the stale factor of the bent state).
    assert!(history_mattered.len() >= 2, "{history_mattered:?}");
}

/// Steps of a beam large enough that every vector pass of the residual, the merit function
/// and the line search runs in parallel chunks (38k DOFs), and that PCG's and the V-cycle's
/// fused passes do: the same bits on one thread as on two, with the direct solver and with
/// PCG-AMG, and with stiffness damping (the residual's `K u`).
#[test]
fn large_steps_are_the_same_on_one_thread_and_two() {
    use deform_integrator::benchmark::beam_integrator;
    let run = |threads: usize, policy: &str, gamma: f64| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let (mut sim, mut state) = beam_integrator(14, policy).unwrap();
            let mut options = sim.options().clone();
            options.gamma = gamma;
            sim.set_options(options).unwrap();
            let mut iterations = 0;
            for _ in 0..2 {
                iterations += sim.step(&mut state).unwrap().iterations.len();
            }
            (state, iterations)
        })
    };
    for (policy, gamma) in [
        ("Fixed(Pcg(preconditioner: Amg()))", 0.0),
        ("Fixed(Direct())", 0.01),
    ] {
        let (one, its_one) = run(1, policy, gamma);
        let (two, its_two) = run(2, policy, gamma);
        assert_eq!(its_one, its_two, "{policy}");
        assert!(its_one >= 2, "{policy}: Newton iterated");
        assert!(one.x.iter().any(|x| x.abs() > 0.0));
        for (what, a, b) in [("x", &one.x, &two.x), ("v", &one.v, &two.v)] {
            let differs = a
                .iter()
                .zip(b.iter())
                .position(|(p, q)| p.to_bits() != q.to_bits());
            assert_eq!(differs, None, "{policy}: {what} differs at this DOF");
        }
    }
}

/// `NewtonOptions::linear_floor`: the iterative solves stop at a tenth of Newton's tolerance
/// where their own 1e-8 asks for more, so the steps take fewer linear iterations and the
/// same Newton iterations, and end within Newton's tolerance of the exact steps.
#[test]
fn the_linear_floor_saves_linear_iterations_within_newtons_tolerance() {
    let mesh = BoxGrid::beam(2).build().unwrap();
    let run = |floor: f64, p: &str| {
        let mut options = IntegratorOptions::default();
        options.newton.linear_floor = floor;
        let mut s = sim(&mesh, clamp(&mesh), options, p);
        let mut state = s.rest_state();
        let reports: Vec<StepReport> = (0..4).map(|_| s.step(&mut state).unwrap()).collect();
        (state, reports)
    };
    let pcg = "Fixed(Pcg(preconditioner: Jacobi, tolerance: (rel: 1e-8)))";
    let (tight, tight_reports) = run(0.0, pcg);
    let (floored, floored_reports) = run(0.1, pcg);
    // The exact steps, up to rounding: the direct solver with a tolerance 1e4 times tighter.
    let exact = {
        let mut options = IntegratorOptions::default();
        options.newton.rel = 1e-10;
        let mut s = sim(&mesh, clamp(&mesh), options, "Fixed(Direct())");
        let mut state = s.rest_state();
        for _ in 0..4 {
            s.step(&mut state).unwrap();
        }
        state
    };
    let sum = |r: &[StepReport], f: fn(&StepReport) -> usize| r.iter().map(f).sum::<usize>();
    assert_eq!(
        sum(&tight_reports, StepReport::newton_iterations),
        sum(&floored_reports, StepReport::newton_iterations)
    );
    let (tight_linear, floored_linear) = (
        sum(&tight_reports, StepReport::linear_iterations),
        sum(&floored_reports, StepReport::linear_iterations),
    );
    assert!(
        (floored_linear as f64) < 0.9 * tight_linear as f64,
        "{floored_linear} linear iterations with the floor, {tight_linear} without"
    );
    for r in &floored_reports {
        assert!(r.converged && r.final_residual <= 1e-6 * r.initial_residual);
    }
    let error = |s: &State| {
        let d: f64 = s.v.iter().zip(&exact.v).map(|(a, b)| (a - b).powi(2)).sum();
        let n: f64 = exact.v.iter().map(|b| b * b).sum();
        (d / n).sqrt()
    };
    // Newton's own tolerance (1e-6 of the first residual) is what both runs promise; the
    // tight solves land closer by the luck of a quadratic last update.
    let (e_tight, e_floored) = (error(&tight), error(&floored));
    assert!(
        e_floored < 1e-6 && e_tight < 1e-6,
        "velocity error {e_floored:e} with the floor, {e_tight:e} without"
    );
}
