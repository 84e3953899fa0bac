//! The contact potential against differences of itself, and the step bound against an exact
//! check of the path.

use deform_contact::{Barrier, ContactError, ContactHessian, ContactModel, Obstacle, STEP_MARGIN};
use nalgebra::{DMatrix, Vector3};
use proptest::prelude::*;
use proptest::test_runner::TestCaseError;

fn model() -> ContactModel {
    let obstacles = vec![
        Obstacle::Plane {
            point: [0.0, 0.0, 0.0],
            normal: [0.0, 0.0, 1.0],
        },
        Obstacle::Sphere {
            center: [0.5, 0.0, 0.3],
            radius: 0.2,
        },
        Obstacle::Box {
            min: [-0.6, -0.1, 0.0],
            max: [-0.4, 0.1, 0.2],
        },
        Obstacle::OrientedBox {
            center: [0.0, 0.6, 0.15],
            half_extents: [0.1, 0.05, 0.1],
            rotation: [0.3, 0.2, 0.5],
        },
    ];
    let barrier = Barrier::new(0.05, 1e3);
    // Vertex 1 is not a surface vertex: it never feels contact.
    ContactModel::new(obstacles, barrier, vec![0, 2, 3]).unwrap()
}

/// [`model`] with friction as `spec` says; when `turning`, each obstacle turns by 0.3 rad
/// about its centre and drifts during a step of 0.01 s (the sticking positions turn with
/// it), placed for the step from 0.
fn frictional_model(spec: &deform_contact::FrictionSpec, turning: bool) -> ContactModel {
    let m = model().with_friction(spec).unwrap();
    if !turning {
        return m;
    }
    let turn = |obstacle| {
        let m = deform_contact::ObstacleMotion::default().obstacle(obstacle);
        m.velocity([0.5, -0.2, 0.0])
            .angular_velocity([10.0, -20.0, 20.0])
    };
    let mut m = m.with_motions((0..4).map(turn).collect()).unwrap();
    m.set_step(0.0, 0.01);
    m
}

/// Four vertices, each within `dhat` of one obstacle (or two).
fn positions(t: [f64; 12]) -> Vec<f64> {
    let near = [
        [0.1, 0.2, 0.01],  // above the ground
        [0.3, 0.3, 0.001], // not on the surface
        [0.5, 0.0, 0.53],  // above the sphere
        [-0.5, 0.0, 0.22], // above the box, near the ground too? no: 0.22 m up
    ];
    let mut x = Vec::new();
    for (v, p) in near.iter().enumerate() {
        for k in 0..3 {
            x.push(p[k] + 0.008 * t[3 * v + k]);
        }
    }
    x
}

fn energy(m: &ContactModel, x: &[f64]) -> f64 {
    m.evaluate(x, None, None).unwrap().energy
}

