//! Moving obstacles: a cube squeezed between the ground and a plane (or a triangle mesh)
//! that comes down onto it, a cube carried along by a ground that slides under it, swept
//! along by a turning paddle, and carried round by a turntable (a plane or a mesh). No
//! vertex is ever on or beyond an obstacle where it is at that step, and no edge crosses a
//! mesh obstacle's triangle (exact tests, not the collision detection); the squeezed cube
//! carries the force a uniaxial compression takes; friction drags the cube with the
//! moving ground and turns it with the turntable.

use deform_assembly::MaterialField;
use deform_integrator::{
    ContactSpec, FrictionSpec, Integrator, IntegratorOptions, Obstacle, ObstacleMotion, PolicySpec,
};
use deform_materials::MaterialSpec;
use deform_mesh::TetMesh;
use deform_mesh::generate::BoxGrid;
use nalgebra::Vector3;
mod common;

/// A 10 cm cube of 2 x 2 x 2 cells, `lift` above the ground.
fn cube(lift: f64) -> TetMesh {
    BoxGrid::new([2, 2, 2], [0.1, 0.1, 0.1])
        .origin([0.0, 0.0, lift])
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
        .options(IntegratorOptions::default().dt(0.005).gamma(gamma))
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
    let contact = ContactSpec::default()
        .obstacles(vec![plane(0.0, true), plane(lid, false)])
        .motions(vec![
            ObstacleMotion::default()
                .obstacle(1)
                .velocity([0.0, 0.0, -speed])
                .stop(Some(stop)),
        ]);
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
    let sliding = ContactSpec::default()
        .obstacles(vec![plane(0.0, true)])
        .motions(vec![ObstacleMotion::default().obstacle(0).velocity([
            ground_speed,
            0.0,
            0.0,
        ])]);
    let friction = FrictionSpec::new(vec![0.5]).velocity_threshold(1e-3);
    let contact = sliding.clone().friction(Some(friction));
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
    let mut still = sim(&mesh, sliding, 0.0);
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
            ObstacleMotion::default().obstacle(3).velocity([0.0; 3]),
            "obstacle 3 does not exist",
        ),
        (
            ObstacleMotion::default()
                .obstacle(0)
                .velocity([0.0; 3])
                .start(1.0)
                .stop(Some(0.5)),
            "not before start",
        ),
    ] {
        let e = Integrator::builder(&mesh, MaterialField::Uniform(model.clone()))
            .contact(
                ContactSpec::default()
                    .obstacles(vec![plane(0.0, true)])
                    .motions(vec![motion]),
            )
            .build()
            .unwrap_err()
            .to_string();
        assert!(e.contains("motions[0]") && e.contains(expected), "{e}");
    }
}

/// A square of side `2 half` centred at `(cx, cy, z)`, two triangles, as `.obj` text.
fn square(half: f64, (cx, cy): (f64, f64), z: f64) -> String {
    let mut text = String::new();
    for (x, y) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
        text += &format!("v {} {} {z}\n", cx + half * x, cy + half * y);
    }
    text + "f 1 2 3\nf 1 3 4\n"
}

/// The mesh obstacles where they are at time `t` against the body's surface: whether an
/// edge of one crosses a triangle of the other.
fn crosses_meshes(sim: &Integrator, mesh: &TetMesh, x: &[f64], t: f64) -> bool {
    let faces = deform_mesh::topology::boundary_faces(mesh);
    let body: Vec<Vector3<f64>> = x.chunks(3).map(Vector3::from_column_slice).collect();
    let (_, meshes) = sim.contact().unwrap().placed_at(t);
    meshes.iter().any(|(p, tri)| {
        let p: Vec<Vector3<f64>> = p.chunks(3).map(Vector3::from_column_slice).collect();
        common::surfaces_cross((&body, &faces), (&p, tri))
    })
}

/// The least signed distance of a vertex to an analytic obstacle where it is at time `t`.
fn least_distance(sim: &Integrator, x: &[f64], t: f64) -> f64 {
    let (obstacles, _) = sim.contact().unwrap().placed_at(t);
    let points = x.chunks(3).map(Vector3::from_column_slice);
    points
        .flat_map(|p| obstacles.iter().map(move |o| o.distance(&p)))
        .fold(f64::INFINITY, f64::min)
}

