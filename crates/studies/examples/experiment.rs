//! Runs an experiment file from Rust, without the runner: the dataset, the learning, and
//! the report as data (printed here as its headline figures); given a folder, the report is
//! also written there as the runner writes it (report.md and its plots).
//!
//! ```sh
//! cargo run --release -p deform-studies --example experiment -- assets/experiments/tune_solver.ron [OUT]
//! ```

use std::path::PathBuf;

use deform_studies::{Experiment, ExperimentObserver, Stage, TaskReport, run};

/// Prints each stage as it starts.
struct Print;

impl ExperimentObserver for Print {
    fn start(&mut self, stage: Stage, total: u64) {
        eprintln!("{} ({total} units)", stage.name());
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let path = PathBuf::from(
        args.next()
            .unwrap_or_else(|| "assets/experiments/tune_solver.ron".into()),
    );
    let out = args.next().map(PathBuf::from);
    let experiment = Experiment::load(&path)?;
    let report = run(&experiment, out.as_deref(), &mut Print)?;
    println!(
        "{}: {} vertices, {} tets, {:.1} s",
        report.name, report.vertices, report.tets, report.seconds
    );
    match &report.task {
        TaskReport::FitMaterial(r) => println!("{}", r.headline()),
        TaskReport::SelectModel(r) => {
            for m in &r.ensemble.members {
                println!("{}: {:.1} % of the energy", m.model, 100.0 * m.energy_share);
            }
        }
        TaskReport::SelectSolver(r) => {
            for case in &r.cases {
                for row in &case.rows {
                    println!(
                        "{} | {}: work {:.3e}",
                        case.label,
                        row.contender.name(),
                        row.measured.work
                    );
                }
            }
        }
        TaskReport::TuneBackwardEuler(r) => {
            let (e, w, t) = r.ratios();
            println!("tuned / untuned: error {e:.2}x, work {w:.2}x, time {t:.2}x");
        }
        TaskReport::TuneSolver(r) => println!("tuned / configured work: {:.3}", r.work_ratio()),
        TaskReport::Coarsen(r) => println!("{}", r.headline()),
    }
    if let Some(out) = &out {
        deform_studies::write_report(&report, out)?;
        println!("report: {}", out.join("report.md").display());
    }
    Ok(())
}