proptest! {
    /// Forces are minus the energy's central differences; the Hessian blocks are symmetric
    /// positive semidefinite, equal to the differences of the gradient where the exact
    /// Hessian is (the plane and the box's faces), and above them otherwise (the projection
    /// only removes negative curvature).
    #[test]
    fn forces_and_hessian_match_differences(t in proptest::array::uniform12(-1.0f64..1.0)) {
        let m = model();
        let x = positions(t);
        let mut f = vec![0.0; x.len()];
        let mut blocks = ContactHessian::default();
        let s = m.evaluate(&x, Some(&mut f), Some(&mut blocks)).unwrap();
        prop_assert!(s.active >= 3, "{s:?}");
        let h = 1e-7;
        let n = x.len();
        let mut hessian_fd = DMatrix::zeros(n, n);
        for i in 0..n {
            let (mut a, mut b) = (x.clone(), x.clone());
            a[i] += h;
            b[i] -= h;
            let g = -(energy(&m, &a) - energy(&m, &b)) / (2.0 * h);
            prop_assert!((g - f[i]).abs() <= 1e-6 * (1.0 + f[i].abs()), "force {i}: {g} {}", f[i]);
            let (mut fa, mut fb) = (vec![0.0; n], vec![0.0; n]);
            m.evaluate(&a, Some(&mut fa), None).unwrap();
            m.evaluate(&b, Some(&mut fb), None).unwrap();
            for j in 0..n {
                hessian_fd[(j, i)] = -(fa[j] - fb[j]) / (2.0 * h);
            }
        }
        let mut hessian = DMatrix::zeros(n, n);
        for (v, b) in &blocks.vertex {
            hessian.view_mut((3 * v, 3 * v), (3, 3)).copy_from(b);
            prop_assert!((b - b.transpose()).norm() <= 1e-12 * b.norm());
            prop_assert!(b.symmetric_eigenvalues().min() >= -1e-9 * b.norm());
        }
        let scale = hessian_fd.norm();
        let excess = (&hessian - &hessian_fd).symmetric_eigenvalues().min();
        prop_assert!(excess >= -1e-5 * scale, "projected less exact has eigenvalue {excess}");
        // Vertex 0 (the plane) is exact.
        let exact = hessian_fd.view((0, 0), (3, 3)) - hessian.view((0, 0), (3, 3));
        prop_assert!(exact.norm() <= 1e-5 * scale, "{exact}");
        // Vertex 1 is not on the surface: no force, no block.
        prop_assert!(f[3..6].iter().all(|&v| v == 0.0));
        prop_assert!(blocks.vertex.iter().all(|(v, _)| *v != 1));
    }

    /// No vertex comes closer than the margin on the bounded path, checked on a fine sampling
    /// of the path against every obstacle.
    #[test]
    fn bounded_steps_never_interpenetrate(
        t in proptest::array::uniform12(-1.0f64..1.0),
        dx in proptest::collection::vec(-0.5f64..0.5, 12),
    ) {
        let m = model();
        let x = positions(t);
        let s = m.step_bound(&x, &dx);
        prop_assert!((0.0..=1.0).contains(&s));
        for k in 0..=400 {
            let a = s * k as f64 / 400.0;
            for &v in m.vertices() {
                let p0 = Vector3::new(x[3 * v], x[3 * v + 1], x[3 * v + 2]);
                let p = p0 + Vector3::new(dx[3 * v], dx[3 * v + 1], dx[3 * v + 2]) * a;
                for o in m.obstacles() {
                    let margin = STEP_MARGIN * o.distance(&p0);
                    prop_assert!(o.distance(&p) >= margin * (1.0 - 1e-9), "vertex {v} at {a} of {s}");
                }
            }
        }
        let trial: Vec<f64> = x.iter().zip(&dx).map(|(a, b)| a + s * b).collect();
        prop_assert!(m.evaluate(&trial, None, None).is_ok());
    }
}

#[test]
fn a_vertex_inside_is_named_and_bad_parameters_are_refused() {
    let m = model();
    let mut x = positions([0.0; 12]);
    x[2] = -1e-3;
    assert_eq!(
        m.evaluate(&x, None, None),
        Err(ContactError::Penetration {
            vertex: 0,
            obstacle: 0,
            distance: -1e-3
        })
    );
    assert_eq!(m.step_bound(&x, &[0.0; 12]), 1.0);
    let bad = ContactModel::new(vec![], Barrier::new(0.0, 1.0), vec![]);
    assert!(matches!(bad, Err(ContactError::Invalid { field, .. }) if field == "dhat"));
    let spec: deform_contact::ContactSpec = ron::from_str(
        "(obstacles: [Plane(point: (0, 0, 0), normal: (0, 0, 1))], dhat: Some(1e-3))",
    )
    .unwrap();
    assert_eq!(spec.dhat, Some(1e-3));
    assert!(ron::from_str::<deform_contact::ContactSpec>("(obstacles: [], dhta: 1)").is_err());
}

