//! Force-model optimisation: the scene's material family, its Lame pair fitted by equation
//! error (stage 1) and then, optionally, by output error through the steps (stage 2); free
//! rollouts on the test trajectories with the true, stage-1 and fitted parameters.

use std::time::Instant;

use deform_materials::Lame;
use serde::{Deserialize, Serialize};

use crate::{
    Context, ExperimentObserver, Series, Stage, Task, mean_rollout, with_friction, with_lame,
};
use deform_learn::LearnError;
use deform_learn::dataset::Split;
use deform_learn::fit::{Unusable, fit_equation_error};
use deform_learn::output::{Field, OutputError, OutputErrorFit, fit_output_error_field};
use deform_learn::rollout::{mean_error, stable_or};

/// Which parameters a row of the fit table holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Estimate {
    /// The base model's own.
    Truth,
    /// The scene's own moduli when the data were imported: a guess, not the truth (which
    /// deform does not know).
    SceneGuess,
    /// Stage 1.
    EquationError,
    /// Stage 2.
    OutputError,
}

impl Estimate {
    /// Its name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Estimate::Truth => "truth",
            Estimate::SceneGuess => "scene's guess",
            Estimate::EquationError => "equation error",
            Estimate::OutputError => "output error",
        }
    }
}

/// One estimate of the moduli.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct ModuliRow {
    /// Which.
    pub estimate: Estimate,
    /// Young's modulus (Pa).
    pub young: f64,
    /// Poisson's ratio.
    pub poisson: f64,
    /// Time the fit took, seconds (`None` for the truth).
    pub seconds: Option<f64>,
}

/// What a material fit found.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct FitMaterialReport {
    /// Truth (or the scene's guess), stage 1 and (when run) stage 2, in that order; an
    /// estimate that is no material is left out (`stage1_unusable` says why).
    pub rows: Vec<ModuliRow>,
    /// Stage 2's result, when it ran.
    pub output_error: Option<OutputErrorFit>,
    /// Stage 2 started from the prior, whose loss (first) beat the stage-1 estimate's
    /// (infinite when that is no material).
    pub started_from_prior: Option<(f64, f64)>,
    /// Why the stage-1 estimate is no model, when it is not: stage 2 then starts from the
    /// task's `start`, or else from the scene's own moduli.
    #[serde(default)]
    pub stage1_unusable: Option<deform_learn::fit::Unusable>,
    /// Why stage 2's model was rejected, when it was: its free rollout of a training
    /// trajectory failed. The rows then end with stage 2's start (its fit is still in
    /// `output_error`), and the fitted rollouts are the start's.
    #[serde(default)]
    pub unstable: Option<String>,
    /// Mean test rollout error per recorded state with the true (or the scene's), stage-1
    /// and fitted parameters, each where it is a material; the fitted one is named
    /// [`FITTED`].
    pub rollouts: Vec<Series>,
    /// Contact's parameters, in a scene with contact: the scene's and stage 1's.
    #[serde(default)]
    pub contact: Option<ContactParameters>,
}

/// Contact's parameters as the scene has them (the truth with generated data) and as
/// stage 1 fitted them (`None` where it did not: contact the data never touch, friction
/// not asked for).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct ContactParameters {
    /// The barrier's stiffness (N/m): the scene's, stage 1's.
    pub kappa: (f64, Option<f64>),
    /// Each obstacle's coefficient of friction: the scene's (0 without friction), stage
    /// 1's; the analytic obstacles, the mesh obstacles, then the body's own surface.
    pub friction: Vec<(f64, Option<f64>)>,
    /// Whether the last coefficient is the body's own surface's (self-contact).
    pub self_contact: bool,
    /// Each coefficient of friction as stage 2 fitted them, when it did (stage 1 was asked
    /// to fit friction and stage 2 ran); in `friction`'s order.
    #[serde(default)]
    pub output_error: Option<Vec<f64>>,
}

impl ContactParameters {
    /// The scene's contact against stage 1's `fit`.
    fn of(
        sim: &deform_integrator::Integrator,
        fit: Option<&deform_learn::EquationErrorFit>,
    ) -> Option<Self> {
        let model = sim.contact()?;
        let scene_mu = |i: usize| model.friction().map_or(0.0, |(mu, _)| mu[i]);
        let fitted_mu = |i: usize| fit.and_then(|f| f.friction.get(i).copied());
        Some(Self {
            kappa: (model.barrier().kappa, fit.and_then(|f| f.kappa)),
            friction: (0..model.frictional())
                .map(|i| (scene_mu(i), fitted_mu(i)))
                .collect(),
            self_contact: model.self_contact_surface().is_some(),
            output_error: None,
        })
    }

