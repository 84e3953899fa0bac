//! Unit tests of surface pairs: distances, barrier derivatives against finite differences,
//! the collision bound, lagged friction.

use super::*;
use proptest::prelude::*;

/// Two tetrahedra's surfaces: the second's apex `gap` above the first's top face, an
/// edge of it crossing over an edge of the first.
fn pair(gap: f64, jitter: [f64; 24]) -> (SelfContact, Vec<f64>) {
    let mut x = vec![
        0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0, //
        0.5, -0.3, gap, 0.5, 0.3, gap, 0.9, 0.0, 0.7, 0.1, 0.1, 0.8,
    ];
    for (x, j) in x.iter_mut().zip(jitter) {
        *x += j;
    }
    let faces = |o: usize| {
        [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]].map(|f: [usize; 3]| f.map(|v| v + o))
    };
    let triangles = [faces(0), faces(4)].concat();
    (SelfContact::new(triangles, &x).unwrap(), x)
}

/// Faces that touch at rest (the second tetrahedron's base edge lying across the first's
/// top face) are refused as touching, naming the pair, not blamed on `dhat`; a pair apart
/// but within `dhat` still is.
#[test]
fn faces_touching_at_rest_are_named_not_blamed_on_dhat() {
    let (touching, x) = pair(0.0, [0.0; 24]);
    let message = touching.check_separated(&x, 0.1).unwrap_err().to_string();
    assert!(
        message.contains("self_contact") && message.contains("touch at rest"),
        "{message}"
    );
    let (close, x) = pair(0.05, [0.0; 24]);
    let message = close.check_separated(&x, 0.1).unwrap_err().to_string();
    assert!(
        message.contains("dhat") && message.contains("apart at rest"),
        "{message}"
    );
}

/// The second tetrahedron as a fixed mesh obstacle gives the first the same energy,
/// forces and Hessian blocks as the two in self-contact (no pair within one tetrahedron
/// is within `dhat`), and the obstacle no force or block.
#[test]
fn a_fixed_mesh_acts_as_the_same_surface_in_self_contact() {
    let b = Barrier {
        dhat: 0.1,
        kappa: 10.0,
    };
    let (both, x) = pair(0.03, [0.0; 24]);
    let faces = [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]];
    let mesh = SelfContact::with_meshes(
        faces.to_vec(),
        &x[..12],
        false,
        &[(x[12..].to_vec(), faces.to_vec())],
    )
    .unwrap();
    let eval = |s: &SelfContact, y: &[f64]| {
        let mut summary = ContactSummary {
            energy: 0.0,
            active: 0,
            min_distance: f64::INFINITY,
        };
        let (mut f, mut h) = (vec![0.0; y.len()], ContactHessian::default());
        s.evaluate(y, (b, true), &mut summary, Some(&mut f), Some(&mut h))
            .unwrap();
        (summary, f, h)
    };
    let (s2, f2, h2) = eval(&both, &x);
    let (s1, f1, h1) = eval(&mesh, &x[..12]);
    assert!(s1.active >= 2 && s1.active == s2.active, "{s1:?} {s2:?}");
    assert!(
        (s1.energy - s2.energy).abs() <= 1e-12 * s2.energy,
        "{s1:?} {s2:?}"
    );
    for i in 0..12 {
        assert!(
            (f1[i] - f2[i]).abs() <= 1e-9 * (1.0 + f2[i].abs()),
            "{i}: {} {}",
            f1[i],
            f2[i]
        );
    }
    let sum = |h: &ContactHessian, a: usize, c: usize| -> nalgebra::Matrix3<f64> {
        let v = h
            .vertex
            .iter()
            .filter(|(v, _)| a == c && *v == a)
            .map(|(_, m)| *m);
        let k = h
            .coupling
            .iter()
            .filter(|(i, j, _)| (*i, *j) == (a, c))
            .map(|(_, _, m)| *m);
        v.chain(k).sum()
    };
    for a in 0..4 {
        for c in 0..4 {
            let (m1, m2) = (sum(&h1, a, c), sum(&h2, a, c));
            assert!(
                (m1 - m2).norm() <= 1e-9 * (1.0 + m2.norm()),
                "block {a} {c}"
            );
        }
    }
    let obstacle_blocks = h1
        .vertex
        .iter()
        .map(|(v, _)| *v)
        .chain(h1.coupling.iter().flat_map(|(i, j, _)| [*i, *j]));
    assert!(obstacle_blocks.clone().all(|v| v < 4));
    // The step bound moves only the body: the mesh stays where it is.
    let up: Vec<f64> = (0..12)
        .map(|i| if i % 3 == 2 { 1.0 } else { 0.0 })
        .collect();
    let mut away = vec![0.0; 24];
    away[..12].copy_from_slice(&up);
    assert!(mesh.step_bound(&x[..12], &up, 0.1, false) < 1.0);
    assert!(
        (mesh.step_bound(&x[..12], &up, 0.1, false) - both.step_bound(&x, &away, 0.1, false)).abs()
            < 1e-12
    );
}

