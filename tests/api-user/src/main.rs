//! Builds every public options, configuration and data struct a user sets up, the way the
//! docs show (constructors, `Default` and setters named like the fields), then runs a short
//! simulation with them. It compiles against deform's public API only, from outside its
//! workspace: adding a field to any of these structs must not break it.

use std::path::Path;

use deform_contact::{ContactSpec, FrictionSpec, MeshObstacle, Obstacle, ObstacleMotion};
use deform_integrator::scene::{ConstraintSpec, Initial, MeshSource, Output};
use deform_integrator::{
    IntegratorOptions, LoadForce, LoadSpec, NewtonOptions, NoObserver, RunOptions, Scene,
};
use deform_learn::import::{ImportSpec, ImportedTrajectory, VelocitySource};
use deform_learn::{DatasetSpec, EquationErrorOptions, Noise, OutputErrorOptions, Variations};
use deform_materials::{EnsembleMember, MaterialSpec, Moduli};
use deform_mesh::MeshOptions;
use deform_mesh::generate::BoxGrid;
use deform_mesh::select::Selector;
use deform_solvers::{Tolerance, WorkWeights};
use deform_studies::coarsen::CoarseSettings;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let young = Moduli::Young { e: 1e5, nu: 0.4 };
    let clamp = Selector::Plane {
        point: [0.0; 3],
        normal: [-1.0, 0.0, 0.0],
    };
    let newton = NewtonOptions::default().rel(1e-8).max_iterations(30);
    let options = IntegratorOptions::default()
        .dt(0.01)
        .gamma(0.01)
        .newton(newton);
    let contact = ContactSpec::default()
        .obstacles(vec![Obstacle::Plane {
            point: [0.0, 0.0, -0.5],
            normal: [0.0, 0.0, 1.0],
        }])
        .friction(Some(FrictionSpec::new(vec![0.3])))
        .motions(vec![
            ObstacleMotion::default().obstacle(0).velocity([0.0; 3]),
        ]);
    let _mesh_obstacle = MeshObstacle::new("ground.obj").offset([0.0, 0.0, -1.0]);
    let scene = Scene::new(
        "user",
        MeshSource::Generate(BoxGrid::new([4, 1, 1], [1.0, 0.25, 0.25])),
        MaterialSpec::NeoHookean(young),
        1000.0,
        5,
    )
    .constraints(vec![ConstraintSpec::new(clamp.clone())])
    .loads(vec![LoadSpec::new(Selector::All, [0.0, 0.0, -1.0])])
    .contact(Some(contact))
    .integrator(options)
    .initial(Initial::default().velocity([0.0, 0.1, 0.0]))
    .output(Output::default().every(0));
    let mut built = scene.build(Path::new("."))?;
    let run = built
        .integrator
        .run(&mut built.state, &RunOptions::steps(5), &mut NoObserver);
    let summary = run.into_result()?;
    println!(
        "{} steps, {} Newton iterations",
        summary.steps, summary.newton_iterations
    );

    // What the learning layer takes.
    let _ensemble = EnsembleMember::new(1.0, MaterialSpec::NeoHookean(young));
    let _load = LoadForce::new([1.0, 0.0, 0.0]).until(Some(0.1));
    let _spec = DatasetSpec::new(4, 10, 1)
        .variations(Variations::default())
        .split((0.5, 0.25));
    let _noise = Noise::default().position(0.01).seed(7);
    let _stage1 = EquationErrorOptions::default();
    let _stage2 = OutputErrorOptions::default().rollout(5).max_iterations(20);
    let trajectory = ImportedTrajectory::new("x.npy", VelocitySource::Derived);
    let _import = ImportSpec::new(
        0.01,
        [0.0, 0.0, -9.81],
        Default::default(),
        vec![trajectory],
    )
    .split((0.5, 0.25));
    let _coarse = CoarseSettings::new(20, OutputErrorOptions::default()).regions(4);
    let _tolerance = Tolerance::default().rel(1e-8);
    let _weights = WorkWeights::factor(0.1).sweep(2.0);
    let _mesh_options = MeshOptions::default().allow_nonmanifold(false);
    Ok(())
}
