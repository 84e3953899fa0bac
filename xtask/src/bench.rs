//! `cargo xtask bench ...`: quick, scriptable measurements on the beam family of
//! `docs/benchmarks.md`, printed as one JSON object per line so `bench/peers/*.py` can put
//! them beside the peers measured in the same run. (The criterion benches of each crate are
//! the detailed, statistically careful version.)

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use deform_fs::write_atomic;
use deform_integrator::benchmark::{
    AssemblyOutputs, ITERATIVE_SOLVERS, STEP_POLICIES, beam, beam_free_coordinates,
    beam_integrator, beam_integrator_with, beam_system, time_assembly, time_direct, time_iterative,
};
use deform_integrator::{MaterialField, Model, State};
use deform_materials::StableNeoHookean;
use deform_mesh::io::{MshFormat, MshVersion, write_msh};

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
    /// The coarsening study's fits: a fine beam's trajectories carried onto a coarser beam,
    /// then the homogeneous, per-region and per-element fits (fit time per model).
    Coarsen(CoarsenArgs),
    /// Each stage of the assembly, the solvers and a Backward-Euler step at 1, 2, ...
    /// threads: times, speed-ups and the serial fraction they imply (Amdahl).
    Scaling(ScalingArgs),
}

/// `bench scaling`.
#[derive(Debug, Args)]
pub struct ScalingArgs {
    /// Beam size parameter (n = 16: 98,304 tets; n = 32: 786,432).
    #[arg(long, default_value_t = 16)]
    pub n: usize,
    /// Thread counts (comma-separated; 1 up to the machine's threads by default).
    #[arg(long, value_delimiter = ',')]
    pub threads: Vec<usize>,
    /// Rounds: each times every stage once at every thread count, alternating the order of
    /// the counts (medians over rounds are reported).
    #[arg(long, default_value_t = 3)]
    pub repeats: usize,
    /// Only these stages (comma-separated names, e.g. `assembly_all,factorize`); all by
    /// default.
    #[arg(long, value_delimiter = ',')]
    pub stages: Vec<String>,
    /// The thread count the serial fractions predict the speed-up for.
    #[arg(long, default_value_t = 16)]
    pub predict: usize,
}

/// `bench coarsen`.
#[derive(Debug, Args)]
pub struct CoarsenArgs {
    /// The fine beam (n = 8: 12,288 tets).
    #[arg(long, default_value_t = 8)]
    pub fine: usize,
    /// The coarse beam (n = 4: 1,536 tets).
    #[arg(long, default_value_t = 4)]
    pub coarse: usize,
    /// Training trajectories (one more is made for validation).
    #[arg(long, default_value_t = 3)]
    pub trajectories: usize,
    /// Steps per trajectory.
    #[arg(long, default_value_t = 100)]
    pub steps: usize,
    /// Steps per rollout of the fits.
    #[arg(long, default_value_t = 25)]
    pub rollout: usize,
    /// The per-element regularisation weights (comma-separated; fitted concurrently).
    #[arg(long, value_delimiter = ',', default_value = "0")]
    pub weights: Vec<f64>,
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
    /// Also time the energy alone, energy + forces and K alone (what the Newton loop asks
    /// for in its stages).
    #[arg(long)]
    pub outputs: bool,
    /// Elements per block of the assembly (its default when not given).
    #[arg(long)]
    pub block_elements: Option<usize>,
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
    /// Write the free vertices' rest positions here (`.npy`, one row per 3 matrix rows), for
    /// peers' rigid-body modes.
    #[arg(long)]
    pub export_coordinates: Option<PathBuf>,
    /// Repetitions (medians are reported).
    #[arg(long, default_value_t = 3)]
    pub repeats: usize,
    /// Skip the direct solver (its factor needs several GB at n = 32).
    #[arg(long)]
    pub no_direct: bool,
    /// Only these iterative solvers (comma-separated names, e.g. `pcg_ic0_1e-6,pcg_amg_1e-6`);
    /// all by default.
    #[arg(long, value_delimiter = ',')]
    pub solvers: Vec<String>,
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
    /// Only these policies (comma-separated names, e.g. `pcg_amg,pcg_ic0`); all by default.
    #[arg(long, value_delimiter = ',')]
    pub policies: Vec<String>,
    /// Also run each policy with a ground plane this far (m) below the beam, which its tip
    /// reaches as it sags, and compare the cost of a step with contact to one without.
    #[arg(long)]
    pub ground: Option<f64>,
}

pub fn run(task: BenchTask) -> Result<()> {
    match task {
        BenchTask::Assembly(a) => assembly(a),
        BenchTask::Solvers(s) => solvers(s),
        BenchTask::Step(s) => step(s),
        BenchTask::Coarsen(c) => coarsen(c),
        BenchTask::Scaling(s) => scaling(s),
    }
}

