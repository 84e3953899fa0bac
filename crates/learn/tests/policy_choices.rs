//! The learned policy's choices on synthetic datasets where the answer is known.
//!
//! Holding a factor: a factorisation costs 1000, a solve iteration 10, and a stale factor of
//! age `a` needs `1 + 5a` PCG iterations. The cycle's running average after the factorising solve
//! (1010) and stale solves of 60, 110, 160, 210, 260 stays above each next cost until age 6
//! (310 > 1810 / 6), so the optimal cycle is one factorisation and five stale solves, and the
//! policy repeats it; a fresh factorisation every time (1010 per solve) is never chosen.
//!
//! Weighted work: PCG-IC(0) costs 1000 flops a solve, 400 of them in its triangular sweeps,
//! and PCG-AMG costs 1500 flops with no sweeps; plain flops choose IC(0), and sweeps weighted
//! 3x (1000 + 2 x 400 = 1800) choose AMG.

use std::path::Path;

use deform_integrator::{IterationReport, PolicyContext, Scene, SolverPolicy};
use deform_learn::policy::{LearnedPolicy, PolicyOptions};
use deform_learn::solver_data::{FEATURES, Outcome, SolverDataset, SolverMeta};
use deform_solvers::{
    PreconditionerSpec, SetupStats, SolveStats, SolverSpec, Termination, WorkWeights,
};

const FACTOR: f64 = 1000.0;
const PER_ITERATION: f64 = 10.0;

fn stale_iterations(age: usize) -> usize {
    if age == 0 { 1 } else { 1 + 5 * age }
}

/// One candidate's logged outcome.
fn outcome(setup: f64, solve: f64, sweep: f64, iterations: f64, age: usize) -> Outcome {
    Outcome::default()
        .flops(setup + solve)
        .setup_flops(setup)
        .sweep_flops(sweep)
        .reused(age > 0)
        .ok(true)
        .relative_residual(1e-11)
        .iterations(iterations)
        .age(age as f64)
}

/// A dataset of `candidates` (RON) with `outcomes`, every sample at the same features.
fn synthetic(candidates: &[&str], outcomes: Vec<Vec<Outcome>>) -> SolverDataset {
    let scene_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/scenes/fit_beam.ron");
    let features = vec![0.0, 0.0, -3.0, 0.0, 0.0, 0.01, 3.0, 5.0, 0.0];
    SolverDataset {
        meta: SolverMeta::new(
            FEATURES.iter().map(|s| (*s).to_owned()).collect(),
            candidates
                .iter()
                .map(|t| ron::from_str(t).unwrap())
                .collect(),
            Scene::load(&scene_path).unwrap(),
            1,
        ),
        features: vec![features; outcomes.len()],
        outcomes,
    }
}

fn dataset() -> SolverDataset {
    let outcomes = (0..=20)
        .map(|age| {
            let its = stale_iterations(age) as f64;
            let setup = if age == 0 { FACTOR } else { 0.0 };
            vec![
                outcome(FACTOR, PER_ITERATION, 0.0, 1.0, 0),
                outcome(setup, its * PER_ITERATION, 0.0, its, age),
            ]
        })
        .collect();
    synthetic(
        &[
            "Direct()",
            "Pcg(preconditioner: StaleCholesky(max_age: 100), tolerance: (rel: 1e-10))",
        ],
        outcomes,
    )
}

/// The first Newton iteration of step `step` of a 1000-DOF system.
fn context(step: usize) -> PolicyContext<'static> {
    PolicyContext {
        step,
        iteration: 0,
        dt: 0.01,
        num_free: 1000,
        residual: 1e-3,
        initial_residual: 1e-3,
        history: &[],
    }
}

/// The report of a solve with these statistics.
fn report(solver: &SolverSpec, factorised: bool, iterations: usize) -> IterationReport {
    let setup = SetupStats::default()
        .analyzed(false)
        .reused(!factorised)
        .flops(if factorised { FACTOR as u64 } else { 0 })
        .factor_nnz(usize::from(factorised))
        .seconds(0.0);
    let solve = SolveStats::new(solver.name(), 1.0)
        .termination(Termination::Converged)
        .iterations(iterations)
        .matvecs(iterations)
        .flops((iterations as f64 * PER_ITERATION) as u64);
    IterationReport::new(0, solver.clone(), solve)
        .residual(1e-3)
        .setup(setup)
}

#[test]
fn the_policy_keeps_a_factor_exactly_while_the_next_stale_solve_is_below_the_cycle_average() {
    let mut policy = LearnedPolicy::train(
        &dataset(),
        PolicyOptions::new(1e5)
            .neighbours(1)
            .min_success(0.5)
            .weights(WorkWeights::default())
            .forcing(None),
    );
    let mut age = 0;
    let mut refreshes = Vec::new();
    for solve in 0..14 {
        let context = context(solve);
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

fn first_choice(sweep: f64) -> SolverSpec {
    let mut policy = LearnedPolicy::train(
        &synthetic(
            &[
                "Pcg(preconditioner: Ic0, tolerance: (rel: 1e-8))",
                "Pcg(preconditioner: Amg(), tolerance: (rel: 1e-8))",
            ],
            vec![vec![
                outcome(100.0, 900.0, 400.0, 20.0, 0),
                outcome(900.0, 600.0, 0.0, 5.0, 0),
            ]],
        ),
        PolicyOptions::new(1e5)
            .neighbours(1)
            .min_success(0.5)
            .weights(WorkWeights::factor(1.0).sweep(sweep))
            .forcing(None),
    );
    policy.choose(&context(0)).solver
}

fn preconditioner(spec: &SolverSpec) -> Option<PreconditionerSpec> {
    match spec {
        SolverSpec::Pcg { preconditioner, .. } => Some(*preconditioner),
        _ => None,
    }
}

#[test]
fn weighted_sweeps_move_the_choice_from_ic0_to_amg() {
    assert_eq!(
        preconditioner(&first_choice(1.0)),
        Some(PreconditionerSpec::Ic0)
    );
    assert!(matches!(
        preconditioner(&first_choice(3.0)),
        Some(PreconditionerSpec::Amg { .. })
    ));
    // Just below the break-even weight (1000 + 400 (w - 1) = 1500 at w = 2.25): IC(0).
    assert_eq!(
        preconditioner(&first_choice(2.2)),
        Some(PreconditionerSpec::Ic0)
    );
}
