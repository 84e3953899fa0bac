//! `cargo xtask simulate SCENE.ron [--steps N] [--out DIR]`: runs a scene with a progress
//! bar and writes `.vtu` frames, a `.pvd` series, a per-step CSV and a summary.

use std::fmt::Write as _;
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use deform_fs::write_atomic;
use deform_integrator::{Observer, RunOptions, Scene, State, StepReport};
use deform_mesh::io::{Pvd, Vtu};
use indicatif::{ProgressBar, ProgressStyle};

/// Arguments of `simulate`.
#[derive(Debug, Args)]
pub struct SimulateArgs {
    /// The scene file (RON).
    pub scene: PathBuf,
    /// Override the number of steps.
    #[arg(long)]
    pub steps: Option<usize>,
    /// Output directory (default `target/deform/simulate/<scene name>`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// No progress bar (for scripts and CI logs).
    #[arg(long)]
    pub quiet: bool,
}

/// What a run produced, for the summary and for callers such as the demo.
#[derive(Debug, Clone)]
pub struct RunSummary {
    /// Output directory.
    pub out: PathBuf,
    /// Steps taken.
    pub steps: usize,
    /// Newton iterations in total.
    pub newton: usize,
    /// Linear iterations in total.
    pub linear: usize,
    /// Wall time of the steps, seconds.
    pub seconds: f64,
    /// Final position of the tracked vertex.
    pub tracked: [f64; 3],
}

pub fn run(args: SimulateArgs) -> Result<()> {
    let summary = simulate(&args.scene, args.steps, args.out.as_deref(), args.quiet)?;
    println!(
        "{} steps, {} Newton iterations, {} linear iterations, {:.2} s; tracked vertex at ({:.5}, {:.5}, {:.5})",
        summary.steps,
        summary.newton,
        summary.linear,
        summary.seconds,
        summary.tracked[0],
        summary.tracked[1],
        summary.tracked[2]
    );
    println!("frames: {}", summary.out.join("series.pvd").display());
    Ok(())
}

/// Runs `scene_path`; see the module docs.
pub fn simulate(
    scene_path: &Path,
    steps: Option<usize>,
    out: Option<&Path>,
    quiet: bool,
) -> Result<RunSummary> {
    let scene = Scene::load(scene_path)?;
    let built = scene.build(scene_path)?;
    let (mesh, mut sim, mut state) = (built.mesh, built.integrator, built.state);
    let steps = steps.unwrap_or(scene.steps);
    let out = out.map_or_else(
        || Path::new("target/deform/simulate").join(&scene.name),
        Path::to_path_buf,
    );
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let tracked = scene.tracked_vertex(&mesh);
    let mut pvd = Pvd::new(out.join("series.pvd"));
    let write_frame = |pvd: &mut Pvd, index: usize, x: &[f64], v: &[f64], t: f64| -> Result<()> {
        if scene.output.every == 0 {
            return Ok(());
        }
        let file = out.join(format!("frame_{index:05}.vtu"));
        Vtu::deformed(&mesh, x)
            .point_vectors("velocity", v)
            .write(&file)?;
        pvd.push(t, &file)?;
        Ok(())
    };
    write_frame(&mut pvd, 0, &state.x, &state.v, state.t)?;

    let bar = if quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(steps as u64)
    };
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} {bar:30} {pos}/{len} steps  {msg}  [{elapsed_precise}, eta {eta}]",
        )
        .expect("a valid template"),
    );
    let mut log = StepLog {
        csv: String::from(
            "step,t,dt,newton_iterations,linear_iterations,initial_residual,final_residual,elastic_energy,kinetic_energy,flops,seconds,retries,tracked_x,tracked_y,tracked_z\n",
        ),
        masses: sim.assembly().vertex_masses(sim.mass()),
        tracked,
        bar: &bar,
        frame: &mut |step: usize, state: &State| {
            if scene.output.every > 0 && step.is_multiple_of(scene.output.every) {
                write_frame(&mut pvd, step, &state.x, &state.v, state.t)?;
            }
            Ok(())
        },
        error: None,
    };
    let started = Instant::now();
    let run = sim.run(&mut state, &RunOptions::steps(steps), &mut log);
    if let Some(e) = log.error {
        return Err(e);
    }
    let run = run.into_result().with_context(|| {
        format!(
            "{}: step (t = {:.4} s) failed",
            scene_path.display(),
            state.t
        )
    })?;
    let csv = log.csv;
    let (newton, linear, seconds) = (
        run.newton_iterations,
        run.linear_iterations,
        run.step_seconds,
    );
    bar.finish_and_clear();
    write_atomic(&out.join("steps.csv"), |w| w.write_all(csv.as_bytes()))?;
    let summary = RunSummary {
        out: out.clone(),
        steps,
        newton,
        linear,
        seconds,
        tracked: [
            state.x[3 * tracked],
            state.x[3 * tracked + 1],
            state.x[3 * tracked + 2],
        ],
    };
    let text = format!(
        "scene: {}\nmesh: {} vertices, {} tets, {} free DOFs\npolicy: {}\nsteps: {steps} (dt = {} s, t = {:.4} s)\nNewton iterations: {newton} ({:.2} per step)\nlinear iterations: {linear}\nwall time: {:.3} s of steps, {:.3} s total\ntracked vertex {tracked}: ({:.6}, {:.6}, {:.6})\n",
        scene.name,
        mesh.num_vertices(),
        mesh.num_tets(),
        sim.dofs().num_free(),
        sim.policy().name(),
        scene.integrator.dt,
        state.t,
        newton as f64 / steps as f64,
        seconds,
        started.elapsed().as_secs_f64(),
        summary.tracked[0],
        summary.tracked[1],
        summary.tracked[2],
    );
    write_atomic(&out.join("summary.txt"), |w| w.write_all(text.as_bytes()))?;
    Ok(summary)
}

/// Writes `steps.csv` rows and frames and moves the bar, step by step.
struct StepLog<'a> {
    csv: String,
    masses: Vec<f64>,
    tracked: usize,
    bar: &'a ProgressBar,
    frame: &'a mut dyn FnMut(usize, &State) -> Result<()>,
    error: Option<anyhow::Error>,
}

impl Observer for StepLog<'_> {
    fn step(&mut self, report: &StepReport, state: &State) -> ControlFlow<()> {
        let step = report.step + 1;
        let kinetic: f64 = state
            .v
            .iter()
            .enumerate()
            .map(|(i, v)| 0.5 * self.masses[i / 3] * v * v)
            .sum();
        let tracked = &state.x[3 * self.tracked..3 * self.tracked + 3];
        let _ = writeln!(
            self.csv,
            "{step},{:.6},{:e},{},{},{:e},{:e},{:e},{:e},{},{:.6},{},{:.9},{:.9},{:.9}",
            report.t,
            report.dt,
            report.newton_iterations(),
            report.linear_iterations(),
            report.initial_residual,
            report.final_residual,
            report.energy,
            kinetic,
            report.flops(),
            report.seconds,
            report.retries,
            tracked[0],
            tracked[1],
            tracked[2]
        );
        if let Err(e) = (self.frame)(step, state) {
            self.error = Some(e);
            return ControlFlow::Break(());
        }
        self.bar.set_message(format!(
            "t={:.3}s newton={} linear={} {:.0} ms/step",
            state.t,
            report.newton_iterations(),
            report.linear_iterations(),
            1e3 * report.seconds
        ));
        self.bar.inc(1);
        ControlFlow::Continue(())
    }
}
