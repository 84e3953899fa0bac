//! Solve a 3D Poisson-like SPD system with CG, PCG (IC(0)) and the sparse Cholesky, and
//! print what each cost.
//!
//! `cargo run --release -p deform-solvers --example pcg`

use deform_solvers::SolverSpec;
use sprs::TriMat;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // 7-point Laplacian on a 30^3 grid, shifted to be well posed.
    let m = 30;
    let n = m * m * m;
    let id = |i: usize, j: usize, k: usize| (i * m + j) * m + k;
    let mut t = TriMat::new((n, n));
    for i in 0..m {
        for j in 0..m {
            for k in 0..m {
                t.add_triplet(id(i, j, k), id(i, j, k), 6.01);
                for (a, b, c) in [(i + 1, j, k), (i, j + 1, k), (i, j, k + 1)] {
                    if a < m && b < m && c < m {
                        t.add_triplet(id(i, j, k), id(a, b, c), -1.0);
                        t.add_triplet(id(a, b, c), id(i, j, k), -1.0);
                    }
                }
            }
        }
    }
    let a: sprs::CsMat<f64> = t.to_csr();
    let b = vec![1.0; n];
    for spec in [
        "Cg(tolerance: (rel: 1e-8))",
        "Pcg(preconditioner: Ic0, tolerance: (rel: 1e-8))",
        "Direct()",
    ] {
        let mut solver = ron::from_str::<SolverSpec>(spec)?.build()?;
        solver.analyze(&a)?;
        let setup = solver.factorize(&a)?;
        let mut x = vec![0.0; n];
        let stats = solver.solve(&a, &b, &mut x)?;
        println!(
            "{:<28} {:>4} iterations, residual {:.1e}, set-up {:.3} s ({:.2e} flops), solve {:.3} s ({:.2e} flops)",
            solver.name(),
            stats.iterations,
            stats.relative_residual(),
            setup.seconds,
            setup.flops as f64,
            stats.seconds,
            stats.flops as f64
        );
    }
    Ok(())
}
