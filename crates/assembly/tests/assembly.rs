//! Derivative checks, symmetry, rigid motions, refills, reduction, parameter gradients,
//! errors and thread-count independence of the assembly, for every material model.

use std::collections::BTreeMap;

use deform_assembly::{
    Assembly, AssemblyError, DofMap, Grouping, Mass, MaterialField, Outputs, StiffnessMatrix,
    StiffnessShift, Tangent,
};
use deform_materials::{MaterialSpec, Model};
use deform_mesh::TetMesh;
use deform_mesh::generate::BoxGrid;
use nalgebra::{DMatrix, Rotation3, Vector3};
use proptest::prelude::*;
use sprs::CsMat;

const SPECS: [&str; 8] = [
    "LinearElastic(Young(e: 1e5, nu: 0.3))",
    "CorotatedLinear(moduli: Young(e: 1e5, nu: 0.3))",
    "CorotatedLinear(moduli: Young(e: 1e5, nu: 0.3), lagged_rotation: true)",
    "FixedCorotated(Young(e: 1e5, nu: 0.3))",
    "StVenantKirchhoff(Young(e: 1e5, nu: 0.3))",
    "NeoHookean(Young(e: 1e5, nu: 0.3))",
    "StableNeoHookean(Young(e: 1e5, nu: 0.3))",
    "Ensemble([(weight: 0.5, model: NeoHookean(Young(e: 1e5, nu: 0.3))), (weight: 0.5, model: CorotatedLinear(moduli: Young(e: 2e5, nu: 0.2)))])",
];

fn model(spec: &str) -> Model {
    ron::from_str::<MaterialSpec>(spec)
        .unwrap()
        .build()
        .unwrap()
}

fn small_mesh() -> TetMesh {
    BoxGrid::beam(1).cells([2, 1, 1]).build().unwrap()
}

/// A smooth, moderately large deformation plus a deterministic per-DOF wiggle.
fn deformed(mesh: &TetMesh, amount: f64) -> Vec<f64> {
    mesh.rest_positions_flat()
        .chunks(3)
        .enumerate()
        .flat_map(|(v, p)| {
            let wiggle = |c: usize| amount * 0.02 * (((7 * v + 3 * c) % 11) as f64 / 11.0 - 0.5);
            [
                p[0] + amount * 0.1 * p[0] * p[2] + wiggle(0),
                p[1] + amount * 0.05 * (3.0 * p[0]).sin() + wiggle(1),
                p[2] - amount * 0.2 * p[0] * p[0] + wiggle(2),
            ]
        })
        .collect()
}

fn dense(k: &CsMat<f64>) -> DMatrix<f64> {
    let mut d = DMatrix::zeros(k.rows(), k.cols());
    for (v, (i, j)) in k.iter() {
        d[(i, j)] = *v;
    }
    d
}

fn forces(asm: &mut Assembly, x: &[f64]) -> Vec<f64> {
    let mut f = vec![0.0; x.len()];
    asm.forces(x, &mut f).unwrap();
    f
}

fn stiffness(asm: &mut Assembly, x: &[f64], tangent: Tangent) -> StiffnessMatrix {
    let mut k = asm.stiffness_matrix();
    asm.stiffness(x, tangent, &mut k).unwrap();
    k
}

fn max_abs(v: impl IntoIterator<Item = f64>) -> f64 {
    v.into_iter().fold(0.0, |m, x| m.max(x.abs()))
}

#[test]
fn forces_are_minus_the_energy_gradient_and_k_is_minus_the_force_jacobian() {
    let mesh = small_mesh();
    let x = deformed(&mesh, 1.0);
    for spec in SPECS {
        let mut asm = Assembly::new(&mesh, MaterialField::Uniform(model(spec))).unwrap();
        let f = forces(&mut asm, &x);
        let k = dense(&stiffness(&mut asm, &x, Tangent::Exact));
        let h = 1e-6;
        let (fscale, kscale) = (max_abs(f.iter().copied()), max_abs(k.iter().copied()));
        for i in 0..x.len() {
            let (mut xp, mut xm) = (x.clone(), x.clone());
            xp[i] += h;
            xm[i] -= h;
            let de = (asm.energy(&xp).unwrap() - asm.energy(&xm).unwrap()) / (2.0 * h);
            assert!(
                (f[i] + de).abs() <= 1e-6 * fscale,
                "{spec}: dof {i}: f {} vs -dE/dx {}",
                f[i],
                -de
            );
            // The lagged-rotation tangent is by design not the exact Jacobian away from pure
            // rotations (the materials crate checks it there).
            if spec.contains("lagged_rotation: true") {
                continue;
            }
            let (fp, fm) = (forces(&mut asm, &xp), forces(&mut asm, &xm));
            for j in 0..x.len() {
                let dfd = -(fp[j] - fm[j]) / (2.0 * h);
                assert!(
                    (k[(j, i)] - dfd).abs() <= 1e-6 * kscale,
                    "{spec}: K[{j},{i}] = {} vs -df/dx {}",
                    k[(j, i)],
                    dfd
                );
            }
        }
    }
}

