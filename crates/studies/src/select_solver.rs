//! Solver selection: every candidate solves every Newton iteration's system of the training
//! trajectories (counterfactual logging), a policy is learned from the logs (and its Newton
//! settings optionally tuned), and it is measured against each fixed candidate, the
//! Eisenstat-Walker rule and the hand schedule on the test trajectories and on held-out
//! scenes ([`deform_learn::compare`]).

use std::fmt::Write as _;
use std::path::PathBuf;

use deform_integrator::{
    EisenstatWalker, Fixed, IntegratorOptions, Projection, Scene, SolverPolicy, StaleFactor,
};
use deform_solvers::{SolverSpec, WorkWeights};
use serde::{Deserialize, Serialize};

use crate::{Context, ExperimentObserver, Stage, Task};
use deform_learn::LearnError;
use deform_learn::compare::{Case, Contestant, Measured, measure_all};
use deform_learn::dataset::Split;
use deform_learn::policy::{LearnedPolicy, PolicyOptions};
use deform_learn::solver_data::{Run, collect_runs};
use deform_learn::tuning::{Tuning, TuningSample, tune_policy};

/// The learned policy's tuned settings: Newton's relative tolerance, the largest forcing
/// term and the tangent projection.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct TunedLearned {
    /// Newton's relative tolerance.
    pub newton_rel: f64,
    /// Its forcing terms `(eta_max, gamma)`, when it has them.
    pub forcing: Option<(f64, f64)>,
    /// Newton's tangent projection, when it replaces the scenes' own.
    pub projection: Option<Projection>,
}

impl TunedLearned {
    /// From tuned log10 values: Newton rel, then eta_max when there is forcing.
    pub fn from_values(
        p: &[f64],
        forcing: Option<(f64, f64)>,
        projection: Option<Projection>,
    ) -> Self {
        Self {
            newton_rel: 10f64.powf(p[0]),
            forcing: forcing.map(|(eta, gamma)| (p.get(1).map_or(eta, |e| 10f64.powf(*e)), gamma)),
            projection,
        }
    }

    /// Sets the tuned Newton options.
    pub fn apply(&self, o: &mut IntegratorOptions) {
        o.newton.rel = self.newton_rel;
        if let Some(p) = self.projection {
            o.newton.project = p;
        }
    }

    /// A short description.
    pub fn label(&self) -> String {
        let mut s = format!("Newton rel {:.1e}", self.newton_rel);
        if let Some((eta, _)) = self.forcing {
            s += &format!(", eta_max {eta:.1e}");
        }
        if let Some(p) = self.projection {
            s += &format!(", projection {p:?}");
        }
        s
    }
}

/// A policy in the comparison.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Contender {
    /// One candidate throughout.
    Fixed(SolverSpec),
    /// The Eisenstat-Walker rule on an iterative candidate.
    EisenstatWalker(SolverSpec),
    /// Stale-factor PCG refactorising above this many iterations.
    HandSchedule(SolverSpec, usize),
    /// The learned policy.
    Learned,
    /// The learned policy with tuned Newton settings and forcing term.
    LearnedTuned(TunedLearned),
    /// A fixed candidate with the learned policy's tuned Newton settings (what tuning
    /// Newton alone gives).
    FixedTunedNewton(SolverSpec, TunedLearned),
}

impl Contender {
    /// Its name in reports.
    pub fn name(&self) -> String {
        match self {
            Contender::Fixed(s) => format!("fixed {}", s.name()),
            Contender::EisenstatWalker(s) => format!("Eisenstat-Walker {}", s.name()),
            Contender::HandSchedule(_, above) => {
                format!("hand schedule: refactorise above {above} iterations")
            }
            Contender::Learned => "learned".into(),
            Contender::LearnedTuned(t) => format!("learned, tuned ({})", t.label()),
            Contender::FixedTunedNewton(s, _) => {
                format!("fixed {}, the tuned Newton settings", s.name())
            }
        }
    }

