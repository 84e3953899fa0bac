//! Unit tests of the parent module.

use std::path::Path;

use super::*;
use crate::dataset::{DatasetSpec, Split, generate};

/// The n = 1 beam (tight Newton) and three 3-step trajectories of it.
fn tiny_beam() -> (
    deform_integrator::Scene,
    crate::dataset::Dataset,
    &'static Path,
) {
    let text = r#"Scene(name: "t", mesh: Beam(1), material: NeoHookean(Young(e: 1e5, nu: 0.4)),
        density: 1000.0, constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
        integrator: (dt: 0.01, newton: (rel: 1e-10, abs: 1e-12)), steps: 3)"#;
    let origin = Path::new("t.ron");
    let scene = deform_integrator::Scene::parse(text, origin).unwrap();
    let data = generate(&scene, origin, &DatasetSpec::new(3, 3, 5), |_, _| ()).unwrap();
    (scene, data, origin)
}

/// The loss and its gradients have the same bits on 1, 2 or 3 threads (rollouts one by
/// one on the objective's integrator, or side by side on its forks), with a trajectory
/// under other conditions, start offsets, fitted damping and a policy that carries a
/// stale factor from solve to solve (so that a rollout would depend on the one before
/// it without the restart).
#[test]
fn rollouts_give_the_same_bits_on_any_number_of_threads() {
    let (scene, mut data, origin) = tiny_beam();
    data.trajectories[1].conditions.gravity = Some([0.0, 4.0, -2.0]);
    let all: Vec<&Trajectory> = data.trajectories.iter().collect();
    let policy = "StaleFactor(solver: Pcg(preconditioner: StaleCholesky(max_age: 1000), tolerance: (rel: 1e-6)), refactor_above: 1000)";
    let evaluate = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let mut sim = scene.build(origin).unwrap().integrator;
            let spec: deform_integrator::PolicySpec = ron::from_str(policy).unwrap();
            sim.set_policy(spec.build().unwrap());
            let options = OutputErrorOptions {
                rollout: 2,
                starts: Some(StartPrior::default()),
                ..Default::default()
            };
            let objective = OutputError::new(&mut sim, &all, options, |_, _| {})
                .unwrap()
                .with_damping();
            let c: Vec<f64> = objective.uniform_start().iter().map(|v| v * 1.2).collect();
            let o: Vec<f64> = (0..objective.num_start_parameters())
                .map(|i| 1e-4 * ((i % 7) as f64 - 3.0))
                .collect();
            // A second evaluation reuses the lanes of the first.
            let first = objective.evaluate_with_starts(&c, Some(&o)).unwrap();
            let c: Vec<f64> = c.iter().map(|v| v * 0.9).collect();
            (first, objective.evaluate_with_starts(&c, Some(&o)).unwrap())
        })
    };
    let one = evaluate(1);
    assert!(one.0.0 > 0.0 && one.0.2.iter().any(|g| *g != 0.0));
    assert_eq!(evaluate(2), one);
    assert_eq!(evaluate(3), one);
}

/// A fit stops once `patience` simulated evaluations in a row have not lowered the best
/// loss (here the data's own model, loss 0, and trial points off it); with patience 0
/// it never does.
#[test]
fn a_fit_that_makes_no_progress_stops_after_its_patience() {
    let (scene, data, origin) = tiny_beam();
    let train = data.split(Split::Train);
    for patience in [0, 3] {
        let mut sim = scene.build(origin).unwrap().integrator;
        let options = OutputErrorOptions {
            rollout: 3,
            patience,
            ..Default::default()
        };
        let objective = OutputError::new(&mut sim, &train, options, |_, _| {}).unwrap();
        let start = objective.uniform_start();
        let problem = LogProblem::new(&objective, &start);
        let p0 = problem.parameters();
        let (best, _) = problem.evaluate(&p0).unwrap();
        // Each trial point is new (not cached) and worse than the data's model.
        let trial = |k: usize| {
            let mut p = p0.clone();
            p[0] += 0.1 * k as f64;
            problem.evaluate(&p)
        };
        for k in 1..3 {
            assert!(trial(k).unwrap().0 > best);
        }
        match (patience, trial(3)) {
            (0, result) => assert!(result.is_ok()),
            (_, Err(FitError::Stalled { patience: 3 })) => {}
            (_, other) => panic!("expected a stall, got {other:?}"),
        }
        assert_eq!(*objective.evaluations.borrow(), 4);
    }
}