    /// Where stage 2 starts each coefficient of friction: stage 1's estimate where it is a
    /// coefficient (finite, not negative), else the scene's.
    fn stage1_or_scene(&self) -> Vec<f64> {
        let usable = |f: &f64| f.is_finite() && *f >= 0.0;
        (self.friction.iter())
            .map(|(scene, fit)| fit.filter(usable).unwrap_or(*scene))
            .collect()
    }
}

impl FitMaterialReport {
    /// Whether the first row is the truth (generated data) rather than the scene's guess
    /// (imported data): only then are [`FitMaterialReport::errors`] errors.
    pub fn truth_known(&self) -> bool {
        self.rows.first().map(|r| r.estimate) == Some(Estimate::Truth)
    }

    /// Row `i`'s relative errors in Young's modulus and Poisson's ratio against the truth
    /// (with imported data, the relative changes from the scene's guess).
    pub fn errors(&self, i: usize) -> (f64, f64) {
        let (truth, row) = (&self.rows[0], &self.rows[i]);
        (
            (row.young - truth.young).abs() / truth.young,
            (row.poisson - truth.poisson).abs() / truth.poisson,
        )
    }

    /// The last estimate's relative error in Young's modulus; `None` without an estimate
    /// (stage 1 unusable and no stage 2).
    pub fn young_error(&self) -> Option<f64> {
        (self.rows.len() > 1).then(|| self.errors(self.rows.len() - 1).0)
    }

    /// The last estimate's relative error in Poisson's ratio; `None` likewise.
    pub fn poisson_error(&self) -> Option<f64> {
        (self.rows.len() > 1).then(|| self.errors(self.rows.len() - 1).1)
    }

    /// Mean rollout error of the fitted parameters over the true (or the scene's); `None`
    /// without a fitted material, or when the true parameters reproduce the data exactly
    /// (clean data made by deform), where no ratio means anything.
    pub fn rollout_ratio(&self) -> Option<f64> {
        let truth = mean_error(&self.rollouts.first()?.values);
        let fitted = self.rollouts.iter().find(|s| s.name == FITTED)?;
        (truth > 0.0).then(|| mean_error(&fitted.values) / truth)
    }

    /// The fitted over the true (or the scene's) rollout error as a phrase; where there is
    /// no ratio, why.
    pub fn rollout_phrase(&self) -> String {
        let against = if self.truth_known() {
            "true"
        } else {
            "scene's guess"
        };
        match self.rollout_ratio() {
            Some(ratio) => format!("rollout error fitted / {against} {ratio:.3}"),
            None if self.rows.len() < 2 => "no fitted material to roll out".to_owned(),
            None => "no rollout ratio: the true parameters reproduce the data exactly".to_owned(),
        }
    }

    /// The one-line summary: the estimate's error (or, with imported data, the estimate)
    /// and the rollout ratio.
    pub fn headline(&self) -> String {
        let (Some(de), Some(dnu), Some(last)) =
            (self.young_error(), self.poisson_error(), self.rows.last())
        else {
            let why = self.stage1_unusable.as_ref().map(ToString::to_string);
            return format!(
                "no estimate: stage 1 is unusable ({}) and stage 2 did not run",
                why.unwrap_or_default()
            );
        };
        let phrase = self.rollout_phrase();
        match self.truth_known() {
            true => format!(
                "E off by {:.3} %, nu by {:.3} %; {phrase}",
                100.0 * de,
                100.0 * dnu
            ),
            false => format!(
                "E = {:.5e} Pa, nu = {:.4} (imported data: the truth is the user's); {phrase}",
                last.young, last.poisson
            ),
        }
    }
}

/// The name of the fitted parameters' rollout series.
pub const FITTED: &str = "fitted";

/// Stage 1 on `train`, why its estimate is no model (when it is not) and the seconds it
/// took. Stage 1 needs whole states: on data of markers only it does not run.
fn stage1(
    sim: &deform_integrator::Integrator,
    train: &[&deform_learn::Trajectory],
    options: deform_learn::EquationErrorOptions,
) -> Result<
    (
        Option<deform_learn::EquationErrorFit>,
        Option<Unusable>,
        f64,
    ),
    LearnError,
> {
    let started = Instant::now();
    if let Some(trajectory) = train.iter().position(|t| t.observed.is_some()) {
        return Ok((None, Some(Unusable::MarkersOnly { trajectory }), 0.0));
    }
    let fit = fit_equation_error(sim, train, options)?;
    let unusable = fit.unusable();
    Ok((Some(fit), unusable, started.elapsed().as_secs_f64()))
}

