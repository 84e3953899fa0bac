//! Scenes, datasets and helpers shared by the fit tests.
#![allow(dead_code, unused_imports)]

use deform_solvers::WorkWeights;
use std::path::Path;

use deform_integrator::Scene;
use deform_learn::DatasetSpec;
use deform_learn::dataset::{self, generate};
use deform_learn::fit::lame_of;
use deform_learn::import::{Velocities, import_trajectory};
use deform_learn::{
    Dataset, EquationErrorOptions, FieldLayout, Noise, Split, Variations, fit_equation_error,
    fit_equation_error_field, npy,
};

pub fn scene(extra: &str, mesh: &str) -> Scene {
    let text = format!(
        r#"Scene(
            name: "fit",
            mesh: {mesh},
            material: NeoHookean(Young(e: 1e5, nu: 0.4)),
            density: 1000.0,
            constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
            integrator: (dt: 0.01, newton: (rel: 1e-11, abs: 1e-13), {extra}),
            steps: 1,
        )"#
    );
    ron::from_str(&text).unwrap()
}

/// Solver configurations from their RON texts.
pub fn specs(texts: &[&str]) -> Vec<deform_solvers::SolverSpec> {
    texts.iter().map(|t| ron::from_str(t).unwrap()).collect()
}

pub fn make(scene: &Scene, count: usize, steps: usize) -> Dataset {
    generate(
        scene,
        Path::new("test"),
        &DatasetSpec::new(count, steps, 42)
            .variations(Variations::default())
            .split((0.6, 0.2)),
        |_, _| {},
    )
    .unwrap()
}

pub fn relative(a: f64, b: f64) -> f64 {
    (a - b).abs() / b.abs()
}

/// The 10 cm cube of 2 x 2 x 2 cells 1 mm above the ground (a scene's `mesh` field).
pub const CUBE: &str =
    "Generate((cells: (2, 2, 2), size: (0.1, 0.1, 0.1), origin: (0.0, 0.0, 0.001)))";

/// One mesh of a slab (`(cells, size, origin)`, its top at z = 0) and a 10 cm cube of
/// 2 x 2 x 2 cells `gap` above it, written to `slab_and_cube.msh` in `dir`.
pub fn slab_and_cube(
    dir: &Path,
    (cells, size, origin): ([usize; 3], [f64; 3], [f64; 3]),
    gap: f64,
) -> std::path::PathBuf {
    let grid =
        |cells, size, origin| deform_mesh::generate::BoxGrid::new(cells, size).origin(origin);
    let mesh = deform_mesh::generate::boxes(&[
        grid(cells, size, origin),
        grid([2, 2, 2], [0.1, 0.1, 0.1], [0.0, 0.0, gap]),
    ])
    .unwrap();
    let file = dir.join("slab_and_cube.msh");
    deform_mesh::io::write(&file, &mesh).unwrap();
    file
}

/// A cube dropped on an incline (the ground, gravity tilted 30 degrees) with friction, from
/// random initial velocities: the equation error recovers the Lame pair and the coefficient
/// `trajectories` x `steps` of the contact scene `truth`, thrown at random velocities of
/// `speed` (all for training).
pub fn contact_data(truth: &Scene, speed: f64, steps: usize) -> Dataset {
    let spec = DatasetSpec::new(2, steps, 7)
        .variations(
            Variations::default()
                .speed(speed)
                .spin(0.0)
                .stretch(0.0)
                .rest(false),
        )
        .split((1.0, 0.0));
    generate(truth, Path::new("test"), &spec, |_, _| {}).unwrap()
}

/// The equation error of `data` from other moduli (E 3e5, nu 0.3) and, when `friction` is
/// fitted, without the scene's friction: the Lame pair within 1 % of the truth's (E 1e5,
/// nu 0.4). The fit and the model it started from.
pub fn fit_contact_moduli(
    truth: &Scene,
    data: &Dataset,
    friction: bool,
) -> (
    deform_learn::EquationErrorFit,
    deform_integrator::Integrator,
) {
    let mut guess = truth.clone();
    guess.material = ron::from_str("NeoHookean(Young(e: 3e5, nu: 0.3))").unwrap();
    if friction {
        guess.contact.as_mut().unwrap().friction = None;
    }
    let sim = guess.build(Path::new("test")).unwrap().integrator;
    let options = EquationErrorOptions::default().friction(friction);
    let fit = fit_equation_error(&sim, &data.split(Split::Train), options).unwrap();
    let lame = lame_of(&fit, 0).unwrap();
    let (mu, lambda) = (1e5 / (2.0 * 1.4), 1e5 * 0.4 / (1.4 * 0.2));
    assert!(relative(lame.mu, mu) < 0.01, "mu {} against {mu}", lame.mu);
    assert!(
        relative(lame.lambda, lambda) < 0.01,
        "lambda {} against {lambda}",
        lame.lambda
    );
    (fit, sim)
}