    /// A fixed candidate (the baselines "in hindsight").
    pub fn is_fixed(&self) -> bool {
        matches!(self, Contender::Fixed(_))
    }

    /// A fixed candidate that keeps a factor across solves (a schedule in disguise).
    pub fn reuses_factor(&self) -> bool {
        matches!(self, Contender::Fixed(s) if s.is_stale_cholesky())
    }

    /// The learned policy, tuned or not.
    pub fn is_learned(&self) -> bool {
        matches!(self, Contender::Learned | Contender::LearnedTuned(_))
    }

    /// The Newton settings it runs with, when not the scenes' own.
    pub fn settings(&self) -> Option<TunedLearned> {
        match self {
            Contender::LearnedTuned(t) | Contender::FixedTunedNewton(_, t) => Some(*t),
            _ => None,
        }
    }

    fn policy(&self, learned: &LearnedPolicy) -> Box<dyn SolverPolicy> {
        match self {
            Contender::Fixed(s) | Contender::FixedTunedNewton(s, _) => Box::new(Fixed(s.clone())),
            Contender::EisenstatWalker(s) => Box::new(EisenstatWalker::new(s.clone())),
            Contender::HandSchedule(s, above) => Box::new(StaleFactor::new(s.clone(), *above)),
            Contender::Learned => Box::new(learned.clone()),
            Contender::LearnedTuned(t) => Box::new(learned.with_forcing(t.forcing)),
        }
    }
}

/// A policy's totals on a case.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct PolicyRow {
    /// The policy.
    pub contender: Contender,
    /// What it did.
    pub measured: Measured,
}

/// What a row is compared by.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Key {
    /// Deterministic work.
    Work,
    /// Median linear-solver time.
    SolverSeconds,
    /// Median whole-step time.
    StepSeconds,
}

impl Key {
    /// Every key, in report order.
    pub const ALL: [Key; 3] = [Key::Work, Key::SolverSeconds, Key::StepSeconds];

    /// The row's value.
    pub fn of(self, m: &Measured) -> f64 {
        match self {
            Key::Work => m.work,
            Key::SolverSeconds => m.seconds,
            Key::StepSeconds => m.step_seconds,
        }
    }
}

/// The policies on one case.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct CaseReport {
    /// The case (`test trajectories of ...`, `held-out ...`).
    pub label: String,
    /// Every policy, fixed candidates first.
    pub rows: Vec<PolicyRow>,
}

/// Relative position accuracy a policy must keep to count as a baseline.
pub const BASELINE_ACCURACY: f64 = 1e-6;

impl CaseReport {
    /// The best fixed candidate in hindsight by `key` among those within
    /// [`BASELINE_ACCURACY`]; `without_reuse` leaves out stale-factor ones.
    pub fn best_fixed(&self, without_reuse: bool, key: Key) -> Option<&PolicyRow> {
        self.rows
            .iter()
            .filter(|r| r.contender.is_fixed() && r.within_accuracy())
            .filter(|r| !(without_reuse && r.contender.reuses_factor()))
            .min_by(|a, b| key.of(&a.measured).total_cmp(&key.of(&b.measured)))
    }

    /// `row`'s `key` over the best fixed candidate's (see [`Self::best_fixed`]).
    pub fn ratio_to_best(&self, row: &PolicyRow, without_reuse: bool, key: Key) -> Option<f64> {
        let best = self.best_fixed(without_reuse, key)?;
        Some(key.of(&row.measured) / key.of(&best.measured).max(f64::MIN_POSITIVE))
    }

    /// The case's summary, from its table: the learned policy's work and solver time over
    /// the best fixed solver's (without factor reuse) and, when its Newton settings were
    /// tuned, the work of its solver choice alone (over the direct solver with the same
    /// settings), so that a gain is credited to the choice or to the tuning as the table
    /// does.
    pub fn headline(&self) -> Option<String> {
        let l = self.learned()?;
        let work = self.ratio_to_best(l, true, Key::Work)?;
        let time = self.ratio_to_best(l, true, Key::SolverSeconds)?;
        let mut line = format!(
            "{}: {} / best fixed without reuse {work:.2}x work, {time:.2}x solver time",
            self.label,
            l.contender.name()
        );
        if let Some((_, d, [choice, ..])) = self.solver_choice_alone() {
            let _ = write!(
                line,
                "; the solver choice alone {choice:.2}x the work of {} with the same Newton settings",
                d.contender.name()
            );
        }
        Some(line)
    }