#[test]
fn k_is_exactly_symmetric_and_matrix_free_products_agree() {
    let mesh = BoxGrid::beam(1).build().unwrap();
    let x = deformed(&mesh, 1.0);
    let dx: Vec<f64> = (0..x.len())
        .map(|i| ((i * 37) % 17) as f64 / 17.0 - 0.5)
        .collect();
    for spec in SPECS {
        let mut asm = Assembly::new(&mesh, MaterialField::Uniform(model(spec))).unwrap();
        for tangent in [Tangent::Exact, Tangent::Projected] {
            let k = stiffness(&mut asm, &x, tangent);
            let kd = dense(&k);
            assert!(
                kd == kd.transpose(),
                "{spec} {tangent:?}: K is not exactly symmetric"
            );
            let kdx = &kd * nalgebra::DVector::from_column_slice(&dx);
            let scale = max_abs(kdx.iter().copied());
            let op = asm.tangents(&x, tangent).unwrap();
            let mut y = vec![0.0; x.len()];
            op.apply(&dx, &mut y);
            assert!(
                max_abs(y.iter().zip(kdx.iter()).map(|(a, b)| a - b)) <= 1e-10 * scale,
                "{spec}"
            );
            let mut diag = vec![0.0; x.len()];
            op.diagonal(&mut diag);
            for (i, d) in diag.iter().enumerate() {
                assert!(
                    (d - kd[(i, i)]).abs() <= 1e-10 * kscale_of(&kd),
                    "{spec}: diag {i}"
                );
            }
            if tangent == Tangent::Exact {
                let mut df = vec![0.0; x.len()];
                asm.force_differential(&x, &dx, &mut df).unwrap();
                assert!(
                    max_abs(df.iter().zip(kdx.iter()).map(|(a, b)| a + b)) <= 1e-9 * scale,
                    "{spec}"
                );
            } else {
                let min = kd.symmetric_eigenvalues().min();
                assert!(
                    min >= -1e-8 * kscale_of(&kd),
                    "{spec}: projected K has eigenvalue {min}"
                );
            }
        }
    }
}

fn kscale_of(k: &DMatrix<f64>) -> f64 {
    max_abs(k.iter().copied())
}

#[test]
fn rigid_motions_cost_nothing() {
    let mesh = BoxGrid::beam(1).build().unwrap();
    let rest = mesh.rest_positions_flat();
    let rotation = Rotation3::from_axis_angle(&Vector3::y_axis(), 0.7)
        * Rotation3::from_axis_angle(&Vector3::x_axis(), -1.1);
    let x = deformed(&mesh, 1.0);
    let moved: Vec<f64> = x
        .chunks(3)
        .flat_map(|p| {
            let q = rotation * Vector3::new(p[0], p[1], p[2]) + Vector3::new(0.3, -2.0, 5.0);
            [q.x, q.y, q.z]
        })
        .collect();
    for spec in SPECS {
        let mut asm = Assembly::new(&mesh, MaterialField::Uniform(model(spec))).unwrap();
        let k = dense(&stiffness(&mut asm, &rest, Tangent::Exact));
        let scale = kscale_of(&k);
        // Translations and infinitesimal rotations are in K's null space at rest.
        let mut fields: Vec<Vec<f64>> = (0..3)
            .map(|c| {
                (0..rest.len())
                    .map(|i| f64::from(u8::from(i % 3 == c)))
                    .collect()
            })
            .collect();
        for axis in [Vector3::x(), Vector3::y(), Vector3::z()] {
            fields.push(
                rest.chunks(3)
                    .flat_map(|p| {
                        let w = axis.cross(&Vector3::new(p[0], p[1], p[2]));
                        [w.x, w.y, w.z]
                    })
                    .collect(),
            );
        }
        for u in &fields {
            let ku = &k * nalgebra::DVector::from_column_slice(u);
            assert!(ku.amax() <= 1e-10 * scale, "{spec}: K u = {}", ku.amax());
        }
        // Forces sum to zero (momentum) at any state.
        let f = forces(&mut asm, &x);
        let mut total = Vector3::zeros();
        for c in f.chunks(3) {
            total += Vector3::new(c[0], c[1], c[2]);
        }
        assert!(
            total.amax() <= 1e-10 * max_abs(f.iter().copied()),
            "{spec}: {total}"
        );
        // Frame invariance (not for small-strain linear elasticity).
        if !spec.starts_with("LinearElastic") {
            let (e0, e1) = (asm.energy(&x).unwrap(), asm.energy(&moved).unwrap());
            assert!((e0 - e1).abs() <= 1e-10 * e0.abs(), "{spec}: {e0} vs {e1}");
        }
    }
}

