//! Small problems run whole jobs side by side (issue 42): the policies' timed runs and the
//! counterfactual logs give the same bits on one thread as on two, where they run two at a
//! time, and the same as one by one.

use std::path::Path;

use deform_integrator::{Fixed, IntegratorOptions, Scene, SolverPolicy};
use deform_learn::compare::{Case, Contestant, Measured, measure, measure_all};
use deform_learn::solver_data::{SolverDataset, collect_runs};
use deform_solvers::{SolverSpec, WorkWeights};

fn beam(velocity: [f64; 3]) -> Scene {
    let mut s: Scene = ron::from_str(
        r#"Scene(
            name: "lanes",
            mesh: Beam(1),
            material: NeoHookean(Young(e: 1e5, nu: 0.4)),
            density: 1000.0,
            constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
            integrator: (dt: 0.01, newton: (rel: 1e-9)),
            steps: 1,
        )"#,
    )
    .unwrap();
    s.initial.velocity = velocity;
    s
}

fn specs() -> Vec<SolverSpec> {
    [
        "Direct()",
        "Pcg(preconditioner: Ic0, tolerance: (rel: 1e-10))",
    ]
    .iter()
    .map(|t| ron::from_str(t).unwrap())
    .collect()
}

fn on_threads<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(f)
}

/// Everything but the times.
fn deterministic(m: &Measured) -> impl PartialEq + std::fmt::Debug {
    let (flops, work, error) = (m.flops.to_bits(), m.work.to_bits(), m.error.to_bits());
    let per_step: Vec<_> = m.per_step.iter().map(|(w, n)| (w.to_bits(), *n)).collect();
    let choices: Vec<_> = m.choices.iter().map(ToString::to_string).collect();
    let counts = (m.newton, m.linear, m.fallbacks, m.failed, m.deterministic);
    (flops, work, error, per_step, choices, counts)
}

#[test]
fn policies_measured_side_by_side_match_one_by_one() {
    let origin = Path::new("t");
    let case = Case {
        label: "two releases".into(),
        runs: vec![
            (beam([0.0, 0.0, -1.0]), origin),
            (beam([0.0, 0.5, 0.5]), origin),
        ],
        steps: 4,
    };
    let references = case.references().unwrap();
    let specs = specs();
    let policies: Vec<_> = specs
        .iter()
        .map(|s| move || Box::new(Fixed(s.clone())) as Box<dyn SolverPolicy>)
        .collect();
    let tight = |o: &mut IntegratorOptions| o.newton.rel = 1e-11;
    let contestants: Vec<_> = policies
        .iter()
        .map(|make| Contestant {
            make,
            options: &tight,
        })
        .collect();
    let weights = WorkWeights::default();
    let all = |threads| {
        on_threads(threads, || {
            let mut finished = 0;
            let m = measure_all(&case, &references, &contestants, weights, 3, &mut || {
                finished += 1;
            });
            (m.unwrap(), finished)
        })
    };
    let (one, finished) = all(1);
    let (two, _) = all(2);
    assert_eq!(finished, 6, "one progress event per repeat");
    for (k, c) in contestants.iter().enumerate() {
        let alone = measure(&case, &references, c.make, c.options, weights, 3).unwrap();
        assert!(alone.work > 0.0 && alone.error < 1e-6 && !alone.failed);
        assert_eq!(alone.per_step.len(), 8, "both runs' steps, once");
        assert_eq!(deterministic(&one[k]), deterministic(&alone));
        assert_eq!(deterministic(&two[k]), deterministic(&alone));
    }
    // Each contestant's own figures, not its neighbour's.
    assert_ne!(one[0].work, one[1].work);
}

#[test]
fn solver_logs_side_by_side_match_one_by_one() {
    let origin = Path::new("t");
    let runs: Vec<(Scene, &Path, usize)> = vec![
        (beam([0.0, 0.0, -1.0]), origin, 3),
        (beam([0.0, 1.0, 0.0]), origin, 2),
        (beam([0.5, 0.0, 0.0]), origin, 3),
    ];
    let specs = specs();
    let log = |threads| {
        on_threads(threads, || {
            let mut steps = 0;
            let d = collect_runs(&runs, &specs, |_| steps += 1).unwrap();
            (d, steps)
        })
    };
    let without_seconds = |mut d: SolverDataset| {
        for o in d.outcomes.iter_mut().flatten() {
            o.seconds = 0.0;
        }
        d
    };
    let (one, steps) = log(1);
    let (two, _) = log(2);
    assert_eq!(steps, 8);
    let first = deform_learn::solver_data::collect(&runs[0].0, origin, &specs, 3, |_| {}).unwrap();
    assert!(one.len() > first.len());
    assert_eq!(&one.features[..first.len()], &first.features[..]);
    assert_eq!(without_seconds(one), without_seconds(two));
}
