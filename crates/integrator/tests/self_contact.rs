//! Self-contact in the Newton loop: two cubes of one mesh, the upper one thrown onto the
//! lower one resting on the ground. No surface edge ever crosses a surface triangle
//! (checked exactly on every step, independently of the collision detection), the total
//! energy never grows, and every solver, assembled or matrix-free, takes the same steps.

use deform_assembly::MaterialField;
use deform_integrator::{
    Constraint, ContactSpec, FrictionSpec, Integrator, IntegratorOptions, Motion, Obstacle,
    PolicySpec, State,
};
use deform_materials::MaterialSpec;
use deform_mesh::TetMesh;
use deform_mesh::generate::BoxGrid;
mod common;

use common::{crosses, edges, total_energy};
use nalgebra::Vector3;

/// Two 10 cm cubes of 2 x 2 x 2 cells in one mesh: the lower one 1 mm above the ground, the
/// upper one `gap` above it and shifted by 3 cm in x and y, so that corners and edges meet
/// faces and edges.
fn stack(gap: f64) -> TetMesh {
    deform_mesh::generate::boxes(&[cube([0.0, 0.0, 1e-3]), cube([0.03, 0.03, 0.101 + gap])])
        .unwrap()
}

/// A 10 cm box of 2 x 2 x 2 cells at `origin`.
fn cube(origin: [f64; 3]) -> BoxGrid {
    box_grid([2, 2, 2], [0.1; 3], origin)
}

fn box_grid(cells: [usize; 3], size: [f64; 3], origin: [f64; 3]) -> BoxGrid {
    BoxGrid::new(cells, size).origin(origin)
}

fn sim(mesh: &TetMesh, policy: &str) -> Integrator {
    let model = ron::from_str::<MaterialSpec>("NeoHookean(Young(e: 1e5, nu: 0.4))")
        .unwrap()
        .build()
        .unwrap();
    Integrator::builder(mesh, MaterialField::Uniform(model))
        .density(1000.0)
        .options(IntegratorOptions::default().dt(2e-3))
        .policy(
            ron::from_str::<PolicySpec>(policy)
                .unwrap()
                .build()
                .unwrap(),
        )
        .contact(
            ContactSpec::default()
                .obstacles(vec![Obstacle::Plane {
                    point: [0.0; 3],
                    normal: [0.0, 0.0, 1.0],
                }])
                .self_contact(true),
        )
        .build()
        .unwrap()
}

/// Throws the upper cube (the second half of the vertices) down at `speed`.
fn thrown(sim: &Integrator, mesh: &TetMesh, speed: f64) -> State {
    let mut s = sim.rest_state();
    let half = mesh.num_vertices() / 2;
    s.v.chunks_mut(3).skip(half).for_each(|v| v[2] = -speed);
    s
}

/// The first surface edge crossing a surface triangle that shares no vertex with it.
fn intersection(mesh: &TetMesh, x: &[f64]) -> Option<([usize; 2], [usize; 3])> {
    let faces = deform_mesh::topology::boundary_faces(mesh);
    let edges = edges(&faces);
    let p = |v: usize| Vector3::new(x[3 * v], x[3 * v + 1], x[3 * v + 2]);
    for e in &edges {
        for f in &faces {
            if f.contains(&e[0]) || f.contains(&e[1]) {
                continue;
            }
            if crosses(p(e[0]), p(e[1]), [p(f[0]), p(f[1]), p(f[2])]) {
                return Some((*e, *f));
            }
        }
    }
    None
}

#[test]
fn a_cube_thrown_onto_another_never_passes_through_it() {
    let mesh = stack(0.01);
    let mut sim = sim(&mesh, "Fixed(Direct())");
    let mut s = thrown(&sim, &mesh, 3.0);
    let mut energy = total_energy(&mut sim, &s);
    let mut touched = 0;
    for step in 0..60 {
        let report = sim.step(&mut s).unwrap();
        if let Some(found) = intersection(&mesh, &s.x) {
            panic!(
                "step {step}: edge {:?} crosses triangle {:?}",
                found.0, found.1
            );
        }
        let now = total_energy(&mut sim, &s);
        assert!(
            now <= energy * (1.0 + 1e-9) + 1e-12,
            "step {step}: energy grew from {energy} to {now}"
        );
        energy = now;
        // Pairs beyond the bottom face's vertices on the ground: the cubes touch.
        let on_ground = 9;
        touched += usize::from(report.contact.unwrap().active > on_ground);
    }
    assert!(touched > 10, "the cubes touched on {touched} steps only");
    // The upper cube rests on the lower one: its lowest vertex above the lower's top.
    let half = mesh.num_vertices() / 2;
    let low =
        s.x.chunks(3)
            .skip(half)
            .map(|p| p[2])
            .fold(f64::INFINITY, f64::min);
    let top =
        s.x.chunks(3)
            .take(half)
            .map(|p| p[2])
            .fold(f64::NEG_INFINITY, f64::max);
    assert!(
        low > top - 0.03,
        "upper cube's lowest point {low}, lower cube's top {top}"
    );
}