proptest! {
    /// The friction potential, lagged at a start, against differences of itself: forces are
    /// minus its gradient and the blocks its exact Hessian, below and above the smoothing
    /// threshold, with the obstacles still or turning during the step; it resists the
    /// motion (the force opposes the tangential slip).
    #[test]
    fn friction_matches_differences_in_both_regimes(
        t in proptest::array::uniform12(-1.0f64..1.0),
        slide in proptest::collection::vec(-1.0f64..1.0, 12),
        far in proptest::bool::ANY,
        turning in proptest::bool::ANY,
    ) {
        let spec = deform_contact::FrictionSpec::new(vec![0.5, 0.3, 0.8, 0.6]).velocity_threshold(1e-3);
        let m = frictional_model(&spec, turning);
        let start = positions(t);
        let dt = 0.01;
        let lag = m.lag_friction(&start, dt);
        prop_assert!(lag.pairs.len() >= 3);
        // Displacements of 1e-5 m (below eps = 1e-5 m... around it) or 1e-3 m (sliding).
        let scale = if far { 1e-3 } else { 1e-5 };
        let x: Vec<f64> = start.iter().zip(&slide).map(|(a, b)| a + scale * b).collect();
        let n = x.len();
        let mut f = vec![0.0; n];
        let mut blocks = ContactHessian::default();
        let energy = |y: &[f64]| m.add_friction(&lag, y, None, None);
        m.add_friction(&lag, &x, Some(&mut f), Some(&mut blocks));
        // Steps small against the smoothing length eps too: a sliding displacement may
        // leave a vertex inside it, where f0 is cubic with a third derivative of 2 / eps^2.
        let h = 1e-4 * scale.min(spec.velocity_threshold * dt);
        let mut hessian = DMatrix::zeros(n, n);
        for (v, b) in &blocks.vertex {
            let mut view = hessian.view_mut((3 * v, 3 * v), (3, 3));
            view += b;
        }
        for i in 0..n {
            let (mut a, mut b) = (x.clone(), x.clone());
            a[i] += h;
            b[i] -= h;
            let g = -(energy(&a) - energy(&b)) / (2.0 * h);
            prop_assert!((g - f[i]).abs() <= 1e-5 * (1.0 + f[i].abs()), "force {i}: {g} {}", f[i]);
            let (mut fa, mut fb) = (vec![0.0; n], vec![0.0; n]);
            m.add_friction(&lag, &a, Some(&mut fa), None);
            m.add_friction(&lag, &b, Some(&mut fb), None);
            for j in 0..n {
                let d = -(fa[j] - fb[j]) / (2.0 * h);
                // `|u| u` is not twice differentiable at u = 0: differences there are off by
                // about h / eps of the Hessian's size.
                prop_assert!((d - hessian[(j, i)]).abs() <= 1e-3 * hessian.amax(),
                    "hessian ({j}, {i}): {d} {}", hessian[(j, i)]);
            }
        }
        // Each pair's force opposes its slip: the vertex's displacement from where it would
        // be had it stuck to the obstacle (which turns, when turning).
        for pair in &lag.pairs {
            let one = deform_contact::FrictionLag::default().pairs(vec![pair.clone()]).threshold(lag.threshold);
            let mut f = vec![0.0; n];
            m.add_friction(&one, &x, Some(&mut f), None);
            let v = pair.vertices[0].0;
            let slip = Vector3::new(x[3 * v], x[3 * v + 1], x[3 * v + 2]) - pair.start;
            let work = Vector3::new(f[3 * v], f[3 * v + 1], f[3 * v + 2]).dot(&slip);
            prop_assert!(work <= 0.0, "friction did work {work}");
        }
    }

    /// Newton's secant curvature for pairs its direction carries past their sticking
    /// position: without flags `add_friction_with` is `add_friction`; a flagged sliding
    /// pair's Hessian is `limit / s` across the whole tangent plane, and its quadratic model
    /// majorises the potential (lies above it for any displacement), so a step taken on it
    /// never overshoots friction. `flag_reversals` flags exactly the sliding pairs whose
    /// slip the displacement reverses.
    #[test]
    fn the_secant_friction_model_majorises_and_flags_reversals(
        t in proptest::array::uniform12(-1.0f64..1.0),
        slide in proptest::collection::vec(-1.0f64..1.0, 12),
        step in proptest::collection::vec(-1.0f64..1.0, 12),
        back in 0.0f64..3.0,
    ) {
        let spec = deform_contact::FrictionSpec::new(vec![0.5, 0.3, 0.8, 0.6]).velocity_threshold(1e-3);
        let m = frictional_model(&spec, false);
        let start = positions(t);
        let lag = m.lag_friction(&start, 0.01);
        let n = start.len();
        // Sliding: displacements of 1 mm against eps = 1e-5 m.
        let x: Vec<f64> = start.iter().zip(&slide).map(|(a, b)| a + 1e-3 * b).collect();
        let (mut f, mut f_with) = (vec![0.0; n], vec![0.0; n]);
        let (mut h, mut h_with) = (ContactHessian::default(), ContactHessian::default());
        let e = m.add_friction(&lag, &x, Some(&mut f), Some(&mut h));
        let none = vec![false; lag.pairs.len()];
        let e_with = m.add_friction_with(&lag, &x, Some(&mut f_with), Some(&mut h_with), &none);
        prop_assert_eq!(e, e_with);
        prop_assert_eq!(&f, &f_with);
        prop_assert_eq!(&h.vertex, &h_with.vertex);
        // A displacement that takes each vertex `back` times its slip back (past the
        // sticking position beyond 1), plus a little off the line.
        let mut dx = vec![0.0; n];
        for pair in &lag.pairs {
            let v = pair.vertices[0].0;
            for k in 0..3 {
                let slip = x[3 * v + k] - pair.start[k];
                dx[3 * v + k] = -back * slip + 1e-4 * step[3 * v + k];
            }
        }
        let mut flags = vec![false; lag.pairs.len()];
        let flagged = m.flag_reversals(&lag, &x, &dx, &mut flags);
        prop_assert_eq!(flagged, flags.iter().filter(|f| **f).count());
        for (pair, flag) in lag.pairs.iter().zip(&flags) {
            let u = pair.basis.transpose() * (x_of(&x, pair) - pair.start);
            let w = pair.basis.transpose() * (x_of(&x, pair) + x_of(&dx, pair) - pair.start);
            prop_assert_eq!(*flag, u.norm() >= lag.threshold && u.dot(&w) < 0.0);
        }
        // Every pair flagged: the secant model lies above the potential along dx.
        let all = vec![true; lag.pairs.len()];
        let mut hs = ContactHessian::default();
        m.add_friction_with(&lag, &x, None, Some(&mut hs), &all);
        for ((v, b), (w, exact)) in hs.vertex.iter().zip(&h.vertex) {
            prop_assert_eq!(v, w);
            // Larger than the exact one (by limit / s along the slip), and isotropic.
            prop_assert!((b - exact).symmetric_eigen().eigenvalues.min() >= -1e-9 * b.norm());
        }
        for a in [0.25, 0.5, 1.0, 1.5] {
            let y: Vec<f64> = x.iter().zip(&dx).map(|(p, d)| p + a * d).collect();
            let mut model = e;
            for (k, fi) in f.iter().enumerate() {
                model -= fi * a * dx[k];
            }
            for (v, b) in &hs.vertex {
                let d = Vector3::new(dx[3 * v], dx[3 * v + 1], dx[3 * v + 2]) * a;
                model += 0.5 * d.dot(&(b * d));
            }
            let actual = m.add_friction(&lag, &y, None, None);
            prop_assert!(actual <= model + 1e-12 * e.abs().max(1e-12), "at {a}: {actual} > {model}");
        }
    }
}

