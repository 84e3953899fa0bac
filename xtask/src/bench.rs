//! `cargo xtask bench ...`: quick, scriptable measurements on the beam family of
//! `shared/BENCHMARKS.md`, printed as one JSON object per line so `bench/peers/*.py` can put
//! them beside the peers measured in the same run. (The criterion benches of each crate are
//! the detailed, statistically careful version.)

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use deform_assembly::{Assembly, MaterialField, Outputs, Tangent};
use deform_fs::write_atomic;
use deform_integrator::benchmark::{beam, beam_free_coordinates, beam_system};
use deform_integrator::{
    Constraint, Integrator, IntegratorOptions, Motion, OnStep, PolicySpec, RunOptions, State,
    StepReport,
};
use deform_materials::{Model, StableNeoHookean};
use deform_mesh::io::{MshFormat, MshVersion, write_msh};
use deform_solvers::{Precision, SolverSpec};

/// Which measurement.
#[derive(Debug, Subcommand)]
pub enum BenchTask {
    /// Energy + forces + K of the beam (median of `--repeats`).
    Assembly(AssemblyArgs),
    /// The Backward-Euler system of the beam: direct and iterative solves; optionally export
    /// it as Matrix Market for other solvers.
    Solvers(SolversArgs),
    /// One implicit step from rest (clamped beam under gravity) per solver policy.
    Step(StepArgs),
}

/// `bench assembly`.
#[derive(Debug, Args)]
pub struct AssemblyArgs {
    /// Beam size parameter (n = 16: 98,304 tets).
    #[arg(long, default_value_t = 16)]
    pub n: usize,
    /// `NeoHookean` or `StableNeoHookean`.
    #[arg(long, default_value = "NeoHookean")]
    pub model: String,
    /// Repetitions (the median is reported).
    #[arg(long, default_value_t = 10)]
    pub repeats: usize,
    /// Also write the beam as Gmsh 4.1 (for peers that read meshes).
    #[arg(long)]
    pub export_mesh: Option<PathBuf>,
}

/// `bench solvers`.
#[derive(Debug, Args)]
pub struct SolversArgs {
    /// Beam size parameter (n = 16: 55,488 free DOFs).
    #[arg(long, default_value_t = 16)]
    pub n: usize,
    /// Write the matrix here (Matrix Market, general real, full storage).
    #[arg(long)]
    pub export: Option<PathBuf>,
    /// Repetitions (medians are reported).
    #[arg(long, default_value_t = 3)]
    pub repeats: usize,
    /// Skip the direct solver (its factor needs several GB at n = 32).
    #[arg(long)]
    pub no_direct: bool,
}

/// `bench step`.
#[derive(Debug, Args)]
pub struct StepArgs {
    /// Beam size parameter (n = 8: 12,288 tets; n = 16: 98,304 tets).
    #[arg(long, default_value_t = 8)]
    pub n: usize,
    /// Time steps per policy.
    #[arg(long, default_value_t = 1)]
    pub steps: usize,
}