#[test]
fn refills_equal_fresh_assembly_and_reduction_equals_restriction() {
    let mesh = BoxGrid::beam(1).build().unwrap();
    let mut asm = Assembly::new(&mesh, MaterialField::Uniform(model(SPECS[5]))).unwrap();
    let (x1, x2) = (deformed(&mesh, 0.5), deformed(&mesh, 1.0));
    let mut k = asm.stiffness_matrix();
    asm.stiffness(&x1, Tangent::Exact, &mut k).unwrap();
    asm.stiffness(&x2, Tangent::Exact, &mut k).unwrap();
    let fresh = stiffness(
        &mut Assembly::new(&mesh, MaterialField::Uniform(model(SPECS[5]))).unwrap(),
        &x2,
        Tangent::Exact,
    );
    assert_eq!(k, fresh);
    // Energy, forces and K in one pass equal the separate calls.
    let (mut e, mut f, mut k2) = (0.0, vec![0.0; x2.len()], asm.stiffness_matrix());
    asm.evaluate(
        &x2,
        Outputs {
            energy: Some(&mut e),
            forces: Some(&mut f),
            stiffness: Some(&mut k2),
            tangent: Tangent::Exact,
            ..Outputs::default()
        },
    )
    .unwrap();
    assert_eq!(e, asm.energy(&x2).unwrap());
    assert_eq!(f, forces(&mut asm, &x2));
    assert_eq!(k2, fresh);

    let clamped: Vec<usize> = (0..mesh.num_vertices())
        .filter(|&v| mesh.rest_positions()[v].x < 1e-9)
        .collect();
    let dofs = DofMap::new(mesh.num_vertices(), &clamped).unwrap();
    assert_eq!(dofs.num_free(), 3 * (mesh.num_vertices() - clamped.len()));
    let mut reduced = dofs.reduced_matrix(&asm.stiffness_matrix()).unwrap();
    dofs.restrict_matrix(&k, &mut reduced).unwrap();
    let (kd, rd) = (dense(&k), dense(&reduced.matrix));
    for (a, &i) in dofs.free_dofs().iter().enumerate() {
        for (b, &j) in dofs.free_dofs().iter().enumerate() {
            assert_eq!(rd[(a, b)], kd[(i, j)]);
        }
    }
    let mut rf = vec![0.0; dofs.num_free()];
    dofs.restrict(&f, &mut rf).unwrap();
    let mut back = vec![7.0; f.len()];
    dofs.scatter(&rf, &mut back).unwrap();
    for v in 0..mesh.num_vertices() {
        for c in 0..3 {
            let expect = if dofs.is_constrained(v) {
                7.0
            } else {
                f[3 * v + c]
            };
            assert_eq!(back[3 * v + c], expect);
        }
    }
    assert!(matches!(
        DofMap::new(3, &[3]),
        Err(AssemblyError::VertexOutOfRange { vertex: 3, .. })
    ));
}

#[test]
fn mass_and_damping() {
    let mesh = BoxGrid::beam(1).build().unwrap();
    let mut asm = Assembly::new(&mesh, MaterialField::Uniform(model(SPECS[5]))).unwrap();
    let volume: f64 = mesh.volumes().iter().sum();
    let (lumped, consistent) = (
        Mass::lumped(&mesh, 1000.0),
        Mass::consistent(&mesh, 1000.0, asm.pattern()),
    );
    let total: f64 = asm.vertex_masses(&lumped).iter().sum();
    assert!((total - 1000.0 * volume).abs() < 1e-12 * total);
    let rows = asm.vertex_masses(&consistent);
    for (a, b) in rows.iter().zip(asm.vertex_masses(&lumped)) {
        assert!((a - b).abs() < 1e-12 * b);
    }
    let x = deformed(&mesh, 1.0);
    let k = stiffness(&mut asm, &x, Tangent::Exact);
    let v: Vec<f64> = (0..x.len()).map(|i| (i as f64 * 0.37).sin()).collect();
    for mass in [&lumped, &consistent] {
        let mut a = asm.stiffness_matrix();
        asm.combine(0.3, mass, 0.01, &k, &mut a).unwrap();
        let mut mv = vec![0.0; v.len()];
        asm.mass_apply(mass, &v, &mut mv).unwrap();
        let kv = dense(&k) * nalgebra::DVector::from_column_slice(&v);
        let av = dense(&a) * nalgebra::DVector::from_column_slice(&v);
        let mut fd = vec![0.0; v.len()];
        asm.damping_forces(0.3, 0.01, mass, &k, &v, &mut fd)
            .unwrap();
        for i in 0..v.len() {
            let expect = 0.3 * mv[i] + 0.01 * kv[i];
            assert!(
                (av[i] - expect).abs() <= 1e-10 * expect.abs().max(1.0),
                "{i}"
            );
            assert!(
                (fd[i] + expect).abs() <= 1e-10 * expect.abs().max(1.0),
                "{i}"
            );
        }
        // Combined straight into the free DOFs: the same values as combining, then
        // restricting.
        let clamped: Vec<usize> = (0..mesh.num_vertices())
            .filter(|&v| mesh.rest_positions()[v].x < 1e-9)
            .collect();
        let dofs = DofMap::new(mesh.num_vertices(), &clamped).unwrap();
        let mut restricted = dofs.reduced_matrix(&a).unwrap();
        dofs.restrict_matrix(&a, &mut restricted).unwrap();
        let mut direct = dofs.reduced_matrix(&a).unwrap();
        direct.matrix.data_mut().fill(f64::NAN);
        asm.combine_reduced(0.3, mass, 0.01, &k, &dofs, &mut direct)
            .unwrap();
        assert_eq!(direct.matrix, restricted.matrix);
        let other = DofMap::new(mesh.num_vertices() + 1, &[]).unwrap();
        assert!(matches!(
            asm.combine_reduced(0.3, mass, 0.01, &k, &other, &mut direct),
            Err(AssemblyError::PatternMismatch)
        ));
    }
}