/// A pair's contact point (one vertex of weight 1 against an analytic obstacle).
fn x_of(x: &[f64], pair: &deform_contact::FrictionPair) -> Vector3<f64> {
    let v = pair.vertices[0].0;
    Vector3::new(x[3 * v], x[3 * v + 1], x[3 * v + 2])
}

proptest! {
    /// Friction against a triangle-mesh obstacle (a tetrahedron whose apex edge crosses
    /// over a fixed tetrahedron's top edge, near its top face): forces are minus the
    /// potential's gradient and the blocks, vertex and coupling, its Hessian; no force on
    /// the fixed mesh.
    #[test]
    fn mesh_friction_matches_differences(
        jitter in proptest::array::uniform12(-0.003f64..0.003),
        slide in proptest::collection::vec(-1.0f64..1.0, 12),
        far in proptest::bool::ANY,
    ) {
        let faces = vec![[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]];
        let fixed = vec![0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0];
        let mut start = vec![0.5, -0.3, 0.03, 0.5, 0.3, 0.03, 0.9, 0.0, 0.7, 0.1, 0.1, 0.8];
        for (x, j) in start.iter_mut().zip(jitter) {
            *x += j;
        }
        let barrier = Barrier::new(0.1, 10.0);
        let m = ContactModel::new(vec![], barrier, vec![0, 1, 2, 3])
            .unwrap()
            .with_mesh_obstacles(faces.clone(), &start, vec![(fixed, faces)])
            .unwrap()
            .with_friction(&deform_contact::FrictionSpec::new(vec![0.4]).velocity_threshold(1e-3))
            .unwrap();
        let dt = 0.01;
        let lag = m.lag_friction(&start, dt);
        prop_assert!(lag.pairs.iter().any(|p| p.vertices.len() > 1), "{:?}", lag.pairs.len());
        let scale = if far { 1e-3 } else { 1e-5 };
        let x: Vec<f64> = start.iter().zip(&slide).map(|(a, b)| a + scale * b).collect();
        friction_matches_differences(&m, &lag, &x, 1e-4 * scale.min(1e-3 * dt))?;
    }
}

