//! The learned policy minimises work as weighted by `PolicyOptions::weights`: on a synthetic
//! dataset where PCG-IC(0) costs 1000 flops a solve, 400 of them in its triangular sweeps,
//! and PCG-AMG costs 1500 flops with no sweeps, plain flops choose IC(0), and sweeps weighted
//! 3x (1000 + 2 x 400 = 1800) choose AMG.

use std::path::Path;

use deform_integrator::{PolicyContext, Scene, SolverPolicy};
use deform_learn::policy::{LearnedPolicy, PolicyOptions};
use deform_learn::solver_data::{FEATURES, Outcome, SolverDataset, SolverMeta};
use deform_solvers::{PreconditionerSpec, SolverSpec, WorkWeights};

fn outcome(setup: f64, solve: f64, sweep: f64, iterations: f64) -> Outcome {
    Outcome {
        flops: setup + solve,
        setup_flops: setup,
        sweep_flops: sweep,
        reused: false,
        seconds: 0.0,
        ok: true,
        relative_residual: 1e-9,
        iterations,
        age: 0.0,
    }
}

fn dataset() -> SolverDataset {
    let candidates: Vec<SolverSpec> = [
        "Pcg(preconditioner: Ic0, tolerance: (rel: 1e-8))",
        "Pcg(preconditioner: Amg(), tolerance: (rel: 1e-8))",
    ]
    .iter()
    .map(|t| ron::from_str(t).unwrap())
    .collect();
    let scene_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/scenes/fit_beam.ron");
    SolverDataset {
        meta: SolverMeta {
            features: FEATURES.iter().map(|s| (*s).to_owned()).collect(),
            candidates,
            scene: Scene::load(&scene_path).unwrap(),
            steps: 1,
        },
        features: vec![vec![0.0, 0.0, -3.0, 0.0, 0.0, 0.01, 3.0, 5.0, 0.0]],
        outcomes: vec![vec![
            outcome(100.0, 900.0, 400.0, 20.0),
            outcome(900.0, 600.0, 0.0, 5.0),
        ]],
    }
}

fn first_choice(sweep: f64) -> SolverSpec {
    let mut policy = LearnedPolicy::train(
        &dataset(),
        PolicyOptions {
            neighbours: 1,
            min_success: 0.5,
            weights: WorkWeights { factor: 1.0, sweep },
            young: 1e5,
            forcing: None,
        },
    );
    let context = PolicyContext {
        step: 0,
        iteration: 0,
        dt: 0.01,
        num_free: 1000,
        residual: 1e-3,
        initial_residual: 1e-3,
        history: &[],
    };
    policy.choose(&context).solver
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
