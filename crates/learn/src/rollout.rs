//! Free rollouts against data, and the one definition of the rollout error every report
//! uses: the root-mean-square vertex distance between the simulated and the recorded
//! positions at each recorded state, and its mean over the predicted states (the start,
//! where the error is 0 by construction, is not counted).

use deform_integrator::{Integrator, OnStep, RunOptions, RunSummary, State, StepReport};
use deform_solvers::WorkWeights;

use crate::dataset::{Dataset, Split, Trajectory, state_at};
use crate::error::LearnError;

/// Root-mean-square distance between the vertices of two flat `3N` position vectors.
pub fn rms_distance(x: &[f64], y: &[f64]) -> f64 {
    let sq: f64 = x.iter().zip(y).map(|(a, b)| (a - b).powi(2)).sum();
    (sq / (x.len() / 3).max(1) as f64).sqrt()
}

/// The rollout error's distance at frame `n` of `t` for positions `x`: [`rms_distance`] to
/// the recorded state, or over the observed markers only
/// ([`crate::observe::Observed::rms_distance`]).
pub fn distance_to(t: &Trajectory, n: usize, x: &[f64]) -> f64 {
    match &t.observed {
        Some(o) => o.rms_distance(x, n),
        None => rms_distance(x, &t.x[n]),
    }
}

/// Mean of a rollout's errors over its predicted states (entry 0, the start, excluded).
pub fn mean_error(errors: &[f64]) -> f64 {
    let predicted = errors.get(1..).unwrap_or(&[]);
    predicted.iter().sum::<f64>() / predicted.len().max(1) as f64
}

/// A free rollout: errors at the recorded states and what the steps cost.
#[derive(Debug, Clone)]
pub struct Rollout {
    /// [`rms_distance`] to the data at each recorded state; entry 0 (the start) is 0.
    pub errors: Vec<f64>,
    /// The run (totals over every step taken).
    pub summary: RunSummary,
}

/// Rolls `sim` out from the trajectory's first state under its conditions, `refine` steps
/// per recorded step (the data's step is `refine` times the integrator's), and measures it
/// against the data.
/// `on_sample(n, state)` sees the state at each recorded index `n` (0 first), e.g. to write
/// frames.
///
/// # Errors
/// [`LearnError::Step`] naming `what` and the failed step.
pub fn rollout(
    sim: &mut Integrator,
    t: &Trajectory,
    refine: usize,
    weights: WorkWeights,
    what: &str,
    on_sample: &mut dyn FnMut(usize, &State),
) -> Result<Rollout, LearnError> {
    t.under(sim, |sim| {
        rollout_in(sim, t, refine, weights, what, on_sample)
    })?
}

/// [`rollout`] under the conditions in force.
fn rollout_in(
    sim: &mut Integrator,
    t: &Trajectory,
    refine: usize,
    weights: WorkWeights,
    what: &str,
    on_sample: &mut dyn FnMut(usize, &State),
) -> Result<Rollout, LearnError> {
    let refine = refine.max(1);
    let mut state = state_at(t, 0, sim.options().dt * refine as f64);
    on_sample(0, &state);
    let mut errors = vec![0.0];
    let mut taken: usize = 0;
    let summary = sim.run(
        &mut state,
        &RunOptions::steps(t.steps() * refine).with_weights(weights),
        &mut OnStep(|_: &StepReport, s: &State| {
            taken += 1;
            if taken.is_multiple_of(refine) {
                let n = taken / refine;
                errors.push(distance_to(t, n, &s.x));
                on_sample(n, s);
            }
        }),
    );
    let summary = summary
        .into_result()
        .map_err(|e| LearnError::step(what, e))?;
    Ok(Rollout { errors, summary })
}

/// [`rollout`] at the integrator's own step: the error at each recorded state.
///
/// # Errors
/// As [`rollout`].
pub fn rollout_error(sim: &mut Integrator, t: &Trajectory) -> Result<Vec<f64>, LearnError> {
    Ok(rollout(sim, t, 1, WorkWeights::default(), "rollout", &mut |_, _| {})?.errors)
}

/// The mean over trajectories of [`rollout_error`] at each recorded state.
///
/// # Errors
/// As [`rollout`], naming the trajectory by its index in `trajectories`.
pub fn mean_rollout_errors(
    sim: &mut Integrator,
    trajectories: &[&Trajectory],
) -> Result<Vec<f64>, LearnError> {
    let named = trajectories.iter().enumerate();
    mean_of(
        sim,
        named
            .map(|(k, t)| (format!("trajectory {k}"), *t))
            .collect(),
    )
}

