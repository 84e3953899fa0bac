//! The deform runner. `cargo xtask --help` lists the tasks.
//!
//! Tasks are plain Rust (no make, no shell scripts); each lives in its own module.

mod mesh;

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
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let result = match cli.task {
        Task::Mesh(task) => mesh::run(task),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
