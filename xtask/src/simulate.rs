//! `cargo xtask simulate SCENE.ron [--steps N] [--out DIR]`: runs a scene with
//! `deform_integrator::simulate` behind a progress bar; it writes `.vtu` frames, a `.pvd`
//! series, a per-step CSV and a summary.

use std::ops::ControlFlow;
use std::path::{Path, PathBuf};

use anyhow::Result;
use clap::Args;
use deform_integrator::{Observer, Simulation, State, StepReport};
use indicatif::ProgressBar;

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

pub fn run(args: SimulateArgs) -> Result<()> {
    let sim = simulate(&args.scene, args.steps, args.out.as_deref(), args.quiet)?;
    let (r, p) = (&sim.run, sim.tracked.1);
    println!(
        "{} steps, {} Newton iterations, {} linear iterations, {:.2} s; tracked vertex at ({:.5}, {:.5}, {:.5})",
        r.steps, r.newton_iterations, r.linear_iterations, r.step_seconds, p[0], p[1], p[2]
    );
    println!("frames: {}", sim.out.join("series.pvd").display());
    Ok(())
}

/// Runs `scene_path` with a progress bar (hidden when `quiet`).
pub fn simulate(
    scene_path: &Path,
    steps: Option<usize>,
    out: Option<&Path>,
    quiet: bool,
) -> Result<Simulation> {
    let total = match steps {
        Some(n) => n,
        None => deform_integrator::Scene::load(scene_path)?.steps,
    };
    let bar = crate::experiment::bar(quiet, total as u64, "steps");
    let mut lines = crate::experiment::Lines::new(quiet);
    lines.tick("steps", &bar, true);
    let result = deform_integrator::simulate(scene_path, steps, out, &mut Bar(&bar, &mut lines));
    lines.tick("steps", &bar, true);
    bar.finish_and_clear();
    Ok(result?)
}

/// The progress bar as an observer.
struct Bar<'a>(&'a ProgressBar, &'a mut crate::experiment::Lines);

impl Observer for Bar<'_> {
    fn step(&mut self, report: &StepReport, state: &State) -> ControlFlow<()> {
        self.0.set_message(format!(
            "t={:.3}s newton={} linear={} {:.0} ms/step",
            state.t,
            report.newton_iterations(),
            report.linear_iterations(),
            1e3 * report.seconds
        ));
        self.0.inc(1);
        self.1.tick("steps", self.0, false);
        ControlFlow::Continue(())
    }
}