/// Times the coarse fits ([`deform_studies::coarsen::bench::bench_coarse_fits`]) and prints
/// a JSON line per fitted model, then the totals.
fn coarsen(args: CoarsenArgs) -> Result<()> {
    use deform_studies::coarsen::bench::{CoarsenBench, bench_coarse_fits};
    let mut bench = CoarsenBench::default();
    (bench.fine, bench.coarse) = (args.fine, args.coarse);
    (bench.trajectories, bench.steps) = (args.trajectories, args.steps);
    (bench.rollout, bench.weights) = (args.rollout, args.weights.clone());
    let t = bench_coarse_fits(&bench)?;
    let fitted = t.fits.models.iter();
    for (model, fit) in fitted.filter_map(|m| Some((m.model, m.fit.as_ref()?))) {
        println!(
            r#"{{"what": "coarsen", "model": "{}", "fine_tets": {}, "coarse_tets": {}, "trajectories": {}, "steps": {}, "rollout": {}, "coefficients": {}, "evaluations": {}, "fit_seconds": {:.1}, "termination": "{}"}}"#,
            model.name(),
            deform_mesh::generate::BoxGrid::beam(args.fine).num_tets(),
            t.coarse_tets,
            args.trajectories,
            args.steps,
            args.rollout,
            fit.coefficients,
            fit.evaluations,
            fit.seconds,
            fit.termination.describe()
        );
    }
    println!(
        r#"{{"what": "coarsen", "model": "all", "generate_seconds": {:.1}, "fit_seconds": {:.1}}}"#,
        t.generate_seconds, t.fit_seconds
    );
    Ok(())
}

fn assembly(args: AssemblyArgs) -> Result<()> {
    let (mesh, nh, _) = beam(args.n);
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
        let format = MshFormat {
            version: MshVersion::V4_1,
            binary: true,
        };
        write_msh(path, &mesh, format).with_context(|| format!("writing {}", path.display()))?;
    }
    // Energy + forces + K (the peers' figure) first; with `--outputs` also each part the
    // Newton loop asks for alone.
    let kinds: &[AssemblyOutputs] = if args.outputs {
        &AssemblyOutputs::ALL
    } else {
        &[AssemblyOutputs::All]
    };
    for &outputs in kinds {
        let s = time_assembly(
            args.n,
            material.clone(),
            outputs,
            args.block_elements,
            args.repeats,
        )?;
        println!(
            r#"{{"what": "assembly", "impl": "deform", "model": "{}", "outputs": "{}", "tets": {}, "threads": {}, "seconds": {s:.6}, "tets_per_second": {:.0}}}"#,
            args.model,
            outputs.name(),
            mesh.num_tets(),
            rayon::current_num_threads(),
            mesh.num_tets() as f64 / s
        );
    }
    Ok(())
}