#[test]
fn parameter_gradients_equal_finite_differences() {
    // Two regions with different Lame pairs; the Jacobian per region against perturbing each.
    let mesh = small_mesh();
    let regions: Vec<u32> = (0..mesh.num_tets())
        .map(|e| if e < mesh.num_tets() / 2 { 1 } else { 2 })
        .collect();
    let mesh = TetMesh::try_with_options(
        mesh.rest_positions().to_vec(),
        mesh.tets().to_vec(),
        Some(regions),
        &Default::default(),
    )
    .unwrap();
    let x = deformed(&mesh, 1.0);
    let dx: Vec<f64> = (0..x.len())
        .map(|i| ((i * 13) % 7) as f64 / 7.0 - 0.5)
        .collect();
    for base in [
        "NeoHookean",
        "StVenantKirchhoff",
        "CorotatedLinear",
        "StableNeoHookean",
    ] {
        let make = |lame: [(f64, f64); 2]| {
            let mut table = BTreeMap::new();
            for (r, (mu, lambda)) in [1u32, 2].into_iter().zip(lame) {
                let spec = if base == "CorotatedLinear" {
                    format!("CorotatedLinear(moduli: Lame(mu: {mu}, lambda: {lambda}))")
                } else {
                    format!("{base}(Lame(mu: {mu}, lambda: {lambda}))")
                };
                table.insert(r, model(&spec));
            }
            Assembly::new(&mesh, MaterialField::by_region(&mesh, &table).unwrap()).unwrap()
        };
        let lame = [(3e4, 5e4), (1e4, 2e4)];
        let asm = make(lame);
        let grouping = Grouping::by_region(&asm);
        assert_eq!(grouping.labels(), &[1, 2]);
        let jf = asm.term_forces(&x, &grouping).unwrap();
        let jk = asm.term_stiffness_products(&x, &dx, &grouping).unwrap();
        assert_eq!(jf.num_columns(), 4);
        for (col, (g, k)) in [(0usize, 0usize), (0, 1), (1, 0), (1, 1)]
            .into_iter()
            .enumerate()
        {
            let h = 1.0;
            let perturbed = |s: f64| {
                let mut l = lame;
                if k == 0 {
                    l[g].0 += s * h
                } else {
                    l[g].1 += s * h
                }
                make(l)
            };
            let (mut ap, mut am) = (perturbed(1.0), perturbed(-1.0));
            let (fp, fm) = (forces(&mut ap, &x), forces(&mut am, &x));
            let fd: Vec<f64> = fp
                .iter()
                .zip(&fm)
                .map(|(a, b)| (a - b) / (2.0 * h))
                .collect();
            let got = jf.column(col);
            let scale = max_abs(fd.iter().copied());
            assert!(
                max_abs(got.iter().zip(&fd).map(|(a, b)| a - b)) <= 1e-6 * scale,
                "{base} column {col}"
            );
            let kp = dense(&stiffness(&mut ap, &x, Tangent::Exact))
                * nalgebra::DVector::from_column_slice(&dx);
            let km = dense(&stiffness(&mut am, &x, Tangent::Exact))
                * nalgebra::DVector::from_column_slice(&dx);
            let got = jk.column(col);
            let scale = kp.amax();
            for i in 0..x.len() {
                assert!(
                    (got[i] - (kp[i] - km[i]) / (2.0 * h)).abs() <= 1e-6 * scale,
                    "{base} K column {col}"
                );
            }
        }
    }
}

