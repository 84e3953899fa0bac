//! Every iterative solver on random sparse SPD systems against a dense Cholesky reference;
//! CG's finite termination; warm starts; indefinite input; argument errors.

use deform_solvers::{SolverError, SolverSpec, Termination};
use nalgebra::{DMatrix, DVector};
use proptest::prelude::*;
use sprs::{CsMat, TriMat};

/// `A = B^T B + c I` with a sparse random `B` whose rows couple nearby unknowns, so `A`
/// is banded-sparse like a stiffness matrix. Returned as CSR (full storage) and dense.
fn spd(n: usize, entries: &[(usize, usize, f64)], c: f64) -> (CsMat<f64>, DMatrix<f64>) {
    let mut b = DMatrix::zeros(n, n);
    for &(i, off, v) in entries {
        let i = i % n;
        let j = (i + off % 4) % n;
        b[(i, j)] += v;
    }
    let a = b.transpose() * &b + DMatrix::identity(n, n) * c;
    let mut t = TriMat::new((n, n));
    for i in 0..n {
        for j in 0..n {
            if a[(i, j)] != 0.0 {
                t.add_triplet(i, j, a[(i, j)]);
            }
        }
    }
    (t.to_csr(), a)
}

fn all_specs(rel: f64, max_iterations: usize) -> Vec<String> {
    let tol = format!("tolerance: (rel: {rel:e}, max_iterations: {max_iterations})");
    vec![
        format!("Cg({tol})"),
        format!("Pcg(preconditioner: Identity, {tol})"),
        format!("Pcg(preconditioner: Jacobi, {tol})"),
        format!("Pcg(preconditioner: BlockJacobi, {tol})"),
        format!("Pcg(preconditioner: Ssor(omega: 1.2), {tol})"),
        format!("Pcg(preconditioner: Ic0, {tol})"),
        format!("Pcg(preconditioner: Amg(), {tol})"),
    ]
}

fn run(
    spec: &str,
    a: &CsMat<f64>,
    b: &[f64],
    x: &mut [f64],
) -> Result<deform_solvers::SolveStats, SolverError> {
    let mut s = ron::from_str::<SolverSpec>(spec)
        .unwrap_or_else(|e| panic!("{spec}: {e}"))
        .build()
        .unwrap();
    s.analyze(a)?;
    s.factorize(a)?;
    s.solve(a, b, x)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn every_solver_meets_its_tolerance_and_agrees_with_cholesky(
        blocks in 2usize..12,
        entries in prop::collection::vec((0usize..64, 0usize..8, -1.0f64..1.0), 10..120),
        c in 0.05f64..2.0,
        rhs in prop::collection::vec(-1.0f64..1.0, 36),
    ) {
        let n = 3 * blocks;
        let (a, dense) = spd(n, &entries, c);
        let b: Vec<f64> = rhs[..n].to_vec();
        let reference = dense.clone().cholesky().unwrap().solve(&DVector::from_column_slice(&b));
        let cond_bound = {
            let e = dense.symmetric_eigenvalues();
            e.max() / e.min()
        };
        for spec in all_specs(1e-10, 10 * n) {
            let mut x = vec![0.0; n];
            let stats = run(&spec, &a, &b, &mut x).unwrap_or_else(|e| panic!("{spec}: {e}"));
            prop_assert_eq!(stats.termination, Termination::Converged);
            prop_assert!(stats.relative_residual() <= 1e-10, "{}: {}", spec, stats.relative_residual());
            // The true residual, recomputed, and the distance to the Cholesky solution.
            let xr = DVector::from_column_slice(&x);
            let true_res = (&dense * &xr - DVector::from_column_slice(&b)).norm() / DVector::from_column_slice(&b).norm().max(1e-300);
            prop_assert!(true_res < 1e-8, "{}: true residual {}", spec, true_res);
            prop_assert!((xr - &reference).norm() <= 1e-8 * cond_bound * reference.norm().max(1e-12), "{}", spec);
            prop_assert_eq!(stats.residuals.len(), stats.iterations + 1);
            prop_assert!(stats.flops > 0 && stats.matvecs == stats.iterations + 1);
        }
        // Every ordering of the direct solver, and PCG with an exact (fresh) Cholesky factor.
        for spec in [
            "Direct(ordering: Auto)",
            "Direct(ordering: Amd)",
            "Direct(ordering: NestedDissection)",
            "Direct(ordering: Natural, indefinite: Ldlt)",
            "Direct(precision: Mixed)",
        ] {
            let mut x = vec![1.0; n];
            let stats = run(spec, &a, &b, &mut x).unwrap_or_else(|e| panic!("{spec}: {e}"));
            prop_assert_eq!(stats.termination, Termination::Direct);
            let xr = DVector::from_column_slice(&x);
            let err = (xr - &reference).norm();
            prop_assert!(err <= 1e-12 * cond_bound * reference.norm().max(1e-12), "{}: {} vs {} cond {}", spec, err, reference.norm(), cond_bound);
        }
        let mut x = vec![0.0; n];
        let stats = run("Pcg(preconditioner: StaleCholesky(max_age: 0), tolerance: (rel: 1e-10))", &a, &b, &mut x).unwrap();
        prop_assert!(stats.iterations <= 2, "{}", stats.iterations);
        // Jacobi iteration converges when A is strongly diagonally dominant; test it on A + 10 nI.
        let (ad, dd) = spd(n, &entries, c + 10.0 * n as f64);
        let mut x = vec![0.0; n];
        let stats = run("Jacobi(omega: 1.0, tolerance: (rel: 1e-10, max_iterations: 5000))", &ad, &b, &mut x).unwrap();
        let r = (&dd * DVector::from_column_slice(&x) - DVector::from_column_slice(&b)).norm();
        prop_assert!(r <= 1e-9 * DVector::from_column_slice(&b).norm().max(1e-300), "jacobi {}", r);
        prop_assert!(stats.iterations > 0);
    }

    #[test]
    fn cg_terminates_in_at_most_n_iterations_and_warm_starts_are_free(
        blocks in 1usize..5,
        entries in prop::collection::vec((0usize..64, 0usize..8, -1.0f64..1.0), 5..40),
        rhs in prop::collection::vec(-1.0f64..1.0, 12),
    ) {
        let n = 3 * blocks;
        let (a, _) = spd(n, &entries, 0.5);
        let b: Vec<f64> = rhs[..n].to_vec();
        prop_assume!(b.iter().any(|v| v.abs() > 1e-3));
        let mut x = vec![0.0; n];
        // In exact arithmetic CG solves an n x n SPD system in n steps; in floating point,
        // n steps reach a small residual (1e-6 here), not machine precision.
        let stats = run(&format!("Cg(tolerance: (rel: 1e-6, max_iterations: {n}))"), &a, &b, &mut x).unwrap();
        prop_assert!(stats.iterations <= n);
        // Warm starts from an accurate solution return at once.
        let mut x = vec![0.0; n];
        run(&format!("Cg(tolerance: (rel: 1e-13, max_iterations: {}))", 10 * n), &a, &b, &mut x).unwrap();
        for spec in all_specs(1e-8, 100) {
            let mut warm = x.clone();
            let again = run(&spec, &a, &b, &mut warm).unwrap();
            prop_assert_eq!(again.iterations, 0, "{} from the solution", spec);
            prop_assert_eq!(&warm, &x);
        }
    }
}