/// The entries of `all` named in `names` (all of them when `names` is empty), in `all`'s
/// order; an unknown name is an error listing the known ones.
fn chosen<'a>(
    all: &[(&'static str, &'a str)],
    names: &[String],
    option: &str,
) -> Result<Vec<(&'static str, &'a str)>> {
    if let Some(unknown) = names
        .iter()
        .find(|p| !all.iter().any(|(name, _)| name == p))
    {
        let known: Vec<&str> = all.iter().map(|(name, _)| *name).collect();
        bail!(
            "{option}: unknown name {unknown:?}; expected some of {}",
            known.join(", ")
        );
    }
    Ok(all
        .iter()
        .filter(|(name, _)| names.is_empty() || names.iter().any(|n| n == name))
        .copied()
        .collect())
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
    // The free vertices' rest positions: geometric nested dissection as in the integrator
    // (`_graph` rows order from the matrix alone, what PARDISO gets) and AMG's rigid modes.
    let coordinates = beam_free_coordinates(args.n);
    if let Some(path) = &args.export_coordinates {
        let flat: Vec<f64> = coordinates.iter().flatten().copied().collect();
        deform_fs::npy::write(path, &[coordinates.len(), 3], &flat)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    if !args.no_direct {
        for t in time_direct(&a, &b, &coordinates, args.repeats)? {
            report(
                t.name,
                format!(
                    r#""analyze": {:.4}, "factorize": {:.4}, "solve": {:.4}, "total": {:.4}, "factor_nnz": {}, "relative_residual": {:.3e}, "refinement_steps": {}"#,
                    t.analyze,
                    t.factorize,
                    t.solve,
                    t.analyze + t.factorize + t.solve,
                    t.factor_nnz,
                    t.relative_residual,
                    t.refinement_steps
                ),
            );
        }
    }
    let iterative = chosen(&ITERATIVE_SOLVERS, &args.solvers, "--solvers")?;
    for t in time_iterative(&a, &b, &coordinates, &iterative, args.repeats)? {
        report(
            t.name,
            format!(
                r#""iterations": {}, "setup": {:.4}, "seconds": {:.4}, "rounds": [{}], "seconds_per_iteration": {:.3e}, "setup_flops": {}, "solve_flops": {}, "sweep_flops": {}"#,
                t.iterations,
                t.setup,
                t.seconds,
                t.rounds
                    .iter()
                    .map(|s| format!("{s:.4}"))
                    .collect::<Vec<_>>()
                    .join(", "),
                (t.seconds - t.setup) / t.iterations.max(1) as f64,
                t.setup_flops,
                t.solve_flops,
                t.sweep_flops
            ),
        );
    }
    Ok(())
}

fn step(args: StepArgs) -> Result<()> {
    for (name, policy) in chosen(&STEP_POLICIES, &args.policies, "--policies")? {
        let (sim, state) = beam_integrator(args.n, policy)?;
        let mut free = Timed::new(sim, state, name);
        let Some(gap) = args.ground else {
            for _ in 0..args.steps {
                free.step()?;
            }
            continue;
        };
        let ground = deform_integrator::ContactSpec::default().obstacles(vec![
            deform_integrator::Obstacle::Plane {
                point: [0.0, 0.0, -gap],
                normal: [0.0, 0.0, 1.0],
            },
        ]);
        let (sim, state) = beam_integrator_with(args.n, policy, Some(ground))?;
        let surface = sim.contact().map_or(0, |c| c.vertices().len());
        let mut touching = Timed::new(sim, state, name);
        // The two runs take their steps in turn, each step's pair in alternating order, so
        // that both see the machine as it is then: this VM's speed drifts by tens of per
        // cent over a minute, which timed one run after the other moved the ratio alone.
        let mut pairs = Vec::new();
        for k in 0..args.steps {
            let (with, without) = if k % 2 == 0 {
                let without = free.step()?;
                (touching.step()?, without)
            } else {
                let with = touching.step()?;
                (with, free.step()?)
            };
            pairs.push((with, without));
        }
        // The same step with and without the ground, where the ground touches fewer than
        // 5 % of the surface vertices (and at all).
        let few = |active: usize| active > 0 && (active as f64) < 0.05 * surface as f64;
        let ratios: Vec<(f64, f64)> = pairs
            .iter()
            .filter(|(with, _)| few(with.contacts))
            .map(|(with, without)| {
                (
                    with.seconds / without.seconds,
                    with.per_iteration() / without.per_iteration(),
                )
            })
            .collect();
        let median = |mut x: Vec<f64>| {
            x.sort_by(f64::total_cmp);
            x.get(x.len() / 2).copied().unwrap_or(f64::NAN)
        };
        let most = pairs.iter().map(|p| p.0.contacts).max().unwrap_or(0);
        let step_ratio = median(ratios.iter().map(|p| p.0).collect());
        let newton_ratio = median(ratios.iter().map(|p| p.1).collect());
        println!(
            r#"{{"what": "contact_step", "policy": "{name}", "steps": {}, "steps_touching_under_5_percent": {}, "most_in_contact": {most}, "surface_vertices": {surface}, "median_step_ratio": {step_ratio:.2}, "median_newton_iteration_ratio": {newton_ratio:.2}}}"#,
            args.steps,
            ratios.len(),
        );
    }
    Ok(())
}

/// One step's wall time, Newton iterations and active contact pairs.
#[derive(Debug, Clone, Copy)]
struct StepTiming {
    seconds: f64,
    newton: usize,
    contacts: usize,
}

impl StepTiming {
    fn per_iteration(&self) -> f64 {
        self.seconds / self.newton.max(1) as f64
    }
}

/// A simulation whose steps are timed one at a time, each printed as a JSON line.
struct Timed {
    sim: deform_integrator::Integrator,
    state: State,
    name: String,
}

impl Timed {
    fn new(sim: deform_integrator::Integrator, state: State, name: &str) -> Self {
        Self {
            sim,
            state,
            name: name.to_owned(),
        }
    }

    /// Takes one step, printing its JSON line.
    fn step(&mut self) -> Result<StepTiming> {
        let started = Instant::now();
        let report = self.sim.step(&mut self.state)?;
        // Wall time of the whole step as the caller sees it.
        let seconds = started.elapsed().as_secs_f64();
        let tets = self.sim.assembly().num_elements();
        let solve = report.solver_seconds();
        let setup: u64 = report.iterations.iter().map(|i| i.setup.flops).sum();
        // The process's peak so far (it includes earlier policies' runs).
        let peak = deform_mesh::memory::peak_rss_bytes().map_or(-1.0, |b| b as f64 / 1e6);
        // The Newton iterations' stages: assembly and residual, the Newton matrix (with K
        // when the residual came from the line search), the line search. The final
        // convergence check is no iteration: it is in `other_seconds` only.
        let stage = |f: fn(&deform_integrator::StageSeconds) -> f64| -> f64 {
            report.iterations.iter().map(|i| f(&i.stages)).sum()
        };
        let contacts = report.contact.map_or(0, |c| c.active);
        println!(
            r#"{{"what": "step", "impl": "deform", "policy": "{}", "step": {}, "tets": {tets}, "seconds": {seconds:.3}, "newton": {}, "linear": {}, "solve_seconds": {solve:.3}, "other_seconds": {:.3}, "residual_seconds": {:.3}, "matrix_seconds": {:.3}, "line_search_seconds": {:.3}, "flops": {}, "setup_flops": {setup}, "peak_rss_mb": {peak:.1}, "contacts": {contacts}}}"#,
            self.name,
            report.step,
            report.newton_iterations(),
            report.linear_iterations(),
            seconds - solve,
            stage(|s| s.residual),
            stage(|s| s.matrix),
            stage(|s| s.line_search),
            report.flops()
        );
        Ok(StepTiming {
            seconds,
            newton: report.newton_iterations(),
            contacts,
        })
    }
}

/// Times every stage in a pool of each thread count (JSON lines as they come), then a table
/// of speed-ups against one thread and the serial fraction fitted to them.
fn scaling(args: ScalingArgs) -> Result<()> {
    use deform_integrator::benchmark::{
        ScalingStage, amdahl_speedup, median, serial_fraction, time_stages,
    };
    let stages: Vec<ScalingStage> = if args.stages.is_empty() {
        ScalingStage::ALL.to_vec()
    } else {
        let known: Vec<&str> = ScalingStage::ALL.iter().map(|s| s.name()).collect();
        (args.stages.iter())
            .map(|name| {
                ScalingStage::from_name(name).with_context(|| {
                    format!(
                        "--stages: unknown stage {name:?}; expected some of {}",
                        known.join(", ")
                    )
                })
            })
            .collect::<Result<_>>()?
    };
    let available = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut threads = if args.threads.is_empty() {
        (1..=available).collect()
    } else {
        args.threads.clone()
    };
    threads.sort_unstable();
    threads.dedup();
    if threads.first() != Some(&1) {
        bail!("--threads must include 1: speed-ups are against one thread");
    }
    let tets = beam(args.n).0.num_tets();
    // samples[stage][k]: seconds at threads[k], one per round. Each round times every stage
    // once at every thread count, in ascending then descending order of threads, so that a
    // machine that slows down or speeds up during the run (a neighbour on a shared VM) moves
    // every count's times alike instead of the last count's.
    let mut samples = vec![vec![Vec::new(); threads.len()]; stages.len()];
    for round in 0..args.repeats.max(1) {
        let order: Vec<usize> = match round % 2 {
            0 => (0..threads.len()).collect(),
            _ => (0..threads.len()).rev().collect(),
        };
        for k in order {
            let p = threads[k];
            let pool = rayon::ThreadPoolBuilder::new().num_threads(p).build()?;
            let measured = pool.install(|| time_stages(args.n, &stages, 1))?;
            for (s, (stage, seconds)) in measured.into_iter().enumerate() {
                println!(
                    r#"{{"what": "scaling", "stage": "{}", "n": {}, "tets": {tets}, "threads": {p}, "round": {round}, "seconds": {seconds:.6}}}"#,
                    stage.name(),
                    args.n,
                );
                samples[s][k].push(seconds);
            }
        }
    }
    // times[stage][k]: the median at threads[k].
    let times: Vec<Vec<f64>> = (samples.into_iter())
        .map(|per| per.into_iter().map(median).collect())
        .collect();
    let last = *threads.last().expect("at least one count");
    println!(
        "\n| stage | 1 thread (s) | {last} threads (s) | speed-up | serial fraction | predicted on {} |",
        args.predict
    );
    println!("|---|---|---|---|---|---|");
    for (stage, t) in stages.iter().zip(&times) {
        let pairs: Vec<(usize, f64)> = threads.iter().copied().zip(t.iter().copied()).collect();
        let f = serial_fraction(&pairs);
        println!(
            "| {} | {:.4} | {:.4} | {:.2}x | {} | {} |",
            stage.name(),
            t[0],
            t[t.len() - 1],
            t[0] / t[t.len() - 1],
            f.map_or("-".into(), |f| format!("{f:.3}")),
            f.map_or("-".into(), |f| format!(
                "{:.1}x",
                amdahl_speedup(f, args.predict)
            )),
        );
    }
    Ok(())
}