/// Trial points beyond a factor of 10 from the best point so far are not simulated (the
/// line search backs off at no cost); each new best point doubles the radius. A fit from
/// a start 30x too stiff still reaches the data's model without a failed trial.
#[test]
fn trial_points_stay_within_the_trust_region_of_the_best_point() {
    let (scene, data, origin) = tiny_beam();
    let train = data.split(Split::Train);
    let mut sim = scene.build(origin).unwrap().integrator;
    let options = OutputErrorOptions {
        rollout: 3,
        ..Default::default()
    };
    let objective = OutputError::new(&mut sim, &train, options, |_, _| {}).unwrap();
    let truth = objective.uniform_start();
    let start: Vec<f64> = truth.iter().map(|c| 3.0 * c).collect();
    let problem = LogProblem::new(&objective, &start);
    let p0 = problem.parameters();
    let (l0, _) = problem.evaluate(&p0).unwrap();
    let at = |d: f64| {
        let mut p = p0.clone();
        p[0] -= d;
        p
    };
    // 20x away: not simulated, a loss far above.
    let (far, _) = problem.evaluate(&at(3.0)).unwrap();
    assert_eq!(*objective.evaluations.borrow(), 1);
    assert_eq!(far, FAILED_TRIAL_FACTOR * l0);
    // 3x away (towards the data's model): simulated, better, and the radius doubles.
    let (near, _) = problem.evaluate(&at(3f64.ln())).unwrap();
    assert_eq!(*objective.evaluations.borrow(), 2);
    assert!(near < l0);
    assert!((problem.trust.borrow().2 - 2.0 * TRUST_RADIUS).abs() < 1e-15);
    drop(problem);
    let far_start: Vec<f64> = truth.iter().map(|c| 30.0 * c).collect();
    let fit = minimise(&objective, &far_start).unwrap();
    assert_eq!(fit.failed_trials, 0);
    for (c, t) in fit.coefficients.iter().zip(&truth) {
        assert!(
            (c - t).abs() < 1e-4 * t,
            "{:?} against {truth:?}",
            fit.coefficients
        );
    }
}

/// A fit stopped by its own rules says so: the budget and the patience are typed
/// terminations, not argmin's line-search text around them.
#[test]
fn a_fit_stopped_by_its_budget_or_patience_reports_which() {
    let (scene, data, origin) = tiny_beam();
    let train = data.split(Split::Train);
    for (budget, patience) in [(3, 0), (200, 1)] {
        let mut sim = scene.build(origin).unwrap().integrator;
        let options = OutputErrorOptions {
            rollout: 3,
            max_evaluations: budget,
            patience,
            // Never converged: near the optimum the loss stops dropping by 1e-6.
            tolerance: 0.0,
            ..Default::default()
        };
        // Off the data's model (mu and lambda doubled), so the first steps make progress.
        let seen = std::cell::Cell::new(0);
        let count = |_, _| seen.set(seen.get() + 1);
        let objective = OutputError::new(&mut sim, &train, options, count).unwrap();
        let start: Vec<f64> = objective.uniform_start().iter().map(|c| 2.0 * c).collect();
        let fit = minimise(&objective, &start).unwrap();
        // Progress bars count the budget: the final evaluation at the best point, outside
        // it, is not reported.
        assert_eq!(seen.get(), fit.evaluations);
        assert!(seen.get() <= budget);
        assert!(fit.loss < fit.initial_loss);
        let expected = if patience == 0 {
            Termination::Budget { evaluations: 3 }
        } else {
            Termination::Stalled { patience: 1 }
        };
        assert_eq!(fit.termination, expected, "{}", fit.termination.describe());
        // The budget is a limit (more might help); a stall is not.
        assert_eq!(fit.termination.on_limit(), patience == 0);
        // The record starts at the start and holds no iterate without coefficients (the
        // stopped line search's last iteration moved nowhere).
        let first = &fit.iterations[0];
        assert_eq!((first.iteration, first.loss), (0, fit.initial_loss));
        assert_eq!(first.coefficients, start);
        for it in &fit.iterations {
            assert_eq!(it.coefficients.len(), start.len(), "{it:?}");
            assert!(it.coefficients.iter().all(|c| c.is_finite()), "{it:?}");
        }
    }
}