/// [`mean_rollout_errors`] over the trajectories of one split of `data`, each named in a
/// failure as in the dataset ([`Dataset::describe`]).
///
/// # Errors
/// As [`rollout`].
pub fn split_rollout_errors(
    sim: &mut Integrator,
    data: &Dataset,
    split: Split,
) -> Result<Vec<f64>, LearnError> {
    let named = data.indices(split).map(|k| {
        let what = format!("trajectory {k} ({})", data.describe(k));
        (what, &data.trajectories[k])
    });
    mean_of(sim, named.collect())
}

fn mean_of(
    sim: &mut Integrator,
    named: Vec<(String, &Trajectory)>,
) -> Result<Vec<f64>, LearnError> {
    let count = named.len() as f64;
    let mut mean = vec![0.0; named.first().map_or(0, |(_, t)| t.x.len())];
    for (what, t) in named {
        let r = rollout(sim, t, 1, WorkWeights::default(), &what, &mut |_, _| {})?;
        for (m, v) in mean.iter_mut().zip(r.errors) {
            *m += v / count;
        }
    }
    Ok(mean)
}

/// `fitted` when `sim`, holding the model fitted, runs freely over the trajectories of `sets`
/// ([`free_rollout_failure`]), else `fallback` and why not: how every fit's result is kept
/// or rejected before a report shows it.
pub fn stable_or<T>(
    sim: &mut Integrator,
    sets: &[&[&Trajectory]],
    fitted: T,
    fallback: T,
) -> (T, Option<String>) {
    match free_rollout_failure(sim, sets) {
        None => (fitted, None),
        Some(why) => (fallback, Some(why)),
    }
}

/// The first failure of `sim`'s free rollouts of the trajectories of `sets` (training,
/// then validation), naming the trajectory and step; `None` when every one completes: the
/// check every fitted model passes before a report shows it.
pub fn free_rollout_failure(sim: &mut Integrator, sets: &[&[&Trajectory]]) -> Option<String> {
    for (set, name) in sets.iter().zip(["training", "validation"]) {
        for (k, t) in set.iter().enumerate() {
            let what = format!("{name} trajectory {k}");
            let weights = WorkWeights::default();
            if let Err(e) = rollout(sim, t, 1, weights, &what, &mut |_, _| {}) {
                return Some(e.to_string());
            }
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use deform_integrator::Scene;

    use super::*;
    use crate::dataset::{DatasetSpec, generate};

    fn beam(e: f64) -> Scene {
        let text = format!(
            r#"Scene(name: "t", mesh: Beam(1), material: NeoHookean(Young(e: {e:e}, nu: 0.4)),
            density: 1000.0, constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
            integrator: (dt: 0.01, max_retries: 2), steps: 3)"#
        );
        Scene::parse(&text, Path::new("t.ron")).unwrap()
    }

    /// The keep-or-reject rule of every fit (FitMaterial, SelectModel, the demo's story): a
    /// model far too soft (its elements invert under gravity) fails its free rollout and the
    /// fallback is kept, naming the set, trajectory and step; a model that runs is kept.
    #[test]
    fn a_model_that_fails_its_free_rollout_gives_way_to_the_fallback() {
        let origin = Path::new("t.ron");
        let data = generate(&beam(1e5), origin, &DatasetSpec::new(2, 60, 5), |_, _| ()).unwrap();
        let (train, validation) = (vec![&data.trajectories[0]], vec![&data.trajectories[1]]);
        let sets = [train.as_slice(), validation.as_slice()];
        let mut soft = beam(1e-4).build(origin).unwrap().integrator;
        let (kept, why) = stable_or(&mut soft, &sets, "fitted", "start");
        let why = why.expect("rejected");
        assert_eq!(kept, "start");
        assert!(
            why.contains("training trajectory 0") && why.contains("step"),
            "{why}"
        );
        let mut good = beam(1e5).build(origin).unwrap().integrator;
        assert_eq!(
            stable_or(&mut good, &sets, "fitted", "start"),
            ("fitted", None)
        );
        // The validation set is checked too.
        let mut fine_on_train = beam(1e5).build(origin).unwrap().integrator;
        let wild = Trajectory {
            v: vec![vec![1e4; data.trajectories[1].v[0].len()]; data.trajectories[1].v.len()],
            ..data.trajectories[1].clone()
        };
        let sets = [train.as_slice(), &[&wild][..]];
        let (kept, why) = stable_or(&mut fine_on_train, &sets, "fitted", "start");
        assert_eq!(kept, "start");
        assert!(why.expect("rejected").contains("validation trajectory 0"));
    }
}