/// `m`'s friction of `lag` at `x` against central differences of step `h`: forces are minus
/// the potential's gradient, the blocks (vertex and coupling) its symmetric Hessian; the
/// forces.
fn friction_matches_differences(
    m: &ContactModel,
    lag: &deform_contact::FrictionLag,
    x: &[f64],
    h: f64,
) -> Result<Vec<f64>, TestCaseError> {
    let n = x.len();
    let mut f = vec![0.0; n];
    let mut blocks = ContactHessian::default();
    m.add_friction(lag, x, Some(&mut f), Some(&mut blocks));
    let mut hessian = DMatrix::zeros(n, n);
    for (v, b) in &blocks.vertex {
        let mut view = hessian.view_mut((3 * v, 3 * v), (3, 3));
        view += b;
    }
    for (a, b, m) in &blocks.coupling {
        let mut view = hessian.view_mut((3 * a, 3 * b), (3, 3));
        view += m;
    }
    prop_assert!((&hessian - hessian.transpose()).amax() <= 1e-9 * hessian.amax());
    let energy = |y: &[f64]| m.add_friction(lag, y, None, None);
    for i in 0..n {
        let (mut a, mut b) = (x.to_vec(), x.to_vec());
        a[i] += h;
        b[i] -= h;
        let g = -(energy(&a) - energy(&b)) / (2.0 * h);
        prop_assert!(
            (g - f[i]).abs() <= 1e-5 * (1.0 + f[i].abs()),
            "force {i}: {g} {}",
            f[i]
        );
        let (mut fa, mut fb) = (vec![0.0; n], vec![0.0; n]);
        m.add_friction(lag, &a, Some(&mut fa), None);
        m.add_friction(lag, &b, Some(&mut fb), None);
        for j in 0..n {
            let d = -(fa[j] - fb[j]) / (2.0 * h);
            prop_assert!(
                (d - hessian[(j, i)]).abs() <= 1e-3 * hessian.amax().max(1e-12),
                "hessian ({j}, {i}): {d} {}",
                hessian[(j, i)]
            );
        }
    }
    Ok(f)
}