    /// What the learned policy's solver choice adds on top of its tuned Newton settings:
    /// its work, solver time and step time over the direct solver's with the same
    /// settings, when both ran.
    pub fn solver_choice_alone(&self) -> Option<(&PolicyRow, &PolicyRow, [f64; 3])> {
        let (l, d) = (self.learned()?, self.tuned_direct()?);
        l.contender.settings()?;
        let ratio = |k: Key| k.of(&l.measured) / k.of(&d.measured).max(f64::MIN_POSITIVE);
        Some((l, d, Key::ALL.map(ratio)))
    }

    /// The last learned row (tuned when it ran).
    pub fn learned(&self) -> Option<&PolicyRow> {
        self.rows.iter().rev().find(|r| r.contender.is_learned())
    }

    /// The direct solver with the tuned Newton settings.
    pub fn tuned_direct(&self) -> Option<&PolicyRow> {
        self.rows
            .iter()
            .find(|r| matches!(r.contender, Contender::FixedTunedNewton(..)))
    }
}

impl PolicyRow {
    /// Completed and within [`BASELINE_ACCURACY`] of the reference.
    pub fn within_accuracy(&self) -> bool {
        !self.measured.failed && self.measured.error <= BASELINE_ACCURACY
    }
}

/// How the learned policy's settings were tuned.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct PolicyTuning {
    /// The chosen settings.
    pub settings: TunedLearned,
    /// Their evaluation.
    pub best: TuningSample,
    /// Evaluations for the chosen projection.
    pub evaluations: usize,
    /// The accuracy bound.
    pub accuracy: f64,
    /// The tuning's own scenes besides the first training trajectory.
    pub scenes: Vec<PathBuf>,
    /// Every evaluation, with the projection tried (`None`: the scenes' own).
    pub samples: Vec<(Option<Projection>, TuningSample)>,
}

/// What solver selection found.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct SelectSolverReport {
    /// The candidates.
    pub candidates: Vec<SolverSpec>,
    /// Factorisation and sweep flops' weights in work.
    pub weights: WorkWeights,
    /// Runs per policy and case.
    pub repeats: usize,
    /// Logged Newton iterations.
    pub logged: usize,
    /// Training trajectories logged.
    pub training_trajectories: usize,
    /// Extra training scenes logged.
    pub also_train: usize,
    /// The tuning of the learned policy, when it ran.
    pub tuning: Option<PolicyTuning>,
    /// Every case.
    pub cases: Vec<CaseReport>,
}