proptest! {
    /// Forces are minus the energy's central differences; the projected Hessian is
    /// symmetric and lies above the differences of the forces (it only drops negative
    /// curvature).
    #[test]
    fn forces_and_hessian_match_differences(
        gap in 0.02f64..0.08,
        jitter in prop::array::uniform24(-0.004f64..0.004),
    ) {
        let b = Barrier { dhat: 0.1, kappa: 10.0 };
        let (surface, x) = pair(gap, jitter);
        let eval = |y: &[f64], f: Option<&mut [f64]>, h: Option<&mut ContactHessian>| {
            let mut s = ContactSummary { energy: 0.0, active: 0, min_distance: f64::INFINITY };
            surface.evaluate(y, (b, true), &mut s, f, h).unwrap();
            s
        };
        let (mut f, mut hess) = (vec![0.0; 24], ContactHessian::default());
        let s = eval(&x, Some(&mut f), Some(&mut hess));
        prop_assert!(s.active >= 2, "{s:?}");
        prop_assert!(!hess.coupling.is_empty());
        let mut dense = nalgebra::DMatrix::zeros(24, 24);
        for (v, m) in &hess.vertex {
            let mut view = dense.view_mut((3 * v, 3 * v), (3, 3));
            view += m;
        }
        for (i, j, m) in &hess.coupling {
            let mut view = dense.view_mut((3 * i, 3 * j), (3, 3));
            view += m;
        }
        prop_assert!((&dense - dense.transpose()).norm() <= 1e-9 * dense.norm());
        let h = 1e-7;
        let mut fd = nalgebra::DMatrix::zeros(24, 24);
        for i in 0..24 {
            let (mut a, mut c) = (x.clone(), x.clone());
            a[i] += h;
            c[i] -= h;
            let g = -(eval(&a, None, None).energy - eval(&c, None, None).energy) / (2.0 * h);
            prop_assert!((g - f[i]).abs() <= 1e-5 * (1.0 + f[i].abs()), "force {i}: {g} {}", f[i]);
            let (mut fa, mut fc) = (vec![0.0; 24], vec![0.0; 24]);
            eval(&a, Some(&mut fa), None);
            eval(&c, Some(&mut fc), None);
            for j in 0..24 {
                fd[(j, i)] = -(fa[j] - fc[j]) / (2.0 * h);
            }
        }
        let fd = (&fd + fd.transpose()) * 0.5;
        let excess = (&dense - &fd).symmetric_eigenvalues().min();
        prop_assert!(excess >= -1e-5 * fd.norm(), "projected less exact: {excess}");
    }

    /// On the bounded path no edge crosses a triangle of the other body and every
    /// distance stays positive; the bound is not zero.
    #[test]
    fn the_step_bound_keeps_the_path_apart(
        gap in 0.02f64..0.08,
        motion in prop::array::uniform12(-2.0f64..2.0),
    ) {
        let (surface, x) = pair(gap, [0.0; 24]);
        let mut dx = vec![0.0; 24];
        dx[12..].copy_from_slice(&motion);
        dx[14] -= 1.0;
        let s = surface.step_bound(&x, &dx, 0.1, false);
        prop_assert!(s > 0.0);
        for i in 0..=200 {
            let t = s * i as f64 / 200.0;
            let y: Vec<f64> = x.iter().zip(&dx).map(|(x, d)| x + t * d).collect();
            for c in surface.candidates(&y, None, f64::INFINITY, Place::End) {
                let d = surface.distance(c, &surface.points(c, &y, Place::End)).0;
                prop_assert!(d > 0.0, "t = {t}: {} at {d}", surface.pair(c));
            }
        }
    }
}
