//! A coarse beam learns from a fine one (issue 17, first measurement): the fine beam's
//! trajectories are carried onto a beam with 8x fewer tets, and the coarse model's rollout
//! error on held-out trajectories is compared untuned (the fine E and nu), with the best
//! homogeneous Lame pair, a pair per region (eight slabs) and a pair per coarse element (all
//! by the output error with the adjoint). The per-element model is saved as a scene that `cargo xtask simulate`
//! runs, with its field as cell data in a `.vtu` for ParaView.
//!
//! ```sh
//! cargo run --release -p deform-learn --example coarsen -- [FINE_N] [STEPS] [DT_FACTOR]
//! ```

use std::path::Path;
use std::time::Instant;

use deform_assembly::MaterialField;
use deform_integrator::scene::MeshSource;
use deform_integrator::{Integrator, Scene};
use deform_learn::coarsen::{Constraints, coarsen, save_model};
use deform_learn::dataset::{DatasetSpec, Split, Variations, generate};
use deform_learn::rollout::{mean_error, mean_rollout_errors};
use deform_learn::{
    Field, OutputErrorFit, OutputErrorOptions, Regularisation, Trajectory, face_neighbours,
    field_of, fit_output_error, fit_output_error_field, term_coefficients,
};
use deform_mesh::TetMesh;
use deform_mesh::io::Vtu;

const FINE: &str = r#"Scene(name: "fine", mesh: Beam(4), material: NeoHookean(Young(e: 1e5, nu: 0.4)),
    density: 1000.0, constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
    integrator: (dt: 0.01, newton: (rel: 1e-10, abs: 1e-12)), steps: 1)"#;

/// Mean rollout error over `set`.
fn error(sim: &mut Integrator, set: &[&Trajectory]) -> Result<f64, deform_learn::LearnError> {
    mean_rollout_errors(sim, set).map(|e| mean_error(&e))
}

/// Fits a per-element field for each regularisation weight, from the homogeneous fit in
/// `sim`, keeps the one with the least validation error and leaves it in `sim`.
fn choose_field(
    sim: &mut Integrator,
    mesh: &TetMesh,
    labels: &[u32],
    (train, validation): (&[&Trajectory], &[&Trajectory]),
    options: OutputErrorOptions,
    damping: bool,
) -> Result<(f64, OutputErrorFit), Box<dyn std::error::Error>> {
    let homogeneous = sim.assembly().materials().clone();
    let MaterialField::Uniform(base) = &homogeneous else {
        unreachable!("the homogeneous fit is uniform")
    };
    let neighbours = face_neighbours(mesh, labels);
    let mut best: Option<(f64, f64, OutputErrorFit)> = None;
    for weight in [0.0, 1e-3, 1e-2, 1e-1] {
        sim.assembly_mut().set_materials(homogeneous.clone())?;
        let regularisation = Regularisation {
            towards: weight,
            smooth: weight,
            neighbours: neighbours.clone(),
        };
        if damping {
            // Positive starts: the optimiser moves logarithms.
            let mut o = sim.options().clone();
            (o.alpha, o.gamma) = (1e-3, 0.0);
            sim.set_options(o)?;
        }
        let spec = Field {
            labels: labels.to_vec(),
            initial: None,
            regularisation,
            damping,
        };
        let fit = fit_output_error_field(sim, train, &spec, options, |_, _| ())?;
        let e = error(sim, validation)?;
        let loss = fit.loss;
        println!("  regularisation {weight:e}: validation error {e:.4e} m, loss {loss:.3e}");
        if best.as_ref().is_none_or(|b| e < b.1) {
            best = Some((weight, e, fit));
        }
    }
    let (weight, _, mut field) = best.expect("four weights tried");
    if damping {
        let gamma = field.coefficients.pop().expect("damping fitted");
        let alpha = field.coefficients.pop().expect("damping fitted");
        let mut o = sim.options().clone();
        (o.alpha, o.gamma) = (alpha, gamma);
        sim.set_options(o)?;
        println!("  fitted Rayleigh alpha {alpha:.4}, gamma {gamma:.3e}");
    }
    sim.assembly_mut()
        .set_materials(field_of(base, Some(labels), &field.coefficients)?)?;
    Ok((weight, field))
}