/// Where stage 2 may start: stage 1's coefficients, a prior Lame pair (the task's `start`,
/// or the scene's when stage 1 is unusable) and, when it fits friction, the coefficients
/// of friction to start from (appended to either).
struct Start<'a> {
    stage1: &'a [f64],
    prior: Option<Lame>,
    friction: Option<&'a [f64]>,
}

/// What stage 2 found.
struct Stage2 {
    fit: OutputErrorFit,
    /// The fitted coefficients (Lame pair, then friction's), or the start's when the fitted
    /// model failed a free rollout.
    coefficients: Vec<f64>,
    seconds: f64,
    started_from_prior: Option<(f64, f64)>,
    unstable: Option<String>,
}

/// Stage 2: output error on the training data from stage 1's estimate, or from the prior
/// when its loss is lower (or the estimate is no material); the fitted model must then run
/// freely over the training and validation data, or its start stands instead.
fn stage2(
    sim: &mut deform_integrator::Integrator,
    data: &deform_learn::dataset::Dataset,
    options: deform_learn::OutputErrorOptions,
    from: &Start<'_>,
    report: &FitMaterialReport,
    observer: &mut dyn ExperimentObserver,
) -> Result<Stage2, LearnError> {
    let train = data.split(Split::Train);
    let blame = data.blame(&[Split::Train]);
    observer.start(Stage::Fit, options.max_iterations);
    let started = Instant::now();
    let with_friction = |c: &[f64]| [c, from.friction.unwrap_or(&[])].concat();
    let mut initial = with_friction(from.stage1);
    let mut started_from_prior = None;
    if let Some(lame) = from.prior {
        let prior = with_friction(&[lame.mu, lame.lambda]);
        let mut loss_at = |c: &[f64]| {
            let o = OutputError::new(sim, &train, options, |_, _| {})?;
            let o = if from.friction.is_some() {
                o.with_friction()?
            } else {
                o
            };
            o.evaluate(c).map(|(l, _)| l)
        };
        let l0 = loss_at(&prior);
        if let Some(why) = &report.stage1_unusable {
            // Stage 2 can only start from the prior: say why it cannot, if it cannot.
            let l0 = l0.map_err(|e| {
                let e = blame(e);
                let (e0, nu0) = lame.to_young();
                LearnError::Unsupported(format!(
                    "stage 1 is unusable ({why}) and stage 2 cannot start from the prior (E = {e0:.4e} Pa, nu = {nu0:.4}): {e}",
                ))
            })?;
            started_from_prior = Some((l0, f64::INFINITY));
            initial = prior;
        } else {
            let l1 = loss_at(&initial).unwrap_or(f64::INFINITY);
            if let Ok(l0) = l0
                && l0 < l1
            {
                started_from_prior = Some((l0, l1));
                initial = prior;
            }
        }
    }
    let field = Field::default()
        .initial(Some(initial.clone()))
        .friction(from.friction.is_some());
    let fit = fit_output_error_field(sim, &train, &field, options, |k, loss| {
        observer.message(&format!("evaluation {k}, loss {loss:.3e}"));
    })
    .map_err(&blame)?;
    observer.finish();
    let validation = data.split(Split::Validation);
    let sets = [train.as_slice(), validation.as_slice()];
    let (coefficients, unstable) = stable_or(sim, &sets, fit.coefficients.clone(), initial);
    Ok(Stage2 {
        fit,
        coefficients,
        seconds: started.elapsed().as_secs_f64(),
        started_from_prior,
        unstable,
    })
}

/// A row of the fit table, when `(mu, lambda)` is a material.
fn moduli_row(estimate: Estimate, (mu, lambda): (f64, f64), seconds: f64) -> Option<ModuliRow> {
    let (young, poisson) = Lame::try_new(mu, lambda).ok()?.to_young();
    let seconds = Some(seconds);
    Some(ModuliRow {
        estimate,
        young,
        poisson,
        seconds,
    })
}