proptest! {
    /// Friction between two parts of the body's own surface (the mesh test's two
    /// tetrahedra, both the body's, apart at rest): forces and blocks match differences
    /// on all eight vertices, and the pair's forces sum to zero (momentum is kept).
    #[test]
    fn self_friction_matches_differences(
        jitter in proptest::array::uniform12(-0.003f64..0.003),
        slide in proptest::collection::vec(-1.0f64..1.0, 24),
        far in proptest::bool::ANY,
    ) {
        let tet = [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]];
        let faces: Vec<[usize; 3]> = tet.iter().chain(&tet.map(|t| t.map(|v| v + 4))).copied().collect();
        let lower = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0];
        let mut start = vec![0.5, -0.3, 0.03, 0.5, 0.3, 0.03, 0.9, 0.0, 0.7, 0.1, 0.1, 0.8];
        for (x, j) in start.iter_mut().zip(jitter) {
            *x += j;
        }
        start.extend(lower);
        // At rest the upper tetrahedron is far above: self-contact refuses primitives
        // closer than dhat at rest.
        let rest: Vec<f64> = start.iter().enumerate().map(|(i, x)| x + if i < 12 && i % 3 == 2 { 10.0 } else { 0.0 }).collect();
        let barrier = Barrier::new(0.1, 10.0);
        let spec = deform_contact::FrictionSpec::new(vec![]).velocity_threshold(1e-3).self_mu(Some(0.4));
        let m = ContactModel::new(vec![], barrier, (0..8).collect())
            .unwrap()
            .with_self_contact(faces, &rest)
            .unwrap()
            .with_friction(&spec)
            .unwrap();
        prop_assert_eq!(m.frictional(), 1);
        let dt = 0.01;
        let lag = m.lag_friction(&start, dt);
        prop_assert!(lag.pairs.iter().any(|p| p.vertices.len() > 2), "{:?}", lag.pairs.len());
        prop_assert!(lag.pairs.iter().all(|p| p.obstacle == 0));
        let scale = if far { 1e-3 } else { 1e-5 };
        let x: Vec<f64> = start.iter().zip(&slide).map(|(a, b)| a + scale * b).collect();
        let f = friction_matches_differences(&m, &lag, &x, 1e-4 * scale.min(1e-3 * dt))?;
        let size = f.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        prop_assert!(size > 0.0);
        for k in 0..3 {
            let total: f64 = f.iter().skip(k).step_by(3).sum();
            prop_assert!(total.abs() <= 1e-12 * size, "net force {k}: {total}");
        }
    }
}

/// `self_mu` without self-contact, a negative one, and self-contact given after friction are
/// refused, each naming its field.
#[test]
fn bad_self_contact_friction_is_refused_by_field() {
    let spec = |self_mu| {
        let f = deform_contact::FrictionSpec::new(vec![0.3]);
        f.velocity_threshold(1e-3).self_mu(self_mu)
    };
    let field = |e: ContactError| match e {
        ContactError::Invalid { field, .. } => field,
        other => panic!("{other:?}"),
    };
    let e = model().with_friction(&spec(Some(0.2))).err().unwrap();
    assert_eq!(field(e), "friction.self_mu");
    let e = model().with_friction(&spec(Some(-0.2))).err().unwrap();
    assert_eq!(field(e), "friction.self_mu");
    let far = [
        0.0, 0.0, 10.0, 1.0, 0.0, 10.0, 0.0, 1.0, 10.0, 0.0, 0.0, 11.0,
    ];
    let faces = vec![[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]];
    let e = model()
        .with_friction(&spec(None))
        .unwrap()
        .with_self_contact(faces, &far)
        .err()
        .unwrap();
    assert_eq!(field(e), "self_contact");
}

