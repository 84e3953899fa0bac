//! The deform runner. `cargo xtask --help` lists the tasks.
//!
//! Tasks are plain Rust (no make, no shell scripts); each lives in its own module.

mod bench;
mod demo;
mod experiment;
mod mesh;
mod simulate;
mod test;
mod wheel;

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
    /// One abi3 wheel of the Python module (CPython >= 3.9) in target/wheels/.
    Wheel(wheel::WheelArgs),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    // On a worker of the global pool: the serial parts between parallel loops then run on a
    // thread that also runs those loops, instead of handing every loop to another core and
    // waiting (on one thread, every loop moved the work, and its cache, to another core).
    let result = rayon::scope(|_| match cli.task {
        Task::Mesh(task) => mesh::run(task),
        Task::Simulate(args) => simulate::run(args),
        Task::Bench(task) => bench::run(task),
        Task::Demo(args) => demo::run(args),
        Task::Experiment(args) => experiment::run(args).map(|_| ()),
        Task::Test(args) => test::run(args),
        Task::Wheel(args) => wheel::run(args),
    });
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", describe(&e));
            std::process::ExitCode::FAILURE
        }
    }
}

/// The error and its causes joined by `: `, leaving out a cause whose message the text so far
/// already shows (deform's errors name their cause in their own message, and still expose
/// it as `source()` for callers who walk the chain).
fn describe(e: &anyhow::Error) -> String {
    let mut text = e.to_string();
    for cause in e.chain().skip(1) {
        let cause = cause.to_string();
        if !text.contains(&cause) {
            text.push_str(": ");
            text.push_str(&cause);
        }
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An error that shows its cause in its message and exposes it as its source.
    #[derive(Debug)]
    struct Shown {
        source: std::io::Error,
    }

    impl std::fmt::Display for Shown {
        fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            write!(f, "step 3: {}", self.source)
        }
    }

    impl std::error::Error for Shown {
        fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
            Some(&self.source)
        }
    }

    #[test]
    fn causes_already_in_the_message_are_not_repeated() {
        let io = || std::io::Error::other("disk full");
        let shown = anyhow::Error::new(Shown { source: io() });
        assert_eq!(describe(&shown), "step 3: disk full");
        let hidden = anyhow::Error::new(io()).context("writing frame 2");
        assert_eq!(describe(&hidden), "writing frame 2: disk full");
    }
}
