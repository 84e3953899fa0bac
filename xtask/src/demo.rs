//! `cargo xtask demo`: the whole idea end to end on the bundled scenes, in a few minutes:
//! simulate the default scene, then the story (a 4x coarser model of the default scene tuned
//! with the base's data — damping, moduli, solver policy, forcing term — against the untuned
//! one on held-out trajectories, with ParaView frames of all three), then each idea on its
//! own (fit a material to noisy data, select an energy model, let a coarser model learn from
//! the base, learn which linear solver runs when, tune a solver's tolerance). Writes `target/deform/demo/report.md` gathering every
//! experiment's report, with each one's folder (CSV, SVG plots, datasets) beside it.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use deform_fs::write_atomic;

use crate::experiment::{self, ExperimentArgs};
use crate::render;
use crate::simulate;

/// Arguments of `demo`.
#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Output folder.
    #[arg(long, default_value = "target/deform/demo")]
    pub out: PathBuf,
    /// No progress bars.
    #[arg(long)]
    pub quiet: bool,
    /// The base scene to simulate first (default: the bundled cantilever).
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Run every experiment file (`*.ron`) of this folder, in name order, instead of the
    /// bundled set.
    #[arg(long)]
    pub experiments: Option<PathBuf>,
}

const EXPERIMENTS: [(&str, &str); 8] = [
    (
        "tune_backward_euler",
        "the story: a 4x coarser Backward Euler tuned with the base's data, against the untuned one",
    ),
    (
        "fit_material",
        "force-model optimisation: E and nu from trajectories with 1 % position noise",
    ),
    (
        "select_model",
        "model selection: which energy made the data",
    ),
    (
        "coarse_dt",
        "accuracy: a 4x coarser time step learns from the base model",
    ),
    (
        "select_solver",
        "solver selection: a learned policy against fixed solvers and Eisenstat-Walker",
    ),
    (
        "tune_solver",
        "solver optimisation: the least-work tolerance that keeps the trajectory",
    ),
    (
        "tune_jacobi",
        "solver optimisation: Jacobi's relaxation and tolerance, jointly",
    ),
    (
        "tune_refactor",
        "solver optimisation: when stale-factor PCG refactorises, and its tolerance",
    ),
];

/// The experiments to run: `(name, description, file)`.
fn experiments(root: &Path, dir: Option<&Path>) -> Result<Vec<(String, String, PathBuf)>> {
    let Some(dir) = dir else {
        return Ok(EXPERIMENTS
            .iter()
            .map(|(name, what)| {
                let file = root.join(format!("assets/experiments/{name}.ron"));
                ((*name).to_owned(), (*what).to_owned(), file)
            })
            .collect());
    };
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))? {
        let path = entry?.path();
        if path.extension().is_none_or(|x| x != "ron") {
            continue;
        }
        // Scenes may sit beside the experiments that name them; anything else must load.
        if let Err(e) = deform_learn::experiment::Experiment::load(&path) {
            if deform_integrator::Scene::load(&path).is_ok() {
                continue;
            }
            return Err(e.into());
        }
        files.push(path);
    }
    files.sort();
    Ok(files
        .into_iter()
        .map(|f| {
            let name = f
                .file_stem()
                .map_or(String::new(), |s| s.to_string_lossy().into_owned());
            (name.clone(), format!("experiment `{name}`"), f)
        })
        .collect())
}

pub fn run(args: DemoArgs) -> Result<()> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let started = Instant::now();
    let mut rows = Vec::new();
    let mut report = String::from(
        "# deform demo\n\nThe base model is a Backward-Euler simulation (Newton, Rayleigh damping) of linear tetrahedra; data are its trajectories. Each section below is one experiment's report; its folder holds the CSV files, SVG plots and the dataset.\n\n",
    );

    let t = Instant::now();
    let scene = args
        .scene
        .clone()
        .unwrap_or_else(|| root.join("assets/scenes/cantilever.ron"));
    let folder = scene
        .file_stem()
        .map_or("base".to_owned(), |s| s.to_string_lossy().into_owned());
    let sim = simulate::simulate(&scene, None, Some(&args.out.join(&folder)), args.quiet)?;
    rows.push((
        format!("simulate {folder}"),
        t.elapsed().as_secs_f64(),
        format!(
            "{} steps, {} Newton iterations; ParaView: {folder}/series.pvd",
            sim.run.steps, sim.run.newton_iterations
        ),
    ));
    writeln!(
        report,
        "## The base model: `{}`\n\n{} steps, {} Newton iterations, {:.2} s; frames in `{folder}/series.pvd` (open in ParaView), per-step data in `{folder}/steps.csv`.\n",
        scene.display(),
        sim.run.steps,
        sim.run.newton_iterations,
        sim.run.step_seconds
    )?;

    for (name, what, file) in experiments(&root, args.experiments.as_deref())? {
        let t = Instant::now();
        let out = args.out.join(&name);
        let (result, text) = experiment::run(ExperimentArgs {
            experiment: file,
            out: Some(out.clone()),
            quiet: args.quiet,
        })?;
        let summary = render::headline(&result);
        // Demote the experiment's title under the demo's.
        writeln!(
            report,
            "## {what}\n\nFolder `{name}/`.\n\n{}",
            text.replacen("# ", "### ", 1)
        )?;
        rows.push((
            name.clone(),
            t.elapsed().as_secs_f64(),
            if summary.is_empty() {
                format!("{name}/report.md")
            } else {
                format!("{summary} ({name}/report.md)")
            },
        ))
    }
    let mut table = String::from("| stage | time | results |\n|---|---|---|\n");
    for (stage, seconds, note) in &rows {
        writeln!(table, "| {stage} | {seconds:.1} s | {note} |")?;
    }
    let text = format!(
        "{report}\n## Summary\n\n{table}\nTotal {:.1} s.\n",
        started.elapsed().as_secs_f64()
    );
    let path = args.out.join("report.md");
    write_atomic(&path, |w| w.write_all(text.as_bytes()))
        .with_context(|| format!("writing {}", path.display()))?;
    println!("\n{table}\nreport: {}", path.display());
    Ok(())
}