/// Runs [`Task::FitMaterial`].
///
/// # Errors
/// [`LearnError`]; [`LearnError::Unsupported`] when the scene's material is not one model.
pub fn run(
    cx: Context<'_>,
    observer: &mut dyn ExperimentObserver,
) -> Result<FitMaterialReport, LearnError> {
    let Task::FitMaterial {
        equation_error,
        output_error,
        start,
    } = &cx.experiment.task
    else {
        unreachable!("dispatched on the task")
    };
    let origin = cx.experiment.scene.as_path();
    let train = cx.data.split(Split::Train);
    let mut markers_only = cx.data.indices(Split::Train);
    if let (None, Some(k)) = (
        output_error,
        markers_only.find(|&k| cx.data.trajectories[k].observed.is_some()),
    ) {
        return Err(LearnError::Unsupported(format!(
            "FitMaterial on marker data needs `output_error`: training trajectory {k} ({}) observes markers only, and equation error (stage 1) needs whole states",
            cx.data.describe(k)
        )));
    }
    let (stage1, stage1_unusable, stage1_seconds) =
        stage1(&cx.built.integrator, &train, *equation_error)
            .map_err(cx.data.blame(&[Split::Train]))?;
    let stage1_coefficients = stage1
        .as_ref()
        .map_or(vec![f64::NAN; 2], |s| s.coefficients.clone());
    let (mu1, lambda1) = (stage1_coefficients[0], stage1_coefficients[1]);
    let truth = cx.scene.material.build()?.lame().ok_or_else(|| {
        LearnError::Unsupported("the scene's model has no single Lame pair".into())
    })?;
    let (e0, nu0) = truth.to_young();
    // Imported data were made by a model deform does not know: the scene's moduli are a guess.
    let known = matches!(cx.experiment.data, crate::Data::Generate(_));
    let mut rows = vec![ModuliRow {
        estimate: if known {
            Estimate::Truth
        } else {
            Estimate::SceneGuess
        },
        young: e0,
        poisson: nu0,
        seconds: None,
    }];
    rows.extend(moduli_row(
        Estimate::EquationError,
        (mu1, lambda1),
        stage1_seconds,
    ));
    let mut fitted = (mu1, lambda1);
    let mut report = FitMaterialReport {
        rows: Vec::new(),
        output_error: None,
        started_from_prior: None,
        stage1_unusable,
        unstable: None,
        rollouts: Vec::new(),
        contact: ContactParameters::of(&cx.built.integrator, stage1.as_ref()),
    };
    // Stage 2 fits friction too when stage 1 was asked to.
    let friction = (report.contact.as_ref())
        .filter(|c| equation_error.friction && !c.friction.is_empty())
        .map(ContactParameters::stage1_or_scene);
    if let Some(options) = output_error {
        let from = Start {
            stage1: &stage1_coefficients,
            prior: match (start, &report.stage1_unusable) {
                (Some(p), _) => Some(p.to_lame()?),
                (None, Some(_)) => Some(truth),
                (None, None) => None,
            },
            friction: friction.as_deref(),
        };
        let mut sim = cx.built.integrator;
        let s2 = stage2(&mut sim, &cx.data, *options, &from, &report, observer)?;
        rows.extend(moduli_row(
            Estimate::OutputError,
            (s2.coefficients[0], s2.coefficients[1]),
            s2.seconds,
        ));
        fitted = (s2.coefficients[0], s2.coefficients[1]);
        if let (Some(c), Some(_)) = (report.contact.as_mut(), &friction) {
            c.output_error =
                Some(s2.coefficients[s2.coefficients.len() - c.friction.len()..].to_vec());
        }
        report.started_from_prior = s2.started_from_prior;
        report.unstable = s2.unstable;
        report.output_error = Some(s2.fit);
    }
    // Rollouts on the test trajectories with each parameter set.
    observer.start(Stage::Rollouts, 3);
    let first = if known {
        "true parameters"
    } else {
        "scene's parameters"
    };
    // Each estimate rolls out with its own coefficients of friction, where it fitted them
    // (stage 1's where they are coefficients, as stage 2 starts from them).
    let fitted_friction = (report.contact.as_ref())
        .and_then(|c| c.output_error.clone())
        .or_else(|| friction.clone());
    for (name, (mu, lambda), mu_friction) in [
        (first, (truth.mu, truth.lambda), None),
        ("equation error", (mu1, lambda1), friction),
        (FITTED, fitted, fitted_friction),
    ] {
        // An estimate that is no material (stage 1 on noisy data) has no rollout.
        if Lame::try_new(mu, lambda).is_ok() {
            let mut scene = with_lame(&cx.scene, mu, lambda)?;
            if let Some(m) = &mu_friction {
                scene = with_friction(&scene, m)?;
            }
            let errors = mean_rollout(&scene, origin, &cx.data, Split::Test)?;
            report.rollouts.push(Series::new(name, errors));
        }
        observer.advance(1);
    }
    observer.finish();
    report.rows = rows;
    Ok(report)
}