proptest! {
    /// The friction forces at `x1` lagged at `x0` change with `x0` as
    /// `add_friction_start_vjp` says (against central differences of `w . f` in `x0`, the
    /// lag recomputed): through the start points, the normal forces and, on the sphere,
    /// the tangent planes' turn; below and above the smoothing threshold; with the
    /// obstacles still or turning during the step.
    #[test]
    fn friction_start_derivative_matches_differences(
        t in proptest::array::uniform12(-1.0f64..1.0),
        slide in proptest::collection::vec(-1.0f64..1.0, 12),
        w in proptest::collection::vec(-1.0f64..1.0, 12),
        far in proptest::bool::ANY,
        turning in proptest::bool::ANY,
    ) {
        let spec = deform_contact::FrictionSpec::new(vec![0.5, 0.3, 0.8, 0.6]).velocity_threshold(1e-3);
        let m = frictional_model(&spec, turning);
        let x0 = positions(t);
        let scale = if far { 1e-3 } else { 1e-5 };
        let x1: Vec<f64> = x0.iter().zip(&slide).map(|(a, b)| a + scale * b).collect();
        prop_assert!(m.lag_friction(&x0, 0.01).pairs.len() >= 3);
        start_derivative_matches(&m, (&x0, &x1), &w, 1e-6)?;
    }

    /// The same for pairs of the body's surface, whose lag also moves the closest points'
    /// weights: a tetrahedron over a fixed mesh tetrahedron (still, or moving and turning
    /// during the step), and the two as one body in self-contact.
    #[test]
    fn surface_friction_start_derivative_matches_differences(
        jitter in proptest::array::uniform12(-0.003f64..0.003),
        slide in proptest::collection::vec(-1.0f64..1.0, 24),
        w in proptest::collection::vec(-1.0f64..1.0, 24),
        far in proptest::bool::ANY,
        kind in 0usize..3,
    ) {
        let tet = [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]];
        let lower = vec![0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0];
        let mut x0 = vec![0.5, -0.3, 0.03, 0.5, 0.3, 0.03, 0.9, 0.0, 0.7, 0.1, 0.1, 0.8];
        for (x, j) in x0.iter_mut().zip(jitter) {
            *x += j;
        }
        let barrier = Barrier::new(0.1, 10.0);
        let spec = deform_contact::FrictionSpec::new(vec![0.4]).velocity_threshold(1e-3).self_mu(Some(0.3));
        let m = if kind < 2 {
            let m = ContactModel::new(vec![], barrier, (0..4).collect())
                .unwrap()
                .with_mesh_obstacles(tet.to_vec(), &x0, vec![(lower, tet.to_vec())])
                .unwrap();
            let motion = deform_contact::ObstacleMotion::default().obstacle(0).velocity([0.02, -0.01, 0.0]).angular_velocity([0.0, 0.0, 0.3]);
            let mut m = match kind {
                1 => m.with_motions(vec![motion]).unwrap(),
                _ => m,
            };
            m.set_step(0.0, 0.01);
            m.with_friction(&spec.self_mu(None)).unwrap()
        } else {
            let faces: Vec<[usize; 3]> = tet.iter().chain(&tet.map(|t| t.map(|v| v + 4))).copied().collect();
            x0.extend(lower);
            let rest: Vec<f64> = x0.iter().enumerate().map(|(i, x)| x + if i < 12 && i % 3 == 2 { 10.0 } else { 0.0 }).collect();
            ContactModel::new(vec![], barrier, (0..8).collect())
                .unwrap()
                .with_self_contact(faces, &rest)
                .unwrap()
                .with_friction(&spec)
                .unwrap()
        };
        let n = x0.len();
        let scale = if far { 1e-3 } else { 1e-5 };
        let x1: Vec<f64> = x0.iter().zip(&slide).map(|(a, b)| a + scale * b).collect();
        let lag = m.lag_friction(&x0, 0.01);
        prop_assert!(lag.pairs.iter().any(|p| p.vertices.len() > 1), "{} pairs", lag.pairs.len());
        start_derivative_matches(&m, (&x0, &x1), &w[..n], 1e-6)?;
    }
}