/// A trial point the integrator cannot simulate costs far more than the last good one
/// and carries its gradient, so the line search backs off instead of the fit stopping.
#[test]
fn a_trial_point_that_does_not_simulate_is_backed_off_from() {
    let text = r#"Scene(name: "t", mesh: Beam(1), material: NeoHookean(Young(e: 1e5, nu: 0.4)),
        density: 1000.0, constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
        integrator: (dt: 0.01, max_retries: 0, newton: (rel: 1e-10, abs: 1e-12)), steps: 3)"#;
    let origin = Path::new("t.ron");
    let scene = deform_integrator::Scene::parse(text, origin).unwrap();
    let data = generate(&scene, origin, &DatasetSpec::new(3, 3, 5), |_, _| ()).unwrap();
    let mut sim = scene.build(origin).unwrap().integrator;
    // Few Newton iterations: a far stiffer model does not converge in them.
    let mut o = sim.options().clone();
    o.newton.max_iterations = 5;
    sim.set_options(o).unwrap();
    let train = data.split(Split::Train);
    let options = OutputErrorOptions {
        rollout: 3,
        ..Default::default()
    };
    let objective = OutputError::new(&mut sim, &train, options, |_, _| {}).unwrap();
    let start = objective.uniform_start();
    let problem = LogProblem::new(&objective, &start);
    // Far trial points simulated (the trust region is tested on its own).
    problem.trust.borrow_mut().2 = f64::INFINITY;
    let p0 = problem.parameters();
    // Before anything simulated there is nothing to fall back on: the error itself.
    let far: Vec<f64> = p0.iter().map(|p| p + 12.0).collect();
    let error = problem.evaluate(&far).unwrap_err();
    assert!(error.is_failed_simulation(), "{error}");
    let (loss, grad) = problem.evaluate(&p0).unwrap();
    let (penalty, fallback) = problem.evaluate(&far).unwrap();
    assert_eq!(penalty, FAILED_TRIAL_FACTOR * loss.max(f64::MIN_POSITIVE));
    assert_eq!(fallback, grad);
    assert_eq!(*objective.failed_trials.borrow(), 1);
    // Trials that are not finite are not even simulated.
    let evaluations = *objective.evaluations.borrow();
    for beyond in [f64::NAN, f64::INFINITY] {
        let mut p = p0.clone();
        p[0] = beyond;
        assert_eq!(problem.evaluate(&p).unwrap(), (penalty, grad.clone()));
    }
    assert_eq!(*objective.evaluations.borrow(), evaluations);
    assert_eq!(*objective.failed_trials.borrow(), 3);
    // Beyond the bounded log-step the loss is that on the bound, flat outwards.
    let (mut bound, mut beyond) = (p0.clone(), p0.clone());
    bound[0] -= MAX_LOG_DISTANCE;
    beyond[0] -= MAX_LOG_DISTANCE + 3.0;
    let (on, g_on) = problem.evaluate(&bound).unwrap();
    let (out, g_out) = problem.evaluate(&beyond).unwrap();
    assert_eq!(problem.coefficients(&beyond), problem.coefficients(&bound));
    assert_eq!(out, on);
    assert_eq!(g_out[0], 0.0);
    assert_eq!(g_out[1..], g_on[1..]);
    assert!(g_on.iter().all(|g| g.is_finite()));
    // A line search that keeps proposing such points is stopped, not left spinning.
    let calls = CALLS_PER_EVALUATION * options.max_evaluations;
    let mut p = p0.clone();
    p[0] = f64::NAN;
    // Seven calls so far: one failed point before any simulated, then p0, then five more.
    let mut answered = 7;
    while problem.evaluate(&p).is_ok() {
        answered += 1;
        assert!(answered <= calls, "never stopped");
    }
    assert_eq!(answered, calls);
    let error = problem.evaluate(&p0).unwrap_err();
    assert!(matches!(error, FitError::Trials { .. }), "{error}");
}

