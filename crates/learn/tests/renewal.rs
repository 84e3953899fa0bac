//! The learned policy's rule for holding a factor, on a synthetic dataset where the answer is
//! known: a factorisation costs 1000, a solve iteration 10, and a stale factor of age `a`
//! needs `1 + 5a` PCG iterations. The cycle's running average after the factorising solve
//! (1010) and stale solves of 60, 110, 160, 210, 260 stays above each next cost until age 6
//! (310 > 1810 / 6), so the optimal cycle is one factorisation and five stale solves, and the
//! policy repeats it; a fresh factorisation every time (1010 per solve) is never chosen.

use std::path::Path;

use deform_integrator::{IterationReport, PolicyContext, Scene, SolverPolicy};
use deform_learn::policy::{LearnedPolicy, PolicyOptions};
use deform_learn::solver_data::{FEATURES, Outcome, SolverDataset, SolverMeta};
use deform_solvers::{SetupStats, SolveStats, SolverSpec, Termination, WorkWeights};

const FACTOR: f64 = 1000.0;
const PER_ITERATION: f64 = 10.0;

fn stale_iterations(age: usize) -> usize {
    if age == 0 { 1 } else { 1 + 5 * age }
}

fn dataset() -> SolverDataset {
    let candidates: Vec<SolverSpec> = [
        "Direct()",
        "Pcg(preconditioner: StaleCholesky(max_age: 100), tolerance: (rel: 1e-10))",
    ]
    .iter()
    .map(|t| ron::from_str(t).unwrap())
    .collect();
    let scene_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/scenes/fit_beam.ron");
    let features = vec![0.0, 0.0, -3.0, 0.0, 0.0, 0.01, 3.0, 5.0, 0.0];
    let (mut all_features, mut outcomes) = (Vec::new(), Vec::new());
    for age in 0..=20 {
        let its = stale_iterations(age) as f64;
        let setup = if age == 0 { FACTOR } else { 0.0 };
        all_features.push(features.clone());
        outcomes.push(vec![
            Outcome {
                flops: FACTOR + PER_ITERATION,
                setup_flops: FACTOR,
                sweep_flops: 0.0,
                reused: false,
                seconds: 0.0,
                ok: true,
                relative_residual: 1e-12,
                iterations: 1.0,
                age: 0.0,
            },
            Outcome {
                flops: setup + its * PER_ITERATION,
                setup_flops: setup,
                sweep_flops: 0.0,
                reused: age > 0,
                seconds: 0.0,
                ok: true,
                relative_residual: 1e-11,
                iterations: its,
                age: age as f64,
            },
        ]);
    }
    SolverDataset {
        meta: SolverMeta {
            features: FEATURES.iter().map(|s| (*s).to_owned()).collect(),
            candidates,
            scene: Scene::load(&scene_path).unwrap(),
            steps: 1,
        },
        features: all_features,
        outcomes,
    }
}

/// The report of a solve with these statistics.
fn report(solver: &SolverSpec, factorised: bool, iterations: usize) -> IterationReport {
    IterationReport {
        iteration: 0,
        residual: 1e-3,
        energy: 0.0,
        solver: solver.clone(),
        setup: SetupStats {
            analyzed: false,
            reused: !factorised,
            flops: if factorised { FACTOR as u64 } else { 0 },
            factor_nnz: usize::from(factorised),
            seconds: 0.0,
        },
        solve: SolveStats {
            solver: solver.name(),
            iterations,
            residuals: Vec::new(),
            rhs_norm: 1.0,
            termination: Termination::Converged,
            seconds: 0.0,
            matvecs: iterations,
            flops: (iterations as f64 * PER_ITERATION) as u64,
            sweep_flops: 0,
        },
        fallback: false,
        step_length: 1.0,
        update: 0.0,
        seconds: 0.0,
        stages: Default::default(),
        candidates: Vec::new(),
        discarded: Vec::new(),
    }
}

#[test]
fn the_policy_keeps_a_factor_exactly_while_the_next_stale_solve_is_below_the_cycle_average() {
    let mut policy = LearnedPolicy::train(
        &dataset(),
        PolicyOptions {
            neighbours: 1,
            min_success: 0.5,
            weights: WorkWeights::default(),
            young: 1e5,
            forcing: None,
        },
    );
    let mut age = 0;
    let mut refreshes = Vec::new();
    for solve in 0..14 {
        let context = PolicyContext {
            step: solve,
            iteration: 0,
            dt: 0.01,
            num_free: 1000,
            residual: 1e-3,
            initial_residual: 1e-3,
            history: &[],
        };
        let decision = policy.choose(&context);
        assert!(
            decision.solver.is_stale_cholesky(),
            "solve {solve}: {:?}",
            decision.solver
        );
        if decision.refresh {
            age = 0;
            refreshes.push(solve);
        } else {
            age += 1;
        }
        policy.observe(
            &context,
            &report(&decision.solver, decision.refresh, stale_iterations(age)),
        );
    }
    assert_eq!(refreshes, [0, 6, 12]);
}
