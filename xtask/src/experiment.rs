//! `cargo xtask experiment EXPERIMENT.ron [--out DIR]`: runs an experiment with
//! `deform_studies::run` behind progress bars, then renders its report:
//! `report.md`, CSV files and SVG/PNG plots beside the files the experiment wrote.

use std::path::{Path, PathBuf};

use anyhow::Result;
use clap::Args;
use deform_studies::{Experiment, ExperimentObserver, ExperimentReport, Stage};
use indicatif::{ProgressBar, ProgressStyle};

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

/// Progress as plain lines where a bar cannot be drawn (output to a file or a pipe, as in
/// CI or a batch job): a line when a stage starts, at most one a minute while it runs, and
/// one when it ends, so a long fit is never silent.
pub(crate) struct Lines {
    /// Whether lines are printed at all (not quiet, stderr not a terminal).
    on: bool,
    last: std::time::Instant,
}

/// How often [`Lines`] prints while a stage runs.
const LINE_EVERY: std::time::Duration = std::time::Duration::from_secs(60);

impl Lines {
    pub(crate) fn new(quiet: bool) -> Self {
        use std::io::IsTerminal;
        Self {
            on: !quiet && !std::io::stderr().is_terminal(),
            last: std::time::Instant::now(),
        }
    }

    /// Prints `bar`'s state when `force` or a minute has passed since the last line.
    pub(crate) fn tick(&mut self, what: &str, bar: &ProgressBar, force: bool) {
        if let Some(line) = self.line(what, bar, force) {
            eprintln!("{line}");
        }
    }

    /// The line to print now, if any.
    fn line(&mut self, what: &str, bar: &ProgressBar, force: bool) -> Option<String> {
        if !self.on || !(force || self.last.elapsed() >= LINE_EVERY) {
            return None;
        }
        self.last = std::time::Instant::now();
        let len = bar.length().map_or("?".to_owned(), |l| l.to_string());
        Some(format!(
            "{what}: {}/{len} {} [{:.0} s]",
            bar.position(),
            bar.message(),
            bar.elapsed().as_secs_f64()
        ))
    }
}

/// Progress bars, one per stage.
pub(crate) struct Bars {
    quiet: bool,
    current: Option<(ProgressBar, &'static str)>,
    lines: Lines,
}

impl Bars {
    pub(crate) fn new(quiet: bool) -> Self {
        Self {
            quiet,
            current: None,
            lines: Lines::new(quiet),
        }
    }
}

impl ExperimentObserver for Bars {
    fn start(&mut self, stage: Stage, total: u64) {
        self.finish();
        let b = bar(self.quiet, total, stage.name());
        self.lines.tick(stage.name(), &b, true);
        self.current = Some((b, stage.name()));
    }
    fn advance(&mut self, by: u64) {
        if let Some((b, what)) = &self.current {
            b.inc(by);
            self.lines.tick(what, b, false);
        }
    }
    fn message(&mut self, text: &str) {
        if let Some((b, what)) = &self.current {
            b.set_message(text.to_owned());
            self.lines.tick(what, b, false);
        }
    }
    fn finish(&mut self) {
        if let Some((b, what)) = self.current.take() {
            self.lines.tick(what, &b, true);
            b.finish_and_clear();
        }
    }
}

/// Runs the experiment and renders it into its folder; returns the report and its
/// markdown.
pub fn run(args: ExperimentArgs) -> Result<(ExperimentReport, String)> {
    let e = Experiment::load(&args.experiment)?;
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| Path::new("target/deform/experiments").join(&e.name));
    let report = deform_studies::run(&e, Some(&out), &mut Bars::new(args.quiet))?;
    let markdown = deform_studies::write_report(&report, &out)?;
    println!("{markdown}");
    println!("results: {}", out.display());
    Ok((report, markdown))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Without a terminal, a stage prints when it starts and ends and at most once a minute
    /// in between; quiet prints nothing.
    #[test]
    fn progress_without_a_terminal_is_printed_as_lines() {
        let bar = ProgressBar::hidden();
        bar.set_length(10);
        let mut lines = Lines {
            on: true,
            last: std::time::Instant::now(),
        };
        assert_eq!(
            lines.line("fit", &bar, true).as_deref(),
            Some("fit: 0/10  [0 s]")
        );
        bar.inc(3);
        bar.set_message("loss 1e-3");
        assert_eq!(lines.line("fit", &bar, false), None);
        lines.last -= LINE_EVERY;
        let line = lines.line("fit", &bar, false).unwrap();
        assert!(line.starts_with("fit: 3/10 loss 1e-3"), "{line}");
        assert_eq!(Lines::new(true).line("fit", &bar, true), None);
    }
}