pub fn run(task: BenchTask) -> Result<()> {
    match task {
        BenchTask::Assembly(a) => assembly(a),
        BenchTask::Solvers(s) => solvers(s),
        BenchTask::Step(s) => step(s),
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn time<T>(f: impl FnOnce() -> T) -> (T, f64) {
    let t = Instant::now();
    let out = f();
    (out, t.elapsed().as_secs_f64())
}

fn assembly(args: AssemblyArgs) -> Result<()> {
    let (mesh, nh, x) = beam(args.n);
    let material = match args.model.as_str() {
        "NeoHookean" => nh,
        "StableNeoHookean" => {
            let MaterialField::Uniform(Model::NeoHookean(m)) = nh else {
                unreachable!("the benchmark material is Neo-Hookean")
            };
            // The same Lame pair as the peer's (pbatoolkit passes E and nu's Lame pair).
            MaterialField::Uniform(Model::StableNeoHookean(StableNeoHookean { lame: m.lame }))
        }
        other => bail!("--model {other}: expected NeoHookean or StableNeoHookean"),
    };
    if let Some(path) = &args.export_mesh {
        write_msh(
            path,
            &mesh,
            MshFormat {
                version: MshVersion::V4_1,
                binary: true,
            },
        )
        .with_context(|| format!("writing {}", path.display()))?;
    }
    let mut asm = Assembly::new(&mesh, material)?;
    let mut k = asm.stiffness_matrix();
    let mut f = vec![0.0; x.len()];
    let mut samples = Vec::new();
    for _ in 0..args.repeats.max(1) {
        let (r, s) = time(|| {
            let mut e = 0.0;
            asm.evaluate(
                &x,
                Outputs {
                    energy: Some(&mut e),
                    forces: Some(&mut f),
                    stiffness: Some(&mut k),
                    tangent: Tangent::Exact,
                },
            )
        });
        r?;
        samples.push(s);
    }
    let s = median(samples);
    println!(
        r#"{{"what": "assembly", "impl": "deform", "model": "{}", "tets": {}, "threads": {}, "seconds": {s:.6}, "tets_per_second": {:.0}}}"#,
        args.model,
        mesh.num_tets(),
        rayon::current_num_threads(),
        mesh.num_tets() as f64 / s
    );
    Ok(())
}

fn solvers(args: SolversArgs) -> Result<()> {
    let a = beam_system(args.n);
    if let Some(path) = &args.export {
        write_atomic(path, |w| {
            let mut w = std::io::BufWriter::new(w);
            sprs::io::write_matrix_market_to_bufwrite(&mut w, &a)?;
            std::io::Write::flush(&mut w)
        })
        .with_context(|| format!("writing {}", path.display()))?;
    }
    let dofs = a.rows();
    let b: Vec<f64> = (0..dofs).map(|i| ((i % 7) as f64 - 3.0) * 1e-3).collect();
    let report = |name: &str, fields: String| {
        println!(
            r#"{{"what": "solvers", "impl": "deform", "solver": "{name}", "dofs": {dofs}, {fields}}}"#
        );
    };
    // The free vertices' rest positions: geometric nested dissection, as in the integrator;
    // `_graph` variants order from the matrix alone (what PARDISO gets).
    let coordinates = beam_free_coordinates(args.n);
    for (name, parallel, precision, geometry) in [
        ("direct_graph", true, Precision::Double, false),
        ("direct_one_thread", false, Precision::Double, true),
        ("direct", true, Precision::Double, true),
        ("direct_mixed_graph", true, Precision::Mixed, false),
        ("direct_mixed", true, Precision::Mixed, true),
        ("direct_mixed_one_thread", false, Precision::Mixed, true),
    ] {
        if args.no_direct {
            break;
        }
        let (mut analyze, mut factor, mut solve) = (Vec::new(), Vec::new(), Vec::new());
        let (mut nnz, mut residual, mut steps) = (0, f64::NAN, 0);
        for _ in 0..args.repeats.max(1) {
            let spec = SolverSpec::Direct {
                ordering: Default::default(),
                indefinite: Default::default(),
                parallel,
                precision,
            };
            let mut s = spec.build()?;
            if geometry {
                s.set_coordinates(Some(&coordinates));
            }
            analyze.push(time(|| s.analyze(&a)).1);
            let (setup, t) = time(|| s.factorize(&a));
            nnz = setup?.factor_nnz;
            factor.push(t);
            let mut x = vec![0.0; dofs];
            let (r, t) = time(|| s.solve(&a, &b, &mut x));
            let stats = r?;
            residual = stats.relative_residual();
            steps = stats.iterations;
            solve.push(t);
        }
        let (an, fa, so) = (median(analyze), median(factor), median(solve));
        report(
            name,
            format!(
                r#""analyze": {an:.4}, "factorize": {fa:.4}, "solve": {so:.4}, "total": {:.4}, "factor_nnz": {nnz}, "relative_residual": {residual:.3e}, "refinement_steps": {steps}"#,
                an + fa + so
            ),
        );
    }
    for (name, spec) in [
        (
            "cg_1e-6",
            "Cg(tolerance: (rel: 1e-6, max_iterations: 100000))",
        ),
        (
            "pcg_jacobi_1e-6",
            "Pcg(preconditioner: Jacobi, tolerance: (rel: 1e-6, max_iterations: 100000))",
        ),
        (
            "pcg_jacobi_1e-8",
            "Pcg(preconditioner: Jacobi, tolerance: (rel: 1e-8, max_iterations: 100000))",
        ),
        (
            "pcg_ic0_1e-6",
            "Pcg(preconditioner: Ic0, tolerance: (rel: 1e-6, max_iterations: 100000))",
        ),
    ] {
        let mut times = Vec::new();
        let mut iterations = 0;
        for _ in 0..args.repeats.max(1) {
            let mut s = ron::from_str::<SolverSpec>(spec)?.build()?;
            let mut x = vec![0.0; dofs];
            let (r, t) = time(|| -> Result<usize> {
                s.factorize(&a)?;
                Ok(s.solve(&a, &b, &mut x)?.iterations)
            });
            iterations = r?;
            times.push(t);
        }
        let t = median(times);
        report(
            name,
            format!(
                r#""iterations": {iterations}, "seconds": {t:.4}, "seconds_per_iteration": {:.3e}"#,
                t / iterations.max(1) as f64
            ),
        );
    }
    Ok(())
}

fn step(args: StepArgs) -> Result<()> {
    let (mesh, material, _) = beam(args.n);
    let clamp: Vec<usize> = (0..mesh.num_vertices())
        .filter(|&v| mesh.rest_positions()[v].x == 0.0)
        .collect();
    for (name, policy) in [
        ("direct", "Fixed(Direct())"),
        ("direct_one_thread", "Fixed(Direct(parallel: false))"),
        ("direct_mixed", "Fixed(Direct(precision: Mixed))"),
        (
            // Factorise once (PCG with a fresh factor converges in one iteration), then reuse
            // the stale factor in later Newton iterations and steps.
            "stale_cholesky_pcg",
            "Fixed(Pcg(preconditioner: StaleCholesky(max_age: 20), tolerance: (rel: 1e-8)))",
        ),
        (
            // The same with the factor in single precision.
            "stale_cholesky_pcg_mixed",
            "Fixed(Pcg(preconditioner: StaleCholesky(max_age: 20, precision: Mixed), tolerance: (rel: 1e-8)))",
        ),
        (
            // The hand schedule: refactorise after a solve needing more than 20 iterations.
            "stale_factor_20",
            "StaleFactor(solver: Pcg(preconditioner: StaleCholesky(max_age: 1000), tolerance: (rel: 1e-8)), refactor_above: 20)",
        ),
        (
            "pcg_ic0",
            "Fixed(Pcg(preconditioner: Ic0, tolerance: (rel: 1e-8)))",
        ),
        (
            "eisenstat_walker_ic0",
            "EisenstatWalker(solver: Pcg(preconditioner: Ic0, tolerance: (rel: 1e-8)))",
        ),
        (
            "pcg_jacobi",
            "Fixed(Pcg(preconditioner: Jacobi, tolerance: (rel: 1e-8)))",
        ),
    ] {
        let policy = ron::from_str::<PolicySpec>(policy)?
            .build()
            .map_err(anyhow::Error::msg)?;
        let mut sim = Integrator::builder(&mesh, material.clone())
            .density(1000.0)
            .constraints(vec![Constraint {
                vertices: clamp.clone(),
                motion: Motion::Fixed,
            }])
            .options(IntegratorOptions::default())
            .policy(policy)
            .build()?;
        let mut state = sim.rest_state();
        let mut last = Instant::now();
        let run = sim.run(
            &mut state,
            &RunOptions::steps(args.steps),
            &mut OnStep(|report: &StepReport, _: &State| {
                // Wall time of the whole step as the caller sees it (the report's own excludes
                // nothing but the call).
                let seconds = last.elapsed().as_secs_f64();
                let solve = report.solver_seconds();
                let setup: u64 = report.iterations.iter().map(|i| i.setup.flops).sum();
                println!(
                    r#"{{"what": "step", "impl": "deform", "policy": "{name}", "step": {}, "tets": {}, "seconds": {seconds:.3}, "newton": {}, "linear": {}, "solve_seconds": {solve:.3}, "other_seconds": {:.3}, "flops": {}, "setup_flops": {setup}}}"#,
                    report.step,
                    mesh.num_tets(),
                    report.newton_iterations(),
                    report.linear_iterations(),
                    seconds - solve,
                    report.flops()
                );
                last = Instant::now();
            }),
        );
        run.into_result()?;
    }
    Ok(())
}
