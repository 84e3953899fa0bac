//! `cargo xtask experiment EXPERIMENT.ron [--out DIR]`: runs an experiment with
//! `deform_learn::experiment::run` behind progress bars, then renders its report:
//! `report.md`, CSV files and SVG/PNG plots beside the files the experiment wrote.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::Args;
use deform_fs::write_atomic;
use deform_learn::experiment::{self, Experiment, ExperimentObserver, ExperimentReport, Stage};
use indicatif::{ProgressBar, ProgressStyle};

use crate::render;

/// Arguments of `experiment`.
#[derive(Debug, Args)]
pub struct ExperimentArgs {
    /// The experiment file (RON).
    pub experiment: PathBuf,
    /// Results folder (default `target/deform/experiments/<name>`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// No progress bars.
    #[arg(long)]
    pub quiet: bool,
}

/// A progress bar of `len` steps labelled `what` (hidden when `quiet`).
pub(crate) fn bar(quiet: bool, len: u64, what: &str) -> ProgressBar {
    let b = if quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(len)
    };
    b.set_style(
        ProgressStyle::with_template(&format!(
            "{what:>10} {{bar:30}} {{pos}}/{{len}} {{msg}} [{{elapsed_precise}}, eta {{eta}}]"
        ))
        .expect("a valid template"),
    );
    b
}

/// Progress bars, one per stage.
pub(crate) struct Bars {
    quiet: bool,
    current: Option<ProgressBar>,
}

impl Bars {
    pub(crate) fn new(quiet: bool) -> Self {
        Self {
            quiet,
            current: None,
        }
    }
}

impl ExperimentObserver for Bars {
    fn start(&mut self, stage: Stage, total: u64) {
        self.finish();
        self.current = Some(bar(self.quiet, total, stage.name()));
    }
    fn advance(&mut self, by: u64) {
        if let Some(b) = &self.current {
            b.inc(by);
        }
    }
    fn message(&mut self, text: &str) {
        if let Some(b) = &self.current {
            b.set_message(text.to_owned());
        }
    }
    fn finish(&mut self) {
        if let Some(b) = self.current.take() {
            b.finish_and_clear();
        }
    }
}

pub(crate) fn write_text(path: &Path, text: &str) -> Result<()> {
    write_atomic(path, |w| w.write_all(text.as_bytes()))
        .with_context(|| format!("writing {}", path.display()))
}

/// Runs the experiment and renders it into its folder; returns the report and its
/// markdown.
pub fn run(args: ExperimentArgs) -> Result<(ExperimentReport, String)> {
    let e = Experiment::load(&args.experiment)?;
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| Path::new("target/deform/experiments").join(&e.name));
    let report = experiment::run(&e, Some(&out), &mut Bars::new(args.quiet))?;
    let markdown = render::render(&report, &out)?;
    write_text(&out.join("report.md"), &markdown)?;
    println!("{markdown}");
    println!("results: {}", out.display());
    Ok((report, markdown))
}
