//! `cargo xtask test`: the whole test suite, Rust and Python, on a fresh machine with only
//! Rust and Python 3 installed. Runs `cargo test --workspace`, then makes a virtual
//! environment (`target/pyvenv`, once), installs maturin into it, builds the `deform` module
//! into it with maturin together with its declared `test` extra (pytest, meshio, Dask: the
//! same list a user installs with `pip install "./crates/python[test]"`) and runs pytest on
//! `python/tests`.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, bail};

/// Arguments of `cargo xtask test`.
#[derive(Debug, clap::Args)]
pub struct TestArgs {
    /// Only the Python suite (skip `cargo test --workspace`).
    #[arg(long)]
    python_only: bool,
    /// Only the Rust suite.
    #[arg(long, conflicts_with = "python_only")]
    rust_only: bool,
    /// The Python that makes the virtual environment.
    #[arg(long, default_value = "python3")]
    python: String,
    /// Arguments passed on to pytest (after `--`).
    #[arg(last = true)]
    pytest: Vec<String>,
}

/// The workspace root.
pub(crate) fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("xtask sits in the workspace")
        .to_path_buf()
}

/// Runs `cmd`, failing with what it was when it fails.
pub(crate) fn run_command(mut cmd: Command, what: &str) -> Result<()> {
    eprintln!("==> {what}");
    let status = cmd
        .status()
        .with_context(|| format!("{what}: could not start {:?}", cmd.get_program()))?;
    if !status.success() {
        bail!("{what} failed ({status})");
    }
    Ok(())
}

/// The virtual environment `target/pyvenv` (made with `python` the first time) with
/// `requirements` installed by pip (as its command line: `["-r", file]` or package names);
/// its `bin` folder.
pub(crate) fn python_env(root: &Path, python: &str, requirements: &[&str]) -> Result<PathBuf> {
    let venv = root.join("target").join("pyvenv");
    let bin = venv.join("bin");
    if !bin.join("python").exists() {
        let mut cmd = Command::new(python);
        cmd.args(["-m", "venv"]).arg(&venv);
        run_command(cmd, "making the virtual environment target/pyvenv")?;
    }
    let mut cmd = Command::new(bin.join("python"));
    cmd.current_dir(root)
        .args([
            "-m",
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
        ])
        .args(requirements);
    run_command(cmd, &format!("installing {} (pip)", requirements.join(" ")))?;
    Ok(bin)
}

/// Builds and runs `tests/api-user`, a crate outside the workspace that sets up deform's
/// public options and specs as a user's crate does (no struct literals), so a new field
/// that would break users fails here. It shares the workspace's lock file and build folder,
/// so only the crate itself and what it enables differently are compiled.
fn api_user(root: &Path, cargo: &std::ffi::OsStr) -> Result<()> {
    let dir = root.join("tests").join("api-user");
    std::fs::copy(root.join("Cargo.lock"), dir.join("Cargo.lock"))
        .context("copying Cargo.lock for tests/api-user")?;
    let mut cmd = Command::new(cargo);
    cmd.current_dir(&dir)
        .args(["run", "--quiet", "--target-dir"])
        .arg(root.join("target"));
    run_command(
        cmd,
        "the public API from a crate outside the workspace: tests/api-user",
    )
}

/// Runs the suites.
pub fn run(args: TestArgs) -> Result<()> {
    let root = root();
    if !args.python_only {
        let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
        let mut cmd = Command::new(&cargo);
        cmd.current_dir(&root).args(["test", "--workspace"]);
        run_command(cmd, "Rust tests: cargo test --workspace")?;
        api_user(&root, &cargo)?;
    }
    if args.rust_only {
        return Ok(());
    }
    let bin = python_env(&root, &args.python, &["maturin>=1.7,<2"])?;
    let (venv, python) = (root.join("target").join("pyvenv"), bin.join("python"));
    // maturin builds the module with cargo (dev profile: shares the Rust tests' build) and
    // installs it into the environment with the extra the tests need.
    let mut cmd = Command::new(bin.join("maturin"));
    cmd.current_dir(&root)
        .env("VIRTUAL_ENV", &venv)
        .args(["develop", "--quiet", "--extras", "test", "--manifest-path"])
        .arg(root.join("crates").join("python").join("Cargo.toml"));
    run_command(cmd, "building the deform module (maturin develop)")?;
    let mut cmd = Command::new(&python);
    cmd.current_dir(&root)
        .args(["-m", "pytest", "-q", "python/tests"])
        .args(&args.pytest);
    run_command(cmd, "Python tests: pytest python/tests")
}