/// Runs [`Task::SelectSolver`]; the logs are saved in `out/solver_data`.
///
/// # Errors
/// [`LearnError`].
pub fn run(
    cx: Context<'_>,
    observer: &mut dyn ExperimentObserver,
    files: &mut Vec<PathBuf>,
) -> Result<SelectSolverReport, LearnError> {
    let Task::SelectSolver {
        candidates,
        neighbours,
        min_success,
        factor_weight,
        sweep_weight,
        held_out,
        also_train,
        repeats,
        forcing,
        tune,
        refactor_above,
    } = &cx.experiment.task
    else {
        unreachable!("dispatched on the task")
    };
    let weights = &WorkWeights::factor(*factor_weight).sweep(*sweep_weight);
    let origin = cx.experiment.scene.as_path();
    let steps = cx.data.meta.trajectories.first().map_or(0, |t| t.steps);
    let variant = |k: usize| cx.data.scene_of(k, &cx.scene);
    let of_split = |split: Split| cx.data.indices(split);
    // Counterfactual logs from the training trajectories' initial conditions.
    let train = of_split(Split::Train).count();
    let also_steps: usize = also_train.iter().map(|r| r.steps).sum();
    observer.start(Stage::SolverData, (train * steps + also_steps) as u64);
    let also: Vec<Run<'_>> = also_train
        .iter()
        .map(|r| Ok((Scene::load(&r.scene)?, r.scene.as_path(), r.steps)))
        .collect::<Result<_, LearnError>>()?;
    let runs: Vec<Run<'_>> = of_split(Split::Train)
        .map(|k| Ok((variant(k)?, origin, steps)))
        .collect::<Result<Vec<_>, LearnError>>()?
        .into_iter()
        .chain(also)
        .collect();
    let logged = collect_runs(&runs, candidates, |_| observer.advance(1))?;
    observer.finish();
    if let Some(path) = cx.path("solver_data") {
        logged.save(&path)?;
        files.push("solver_data".into());
    }
    let young = cx
        .scene
        .material
        .build()?
        .lame()
        .map_or(1.0, |l| l.to_young().0);
    let learned = LearnedPolicy::train(
        &logged,
        PolicyOptions::new(young)
            .neighbours(*neighbours)
            .min_success(*min_success)
            .weights(*weights)
            .forcing(*forcing),
    );
    let mut contenders = baselines(candidates, *refactor_above);
    contenders.push(Contender::Learned);
    // The learned policy with its Newton options and forcing tuned on the first training
    // run (and the tuning's own scenes).
    let mut tuning = None;
    if let (Some(t), Some(k)) = (tune, of_split(Split::Train).next()) {
        let mut runs: Vec<Run<'_>> = vec![(variant(k)?, origin, steps)];
        for r in &t.scenes {
            runs.push((Scene::load(&r.scene)?, r.scene.as_path(), r.steps));
        }
        let tuned = tune_learned(&learned, &runs, t, *forcing, *weights, observer)?;
        contenders.push(Contender::LearnedTuned(tuned.settings));
        if let Some(direct) = candidates
            .iter()
            .find(|c| matches!(c, SolverSpec::Direct { .. }))
        {
            contenders.push(Contender::FixedTunedNewton(direct.clone(), tuned.settings));
        }
        tuning = Some(tuned);
    }
    let mut cases = vec![Case {
        label: format!("test trajectories of `{}`", cx.scene.name),
        runs: of_split(Split::Test)
            .map(|k| Ok((variant(k)?, origin)))
            .collect::<Result<_, LearnError>>()?,
        steps,
    }];
    for h in held_out {
        let s = Scene::load(&h.scene)?;
        cases.push(Case {
            label: format!("held-out `{}` ({} steps)", s.name, h.steps),
            runs: vec![(s, h.scene.as_path())],
            steps: h.steps,
        });
    }
    let repeats = (*repeats).max(1);
    observer.start(
        Stage::Policies,
        (cases.len() * (contenders.len() * repeats + 1)) as u64,
    );
    let reports = measure_cases(&cases, &contenders, &learned, (*weights, repeats), observer)?;
    observer.finish();
    Ok(SelectSolverReport {
        candidates: candidates.clone(),
        weights: *weights,
        repeats,
        logged: logged.len(),
        training_trajectories: train,
        also_train: also_train.len(),
        tuning,
        cases: reports,
    })
}