#[test]
fn indefinite_input_is_reported() {
    // diag(1, -1, 1): CG meets negative curvature; preconditioner set-ups see the bad pivot.
    let mut t = TriMat::new((3, 3));
    for (i, v) in [1.0, -1.0, 1.0].into_iter().enumerate() {
        t.add_triplet(i, i, v);
    }
    let a: CsMat<f64> = t.to_csr();
    let b = vec![1.0, 1.0, 1.0];
    let mut x = vec![0.0; 3];
    match run("Cg()", &a, &b, &mut x) {
        Err(SolverError::Breakdown { curvature, stats }) => {
            assert!(curvature <= 0.0);
            assert_eq!(stats.termination, Termination::Breakdown);
        }
        other => panic!("expected a breakdown, got {other:?}"),
    }
    for spec in [
        "Direct()",
        "Pcg(preconditioner: StaleCholesky(max_age: 2))",
        "Pcg(preconditioner: Jacobi)",
        "Jacobi()",
        "Pcg(preconditioner: Ic0)",
        "Pcg(preconditioner: Ssor(omega: 1.0))",
    ] {
        let got = run(spec, &a, &b, &mut x);
        assert!(
            matches!(got, Err(SolverError::NotPositiveDefinite { pivot: 1, .. })),
            "{spec}: {got:?}"
        );
        // A failed sparse factorisation is charged (as a whole one); it is spent work.
        if let Err(e) = &got
            && spec.starts_with("Direct")
        {
            let spent = e.spent().expect("the factorisation's cost");
            assert!(spent.flops > 0 && spent.factor_nnz > 0, "{spent:?}");
        }
    }
    // Block Jacobi names the first row of the failing 3x3 block.
    assert!(matches!(
        run("Pcg(preconditioner: BlockJacobi)", &a, &b, &mut x),
        Err(SolverError::NotPositiveDefinite { pivot: 0, .. })
    ));
}

