//! `cargo xtask demo`: the whole idea end to end on the bundled scenes, in a few minutes:
//! simulate the default scene, then the story (a coarse model with 8x fewer tets, at the
//! base's step and 4x larger, fitted field by field to the base's trajectories and compared
//! with the untuned one on held-out motions: error, cost per simulated second, the learned
//! model saved as a scene with its field for ParaView), every idea on one cheap model
//! (damping, moduli, energy model and solver policy of a 4x coarser step, with ParaView
//! frames), then each idea on its own (fit a material to noisy data, select an energy model,
//! let a coarser step learn from the base, learn which linear solver runs when, tune a
//! solver's parameters). Writes `target/deform/demo/report.md` gathering every experiment's
//! report, with each one's folder (CSV, SVG plots, datasets) beside it.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use deform_fs::write_atomic;
use serde::Deserialize;

use crate::experiment::{self, ExperimentArgs};
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
    /// What to run (RON: a base scene and experiments; default `assets/demo.ron`).
    #[arg(long)]
    pub demo: Option<PathBuf>,
}

/// A demo file: the base scene and the experiments, each with its introduction.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Demo {
    scene: PathBuf,
    experiments: Vec<DemoExperiment>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct DemoExperiment {
    file: PathBuf,
    about: String,
}

pub fn run(args: DemoArgs) -> Result<()> {
    let file = args.demo.clone().unwrap_or_else(|| {
        deform_fs::join_clean(
            Path::new(env!("CARGO_MANIFEST_DIR")),
            "../assets/demo.ron".as_ref(),
        )
    });
    let text =
        std::fs::read_to_string(&file).with_context(|| format!("reading {}", file.display()))?;
    let demo: Demo = ron::from_str(&text).with_context(|| format!("{}", file.display()))?;
    let dir = file.parent().unwrap_or(Path::new("."));
    let _lock = deform_fs::lock_folder(&args.out)?;
    let started = Instant::now();
    let mut rows = Vec::new();
    let mut report = String::from(
        "# deform demo\n\nThe base model is a Backward-Euler simulation (Newton, Rayleigh damping) of linear tetrahedra; data are its trajectories. Each section below is one experiment's report; its folder holds the CSV files, SVG plots and the dataset.\n\n",
    );

    let t = Instant::now();
    let scene = deform_fs::join_clean(dir, &demo.scene);
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

    for DemoExperiment { file, about: what } in demo.experiments {
        let file = deform_fs::join_clean(dir, &file);
        let name = file
            .file_stem()
            .map_or(String::new(), |s| s.to_string_lossy().into_owned());
        let t = Instant::now();
        let out = args.out.join(&name);
        let (result, text) = experiment::run(ExperimentArgs {
            experiment: file,
            out: Some(out.clone()),
            quiet: args.quiet,
        })?;
        let summary = result.headline();
        // Demote the title; the plots lie in the experiment's folder.
        let text = rebase_images(&text.replacen("# ", "### ", 1), &name);
        writeln!(report, "## {what}\n\nFolder `{name}/`.\n\n{text}")?;
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
    let page = deform_studies::html::page("deform demo", &text, &args.out)?;
    let html = args.out.join("report.html");
    write_atomic(&html, |w| w.write_all(page.as_bytes()))
        .with_context(|| format!("writing {}", html.display()))?;
    println!(
        "\n{table}\nreport: {} (one page, plots inline: {})",
        path.display(),
        html.display()
    );
    Ok(())
}

/// `markdown` with each image link made relative to the folder above `folder`.
fn rebase_images(markdown: &str, folder: &str) -> String {
    let mut out = String::with_capacity(markdown.len());
    let mut rest = markdown;
    while let Some(start) = rest.find("![") {
        let Some(open) = rest[start..].find("](") else {
            break;
        };
        let cut = start + open + 2;
        out.push_str(&rest[..cut]);
        out.push_str(folder);
        out.push('/');
        rest = &rest[cut..];
    }
    out.push_str(rest);
    out
}

#[cfg(test)]
mod tests {
    #[test]
    fn image_links_point_into_the_experiment_folder() {
        let md = "a ![loss](loss.svg) b [c](d) ![e](f.svg)";
        let got = super::rebase_images(md, "fit");
        assert_eq!(got, "a ![loss](fit/loss.svg) b [c](d) ![e](fit/f.svg)");
    }
}