#[test]
fn inverted_elements_and_bad_input_give_typed_errors() {
    let mesh = small_mesh();
    let mut x = mesh.rest_positions_flat();
    // Push vertex 0 through the opposite faces of its elements: its first element inverts.
    let first = (0..mesh.num_tets())
        .find(|&e| mesh.tets()[e].contains(&0))
        .unwrap();
    x[0] = 0.6;
    x[1] = 0.3;
    x[2] = 0.3;
    let mut nh = Assembly::new(&mesh, MaterialField::Uniform(model(SPECS[5]))).unwrap();
    let mut f = vec![0.0; x.len()];
    match nh.forces(&x, &mut f) {
        Err(AssemblyError::Inadmissible {
            element,
            det,
            model,
        }) => {
            assert!(
                element >= first && det <= 0.0 && model.contains("eo"),
                "{element} {det} {model}"
            );
            assert!(mesh.tets()[element].contains(&0));
        }
        other => panic!("expected an inadmissible element, got {other:?}"),
    }
    // Stable Neo-Hookean is defined there, and finite.
    let mut snh = Assembly::new(&mesh, MaterialField::Uniform(model(SPECS[6]))).unwrap();
    snh.forces(&x, &mut f).unwrap();
    assert!(f.iter().all(|v| v.is_finite()));
    let mut nan = mesh.rest_positions_flat();
    nan[7] = f64::NAN;
    assert!(matches!(
        snh.energy(&nan),
        Err(AssemblyError::NonFinite { vertex: 2, .. })
    ));
    assert!(matches!(
        snh.energy(&nan[..6]),
        Err(AssemblyError::DimensionMismatch { what: "x", .. })
    ));
    // A foreign matrix is checked once when adopted; another assembly's is refused at use,
    // even on the same mesh (each assembly's pattern has its own identity).
    assert!(matches!(
        snh.adopt_stiffness_matrix(CsMat::eye(x.len())),
        Err(AssemblyError::PatternMismatch)
    ));
    let other = Assembly::new(&mesh, MaterialField::Uniform(model(SPECS[0]))).unwrap();
    let mut wrong = other.stiffness_matrix();
    assert!(matches!(
        snh.stiffness(&x, Tangent::Exact, &mut wrong),
        Err(AssemblyError::PatternMismatch)
    ));
    let mut adopted = snh
        .adopt_stiffness_matrix(wrong.into_csr())
        .expect("the same mesh's pattern");
    snh.stiffness(&x, Tangent::Exact, &mut adopted).unwrap();
    assert_eq!(adopted, stiffness(&mut snh, &x, Tangent::Exact));
    assert!(
        Assembly::new(
            &mesh,
            MaterialField::PerElement {
                models: vec![model(SPECS[0])],
                index: vec![0; 3]
            }
        )
        .is_err()
    );
}

#[test]
fn results_do_not_depend_on_the_thread_count() {
    // Beam(6): 5184 tets and 1225 vertices, enough chunks of both for the parallel passes
    // (smaller meshes run on the calling thread).
    let mesh = BoxGrid::beam(6).build().unwrap();
    let x = deformed(&mesh, 1.0);
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                let mut asm =
                    Assembly::new(&mesh, MaterialField::Uniform(model(SPECS[7]))).unwrap();
                let (mut e, mut f, mut k) = (0.0, vec![0.0; x.len()], asm.stiffness_matrix());
                let mut kx = vec![0.0; x.len()];
                let shift = StiffnessShift {
                    direction: &x,
                    step: 1e-7,
                    scale: 0.5,
                };
                asm.evaluate(
                    &x,
                    Outputs {
                        energy: Some(&mut e),
                        forces: Some(&mut f),
                        stiffness: Some(&mut k),
                        tangent: Tangent::Projected,
                        stiffness_product: Some((&x, &mut kx)),
                        stiffness_shift: Some(shift),
                    },
                )
                .unwrap();
                let mut y = vec![0.0; x.len()];
                asm.tangents(&x, Tangent::Exact).unwrap().apply(&f, &mut y);
                let j = asm.term_forces(&x, &Grouping::global(&asm)).unwrap();
                // The Newton matrix on the free DOFs, combined in parallel row chunks, and
                // restricted from the full one in parallel value chunks: the same values.
                let clamped: Vec<usize> = (0..mesh.num_vertices())
                    .filter(|&v| mesh.rest_positions()[v].x < 1e-9)
                    .collect();
                let dofs = DofMap::new(mesh.num_vertices(), &clamped).unwrap();
                let mass = Mass::lumped(&mesh, 1000.0);
                let mut full = asm.stiffness_matrix();
                asm.combine(0.3, &mass, 0.01, &k, &mut full).unwrap();
                let mut restricted = dofs.reduced_matrix(&full).unwrap();
                restricted.matrix.data_mut().fill(f64::NAN);
                dofs.restrict_matrix(&full, &mut restricted).unwrap();
                let mut combined = dofs.reduced_matrix(&full).unwrap();
                combined.matrix.data_mut().fill(f64::NAN);
                asm.combine_reduced(0.3, &mass, 0.01, &k, &dofs, &mut combined)
                    .unwrap();
                assert_eq!(combined.matrix, restricted.matrix);
                (e, f, k, kx, y, j, combined.matrix)
            })
    };
    let one = run(1);
    assert_eq!(one, run(2));
    assert_eq!(one, run(4));
}