#[test]
fn every_solver_takes_the_same_self_contact_steps() {
    let mesh = stack(0.002);
    let run = |policy: &str| {
        let mut sim = sim(&mesh, policy);
        let mut s = thrown(&sim, &mesh, 1.0);
        let mut couplings = false;
        for _ in 0..6 {
            let report = sim.step(&mut s).unwrap();
            couplings |= report.contact.unwrap().active > 9;
        }
        assert!(couplings, "{policy}: the cubes never touched");
        s.x
    };
    let reference = run("Fixed(Direct())");
    for policy in [
        "Fixed(Pcg(preconditioner: Ic0, tolerance: (rel: 1e-12)))",
        "Fixed(MatrixFree(Pcg(preconditioner: BlockJacobi, tolerance: (rel: 1e-12))))",
    ] {
        let x = run(policy);
        let diff = x
            .iter()
            .zip(&reference)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        // Newton takes up to 29 iterations at impact here (the PSD projection of each pair
        // slows it) and stops within its tolerance, so the solvers' states agree to that
        // tolerance, not to rounding as without self-contact (0.17 mm of 10 cm observed).
        assert!(diff < 1e-3, "{policy}: {diff} m from the direct solver's");
    }
}

#[test]
fn surfaces_closer_than_dhat_at_rest_are_refused_by_name() {
    let mesh = stack(1e-6);
    let model = ron::from_str::<MaterialSpec>("NeoHookean(Young(e: 1e5, nu: 0.4))")
        .unwrap()
        .build()
        .unwrap();
    let err = Integrator::builder(&mesh, MaterialField::Uniform(model))
        .contact(ContactSpec::default().self_contact(true))
        .build()
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("apart at rest") && err.contains("dhat"),
        "{err}"
    );
}

/// A 10 cm cube resting on a clamped slab of the same mesh (a 1 m x 0.3 m plate of 5 cm),
/// with gravity tilted by 30 degrees, released: how far the cube's centre of mass travels
/// in `steps` steps with self-contact friction `mu`, and how far Coulomb says.
fn slab_incline_travel(mu: f64, steps: usize, dt: f64) -> (f64, f64) {
    let slab = box_grid([10, 3, 1], [1.0, 0.3, 0.05], [-0.1, -0.1, -0.05]);
    let n = slab.build().unwrap().num_vertices();
    let mesh = deform_mesh::generate::boxes(&[slab, cube([0.0, 0.0, 2e-3])]).unwrap();
    let model = ron::from_str::<MaterialSpec>("NeoHookean(Young(e: 1e6, nu: 0.4))")
        .unwrap()
        .build()
        .unwrap();
    let theta = 30f64.to_radians();
    let options = IntegratorOptions::default()
        .dt(dt)
        .gravity([0.0, 0.0, -9.81 * theta.cos()])
        .gamma(0.01);
    let mut sim = Integrator::builder(&mesh, MaterialField::Uniform(model))
        .density(1000.0)
        .options(options.clone())
        .constraints(vec![Constraint {
            vertices: (0..n).collect(),
            motion: Motion::Fixed,
        }])
        .contact(
            ContactSpec::default().self_contact(true).friction(Some(
                FrictionSpec::new(vec![])
                    .velocity_threshold(1e-3)
                    .self_mu(Some(mu)),
            )),
        )
        .build()
        .unwrap();
    // Settled onto the slab by damped steps under the normal part of gravity (a static
    // solve has no friction, and the edge pairs' barriers push sideways, however little).
    let mut s = sim.rest_state();
    for _ in 0..60 {
        sim.step(&mut s).unwrap();
    }
    s.v.iter_mut().for_each(|v| *v = 0.0);
    sim.set_options(
        options
            .gravity([9.81 * theta.sin(), 0.0, -9.81 * theta.cos()])
            .gamma(0.0),
    )
    .unwrap();
    let masses = sim.assembly().vertex_masses(sim.mass());
    let com = |s: &State| {
        let m: f64 = masses[n..].iter().sum();
        (n..mesh.num_vertices())
            .map(|v| masses[v] * s.x[3 * v])
            .sum::<f64>()
            / m
    };
    let start = com(&s);
    for _ in 0..steps {
        sim.step(&mut s).unwrap();
        assert!(intersection(&mesh, &s.x).is_none());
    }
    // Backward Euler under a constant acceleration a travels a dt^2 N (N + 1) / 2.
    let k = steps as f64;
    let slide = 9.81 * (theta.sin() - mu * theta.cos()) * dt * dt * k * (k + 1.0) / 2.0;
    (com(&s) - start, slide)
}

/// Friction between two parts of one body (IPC's lagged friction on the surface pairs, the
/// relative slip of their closest points): a cube on a clamped slab of the same mesh slides
/// as Coulomb says on a 30-degree incline at mu = 0.3 and sticks at 0.7.
#[test]
fn self_contact_friction_slides_or_sticks_as_coulomb_says() {
    let (steps, dt) = (100, 5e-3);
    let (travel, expected) = slab_incline_travel(0.3, steps, dt);
    assert!(
        (travel - expected).abs() <= 0.02 * expected,
        "slid {travel} m, Coulomb says {expected} m"
    );
    let (travel, _) = slab_incline_travel(0.7, steps, dt);
    let (free, _) = slab_incline_travel(0.0, steps, dt);
    assert!(
        travel.abs() <= 0.02 * free,
        "crept {travel} m (frictionless: {free} m)"
    );
}
