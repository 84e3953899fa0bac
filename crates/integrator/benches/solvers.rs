//! Linear solvers on the Backward-Euler systems `K(x) + M/dt^2` of the beam family of
//! the beam family of `docs/benchmarks.md` (free DOFs: n = 8: 7,776; n = 16: 55,488; n = 32: 418,116):
//! direct Cholesky (analyze, factorize sequential and parallel, solve), CG and PCG to 1e-6
//! and 1e-8 relative residual, the sparse matrix-vector product, and a STREAM-triad loop for
//! the machine's memory bandwidth. Iteration counts and bandwidths are printed to stderr.
//!
//! `cargo bench -p deform-integrator --bench solvers`; `DEFORM_BENCH_SIZES=8,16` picks sizes
//! (default 8,16; the direct solver is skipped above 16: its factor needs 4 GB and a minute
//! per factorisation there; `cargo xtask bench solvers --n 32` runs it once).

use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use deform_integrator::benchmark::beam_system;
use deform_solvers::{Cholesky, Indefinite, LinearOperator, LinearSolver, Ordering, SolverSpec};

/// STREAM triad bandwidth in GB/s, on one thread or on all of the pool's (the SpMV runs on
/// all of them, so that is the bandwidth it is compared with).
fn stream_triad(parallel: bool) -> f64 {
    use rayon::prelude::*;
    // Three arrays of 32 MB each: far beyond the caches.
    let n = 4 << 20;
    let (b, c) = (vec![1.5f64; n], vec![2.5f64; n]);
    let mut a = vec![0.0f64; n];
    let chunk = 1 << 14;
    let mut best = f64::INFINITY;
    for _ in 0..10 {
        let t = Instant::now();
        let triad = |((a, b), c): ((&mut [f64], &[f64]), &[f64])| {
            for i in 0..a.len() {
                a[i] = b[i] + 3.0 * c[i];
            }
        };
        if parallel {
            a.par_chunks_mut(chunk)
                .zip(b.par_chunks(chunk))
                .zip(c.par_chunks(chunk))
                .for_each(triad);
        } else {
            triad(((&mut a, &b), &c));
        }
        black_box(&mut a);
        best = best.min(t.elapsed().as_secs_f64());
    }
    // Read b and c, write a (plus the write-allocate read of a, which STREAM does not count).
    3.0 * 8.0 * n as f64 / best / 1e9
}

fn benches(c: &mut Criterion) {
    let sizes: Vec<usize> = std::env::var("DEFORM_BENCH_SIZES")
        .ok()
        .map(|s| s.split(',').filter_map(|v| v.trim().parse().ok()).collect())
        .unwrap_or_else(|| vec![8, 16]);
    let triad = stream_triad(true);
    eprintln!(
        "STREAM triad: {:.1} GB/s on one thread, {triad:.1} GB/s on {} threads",
        stream_triad(false),
        rayon::current_num_threads()
    );
    let mut group = c.benchmark_group("solvers");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_millis(300));
    for n in sizes {
        let a = beam_system(n);
        let dofs = a.rows();
        let b: Vec<f64> = (0..dofs).map(|i| ((i % 7) as f64 - 3.0) * 1e-3).collect();
        let id = |what: &str| BenchmarkId::new(what, format!("n={n} ({dofs} dofs)"));
        group.measurement_time(Duration::from_secs(if n >= 16 { 20 } else { 5 }));

        // Sparse matrix-vector product and its effective bandwidth (values + column indices
        // + row pointers + x + y, each read or written once).
        let mut y = vec![0.0; dofs];
        let x = vec![1.0; dofs];
        let t = Instant::now();
        let reps = 50;
        for _ in 0..reps {
            a.apply(black_box(&x), &mut y);
        }
        let spmv = t.elapsed().as_secs_f64() / reps as f64;
        let bytes = (a.nnz() * 16 + dofs * 8 * 3) as f64;
        eprintln!(
            "n={n}: {dofs} dofs, {} nonzeros; SpMV {:.3} ms = {:.1} GB/s ({:.0}% of the threads' triad)",
            a.nnz(),
            1e3 * spmv,
            bytes / spmv / 1e9,
            100.0 * bytes / spmv / 1e9 / triad
        );
        group.bench_function(id("spmv"), |bench| {
            bench.iter(|| a.apply(black_box(&x), &mut y))
        });

        if n <= 16 {
            let mut direct = Cholesky::new(Ordering::Auto, Indefinite::Error);
            group.bench_function(id("direct_analyze"), |bench| {
                bench.iter(|| direct.analyze(&a).unwrap())
            });
            for parallel in [false, true] {
                direct.set_parallel(parallel);
                let name = if parallel {
                    "direct_factorize"
                } else {
                    "direct_factorize_one_thread"
                };
                group.bench_function(id(name), |bench| {
                    bench.iter(|| direct.factorize(&a).unwrap())
                });
            }
            let mut sol = vec![0.0; dofs];
            group.bench_function(id("direct_solve"), |bench| {
                bench.iter(|| direct.solve(&a, &b, &mut sol).unwrap())
            });
            eprintln!("n={n}: nnz(L) = {}", direct.factor_nnz());
        }

        for rel in [1e-6, 1e-8] {
            for (label, pre) in [
                ("cg", None),
                ("pcg_jacobi", Some("Jacobi")),
                ("pcg_block_jacobi", Some("BlockJacobi")),
                ("pcg_ic0", Some("Ic0")),
            ] {
                let spec = match pre {
                    None => format!("Cg(tolerance: (rel: {rel:e}, max_iterations: 100000))"),
                    Some(p) => format!(
                        "Pcg(preconditioner: {p}, tolerance: (rel: {rel:e}, max_iterations: 100000))"
                    ),
                };
                let mut solver = ron::from_str::<SolverSpec>(&spec).unwrap().build().unwrap();
                solver.factorize(&a).unwrap();
                let mut sol = vec![0.0; dofs];
                let stats = solver.solve(&a, &b, &mut sol).unwrap();
                eprintln!(
                    "n={n}: {label} to {rel:e}: {} iterations, {:.1} ms, {:.1} us per iteration",
                    stats.iterations,
                    1e3 * stats.seconds,
                    1e6 * stats.seconds / stats.iterations.max(1) as f64
                );
                group.bench_function(id(&format!("{label}_{rel:e}")), |bench| {
                    bench.iter(|| {
                        solver.factorize(&a).unwrap();
                        sol.iter_mut().for_each(|v| *v = 0.0);
                        solver.solve(&a, &b, &mut sol).unwrap()
                    })
                });
            }
        }
    }
    group.finish();
}

criterion_group!(solvers, benches);
criterion_main!(solvers);