#[test]
fn a_mesh_lid_squeezes_the_cube_as_the_plane_lid_does() {
    let dir = tempfile::tempdir().unwrap();
    let lid_file = dir.path().join("lid.obj");
    let mesh = cube(0.001);
    let (lid, speed, stop) = (0.103, 0.05, 0.12);
    // Its diagonal edge passes well clear of the cube: above the cube's top face it
    // would add edge-edge barriers to the face's.
    std::fs::write(&lid_file, square(0.6, (0.45, -0.35), lid)).unwrap();
    let motion = |obstacle| {
        let m = ObstacleMotion::default().obstacle(obstacle);
        m.velocity([0.0, 0.0, -speed]).stop(Some(stop))
    };
    let planes = ContactSpec::default()
        .obstacles(vec![plane(0.0, true), plane(lid, false)])
        .motions(vec![motion(1)]);
    let meshes = ContactSpec::default()
        .obstacles(vec![plane(0.0, true)])
        .meshes(vec![
            deform_integrator::MeshObstacle::new(lid_file).offset([0.0; 3]),
        ])
        .motions(vec![motion(1)]);
    let (mut by_plane, mut by_mesh) = (sim(&mesh, planes, 0.01), sim(&mesh, meshes, 0.01));
    let (mut a, mut b) = (by_plane.rest_state(), by_mesh.rest_state());
    let mut gap = 0.0f64;
    for step in 0..80 {
        by_plane.step(&mut a).unwrap();
        by_mesh.step(&mut b).unwrap();
        let top = lid - speed * b.t.min(stop);
        assert!(
            b.x.chunks(3).all(|p| p[2] > 0.0 && p[2] < top),
            "step {step}: a vertex is outside (0, {top})"
        );
        assert!(
            !crosses_meshes(&by_mesh, &mesh, &b.x, b.t),
            "step {step}: the cube's surface crosses the lid"
        );
        gap =
            a.x.iter()
                .zip(&b.x)
                .fold(gap, |g, (p, q)| g.max((p - q).abs()));
    }
    // The lid's triangles are the plane where the cube can reach them: the same potential,
    // so the same motion up to Newton's tolerance.
    let strain = 1.0 - b.x.chunks(3).map(|p| p[2]).fold(0.0, f64::max) / 0.1;
    assert!(strain > 0.02, "strain {strain}");
    assert!(
        gap < 1e-6,
        "the mesh lid's cube is {gap} m from the plane lid's"
    );
}

#[test]
fn a_turning_paddle_sweeps_a_cube_along_the_ground() {
    let mesh = cube(0.0005);
    // A wall 2 cm thick beside the cube's x = 0 face, turning about a vertical axis 65 cm
    // from the cube: its face meets the cube at about 0.3 m/s.
    let paddle = Obstacle::Box {
        min: [-0.03, -0.3, 0.0],
        max: [-0.005, 0.3, 0.15],
    };
    let contact = ContactSpec::default()
        .obstacles(vec![plane(0.0, true), paddle])
        .motions(vec![
            ObstacleMotion::default()
                .obstacle(1)
                .angular_velocity([0.0, 0.0, -0.5])
                .pivot(Some([-0.0175, -0.6, 0.0])),
        ]);
    let mut sim = sim(&mesh, contact, 0.01);
    let mut s = sim.rest_state();
    let mut least = f64::INFINITY;
    for step in 0..60 {
        sim.step(&mut s).unwrap();
        let d = least_distance(&sim, &s.x, s.t);
        assert!(d > 0.0, "step {step}: a vertex is {d} m inside an obstacle");
        least = least.min(d);
    }
    // In 0.3 s the paddle turns by 0.15 rad: its face moves about 0.1 m at the cube, which
    // it pushes ahead (the cube's near face stays at the paddle, less the barrier's gap).
    let (obstacles, _) = sim.contact().unwrap().placed_at(s.t);
    assert!(matches!(obstacles[1], Obstacle::OrientedBox { .. }));
    let near: Vec<f64> =
        s.x.chunks(3)
            .map(|p| obstacles[1].distance(&Vector3::from_column_slice(p)))
            .collect();
    let mean_x = s.x.chunks(3).map(|p| p[0]).sum::<f64>() / near.len() as f64;
    assert!(mean_x > 0.05 + 0.08, "the cube's centre is at x = {mean_x}");
    let closest = near.iter().copied().fold(f64::INFINITY, f64::min);
    assert!(closest < 0.005, "the paddle is {closest} m from the cube");
}