#[test]
fn a_per_element_field_of_one_model_equals_the_uniform_field() {
    let mesh = BoxGrid::beam(1).build().unwrap();
    let x = deformed(&mesh, 1.0);
    let m = model(SPECS[4]);
    let mut uniform = Assembly::new(&mesh, MaterialField::Uniform(m.clone())).unwrap();
    let mut table = Assembly::new(
        &mesh,
        MaterialField::PerElement {
            models: vec![m],
            index: vec![0; mesh.num_tets()],
        },
    )
    .unwrap();
    assert_eq!(forces(&mut uniform, &x), forces(&mut table, &x));
    assert_eq!(
        stiffness(&mut uniform, &x, Tangent::Exact),
        stiffness(&mut table, &x, Tangent::Exact)
    );
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    #[test]
    fn momentum_and_symmetry_hold_at_random_states(
        noise in prop::collection::vec(-0.02f64..0.02, 60),
        which in 0usize..SPECS.len(),
    ) {
        let mesh = small_mesh();
        let x: Vec<f64> = mesh.rest_positions_flat().iter().zip(noise.iter().cycle()).map(|(p, n)| p + n).collect();
        let mut asm = Assembly::new(&mesh, MaterialField::Uniform(model(SPECS[which]))).unwrap();
        let mut f = vec![0.0; x.len()];
        match asm.forces(&x, &mut f) {
            Ok(()) => {}
            Err(AssemblyError::Inadmissible { .. }) => return Ok(()),
            Err(e) => panic!("{e}"),
        }
        let total: Vector3<f64> = f.chunks(3).map(|c| Vector3::new(c[0], c[1], c[2])).sum();
        prop_assert!(total.amax() <= 1e-9 * max_abs(f.iter().copied()).max(1e-300));
        let k = dense(&stiffness(&mut asm, &x, Tangent::Exact));
        prop_assert!(k == k.transpose(), "K is not exactly symmetric");
    }
}

#[test]
fn term_vector_jacobian_products_equal_the_jacobians_applied_from_the_left() {
    let mesh = small_mesh();
    let x = deformed(&mesh, 1.0);
    let n = x.len();
    let lambda: Vec<f64> = (0..n).map(|i| ((i * 7) % 11) as f64 / 11.0 - 0.4).collect();
    let dx: Vec<f64> = (0..n).map(|i| ((i * 5) % 13) as f64 / 13.0 - 0.5).collect();
    let asm = Assembly::new(
        &mesh,
        MaterialField::Uniform(model("StableNeoHookean(Lame(mu: 3e4, lambda: 5e4))")),
    )
    .unwrap();
    let labels: Vec<u32> = (0..mesh.num_tets() as u32).map(|e| 7 - e % 3).collect();
    let groupings = [
        Grouping::global(&asm),
        Grouping::per_element(&asm),
        Grouping::from_labels(&asm, &labels).unwrap(),
    ];
    assert_eq!(groupings[2].labels(), &[5, 6, 7]);
    for grouping in &groupings {
        for d in [None, Some(dx.as_slice())] {
            let got = asm.term_vjp(&x, d, &lambda, grouping).unwrap();
            let j = match d {
                None => asm.term_forces(&x, grouping).unwrap(),
                Some(d) => asm.term_stiffness_products(&x, d, grouping).unwrap(),
            };
            assert_eq!(got.len(), j.num_columns());
            for (c, g) in got.iter().enumerate() {
                let want: f64 = j.column(c).iter().zip(&lambda).map(|(a, b)| a * b).sum();
                assert!(
                    (g - want).abs() <= 1e-9 * want.abs().max(1e-3),
                    "column {c}: {g} vs {want}"
                );
            }
        }
    }
    // A field's entries sum to the global ones.
    let global = asm.term_vjp(&x, None, &lambda, &groupings[0]).unwrap();
    let field = asm.term_vjp(&x, None, &lambda, &groupings[1]).unwrap();
    for k in 0..2 {
        let sum: f64 = field.iter().skip(k).step_by(2).sum();
        assert!((sum - global[k]).abs() <= 1e-9 * global[k].abs());
    }
    assert!(Grouping::from_labels(&asm, &[1, 2]).is_err());
}