#[test]
fn bad_arguments_and_caps_give_typed_errors() {
    let (a, _) = spd(6, &[(0, 1, 1.0), (3, 2, 0.5)], 0.1);
    let mut x = vec![0.0; 6];
    assert!(matches!(
        run("Cg()", &a, &[1.0; 5], &mut x),
        Err(SolverError::DimensionMismatch {
            what: "b",
            expected: 6,
            found: 5
        })
    ));
    let mut nan = vec![1.0; 6];
    nan[4] = f64::NAN;
    assert!(matches!(
        run("Cg()", &a, &nan, &mut x),
        Err(SolverError::NonFinite {
            what: "b",
            index: 4
        })
    ));
    let b = vec![1.0, -2.0, 3.0, 0.5, 1.0, -1.0];
    match run(
        "Jacobi(omega: 0.1, tolerance: (rel: 1e-12, max_iterations: 3))",
        &a,
        &b,
        &mut x,
    ) {
        Err(SolverError::NotConverged { stats }) => {
            assert_eq!(stats.iterations, 3);
            assert_eq!(stats.termination, Termination::MaxIterations);
            assert_eq!(stats.residuals.len(), 4);
        }
        other => panic!("expected NotConverged, got {other:?}"),
    }
    let mut s = ron::from_str::<SolverSpec>("Cg()")
        .unwrap()
        .build()
        .unwrap();
    assert!(matches!(
        s.solve(&a, &b, &mut x),
        Err(SolverError::NotFactorized)
    ));
    for bad in [
        "Jacobi(omega: 2.5)",
        "Pcg(preconditioner: Ssor(omega: 0.0))",
        "Cg(tolerance: (rel: -1.0))",
        "Cg(tolerance: (max_iterations: 0))",
    ] {
        let spec: SolverSpec = ron::from_str(bad).unwrap();
        assert!(
            matches!(spec.build(), Err(SolverError::InvalidParameter { .. })),
            "{bad}"
        );
    }
    assert!(
        ron::from_str::<SolverSpec>("Cg(tolerance: (rel: 1e-6, relative: 1e-6))").is_err(),
        "unknown fields are rejected"
    );
}

/// A 2x2 matrix that is indefinite in double precision but positive definite once rounded
/// to single (`a12 = 1 + 5e-8` rounds to 1, `a22 = 1 + 8e-8` to `1 + 2^-23`).
fn indefinite_in_double_only() -> CsMat<f64> {
    let mut t = TriMat::new((2, 2));
    t.add_triplet(0, 0, 1.0);
    t.add_triplet(0, 1, 1.0 + 5e-8);
    t.add_triplet(1, 0, 1.0 + 5e-8);
    t.add_triplet(1, 1, 1.0 + 8e-8);
    t.to_csr()
}

#[test]
fn mixed_precision_stays_mixed_after_a_failed_double_refactorisation() {
    use deform_solvers::{Cholesky, Indefinite, LinearSolver, Ordering, Precision};
    let mut c = Cholesky::new(Ordering::Amd, Indefinite::Error);
    c.set_precision(Precision::Mixed);
    // The single factor exists, but refinement cannot converge; the double refactorisation
    // then finds the matrix indefinite and the solve fails.
    let bad = indefinite_in_double_only();
    c.factorize(&bad).unwrap();
    let mut x = vec![0.0; 2];
    assert!(c.solve(&bad, &[1.0, 0.0], &mut x).is_err());
    assert_eq!(c.precision(), Precision::Mixed);
    // The next matrix is factorised in single precision again: its solve refines.
    let (good, _) = spd(2, &[(0, 0, 1.0), (1, 1, 2.0)], 1.0);
    c.factorize(&good).unwrap();
    let stats = c.solve(&good, &[1.0, 1.0], &mut x).unwrap();
    assert!(
        stats.iterations >= 1,
        "solved by a double factor: {stats:?}"
    );
}

/// A residual floor stops every iterative solver at the first residual at or below it, and
/// none before: the same iterates as without it up to there. Direct solvers ignore it.
#[test]
fn a_residual_floor_stops_iterative_solves_where_it_says() {
    // A 1-D Laplacian with a longer-range coupling and a varying diagonal: SPD, and no
    // preconditioner here (IC(0) included) is exact.
    let n = 3000;
    let mut t = TriMat::new((n, n));
    for i in 0..n {
        t.add_triplet(i, i, 2.61 + (i as f64).sin().powi(2));
        for (off, v) in [(1, -1.0), (7, -0.3)] {
            if i + off < n {
                t.add_triplet(i, i + off, v);
                t.add_triplet(i + off, i, v);
            }
        }
    }
    let a: CsMat<f64> = t.to_csr();
    let b: Vec<f64> = (0..n).map(|i| (i as f64 * 0.37).sin()).collect();
    for spec in all_specs(1e-12, 10_000) {
        let mut tight = vec![0.0; n];
        let full = run(&spec, &a, &b, &mut tight).unwrap();
        let floor = 1e-4 * full.rhs_norm;
        let mut s = ron::from_str::<SolverSpec>(&spec).unwrap().build().unwrap();
        s.set_residual_floor(floor);
        s.factorize(&a).unwrap();
        let mut x = vec![0.0; n];
        let floored = s.solve(&a, &b, &mut x).unwrap();
        assert_eq!(floored.termination, Termination::Converged, "{spec}");
        let first = full.residuals.iter().position(|&r| r <= floor).unwrap();
        assert_eq!(floored.residuals, full.residuals[..=first], "{spec}");
        assert!(floored.iterations < full.iterations, "{spec}");
    }
    let mut direct = ron::from_str::<SolverSpec>("Direct()")
        .unwrap()
        .build()
        .unwrap();
    direct.set_residual_floor(1.0);
    direct.analyze(&a).unwrap();
    direct.factorize(&a).unwrap();
    let mut x = vec![0.0; n];
    let stats = direct.solve(&a, &b, &mut x).unwrap();
    assert!(stats.relative_residual() < 1e-12);
}
