//! `cargo xtask wheel`: one abi3 wheel of the `deform` Python module (any CPython >= 3.9 on
//! this platform) in `target/wheels/`, built by maturin in release mode with the runner's
//! own build (the `deform-hack` crate keeps their dependency features one set), so after
//! `cargo xtask demo` it compiles only PyO3 and the module. `pip install` of the wheel then
//! takes seconds in any virtual environment.

use std::process::Command;

use anyhow::{Context, Result};

use crate::test::{python_env, root, run_command};

/// Arguments of `cargo xtask wheel`.
#[derive(Debug, clap::Args)]
pub struct WheelArgs {
    /// The Python that makes the build environment (target/pyvenv) holding maturin.
    #[arg(long, default_value = "python3")]
    python: String,
}

/// Builds the wheel and prints its path.
pub fn run(args: WheelArgs) -> Result<()> {
    let root = root();
    let bin = python_env(&root, &args.python, &["maturin>=1.7,<2"])?;
    let out = root.join("target").join("wheels");
    let mut cmd = Command::new(bin.join("maturin"));
    cmd.current_dir(&root)
        .args(["build", "--release", "--strip", "--manifest-path"])
        .arg(root.join("crates").join("python").join("Cargo.toml"))
        .arg("--out")
        .arg(&out);
    run_command(cmd, "building the abi3 wheel (maturin build --release)")?;
    let mut wheels: Vec<_> = std::fs::read_dir(&out)
        .with_context(|| format!("reading {}", out.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "whl"))
        .collect();
    wheels.sort_by_key(|p| std::fs::metadata(p).and_then(|m| m.modified()).ok());
    let wheel = wheels.last().context("maturin wrote no wheel")?;
    println!("{}", wheel.display());
    println!("install it with: pip install {}", wheel.display());
    Ok(())
}