/// Every contender on every case (`repeats` timed runs each, side by side on small
/// problems; see [`measure_all`]), one progress tick per reference and per run.
fn measure_cases(
    cases: &[Case<'_>],
    contenders: &[Contender],
    learned: &LearnedPolicy,
    (weights, repeats): (WorkWeights, usize),
    observer: &mut dyn ExperimentObserver,
) -> Result<Vec<CaseReport>, LearnError> {
    let mut reports = Vec::new();
    let policies: Vec<_> = contenders
        .iter()
        .map(|c| move || c.policy(learned))
        .collect();
    let settings: Vec<_> = contenders
        .iter()
        .map(|c| {
            let settings = c.settings();
            move |o: &mut IntegratorOptions| {
                if let Some(s) = settings {
                    s.apply(o);
                }
            }
        })
        .collect();
    let contestants: Vec<Contestant<'_>> = (policies.iter().zip(&settings))
        .map(|(make, options)| Contestant { make, options })
        .collect();
    for case in cases {
        let references = case.references()?;
        observer.advance(1);
        let measured = measure_all(
            case,
            &references,
            &contestants,
            weights,
            repeats,
            &mut || observer.advance(1),
        )?;
        let rows = (contenders.iter().zip(measured))
            .map(|(c, measured)| PolicyRow {
                contender: c.clone(),
                measured,
            })
            .collect();
        reports.push(CaseReport {
            label: case.label.clone(),
            rows,
        });
    }
    Ok(reports)
}

/// The baselines: every fixed candidate, the Eisenstat-Walker rule on the first iterative
/// one, the hand schedule on the first stale-factor one.
fn baselines(candidates: &[SolverSpec], refactor_above: usize) -> Vec<Contender> {
    let mut contenders: Vec<Contender> = candidates.iter().cloned().map(Contender::Fixed).collect();
    if let Some(c) = candidates
        .iter()
        .find(|c| !matches!(c, SolverSpec::Direct { .. }) && !c.is_stale_cholesky())
    {
        contenders.push(Contender::EisenstatWalker(c.clone()));
    }
    if let Some(c) = candidates.iter().find(|c| c.is_stale_cholesky()) {
        contenders.push(Contender::HandSchedule(c.clone(), refactor_above));
    }
    contenders
}

/// Tunes the learned policy's Newton rel and largest forcing term (when it has forcing) for
/// each tangent projection tried; keeps the cheapest.
fn tune_learned(
    learned: &LearnedPolicy,
    runs: &[Run<'_>],
    t: &crate::PolicyTune,
    forcing: Option<(f64, f64)>,
    weights: WorkWeights,
    observer: &mut dyn ExperimentObserver,
) -> Result<PolicyTuning, LearnError> {
    let (mut start, mut range) = (vec![vec![-6.0], vec![-9.0]], vec![(-12.0, -3.0)]);
    if let Some((eta_max, _)) = forcing {
        let e = eta_max.log10();
        start = vec![vec![-6.0, e], vec![-9.0, e], vec![-6.0, e - 1.0]];
        range.push((-8.0, -0.3));
    }
    let tuning = Tuning {
        start,
        range,
        weights,
        fallback: true,
        accuracy: t.accuracy,
        max_iterations: t.max_iterations,
    };
    let projections: Vec<Option<Projection>> = std::iter::once(None)
        .chain(t.projections.iter().copied().map(Some))
        .collect();
    observer.start(
        Stage::Tune,
        projections.len() as u64 * tuning.max_evaluations() * runs.len() as u64,
    );
    let mut best: Option<PolicyTuning> = None;
    let mut samples = Vec::new();
    for projection in projections {
        let advance = std::cell::RefCell::new(&mut *observer);
        let make = |p: &[f64], o: &mut IntegratorOptions| {
            advance.borrow_mut().advance(1);
            let settings = TunedLearned::from_values(p, forcing, projection);
            settings.apply(o);
            Some(Box::new(learned.with_forcing(settings.forcing)) as Box<dyn SolverPolicy>)
        };
        let tuned = tune_policy(runs, &make, &tuning)?;
        samples.extend(tuned.samples.iter().map(|s| (projection, s.clone())));
        if best.as_ref().is_none_or(|b| tuned.best.cost < b.best.cost) {
            best = Some(PolicyTuning {
                settings: TunedLearned::from_values(&tuned.log10_values, forcing, projection),
                best: tuned.best.clone(),
                evaluations: tuned.samples.len(),
                accuracy: t.accuracy,
                scenes: t.scenes.iter().map(|r| r.scene.clone()).collect(),
                samples: Vec::new(),
            });
        }
    }
    observer.finish();
    let mut best = best.expect("the scenes' own projection is always tried");
    best.samples = samples;
    Ok(best)
}
