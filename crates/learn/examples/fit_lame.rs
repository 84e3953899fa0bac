//! Fit a Lame pair to trajectories of a Neo-Hookean beam: generate data, add 1 % position
//! noise, fit by equation error, then refine by output error.
//!
//! `cargo run --release -p deform-learn --example fit_lame`

use std::path::Path;

use deform_integrator::Scene;
use deform_learn::DatasetSpec;
use deform_learn::{
    EquationErrorOptions, Noise, OutputErrorOptions, Split, Variations, dataset,
    fit_equation_error, fit_output_error,
};
use deform_materials::Lame;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let scene: Scene = ron::from_str(
        r#"Scene(
            name: "fit",
            mesh: Beam(2),
            material: NeoHookean(Young(e: 1e5, nu: 0.4)),
            density: 1000.0,
            constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
            integrator: (dt: 0.01, newton: (rel: 1e-10, abs: 1e-12)),
            steps: 1,
        )"#,
    )?;
    let origin = Path::new("example");
    let mut data = dataset::generate(
        &scene,
        origin,
        &DatasetSpec::new(5, 20, 42)
            .variations(Variations::default())
            .split((0.6, 0.2)),
        |_, _| {},
    )?;
    let mut sim = scene.build(origin)?.integrator;
    data.add_noise(
        Noise::default().position(0.01).velocity(0.0).seed(7),
        &sim.dofs().constrained_vertices(),
    );
    let train = data.split(Split::Train);
    let stage1 = fit_equation_error(&sim, &train, EquationErrorOptions::default())?;
    let young = |c: &[f64]| Lame::try_new(c[0], c[1]).map(|l| l.to_young());
    let (e1, nu1) = young(&stage1.coefficients)?;
    println!("truth:           E = 1.0000e5, nu = 0.4000");
    println!("equation error:  E = {e1:.4e}, nu = {nu1:.4}");
    let options = OutputErrorOptions::default().rollout(10);
    let fit = fit_output_error(
        &mut sim,
        &train,
        &stage1.coefficients,
        options,
        |k, loss| eprintln!("  evaluation {k}: loss {loss:.4e}"),
    )?;
    let (e2, nu2) = young(&fit.coefficients)?;
    println!(
        "output error:    E = {e2:.4e}, nu = {nu2:.4} ({} iterations, {:?})",
        fit.iterations.len(),
        fit.termination
    );
    Ok(())
}
