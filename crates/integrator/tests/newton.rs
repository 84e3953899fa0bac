//! Newton's loop and its solvers: typed failures with reports, retries, observers and run
//! ends, quadratic convergence, matrix-free directions, counterfactual candidates, tangent
//! projection and fallbacks, the rounding floor, restarts and forks, thread counts, the
//! linear floor.

mod beams;

use beams::*;
use deform_solvers::WorkWeights;
use std::ops::ControlFlow;

use deform_integrator::{
    Integrator, IntegratorError, IntegratorOptions, IterationReport, NewtonOptions, NoObserver,
    Observer, PolicySpec, RunOptions, State, StepError, StepReport, Termination,
};
use deform_mesh::generate::BoxGrid;

#[test]
fn failures_are_typed_carry_reports_and_leave_the_state_alone() {
    let mesh = beam();
    // A one-iteration cap with tight tolerances cannot converge.
    let options = IntegratorOptions::default()
        .newton(
            NewtonOptions::default()
                .max_iterations(1)
                .rel(1e-12)
                .abs(0.0),
        )
        .max_retries(0);
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
    let bad = IntegratorOptions::default().dt(-1.0);
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
    let options = IntegratorOptions::default()
        .dt(0.05)
        .newton(NewtonOptions::default().max_iterations(3))
        .max_retries(4);
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
    let summary = s.run(&mut state, &RunOptions::time(0.025), &mut NoObserver);
    assert_eq!(summary.steps, 3);
    let mut state = s.rest_state();
    let summary = s.run(&mut state, &RunOptions::time(0.03), &mut NoObserver);
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

#[test]
fn newton_with_the_direct_solver_converges_quadratically() {
    // Also with Rayleigh stiffness damping: Newton's matrix then carries the damping force's
    // derivative in x (dt^2 gamma D_u K); without it the rate is linear (negative gamma
    // keeps the positive definite matrix without it, see `Integrator::newton_matrix`).
    let mesh = beam();
    for gamma in [0.0, 0.02] {
        let options = IntegratorOptions::default()
            .gamma(gamma)
            .newton(
                NewtonOptions::default()
                    .rel(1e-13)
                    .abs(1e-13)
                    .line_search(false),
            )
            .max_retries(0);
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
        let options = IntegratorOptions::default()
            .dt(dt)
            .newton(NewtonOptions::default().project(project))
            .max_retries(0);
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
    let options = IntegratorOptions::default()
        .fallback_to_direct(false)
        .max_retries(0);
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

#[test]
fn the_reported_residual_is_that_of_the_end_state_with_and_without_stiffness_damping() {
    // Without stiffness damping the converged check reuses the line search's energy and
    // forces (no K); with it, it assembles K for the damping force. Either way the residual
    // reported must be the end state's.
    let mesh = beam();
    for gamma in [0.0, 0.01] {
        let options = IntegratorOptions::default().alpha(0.5).gamma(gamma);
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

/// A run after `restart`, or on a fork, gives the bits of a new integrator's run, whatever
/// ran before: with a stale factor, adaptive tolerances and a schedule by iteration (all
/// history the policy or the kept solvers carry), so that a fit's rollouts can run on any
/// copy, in any order, on any thread.
#[test]
fn a_restarted_or_forked_integrator_runs_as_a_new_one() {
    let mesh = beam();
    let options = IntegratorOptions::default().max_retries(0);
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
