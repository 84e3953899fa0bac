//! A bundled experiment under an address-space limit (`ulimit -v`, common on shared
//! clusters). faer's matrix product reserves twice the last-level cache per thread that
//! runs it; with a reservation on every worker and lane the process aborted ("memory
//! allocation of 1006632960 bytes failed" under 4 GiB where the L3 is 480 MiB). The test
//! reruns itself in a shell with the limit set, so the limit binds that process only.
#![cfg(target_os = "linux")]

use std::path::Path;
use std::process::Command;

use deform_studies::{Experiment, NoProgress, run};

/// Set in the child that runs under the limit.
const CHILD: &str = "DEFORM_UNDER_ADDRESS_LIMIT";

/// `select_model` (five energy models, output-error fits side by side) under a limit of
/// three threads' matrix-product scratch and 512 MiB: 2,072 MiB on a machine whose L3 is
/// 260 MiB, where it aborted at 2,048 MiB before the kernels were confined; on the 480 MiB
/// machine the limit is 3.3 GiB, below the 4 GiB it aborted under.
#[test]
fn a_bundled_experiment_runs_under_an_address_space_limit() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    if std::env::var_os(CHILD).is_some() {
        let e = Experiment::load(&root.join("assets/experiments/select_model.ron")).unwrap();
        run(&e, None, &mut NoProgress).unwrap();
        let threads = deform_solvers::kernels::kernel_threads();
        println!("kernel threads under the limit: {threads:?}");
        assert!(threads.is_some(), "the limit was not seen");
        return;
    }
    let limit = 3 * deform_solvers::kernels::scratch_per_thread() + (512 << 20);
    let exe = std::env::current_exe().unwrap();
    let output = Command::new("sh")
        .arg("-c")
        .arg(format!("ulimit -v {} && exec \"$0\" \"$@\"", limit >> 10))
        .arg(&exe)
        .args([
            "--exact",
            "a_bundled_experiment_runs_under_an_address_space_limit",
            "--nocapture",
        ])
        .env(CHILD, "1")
        .output()
        .unwrap();
    let (stdout, stderr) = (
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr),
    );
    assert!(
        output.status.success() && stdout.contains("kernel threads under the limit: Some("),
        "under {} MiB: {}\n{stdout}\n{stderr}",
        limit >> 20,
        output.status
    );
}
