//! Moving obstacles: a cube squeezed between the ground and a plane that comes down onto
//! it, and a cube carried along by a ground that slides under it. No vertex is ever on or
//! beyond either plane where it is at that step (exact distances, not the collision
//! detection); the squeezed cube carries the force a uniaxial compression takes; friction
//! drags the cube with the moving ground.

use deform_assembly::MaterialField;
use deform_integrator::{
    ContactSpec, FrictionSpec, Integrator, IntegratorOptions, Obstacle, ObstacleMotion, PolicySpec,
};
use deform_materials::MaterialSpec;
use deform_mesh::TetMesh;
use deform_mesh::generate::BoxGrid;

/// A 10 cm cube of 2 x 2 x 2 cells, `lift` above the ground.
fn cube(lift: f64) -> TetMesh {
    BoxGrid {
        cells: [2, 2, 2],
        size: [0.1, 0.1, 0.1],
        origin: [0.0, 0.0, lift],
        split: Default::default(),
    }
    .build()
    .unwrap()
}

fn sim(mesh: &TetMesh, contact: ContactSpec, gamma: f64) -> Integrator {
    let model = ron::from_str::<MaterialSpec>("NeoHookean(Young(e: 1e5, nu: 0.3))")
        .unwrap()
        .build()
        .unwrap();
    Integrator::builder(mesh, MaterialField::Uniform(model))
        .density(1000.0)
        .options(IntegratorOptions {
            dt: 0.005,
            gamma,
            ..Default::default()
        })
        .policy(
            ron::from_str::<PolicySpec>("Fixed(Direct())")
                .unwrap()
                .build()
                .unwrap(),
        )
        .contact(contact)
        .build()
        .unwrap()
}

/// The mass-weighted mean x-velocity: the body's momentum over its mass.
fn momentum_x(sim: &Integrator, v: &[f64]) -> f64 {
    let masses = sim.assembly().vertex_masses(sim.mass());
    let momentum: f64 = masses.iter().zip(v.chunks(3)).map(|(m, v)| m * v[0]).sum();
    momentum / masses.iter().sum::<f64>()
}

fn plane(z: f64, up: bool) -> Obstacle {
    Obstacle::Plane {
        point: [0.0, 0.0, z],
        normal: [0.0, 0.0, if up { 1.0 } else { -1.0 }],
    }
}

#[test]
fn a_plane_coming_down_squeezes_a_cube_without_passing_into_it() {
    let mesh = cube(0.001);
    // The lid starts 2 mm above the cube and comes down 6 mm in 0.12 s, then stays.
    let (lid, speed, stop) = (0.103, 0.05, 0.12);
    let contact = ContactSpec {
        obstacles: vec![plane(0.0, true), plane(lid, false)],
        motions: vec![ObstacleMotion {
            obstacle: 1,
            velocity: [0.0, 0.0, -speed],
            start: 0.0,
            stop: Some(stop),
            ..Default::default()
        }],
        ..Default::default()
    };
    let mut sim = sim(&mesh, contact, 0.01);
    let mut s = sim.rest_state();
    for step in 0..80 {
        sim.step(&mut s).unwrap();
        let top = lid - speed * s.t.min(stop);
        for (v, p) in s.x.chunks(3).enumerate() {
            assert!(
                p[2] > 0.0 && p[2] < top,
                "step {step}: vertex {v} at z = {} outside (0, {top})",
                p[2]
            );
        }
    }
    // At rest under the lid (damped): the lid's barrier force is what a uniaxial
    // compression of the measured strain takes, E A strain (small strain; the weight,
    // 9.8 N, is carried by the ground).
    let barrier = sim.contact().unwrap().barrier();
    let top = lid - speed * stop;
    let force: f64 = s.x.chunks(3).map(|p| -barrier.first(top - p[2])).sum();
    let (low, high) =
        s.x.chunks(3)
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), p| {
                (l.min(p[2]), h.max(p[2]))
            });
    let strain = 1.0 - (high - low) / 0.1;
    let expected = 1e5 * 0.01 * strain;
    assert!(strain > 0.02, "strain {strain}");
    assert!(
        (force - expected).abs() < 0.15 * expected,
        "lid force {force} N against {expected} N (strain {strain})"
    );
}

#[test]
fn a_sliding_ground_drags_a_cube_along_by_friction() {
    let mesh = cube(0.0005);
    let ground_speed = 0.2;
    let contact = ContactSpec {
        obstacles: vec![plane(0.0, true)],
        motions: vec![ObstacleMotion {
            obstacle: 0,
            velocity: [ground_speed, 0.0, 0.0],
            start: 0.0,
            stop: None,
            ..Default::default()
        }],
        friction: Some(FrictionSpec {
            mu: vec![0.5],
            velocity_threshold: 1e-3,
            self_mu: None,
        }),
        ..Default::default()
    };
    let mut dragged = sim(&mesh, contact, 0.0);
    let mut s = dragged.rest_state();
    for step in 0..100 {
        dragged.step(&mut s).unwrap();
        assert!(
            s.x.chunks(3).all(|p| p[2] > 0.0),
            "step {step}: a vertex is below the ground"
        );
    }
    // mu g = 4.9 m/s^2 brings the cube to the ground's speed within 0.04 s; after 0.5 s
    // it moves with the ground.
    let mean_vx = momentum_x(&dragged, &s.v);
    assert!(
        (mean_vx - ground_speed).abs() < 0.02 * ground_speed,
        "mean velocity {mean_vx} against the ground's {ground_speed}"
    );
    // A frictionless ground slides under the cube without moving it.
    let mut still = sim(
        &mesh,
        ContactSpec {
            obstacles: vec![plane(0.0, true)],
            motions: vec![ObstacleMotion {
                obstacle: 0,
                velocity: [ground_speed, 0.0, 0.0],
                start: 0.0,
                stop: None,
                ..Default::default()
            }],
            ..Default::default()
        },
        0.0,
    );
    let mut s = still.rest_state();
    for _ in 0..20 {
        still.step(&mut s).unwrap();
    }
    // (Its vertices do move sideways, as it bulges under its weight, but its momentum
    // does not.)
    let mean_vx = momentum_x(&still, &s.v);
    assert!(mean_vx.abs() < 1e-9, "mean velocity {mean_vx}");
}

#[test]
fn bad_motions_name_the_field() {
    let mesh = cube(0.01);
    let model = ron::from_str::<MaterialSpec>("NeoHookean(Young(e: 1e5, nu: 0.3))")
        .unwrap()
        .build()
        .unwrap();
    for (motion, expected) in [
        (
            ObstacleMotion {
                obstacle: 3,
                velocity: [0.0; 3],
                start: 0.0,
                stop: None,
                ..Default::default()
            },
            "obstacle 3 does not exist",
        ),
        (
            ObstacleMotion {
                obstacle: 0,
                velocity: [0.0; 3],
                start: 1.0,
                stop: Some(0.5),
                ..Default::default()
            },
            "not before start",
        ),
    ] {
        let e = Integrator::builder(&mesh, MaterialField::Uniform(model.clone()))
            .contact(ContactSpec {
                obstacles: vec![plane(0.0, true)],
                motions: vec![motion],
                ..Default::default()
            })
            .build()
            .unwrap_err()
            .to_string();
        assert!(e.contains("motions[0]") && e.contains(expected), "{e}");
    }
}
