//! Where faer's dense kernels run. faer's x86 matrix product keeps a scratch buffer per
//! thread of twice the last-level cache (960 MiB where the L3 is 480 MiB), reserved on a
//! thread's first product and held while the thread lives; it touches little of it, so
//! resident memory stays small, but the address space is gone. Under an address-space limit
//! (`ulimit -v`, common on shared clusters) every thread that factorised would hold one, and
//! the process aborted once a few had ("memory allocation of 1006632960 bytes failed").
//!
//! So under such a limit the factorisations and solves run on a pool of as many threads as
//! half the limit holds buffers for (at least one); without a limit they run where they are
//! called, as before. Either way the factor's bits are the same: its parallel tasks are
//! fixed, not the pool's size (see [`crate::Cholesky::set_parallel`]).

use std::sync::OnceLock;

/// Runs `f`, which calls faer's dense kernels, on the kernel threads when the address
/// space is limited, else on the calling thread.
pub(crate) fn confined<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    match pool() {
        Some(pool) => pool.install(f),
        None => f(),
    }
}

/// The threads faer's kernels are confined to, when the address space is limited (`None`:
/// no limit, the kernels run on the calling threads).
pub fn kernel_threads() -> Option<usize> {
    pool().map(rayon::ThreadPool::current_num_threads)
}

fn pool() -> Option<&'static rayon::ThreadPool> {
    static POOL: OnceLock<Option<rayon::ThreadPool>> = OnceLock::new();
    POOL.get_or_init(|| {
        let limit = address_space_limit()?;
        let cores = std::thread::available_parallelism().map_or(1, usize::from);
        let threads = threads_within(limit, scratch_per_thread(), cores);
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("deform-kernels-{i}"))
            .build()
            .ok()
    })
    .as_ref()
}

/// Kernel threads whose scratch fits in half of `limit` bytes, at least one and at most
/// `cores`; the other half is left to everything else.
fn threads_within(limit: u64, per_thread: u64, cores: usize) -> usize {
    let fit = (limit / 2) / per_thread.max(1);
    usize::try_from(fit)
        .unwrap_or(usize::MAX)
        .clamp(1, cores.max(1))
}

/// The address-space reservation of one thread's matrix-product scratch in bytes: twice the
/// last-level cache (as the product sizes it, at least 2 MiB); 512 MiB when the cache's
/// size is unknown.
pub fn scratch_per_thread() -> u64 {
    const UNKNOWN: u64 = 256 << 20;
    2 * last_level_cache().map_or(UNKNOWN, |bytes| bytes.max(2 << 20))
}

/// The soft address-space limit in bytes (`ulimit -v`), from `/proc/self/limits`; `None`
/// when unlimited or unknown.
fn address_space_limit() -> Option<u64> {
    let limits = std::fs::read_to_string("/proc/self/limits").ok()?;
    parse_address_space_limit(&limits)
}

fn parse_address_space_limit(limits: &str) -> Option<u64> {
    let line = limits
        .lines()
        .find(|l| l.starts_with("Max address space"))?;
    let soft = line["Max address space".len()..]
        .split_whitespace()
        .next()?;
    soft.parse().ok()
}

/// The largest cache's size in bytes, from sysfs (Linux).
fn last_level_cache() -> Option<u64> {
    let dir = std::path::Path::new("/sys/devices/system/cpu/cpu0/cache");
    let mut largest = None;
    for entry in std::fs::read_dir(dir).ok()?.flatten() {
        let size = std::fs::read_to_string(entry.path().join("size")).ok();
        if let Some(bytes) = size.as_deref().and_then(parse_cache_size) {
            largest = largest.max(Some(bytes));
        }
    }
    largest
}

/// A sysfs cache size: `266240K`, `2048K`, `32M`.
fn parse_cache_size(text: &str) -> Option<u64> {
    let text = text.trim();
    let (digits, unit) = match text.char_indices().find(|(_, c)| !c.is_ascii_digit()) {
        Some((i, _)) => text.split_at(i),
        None => (text, ""),
    };
    let scale = match unit {
        "" => 1,
        "K" => 1 << 10,
        "M" => 1 << 20,
        "G" => 1 << 30,
        _ => return None,
    };
    digits.parse::<u64>().ok()?.checked_mul(scale)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_limit_and_cache_sizes_are_read_as_linux_writes_them() {
        let limits = "Limit                     Soft Limit           Hard Limit           Units     \n\
                      Max stack size            8388608              unlimited            bytes     \n\
                      Max address space         4294967296           unlimited            bytes     \n";
        assert_eq!(parse_address_space_limit(limits), Some(4 << 30));
        let unlimited = limits.replace("4294967296", "unlimited");
        assert_eq!(parse_address_space_limit(&unlimited), None);
        assert_eq!(parse_cache_size("266240K\n"), Some(266_240 << 10));
        assert_eq!(parse_cache_size("32M"), Some(32 << 20));
        assert_eq!(parse_cache_size("12 KB"), None);
    }

    #[test]
    fn kernel_threads_fit_half_the_limit() {
        // 4 GiB with a 480 MiB L3 (960 MiB a thread): two threads, whatever the cores.
        assert_eq!(threads_within(4 << 30, 960 << 20, 64), 2);
        // Never none, never more than the cores.
        assert_eq!(threads_within(1 << 30, 960 << 20, 64), 1);
        assert_eq!(threads_within(1 << 40, 960 << 20, 2), 2);
    }
}