#[test]
fn a_turntable_carries_a_cube_round_by_friction() {
    let dir = tempfile::tempdir().unwrap();
    let table = dir.path().join("table.obj");
    std::fs::write(&table, square(1.0, (0.0, 0.0), 0.0)).unwrap();
    // A 10 cm cube centred 0.3 m from the turntable's axis, the table turning at 1 rad/s
    // from the start: it needs 0.3 m/s^2 to go round, and friction gives up to mu g.
    let mesh = BoxGrid::new([2, 2, 2], [0.1, 0.1, 0.1])
        .origin([0.25, -0.05, 0.0005])
        .build()
        .unwrap();
    let spin = ObstacleMotion::default()
        .obstacle(0)
        .angular_velocity([0.0, 0.0, 1.0])
        .pivot(Some([0.0; 3]));
    let friction = Some(FrictionSpec::new(vec![0.5]).velocity_threshold(1e-3));
    let as_plane = ContactSpec::default()
        .obstacles(vec![plane(0.0, true)])
        .motions(vec![spin.clone()])
        .friction(friction.clone());
    let as_mesh = ContactSpec::default()
        .meshes(vec![
            deform_integrator::MeshObstacle::new(table).offset([0.0; 3]),
        ])
        .motions(vec![spin])
        .friction(friction);
    for (name, contact) in [("plane", as_plane), ("mesh", as_mesh)] {
        let mut sim = sim(&mesh, contact, 0.0);
        let mut s = sim.rest_state();
        for step in 0..100 {
            sim.step(&mut s).unwrap();
            assert!(
                s.x.chunks(3).all(|p| p[2] > 0.0),
                "{name}, step {step}: a vertex is below the table"
            );
            assert!(
                !crosses_meshes(&sim, &mesh, &s.x, s.t),
                "{name}, step {step}"
            );
        }
        // After 0.5 s the cube turns with the table: its centre at 0.3 m moves at 0.3 m/s
        // round the axis. It slid while mu g brought it up to speed, so it lags the
        // table's 0.5 rad by v^2 / (2 mu g r) = 0.031 rad.
        let masses = sim.assembly().vertex_masses(sim.mass());
        let total: f64 = masses.iter().sum();
        let mean = |f: &[f64]| -> Vector3<f64> {
            masses
                .iter()
                .zip(f.chunks(3))
                .map(|(m, p)| Vector3::from_column_slice(p) * *m)
                .sum::<Vector3<f64>>()
                / total
        };
        let (c, v) = (mean(&s.x), mean(&s.v));
        let expected = Vector3::z().cross(&Vector3::new(c.x, c.y, 0.0));
        assert!(
            (v - expected).norm() < 0.03 * expected.norm(),
            "{name}: velocity {v} against {expected}"
        );
        let angle = c.y.atan2(c.x);
        let lag = 0.3f64.powi(2) / (2.0 * 0.5 * 9.81 * 0.3);
        assert!(
            (angle - (0.5 - lag)).abs() < 0.005,
            "{name}: turned {angle} rad against {}",
            0.5 - lag
        );
    }
}

#[test]
fn a_lid_too_fast_for_the_step_is_refused_not_passed_through() {
    let dir = tempfile::tempdir().unwrap();
    let lid_file = dir.path().join("lid.obj");
    std::fs::write(&lid_file, square(0.6, (0.45, -0.35), 0.103)).unwrap();
    let mesh = cube(0.001);
    // 40 m/s: 20 cm in one step of 5 ms, twice the cube's height; nothing carried with the
    // lid can stay above the ground.
    let contact = ContactSpec::default()
        .obstacles(vec![plane(0.0, true)])
        .meshes(vec![
            deform_integrator::MeshObstacle::new(lid_file).offset([0.0; 3]),
        ])
        .motions(vec![
            ObstacleMotion::default()
                .obstacle(1)
                .velocity([0.0, 0.0, -40.0]),
        ]);
    let mut sim = sim(&mesh, contact, 0.01);
    let mut options = sim.options().clone();
    options.max_retries = 0;
    sim.set_options(options).unwrap();
    let mut s = sim.rest_state();
    let e = sim.step(&mut s).unwrap_err().to_string();
    assert!(e.contains("pass through the body"), "{e}");
    // With retries, the halved steps carry the cube's top down with the lid until Newton
    // gives up on the crushed cube: an error either way, never a lid through the cube.
    let mut options = sim.options().clone();
    options.max_retries = 3;
    sim.set_options(options).unwrap();
    let mut s = sim.rest_state();
    assert!(sim.step(&mut s).is_err());
}

/// A ground rising at 1e3 to 1e6 m/s (metres to kilometres a step, against a 10 cm cube)
/// is refused as an obstacle too fast for the step, not reported as an element inverted by
/// the carried surface.
#[test]
fn an_obstacle_too_fast_for_the_step_is_refused_as_such() {
    for speed in [1e3, 1e6] {
        let contact = ContactSpec::default()
            .obstacles(vec![plane(0.0, true)])
            .motions(vec![
                ObstacleMotion::default()
                    .obstacle(0)
                    .velocity([0.0, 0.0, speed]),
            ]);
        let mesh = cube(0.001);
        let mut sim = sim(&mesh, contact, 0.0);
        let mut s = sim.rest_state();
        let message = sim.step(&mut s).unwrap_err().to_string();
        assert!(
            message.contains("moving obstacles would pass through the body"),
            "{speed} m/s: {message}"
        );
    }
}
