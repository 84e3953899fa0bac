//! Step a cantilever under gravity with Backward Euler and print the tip's sag.
//!
//! `cargo run --release -p deform-integrator --example cantilever`

use deform_assembly::MaterialField;
use deform_integrator::{Constraint, Integrator, IntegratorOptions, Motion, PolicySpec};
use deform_materials::MaterialSpec;
use deform_mesh::generate::BoxGrid;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mesh = BoxGrid::beam(4).build()?;
    let model = ron::from_str::<MaterialSpec>("NeoHookean(Young(e: 1e6, nu: 0.4))")?.build()?;
    let rest = mesh.rest_positions();
    let clamp = (0..mesh.num_vertices())
        .filter(|&v| rest[v].x == 0.0)
        .collect();
    let tip = (0..mesh.num_vertices())
        .find(|&v| rest[v].x == 1.0)
        .expect("the beam has a tip");
    let options = IntegratorOptions::default().gamma(0.01);
    let policy = ron::from_str::<PolicySpec>("Fixed(Direct())")?.build()?;
    let constraints = vec![Constraint {
        vertices: clamp,
        motion: Motion::Fixed,
    }];
    let mut sim = Integrator::builder(&mesh, MaterialField::Uniform(model))
        .density(1000.0)
        .constraints(constraints)
        .options(options)
        .policy(policy)
        .build()?;
    let mut state = sim.rest_state();
    for step in 1..=50 {
        let report = sim.step(&mut state)?;
        if step % 10 == 0 {
            println!(
                "t = {:.2} s: tip z = {:+.4} m ({} Newton iterations, residual {:.1e})",
                state.t,
                state.x[3 * tip + 2] - rest[tip].z,
                report.newton_iterations(),
                report.final_residual
            );
        }
    }
    Ok(())
}