/// A Lame pair per region (eight slabs along the beam) from the homogeneous fit in `sim`,
/// which is put back afterwards; returns the test error.
fn fit_regions(
    sim: &mut Integrator,
    mesh: &TetMesh,
    (train, test): (&[&Trajectory], &[&Trajectory]),
    options: OutputErrorOptions,
) -> Result<f64, Box<dyn std::error::Error>> {
    let homogeneous_model = sim.assembly().materials().clone();
    let slab = |e: usize| {
        let x: f64 = mesh.tets()[e]
            .iter()
            .map(|&v| mesh.rest_positions()[v].x)
            .sum();
        ((x / 4.0 * 8.0) as u32).min(7)
    };
    let regions = Field {
        labels: (0..mesh.num_tets()).map(slab).collect(),
        ..Default::default()
    };
    let t = Instant::now();
    let fit = fit_output_error_field(sim, train, &regions, options, |_, _| ())?;
    let per_region = error(sim, test)?;
    println!(
        "per-region fit (8 slabs): loss {:.3e} -> {:.3e} in {} evaluations, {:.1} s; test error {per_region:.4e} m",
        fit.initial_loss,
        fit.loss,
        fit.evaluations,
        t.elapsed().as_secs_f64()
    );
    sim.assembly_mut().set_materials(homogeneous_model)?;
    Ok(per_region)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let fine_n: usize = args.next().map_or(Ok(4), |a| a.parse())?;
    let steps: usize = args.next().map_or(Ok(60), |a| a.parse())?;
    let k: usize = args.next().map_or(Ok(1), |a| a.parse())?;
    let origin = Path::new("fine.ron");
    let mut fine = Scene::parse(FINE, origin)?;
    fine.mesh = MeshSource::Beam(fine_n);
    // Training and validation motions: releases with random velocity fields. Test motions
    // of another kind: pull-and-release (the body stretched or squeezed, then let go).
    let moving = Variations {
        speed: 0.5,
        spin: 1.0,
        stretch: 0.0,
        rest: false,
    };
    let pulled = Variations {
        speed: 0.0,
        spin: 0.0,
        stretch: 0.1,
        rest: false,
    };
    let train_spec = DatasetSpec {
        variations: moving,
        split: (0.67, 0.33),
        ..DatasetSpec::new(6, steps, 3)
    };
    let test_spec = DatasetSpec {
        variations: pulled,
        split: (0.0, 0.0),
        ..DatasetSpec::new(3, steps, 4)
    };
    let data = generate(&fine, origin, &train_spec, |_, _| ())?;
    let started = Instant::now();
    let test_data = generate(&fine, origin, &test_spec, |_, _| ())?;
    let simulated = 3.0 * steps as f64 * fine.integrator.dt;
    let fine_cost = started.elapsed().as_secs_f64() / simulated;
    let mut coarse = Scene {
        mesh: MeshSource::Beam(fine_n / 2),
        ..fine.clone()
    };
    coarse.integrator.dt *= k as f64;
    let map = |d| -> Result<_, deform_learn::LearnError> {
        let (d, report) = coarsen(d, &coarse, origin, Constraints::FromFine)?;
        let mut d = d.subsample(k.max(1));
        d.meta.scene.integrator.dt = coarse.integrator.dt;
        Ok((d, report))
    };
    let (data, report) = map(&data)?;
    let (test_data, _) = map(&test_data)?;
    println!(
        "fine beam n = {fine_n} ({fine_cost:.3} s per simulated second); coarse: {} tets ({}x fewer), {} outside, {k}x the dt; {} train/validation trajectories (releases with velocity), {} test (pull-and-release) x {steps} fine steps",
        report.tets, report.ratio, report.outside, train_spec.trajectories, test_spec.trajectories
    );
    let (train, test) = (data.split(Split::Train), test_data.split(Split::Test));
    let mut sim = data.meta.scene.build(origin)?.integrator;
    let untuned = error(&mut sim, &test)?;
    println!("untuned coarse: test mean RMS rollout error {untuned:.4e} m");
    let options = OutputErrorOptions {
        rollout: 10,
        max_iterations: 50,
        ..Default::default()
    };
    let deform_assembly::MaterialField::Uniform(model) = sim.assembly().materials() else {
        unreachable!("a uniform scene")
    };
    let start = term_coefficients(model);
    let t = Instant::now();
    let fit = fit_output_error(&mut sim, &train, &start, options, |_, _| ())?;
    let homogeneous = error(&mut sim, &test)?;
    println!(
        "homogeneous fit: mu, lambda = {:.4e}, {:.4e}; loss {:.3e} -> {:.3e} in {} evaluations, {:.1} s; test error {homogeneous:.4e} m ({:.3}x untuned)",
        fit.coefficients[0],
        fit.coefficients[1],
        fit.initial_loss,
        fit.loss,
        fit.evaluations,
        t.elapsed().as_secs_f64(),
        homogeneous / untuned
    );
    let mesh = data.meta.scene.build(origin)?.mesh;
    let per_region = fit_regions(&mut sim, &mesh, (&train, &test), options)?;
    println!(
        "  ({:.3}x untuned, {:.3}x homogeneous)",
        per_region / untuned,
        per_region / homogeneous
    );
    let labels: Vec<u32> = (0..mesh.num_tets() as u32).collect();
    let validation = data.split(Split::Validation);
    let t = Instant::now();
    let (weight, field) = choose_field(
        &mut sim,
        &mesh,
        &labels,
        (&train, &validation),
        options,
        k > 1,
    )?;
    println!("chosen regularisation weight {weight:e}");
    let per_element = error(&mut sim, &test)?;
    let mus: Vec<f64> = field.coefficients.iter().step_by(2).copied().collect();
    let (lo, hi) = mus
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), m| (a.min(*m), b.max(*m)));
    println!(
        "per-element fit: {} coefficients, mu in [{lo:.3e}, {hi:.3e}]; loss {:.3e} -> {:.3e} in {} evaluations, {:.1} s; test error {per_element:.4e} m ({:.3}x untuned, {:.3}x homogeneous)",
        field.coefficients.len(),
        field.initial_loss,
        field.loss,
        field.evaluations,
        t.elapsed().as_secs_f64(),
        per_element / untuned,
        per_element / homogeneous
    );
    let started = Instant::now();
    error(&mut sim, &test)?;
    let coarse_cost = started.elapsed().as_secs_f64() / simulated;
    println!(
        "cost per simulated second: coarse {coarse_cost:.4} s, fine {fine_cost:.3} s: {:.3}x",
        coarse_cost / fine_cost
    );
    // The learned model as a scene to keep, and its field for ParaView.
    let out = Path::new("target/deform/coarsen");
    let mut model = Scene {
        name: "coarse_beam".into(),
        ..data.meta.scene.clone()
    };
    (model.integrator.alpha, model.integrator.gamma) = (sim.options().alpha, sim.options().gamma);
    let saved = save_model(&model, &field.coefficients, out)?.remove(0);
    let lambdas: Vec<f64> = field
        .coefficients
        .iter()
        .skip(1)
        .step_by(2)
        .copied()
        .collect();
    let vtu = out.join("coarse_beam_field.vtu");
    Vtu::new(&mesh)
        .cell_scalars("mu", &mus)
        .cell_scalars("lambda", &lambdas)
        .write(&vtu)?;
    println!(
        "saved {} (cargo xtask simulate {0}); field for ParaView: {}",
        saved.display(),
        vtu.display()
    );
    Ok(())
}