#[test]
fn a_field_from_term_coefficients_has_one_model_per_group_and_names_a_bad_one() {
    let base = model("NeoHookean(Lame(mu: 3e4, lambda: 5e4))");
    let field =
        MaterialField::from_term_coefficients(&base, vec![1, 0, 1], &[1e4, 2e4, 3e4, 4e4]).unwrap();
    let MaterialField::PerElement { models, index } = &field else {
        panic!("per element")
    };
    assert_eq!(index, &[1, 0, 1]);
    assert_eq!(models[1].term_coefficients(), vec![3e4, 4e4]);
    let short = MaterialField::from_term_coefficients(&base, vec![0, 1], &[1e4, 2e4]).unwrap_err();
    assert!(
        short.to_string().contains("2 coefficients, expected 4"),
        "{short}"
    );
    let bad = MaterialField::from_term_coefficients(&base, vec![0, 1], &[1e4, 2e4, -1e4, 2e4])
        .unwrap_err();
    assert!(bad.to_string().contains("group 1"), "{bad}");
}

#[test]
fn values_on_the_pattern_equal_the_matrix_bit_for_bit() {
    let mesh = small_mesh();
    let field = MaterialField::Uniform(model("NeoHookean(Young(e: 1e5, nu: 0.4))"));
    let mut asm = Assembly::new(&mesh, field).unwrap();
    let x = deformed(&mesh, 0.05);
    let (mut e1, mut f1, mut k) = (0.0, vec![0.0; x.len()], asm.stiffness_matrix());
    let out = Outputs {
        energy: Some(&mut e1),
        forces: Some(&mut f1),
        stiffness: Some(&mut k),
        tangent: Tangent::Projected,
        ..Outputs::default()
    };
    asm.evaluate(&x, out).unwrap();
    let (indptr, indices) = asm.stiffness_pattern();
    assert_eq!(
        (indptr.as_slice(), indices.as_slice()),
        (k.indptr().raw_storage(), k.indices())
    );
    // The same row pointers with another column in row 0 (its last, moved to the last
    // column) are not the pattern.
    let mut moved = indices.clone();
    let last = indptr[1] - 1;
    assert!(moved[last] < k.cols() - 1);
    moved[last] = k.cols() - 1;
    let other = CsMat::new(k.shape(), indptr.clone(), moved, k.data().to_vec());
    assert!(asm.has_pattern(&k) && !asm.has_pattern(&other));
    let mut values = vec![0.0; indices.len()];
    let (mut e2, mut f2) = (0.0, vec![0.0; x.len()]);
    asm.evaluate_values(
        &x,
        Some(&mut e2),
        Some(&mut f2),
        &mut values,
        Tangent::Projected,
    )
    .unwrap();
    assert_eq!((e1, &f1), (e2, &f2));
    assert_eq!(values, k.data());
    let mut short = vec![0.0; values.len() - 1];
    let e = asm
        .evaluate_values(&x, None, None, &mut short, Tangent::Exact)
        .unwrap_err();
    assert!(e.to_string().contains("values"), "{e}");
}

