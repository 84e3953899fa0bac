//! Model selection: an ensemble of energy models fitted by equation error (and optionally
//! refined by output error), each member's share of the elastic energy on the test
//! trajectories, and each model alone against the ensemble by rollout error (validation to
//! select, test to report).

use deform_materials::MaterialSpec;
use serde::{Deserialize, Serialize};

use crate::{Context, ExperimentObserver, Series, Stage, Task, mean_rollout};
use deform_learn::LearnError;
use deform_learn::dataset::Split;
use deform_learn::ensemble::{EnsembleFit, Member, fit_ensemble, refine_ensemble};
use deform_learn::output::OutputErrorFit;
use deform_learn::rollout::{mean_error, stable_or};

/// A model (one member alone, or the ensemble) and its mean rollout errors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct ModelErrors {
    /// The member, or `None` for the ensemble.
    pub member: Option<Member>,
    /// Mean rollout error on the validation trajectories (m); infinite when it fails.
    pub validation: f64,
    /// The same on the test trajectories.
    pub test: f64,
    /// Why its stage-2 fit was rejected, when it was: the refined model's free rollout of a
    /// training or validation trajectory failed (naming it), and its stage-1 fit stands.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub unstable: Option<String>,
}

/// What model selection found.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct SelectModelReport {
    /// The ensemble (after stage 2 when it ran), energy shares on the test trajectories.
    pub ensemble: EnsembleFit,
    /// Stage 2 of the ensemble, when it ran.
    pub stage2: Option<OutputErrorFit>,
    /// Each member alone, then the ensemble (last).
    pub models: Vec<ModelErrors>,
    /// Mean test rollout error per recorded state of the base model and the ensemble.
    pub rollouts: Vec<Series>,
}

/// Rollout errors below this (m) are rounding noise.
pub const ROUNDING_LEVEL: f64 = 1e-9;

impl SelectModelReport {
    /// The single model with the least validation error; `None` when no single model could
    /// be fitted and rolled out (every validation error infinite).
    pub fn best_single(&self) -> Option<&ModelErrors> {
        let finite = |m: &&ModelErrors| m.member.is_some() && m.validation.is_finite();
        self.models
            .iter()
            .filter(finite)
            .fold(None, |best: Option<&ModelErrors>, m| match best {
                Some(b) if b.validation <= m.validation => Some(b),
                _ => Some(m),
            })
    }

    /// The ensemble's row.
    pub fn ensemble_errors(&self) -> Option<&ModelErrors> {
        self.models.iter().find(|m| m.member.is_none())
    }

    /// The ensemble's test error over the best single model's; `Some(None)` when both are
    /// below [`ROUNDING_LEVEL`], where a ratio of two rounding noises would mislead.
    pub fn ensemble_over_best(&self) -> Option<Option<f64>> {
        let (best, ens) = (self.best_single()?.test, self.ensemble_errors()?.test);
        Some((ens.max(best) >= ROUNDING_LEVEL).then(|| ens / best.max(f64::MIN_POSITIVE)))
    }
}

/// Runs [`Task::SelectModel`].
///
/// # Errors
/// [`LearnError`].
pub fn run(
    cx: Context<'_>,
    observer: &mut dyn ExperimentObserver,
) -> Result<SelectModelReport, LearnError> {
    let Task::SelectModel {
        members,
        output_error,
    } = &cx.experiment.task
    else {
        unreachable!("dispatched on the task")
    };
    let origin = cx.experiment.scene.as_path();
    let train = cx.data.split(Split::Train);
    // Stage 1, then (optionally) stage 2 on the kept members.
    let mut fit_models = |names: &[Member], on: Split| {
        let (evaluate, blame) = (cx.data.split(on), cx.data.blame(&[Split::Train, on]));
        let evaluate = evaluate.as_slice();
        let fit = fit_ensemble(&cx.scene, origin, names, &train, evaluate).map_err(&blame)?;
        let Some(options) = output_error else {
            return Ok::<_, LearnError>((fit, None, None));
        };
        observer.start(Stage::Ensemble, options.max_evaluations as u64);
        let (refined, stage2) = refine_ensemble(
            &fit,
            &cx.scene,
            origin,
            &train,
            evaluate,
            *options,
            |_, loss| {
                observer.advance(1);
                observer.message(&format!("loss {loss:.3e}"));
            },
        )
        .map_err(&blame)?;
        observer.finish();
        // The refined model must run freely on the data it was fitted and chosen on, or
        // stage 1's stands.
        let Some(spec) = refined.spec() else {
            return Ok((refined, Some(stage2), None));
        };
        let scene = cx.scene.clone().material(spec);
        let mut sim = scene.build(origin)?.integrator;
        let validation = cx.data.split(Split::Validation);
        let sets = [train.as_slice(), validation.as_slice()];
        let (kept, unstable) = stable_or(&mut sim, &sets, refined, fit);
        Ok((kept, Some(stage2), unstable))
    };
    let (ensemble, stage2, unstable) = fit_models(members, Split::Test)?;
    // Each model alone against the ensemble, by rollout error on validation (to select)
    // and test (to report), averaged over the rollouts.
    let evaluate = |spec: Option<MaterialSpec>| -> (f64, f64) {
        let Some(spec) = spec else {
            return (f64::INFINITY, f64::INFINITY);
        };
        let mut s = cx.scene.clone();
        s.material = spec;
        let run = |split| {
            mean_rollout(&s, origin, &cx.data, split).map_or(f64::INFINITY, |e| mean_error(&e))
        };
        (run(Split::Validation), run(Split::Test))
    };
    let mut models = Vec::new();
    for &member in members {
        // A model the data leave undefined cannot have made them.
        let outside = ensemble.excluded.iter().any(|e| e.model == member);
        let (validation, test, why) = if outside {
            (f64::INFINITY, f64::INFINITY, None)
        } else {
            let (single, _, why) = fit_models(&[member], Split::Validation)?;
            let (validation, test) = evaluate(single.spec());
            (validation, test, why)
        };
        models.push(ModelErrors {
            member: Some(member),
            validation,
            test,
            unstable: why,
        });
    }
    let (validation, test) = evaluate(ensemble.spec());
    models.push(ModelErrors {
        member: None,
        validation,
        test,
        unstable,
    });
    // Test rollouts of the base scene and of the ensemble.
    let mut rollouts = vec![Series::new(
        "base model",
        mean_rollout(&cx.scene, origin, &cx.data, Split::Test)?,
    )];
    if let Some(spec) = ensemble.spec() {
        let s = cx.scene.clone().material(spec);
        rollouts.push(Series::new(
            "fitted ensemble",
            mean_rollout(&s, origin, &cx.data, Split::Test)?,
        ));
    }
    Ok(SelectModelReport {
        ensemble,
        stage2,
        models,
        rollouts,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A report whose single models all failed (infinite validation errors) names none best.
    #[test]
    fn a_report_whose_single_models_all_failed_names_none_best() {
        let names = [Member::CorotatedLinear, Member::NeoHookean];
        let mut report = SelectModelReport {
            ensemble: EnsembleFit::default(),
            stage2: None,
            models: names
                .iter()
                .map(|&m| ModelErrors {
                    member: Some(m),
                    validation: f64::INFINITY,
                    test: f64::INFINITY,
                    unstable: None,
                })
                .collect(),
            rollouts: Vec::new(),
        };
        assert!(report.best_single().is_none());
        report.models[1].validation = 2.0;
        report.models[0].validation = 3.0;
        assert_eq!(
            report.best_single().and_then(|m| m.member),
            Some(Member::NeoHookean)
        );
    }
}