/// The gradient in the start offsets (the last adjoints of each rollout plus the prior's)
/// equals central differences of the loss, along a random direction, with mass damping
/// (the adjoint is exact for any gamma, see the module docs).
#[test]
fn the_start_gradient_equals_finite_differences() {
    let text = r#"Scene(name: "t", mesh: Beam(1), material: NeoHookean(Young(e: 1e5, nu: 0.4)),
        density: 1000.0, constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
        integrator: (dt: 0.01, alpha: 0.5, newton: (rel: 1e-12, abs: 1e-14)), steps: 3)"#;
    let origin = Path::new("t.ron");
    let scene = deform_integrator::Scene::parse(text, origin).unwrap();
    let data = generate(&scene, origin, &DatasetSpec::new(3, 4, 5), |_, _| ()).unwrap();
    let mut sim = scene.build(origin).unwrap().integrator;
    let train = data.split(Split::Train);
    let options = OutputErrorOptions {
        rollout: 2,
        velocity_weight: 0.3,
        starts: Some(StartPrior::default()),
        ..Default::default()
    };
    let objective = OutputError::new(&mut sim, &train, options, |_, _| {})
        .unwrap()
        .with_damping();
    let c = objective.uniform_start();
    let c: Vec<f64> = c.iter().map(|v| v * 1.3).collect();
    let count = objective.num_start_parameters();
    let dofs = objective.sim.borrow().assembly().num_dofs();
    assert_eq!(
        count,
        2 * 2 * 2 * dofs,
        "2 trajectories of 2 rollouts, positions and velocities"
    );
    let mut rng = crate::rng::Rng::new(3);
    let scale = objective.motion_scale();
    let o: Vec<f64> = (0..count).map(|_| 0.3 * scale * rng.normal()).collect();
    let d: Vec<f64> = (0..count).map(|_| scale * rng.normal()).collect();
    let (_, _, g) = objective.evaluate_with_starts(&c, Some(&o)).unwrap();
    let at = |h: f64| {
        let p: Vec<f64> = o.iter().zip(&d).map(|(o, d)| o + h * d).collect();
        objective.evaluate_with_starts(&c, Some(&p)).unwrap().0
    };
    let h = 1e-4;
    let fd = (at(h) - at(-h)) / (2.0 * h);
    let exact: f64 = g.iter().zip(&d).map(|(g, d)| g * d).sum();
    assert!(
        (fd - exact).abs() <= 1e-5 * exact.abs(),
        "finite differences {fd:e}, adjoint {exact:e}"
    );
    // Constrained DOFs carry no gradient.
    let n = g.len() / 4;
    let clamped = objective.sim.borrow().dofs().constrained_vertices();
    assert!(!clamped.is_empty());
    for v in clamped {
        assert!((0..4).all(|r| (0..3).all(|i| g[r * n + 3 * v + i] == 0.0)));
    }
    // The start offsets are not bounded like the coefficients: one far past
    // MAX_LOG_DISTANCE units (the last free DOF's velocity) keeps its gradient.
    let problem = LogProblem::new(&objective, &c);
    let mut p = problem.parameters();
    let last = p.len() - 1;
    p[last] = 2.0 * MAX_LOG_DISTANCE;
    let (_, g) = problem.evaluate(&p).unwrap();
    assert_ne!(g[last], 0.0);
    drop(problem);
    drop(objective);
    // An exactly known first state stays: its rollout's starts get no gradient (and
    // no offset), the trajectory's later rollouts do.
    let mut exact = train[0].clone();
    exact.exact_start = true;
    let trajectories = [&exact];
    let objective = OutputError::new(&mut sim, &trajectories, options, |_, _| {}).unwrap();
    let count = objective.num_start_parameters();
    let o: Vec<f64> = (0..count).map(|_| 0.3 * scale * rng.normal()).collect();
    let (_, _, g) = objective.evaluate_with_starts(&c[..2], Some(&o)).unwrap();
    let (first, second) = g.split_at(count / 2);
    assert!(first.iter().all(|v| *v == 0.0));
    assert!(second.iter().any(|v| *v != 0.0));
    let (loss, _) = objective.evaluate(&c[..2]).unwrap();
    let mut moved = o.clone();
    moved[..count / 2].iter_mut().for_each(|v| *v = 0.0);
    let (l1, _, _) = objective.evaluate_with_starts(&c[..2], Some(&o)).unwrap();
    let (l2, _, _) = objective
        .evaluate_with_starts(&c[..2], Some(&moved))
        .unwrap();
    assert_eq!(l1, l2, "the first rollout's offsets are ignored");
    assert!(l1 != loss);
}

/// A rollout step that converged only in halved substeps is accepted by default (real
/// data need it) and, when asked, refused naming it: it is not the step the adjoint
/// differentiates.
#[test]
fn a_retried_step_is_accepted_by_default_and_refused_on_request() {
    let (scene, data, origin) = tiny_beam();
    let mut sim = scene.build(origin).unwrap().integrator;
    let mut o = sim.options().clone();
    (o.newton.max_iterations, o.max_retries) = (2, 8);
    sim.set_options(o).unwrap();
    let train = data.split(Split::Train);
    let refuse = OutputErrorOptions {
        allow_retries: false,
        ..Default::default()
    };
    let objective = OutputError::new(&mut sim, &train, refuse, |_, _| {}).unwrap();
    let error = objective.evaluate(&objective.uniform_start()).unwrap_err();
    assert!(
        matches!(error, FitError::Retried { trajectory: 0, step: 0, retries } if retries > 0),
        "{error}"
    );
    assert!(error.is_failed_simulation());
    drop(objective);
    let options = OutputErrorOptions::default();
    assert!(options.allow_retries);
    let objective = OutputError::new(&mut sim, &train, options, |_, _| {}).unwrap();
    assert!(objective.evaluate(&objective.uniform_start()).is_ok());
}