#[test]
fn results_do_not_depend_on_the_block_size_and_errors_name_the_first_element() {
    // Beam(3): 648 tets, so blocks of 512 split it in two and every output crosses a block
    // boundary; a per-element field, so each element's model is looked up by its index.
    let mesh = BoxGrid::beam(3).build().unwrap();
    let x = deformed(&mesh, 1.0);
    let models: Vec<Model> = SPECS.iter().map(|s| model(s)).collect();
    let index: Vec<u32> = (0..mesh.num_tets())
        .map(|e| (e % models.len()) as u32)
        .collect();
    let field = MaterialField::PerElement { models, index };
    let run = |block: Option<usize>, x: &[f64]| {
        let mut asm = Assembly::new(&mesh, field.clone()).unwrap();
        if let Some(b) = block {
            asm.set_block_elements(b);
        }
        let (mut e, mut f, mut k) = (0.0, vec![0.0; x.len()], asm.stiffness_matrix());
        let all = asm.evaluate(
            x,
            Outputs {
                energy: Some(&mut e),
                forces: Some(&mut f),
                stiffness: Some(&mut k),
                tangent: Tangent::Exact,
                ..Outputs::default()
            },
        );
        // Forces alone take the other gather path.
        let mut g = vec![0.0; x.len()];
        let alone = asm.forces(x, &mut g).map(|()| g);
        (all.map(|()| (e, f, k)), alone)
    };
    let whole = run(None, &x);
    for block in [1, 512, 600] {
        let (all, alone) = run(Some(block), &x);
        assert_eq!(
            all.as_ref().unwrap(),
            whole.0.as_ref().unwrap(),
            "block {block}"
        );
        assert_eq!(alone.as_ref().unwrap(), whole.1.as_ref().unwrap());
        assert_eq!(&alone.unwrap(), &all.unwrap().1);
    }
    // Inverted elements in both blocks: the lowest-indexed one is named whatever the blocks.
    let mut bad = x.clone();
    for e in [600, 100] {
        let v = mesh.tets()[e][0];
        let opposite = mesh.tets()[e][1..]
            .iter()
            .fold(Vector3::zeros(), |s, &w| s + mesh.rest_positions()[w])
            / 3.0;
        let p = mesh.rest_positions()[v];
        let through = opposite + 2.0 * (opposite - p);
        bad[3 * v..3 * v + 3].copy_from_slice(through.as_slice());
    }
    let named = |block: Option<usize>| match run(block, &bad).0 {
        Err(AssemblyError::Inadmissible { element, .. }) => element,
        other => panic!(
            "expected an inadmissible element, got {:?}",
            other.map(|r| r.0)
        ),
    };
    let first = named(None);
    assert!(first <= 100, "{first}");
    assert_eq!(named(Some(512)), first);
    assert_eq!(named(Some(1)), first);
}

#[test]
fn the_stiffness_product_and_shift_equal_k_applied_and_its_directional_derivative() {
    // `K w` element by element equals the assembled K applied to w; `K + s D_w K` from one
    // pass equals K plus s times the forward difference of two assemblies (the same step,
    // so both carry the same truncation), and the central difference to its truncation.
    let mesh = BoxGrid::beam(1).build().unwrap();
    let x = deformed(&mesh, 1.0);
    let w: Vec<f64> = (0..x.len())
        .map(|i| ((i * 29) % 13) as f64 / 13.0 - 0.5)
        .collect();
    let step = 1e-7 / max_abs(w.iter().copied());
    let scale = 0.3;
    for spec in SPECS {
        let mut asm = Assembly::new(&mesh, MaterialField::Uniform(model(spec))).unwrap();
        for tangent in [Tangent::Exact, Tangent::Projected] {
            let k = stiffness(&mut asm, &x, tangent);
            let (mut kw, mut shifted) = (vec![0.0; x.len()], asm.stiffness_matrix());
            let outputs = Outputs {
                stiffness: Some(&mut shifted),
                tangent,
                stiffness_product: Some((&w, &mut kw)),
                stiffness_shift: Some(StiffnessShift {
                    direction: &w,
                    step,
                    scale,
                }),
                ..Outputs::default()
            };
            asm.evaluate(&x, outputs).unwrap();
            let expected = &dense(&k) * nalgebra::DVector::from_column_slice(&w);
            let size = max_abs(expected.iter().copied());
            let error = max_abs(kw.iter().zip(expected.iter()).map(|(a, b)| a - b));
            assert!(
                error <= 1e-12 * size,
                "{spec} {tangent:?}: K w off by {error:e}"
            );
            let mut at = |e: f64| -> Vec<f64> {
                let xe: Vec<f64> = x.iter().zip(&w).map(|(x, w)| x + e * w).collect();
                stiffness(&mut asm, &xe, tangent).csr().data().to_vec()
            };
            let (ahead, behind) = (at(step), at(-step));
            let k0 = k.csr().data();
            let forward: Vec<f64> = (0..k0.len())
                .map(|i| k0[i] + scale * (ahead[i] - k0[i]) / step)
                .collect();
            let derivative = max_abs((0..k0.len()).map(|i| (ahead[i] - k0[i]) / step));
            let got = shifted.csr().data();
            let error = max_abs(got.iter().zip(&forward).map(|(a, b)| a - b));
            assert!(
                error <= 1e-6 * scale * derivative.max(1e-3 * max_abs(k0.iter().copied())),
                "{spec} {tangent:?}: K + s D_w K off the forward difference by {error:e}"
            );
            // A linear model's K does not move: its derivative is (rounding) zero.
            if spec.starts_with("LinearElastic") {
                assert!(derivative <= 1e-6 * max_abs(k0.iter().copied()), "{spec}");
                continue;
            }
            let central: Vec<f64> = (0..k0.len())
                .map(|i| k0[i] + scale * (ahead[i] - behind[i]) / (2.0 * step))
                .collect();
            let error = max_abs(got.iter().zip(&central).map(|(a, b)| a - b));
            assert!(
                error <= 1e-4 * scale * derivative,
                "{spec} {tangent:?}: K + s D_w K off the central difference by {error:e}"
            );
        }
    }
}
