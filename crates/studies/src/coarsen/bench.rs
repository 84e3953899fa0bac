//! What `cargo xtask bench coarsen` measures, as a library function: the fine beam's data
//! (the default scene's material, damping and Newton options, clamped at x = 0, released
//! with the demo's coarsening variations), carried onto the coarse beam, and the coarse
//! fits of [`fit_coarse_models`] timed.

use std::path::Path;
use std::time::Instant;

use deform_integrator::Scene;
use deform_integrator::scene::MeshSource;
use deform_learn::coarsen::{Constraints, coarsen};
use deform_learn::{DatasetSpec, LearnError, OutputErrorOptions, Variations};

use super::{CoarseFits, CoarseSettings, fit_coarse_models};
use crate::NoProgress;

/// The sizes of a coarse-fit benchmark.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct CoarsenBench {
    /// The fine beam's size parameter (n = 8: 12,288 tets).
    pub fine: usize,
    /// The coarse beam's (n = 4: 1,536 tets).
    pub coarse: usize,
    /// Training trajectories (one more is made for validation).
    pub trajectories: usize,
    /// Steps per trajectory.
    pub steps: usize,
    /// Steps per rollout of the fits.
    pub rollout: usize,
    /// The per-element regularisation weights (fitted concurrently).
    pub weights: Vec<f64>,
}

impl Default for CoarsenBench {
    fn default() -> Self {
        Self {
            fine: 8,
            coarse: 4,
            trajectories: 3,
            steps: 100,
            rollout: 25,
            weights: vec![0.0],
        }
    }
}

/// What a coarse-fit benchmark measured.
#[derive(Debug)]
#[non_exhaustive]
pub struct CoarsenTimings {
    /// Seconds to make the fine data.
    pub generate_seconds: f64,
    /// Seconds of all the coarse fits.
    pub fit_seconds: f64,
    /// Tets of the coarse mesh.
    pub coarse_tets: usize,
    /// The fits (each with its own evaluations and seconds).
    pub fits: CoarseFits,
}

/// Makes the fine data, carries it onto the coarse beam and times the coarse fits.
///
/// # Errors
/// A dataset that cannot be made, or a fit that fails.
pub fn bench_coarse_fits(b: &CoarsenBench) -> Result<CoarsenTimings, LearnError> {
    let text = format!(
        r#"Scene(name: "fine", mesh: Beam({}), material: NeoHookean(Young(e: 1e6, nu: 0.4)),
            density: 1000.0, constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
            integrator: (dt: 0.01, alpha: 0.5, newton: (rel: 1e-6, max_iterations: 20)), steps: 1)"#,
        b.fine
    );
    let origin = Path::new("bench_coarsen.ron");
    let fine = Scene::parse(&text, origin)?;
    let count = b.trajectories + 1;
    let spec = DatasetSpec::new(count, b.steps, 3)
        .split((b.trajectories as f64 / count as f64, 1.0 / count as f64))
        .variations(
            Variations::default()
                .speed(0.5)
                .spin(1.0)
                .stretch(0.05)
                .rest(false),
        );
    let started = Instant::now();
    let data = deform_learn::dataset::generate(&fine, origin, &spec, |_, _| {})?;
    let generate_seconds = started.elapsed().as_secs_f64();
    let coarse = fine.clone().mesh(MeshSource::Beam(b.coarse));
    let (data, mapping) = coarsen(&data, &coarse, origin, Constraints::FromFine)?;
    let options = OutputErrorOptions::default().rollout(b.rollout);
    let settings = CoarseSettings::new(fine.integrator.newton.max_iterations, options)
        .regularisation(b.weights.clone());
    let started = Instant::now();
    let fits = fit_coarse_models(&data, origin, &settings, &mut NoProgress)?;
    Ok(CoarsenTimings {
        generate_seconds,
        fit_seconds: started.elapsed().as_secs_f64(),
        coarse_tets: mapping.tets,
        fits,
    })
}
