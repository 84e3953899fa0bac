//! Memory a mesh and its simulation need, checked against what the machine has before
//! anything large is allocated: a scene that cannot fit is refused with the figure instead
//! of aborting on an allocation (a `Beam(300)` mesh alone is 80 GB).

/// Bytes of memory available now (Linux: `MemAvailable` of `/proc/meminfo`, further bounded
/// by a cgroup v2 limit); `None` where unknown, and then nothing is refused.
pub fn available_bytes() -> Option<u64> {
    let kib = proc_kib("/proc/meminfo", "MemAvailable:")?;
    let limit = std::fs::read_to_string("/sys/fs/cgroup/memory.max")
        .ok()
        .and_then(|s| s.trim().parse::<u64>().ok());
    Some(limit.map_or(kib * 1024, |l| l.min(kib * 1024)))
}

/// The process's peak resident memory so far, in bytes (Linux: `VmHWM` of
/// `/proc/self/status`); `None` where unknown. What a run measured, beside what
/// [`simulation_lower_bound`] estimates.
pub fn peak_rss_bytes() -> Option<u64> {
    proc_kib("/proc/self/status", "VmHWM:").map(|kib| kib * 1024)
}

/// The value in kB of the line starting with `key` of a `/proc` file such as
/// `/proc/meminfo` (`MemAvailable:   123456 kB`).
fn proc_kib(file: &str, key: &str) -> Option<u64> {
    let text = std::fs::read_to_string(file).ok()?;
    let value = text.lines().find_map(|l| l.strip_prefix(key))?;
    value.trim().trim_end_matches("kB").trim().parse().ok()
}

/// Bytes of a [`crate::TetMesh`] with `vertices` and `tets` while it is built and validated:
/// positions, connectivity, regions, `Dm^-1`, volumes and the face table of the conformity
/// check.
pub fn mesh_bytes(vertices: usize, tets: usize) -> u64 {
    24 * vertices as u64 + (32 + 4 + 72 + 8 + 200) * tets as u64
}

/// A lower bound on the bytes a simulation of such a mesh takes: the mesh, one stiffness
/// matrix in CSR (a tet mesh has at least `vertices + tets - 1` edges, by Euler's formula
/// for a solid, and each edge couples two 3x3 blocks, 16 bytes per entry with its column)
/// and ten state-sized vectors. Solver factors come on top, so a refusal is certain.
pub fn simulation_lower_bound(vertices: usize, tets: usize) -> u64 {
    let (v, t) = (vertices as u64, tets as u64);
    let edges = (v + t).saturating_sub(1);
    let stiffness = 16 * 9 * (v + 2 * edges);
    mesh_bytes(vertices, tets) + stiffness + 10 * 3 * 8 * v
}

/// Refuses `needed` bytes when they exceed what is available, with both figures.
///
/// # Errors
/// The reason, e.g. "needs at least 81.2 GB, 21.9 GB available".
pub fn check_fits(needed: u64) -> Result<(), String> {
    match available_bytes() {
        Some(available) if needed > available => Err(format!(
            "needs at least {:.1} GB, {:.1} GB available",
            needed as f64 / 1e9,
            available as f64 / 1e9
        )),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounds_grow_with_the_mesh_and_huge_ones_are_refused() {
        assert!(available_bytes().is_none_or(|b| b > 0));
        let small = simulation_lower_bound(1000, 5000);
        assert!(small > mesh_bytes(1000, 5000));
        assert!(check_fits(small).is_ok());
        // 2^60 bytes fit on no machine.
        let e = check_fits(1 << 60).unwrap_err();
        assert!(
            e.contains("needs at least") && e.contains("GB available"),
            "{e}"
        );
    }
}
