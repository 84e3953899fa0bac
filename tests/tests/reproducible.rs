//! The learning pipeline gives bit-identical numbers on a rerun and whatever the number of
//! threads: dataset generation, both fitting stages, counterfactual solver logs, the learned
//! policy's choices and its deterministic work. (Wall times are the only thing that
//! differs.)

use deform_integrator::Scene;
use deform_learn::DatasetSpec;
use deform_learn::dataset::generate;
use deform_learn::policy::{LearnedPolicy, PolicyOptions};
use deform_learn::{OutputErrorOptions, Split, Variations, fit_equation_error, fit_output_error};
use deform_solvers::{SolverSpec, WorkWeights};
use deform_tests::asset;

/// Everything the pipeline computes, as bits.
fn pipeline() -> Vec<u64> {
    let path = asset("scenes/fit_beam.ron");
    let scene = Scene::load(&path).unwrap();
    let data = generate(
        &scene,
        &path,
        &DatasetSpec::new(3, 6, 11)
            .variations(
                Variations::default()
                    .speed(1.0)
                    .spin(2.0)
                    .stretch(0.1)
                    .rest(false),
            )
            .split((0.5, 0.2)),
        |_, _| {},
    )
    .unwrap();
    let mut bits: Vec<u64> = data
        .trajectories
        .iter()
        .flat_map(|t| t.x.iter().chain(&t.v).flatten().map(|v| v.to_bits()))
        .collect();
    let train = data.split(Split::Train);
    let mut sim = scene.build(&path).unwrap().integrator;
    let stage1 = fit_equation_error(&sim, &train, Default::default()).unwrap();
    bits.extend(stage1.coefficients.iter().map(|c| c.to_bits()));
    let start: Vec<f64> = stage1.coefficients.iter().map(|c| 1.3 * c).collect();
    let options = OutputErrorOptions::default().rollout(3).max_evaluations(6);
    let stage2 = fit_output_error(&mut sim, &train, &start, options, |_, _| {}).unwrap();
    bits.extend(stage2.coefficients.iter().map(|c| c.to_bits()));
    let candidates: Vec<SolverSpec> = [
        "Direct()",
        "Pcg(preconditioner: StaleCholesky(max_age: 100), tolerance: (rel: 1e-10))",
        "Pcg(preconditioner: Ic0, tolerance: (rel: 1e-10))",
    ]
    .iter()
    .map(|t| ron::from_str(t).unwrap())
    .collect();
    let logged = deform_learn::solver_data::collect(&scene, &path, &candidates, 4, |_| {}).unwrap();
    bits.extend(logged.outcomes.iter().flatten().map(|o| o.flops.to_bits()));
    let policy = LearnedPolicy::train(
        &logged,
        PolicyOptions::new(1e5)
            .neighbours(3)
            .min_success(0.9)
            .weights(WorkWeights::factor(0.1))
            .forcing(Some((0.1, 0.9))),
    );
    let mut built = scene.build(&path).unwrap();
    built.integrator.set_policy(Box::new(policy));
    built.state.v.iter_mut().for_each(|v| *v = 0.3);
    for _ in 0..4 {
        let r = built.integrator.step(&mut built.state).unwrap();
        bits.push(r.flops());
        bits.extend(
            r.iterations
                .iter()
                .flat_map(|i| i.solver.name().into_bytes().into_iter().map(u64::from)),
        );
    }
    bits.extend(built.state.x.iter().map(|v| v.to_bits()));
    bits
}

#[test]
fn the_learning_pipeline_is_identical_for_any_thread_count_and_on_rerun() {
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(pipeline)
    };
    let one = run(1);
    assert!(one.len() > 1000);
    assert_eq!(one, run(1), "rerun");
    assert_eq!(one, run(2), "2 threads");
    assert_eq!(one, run(4), "4 threads");
}

#[test]
fn the_bundled_experiments_name_scenes_that_load() {
    // Held-out and extra training scenes of solver selection, not only the base scene.
    for entry in std::fs::read_dir(asset("experiments")).unwrap() {
        let path = entry.unwrap().path();
        let e = deform_studies::Experiment::load(&path).unwrap();
        if let deform_studies::Task::SelectSolver {
            held_out,
            also_train,
            ..
        } = &e.task
        {
            for run in held_out.iter().chain(also_train) {
                Scene::load(&run.scene).unwrap_or_else(|err| panic!("{}: {err}", path.display()));
                assert!(run.steps > 0);
            }
        }
    }
}