/// `m`'s `add_friction_start_vjp` against extrapolated central differences of `w . f` in
/// `x0` (steps of at most `h`), with `f` the friction forces at `x1` lagged at `x0` (the lag
/// recomputed); away from the smoothing's kinks, where differences are not derivatives: at
/// eps (`f0` is `C^1` there) and at no slip (the force has a `|u| u` term).
fn start_derivative_matches(
    m: &ContactModel,
    (x0, x1): (&[f64], &[f64]),
    w: &[f64],
    h: f64,
) -> Result<(), TestCaseError> {
    let dt = 0.01;
    let lag = m.lag_friction(x0, dt);
    // The force bends on the scale of each slip (`|q|`) and of its distance from the
    // smoothing's kink: steps a hundredth of those.
    let (wide, mut h) = (h, h);
    for p in &lag.pairs {
        let point: Vector3<f64> = p
            .vertices
            .iter()
            .map(|&(v, wv)| Vector3::new(x1[3 * v], x1[3 * v + 1], x1[3 * v + 2]) * wv)
            .sum();
        let r = (p.basis.transpose() * (point - p.start)).norm() / lag.threshold;
        prop_assume!(r > 0.1 && (r - 1.0).abs() > 0.01);
        h = h.min(0.01 * lag.threshold * r.min((r - 1.0).abs()));
    }
    let mut vjp = vec![0.0; x0.len()];
    m.add_friction_start_vjp(&lag, (x0, x1), w, &mut vjp)
        .unwrap();
    let g = |y0: &[f64]| {
        let mut f = vec![0.0; y0.len()];
        m.add_friction(&m.lag_friction(y0, dt), x1, Some(&mut f), None);
        f.iter().zip(w).map(|(a, b)| a * b).sum::<f64>()
    };
    let central = |i: usize, h: f64| {
        let (mut a, mut b) = (x0.to_vec(), x0.to_vec());
        a[i] += h;
        b[i] -= h;
        (g(&a) - g(&b)) / (2.0 * h)
    };
    for i in 0..x0.len() {
        // Richardson's extrapolation of steps h and h / 2 cancels the h^2 error, which the
        // barrier's and the smoothing's steep curvature make large. Steps short enough for
        // the sharpest slip can drown in rounding where the forces are large; the wide step
        // is then exact enough: one of the two must agree.
        let extrapolated = |h: f64| (4.0 * central(i, 0.5 * h) - central(i, h)) / 3.0;
        let (fine, wide) = (extrapolated(h), extrapolated(wide));
        let close = |fd: f64| (fd - vjp[i]).abs() <= 1e-4 * (1.0 + fd.abs());
        prop_assert!(
            close(fine) || close(wide),
            "{i}: differences {fine} and {wide}, derivative {}",
            vjp[i]
        );
    }
    Ok(())
}

proptest! {
    /// The secant correction makes Newton's linear model of a ground contact's force exact
    /// at the distance the step predicts (`b'(d + n . dx)`, also where that lies beyond
    /// `dhat`); corrected blocks stay positive semidefinite, and no step changes nothing.
    #[test]
    fn the_secant_correction_makes_the_barrier_force_exact_where_the_step_lands(
        t in prop::array::uniform12(-1.0f64..1.0),
        s in prop::array::uniform12(-1.0f64..1.0),
    ) {
        let m = model();
        let x = positions(t);
        let dx: Vec<f64> = s.iter().map(|v| 0.03 * v).collect();
        let mut h = ContactHessian::default();
        m.evaluate(&x, None, Some(&mut h)).unwrap();
        let mut delta = ContactHessian::default();
        let changed = m.secant_correction(&x, &dx, &mut delta);
        let block = |hs: &ContactHessian, v: usize| {
            hs.vertex.iter().filter(|(w, _)| *w == v).fold(nalgebra::Matrix3::zeros(), |a, (_, b)| a + b)
        };
        // Vertex 0 is above the ground only (z = 0.01 +- 0.008, dhat 0.05).
        let b = m.barrier();
        let (d, dz) = (x[2], dx[2]);
        let corrected = block(&h, 0) + block(&delta, 0);
        let model_force = (corrected * Vector3::new(dx[0], dx[1], dx[2])).z;
        if d + dz > 0.0 {
            let want = b.first(d + dz) - b.first(d);
            prop_assert!((model_force - want).abs() <= 1e-9 * want.abs().max(b.first(d).abs()), "{model_force} vs {want}");
        }
        for v in [0, 2, 3] {
            let e = (block(&h, v) + block(&delta, v)).symmetric_eigenvalues();
            prop_assert!(e.min() >= -1e-9 * e.max().abs().max(1.0), "{e}");
        }
        // Vertex 0 moving along the normal changes its curvature, unless the step is
        // predicted to pass the ground (where `b'` does not exist and `b''` stays).
        prop_assert!(changed > 0 || dz == 0.0 || d + dz <= 0.0);
        let zero = vec![0.0; x.len()];
        prop_assert_eq!(m.secant_correction(&x, &zero, &mut delta), 0);
        prop_assert!(delta.is_empty());
    }
}
