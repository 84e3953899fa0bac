//! The deform runner. `cargo xtask --help` lists the tasks.
//!
//! Tasks are plain Rust (no make, no shell scripts); each lives in its own module.

mod bench;
mod demo;
mod experiment;
mod mesh;
mod plots;
mod render;
mod simulate;
mod test;

use clap::{Parser, Subcommand};

/// deform's experiment runner.
#[derive(Debug, Parser)]
#[command(name = "cargo xtask", version, about)]
struct Cli {
    #[command(subcommand)]
    task: Task,
}

#[derive(Debug, Subcommand)]
enum Task {
    /// Inspect, convert and generate tetrahedral meshes.
    #[command(subcommand)]
    Mesh(mesh::MeshTask),
    /// The whole idea end to end: simulate, fit, select, learn solver policies, report.
    Demo(demo::DemoArgs),
    /// Quick measurements on the benchmark beams, as JSON lines (see bench/peers/).
    #[command(subcommand)]
    Bench(bench::BenchTask),
    /// Run an experiment (RON): dataset, fits, report.md, CSV and SVG plots.
    Experiment(experiment::ExperimentArgs),
    /// Run a scene (RON): progress bar, .vtu/.pvd frames, per-step CSV, summary.
    Simulate(simulate::SimulateArgs),
    /// Every test: `cargo test --workspace`, then the Python module built into a virtual
    /// environment (target/pyvenv) and pytest.
    Test(test::TestArgs),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let result = match cli.task {
        Task::Mesh(task) => mesh::run(task),
        Task::Simulate(args) => simulate::run(args),
        Task::Bench(task) => bench::run(task),
        Task::Demo(args) => demo::run(args),
        Task::Experiment(args) => experiment::run(args).map(|_| ()),
        Task::Test(args) => test::run(args),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
