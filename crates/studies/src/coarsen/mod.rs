//! Coarse models that learn from fine ones: the base (fine) model's trajectories are carried
//! onto a coarse mesh of the same body ([`deform_learn::coarsen`]), at the base's step and at
//! multiples of it, and the coarse model is fitted to them by output error with the adjoint:
//! one homogeneous Lame pair, a pair per region, a pair per element (its regularisation
//! weight chosen on the validation trajectories), each with Rayleigh damping when asked. All
//! are compared on held-out motions of another kind, simulated by the fine model: the truth.

pub mod bench;
mod per_element;
mod regions;

use self::per_element::*;
use self::regions::*;
use crate::{Context, ExperimentObserver, Series, Stage, Task};
use deform_assembly::MaterialField;
use deform_integrator::benchmark::median;
use deform_integrator::{Integrator, IntegratorOptions, Scene};
use deform_learn::LearnError;
use deform_learn::basis::Basis;
use deform_learn::coarsen::{Constraints, Mapping, coarsen_embedded, save_model};
use deform_learn::dataset::{Dataset, Split, Trajectory, generate};
use deform_learn::output::{
    Field, OutputErrorOptions, Regularisation, Termination, face_neighbours, fit_output_error_field,
};
use deform_learn::rollout::{free_rollout_failure, mean_error, mean_rollout_errors};
use deform_materials::MaterialSpec;
use deform_mesh::TetMesh;
use deform_mesh::io::Vtu;
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Which model a row of the table is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum CoarseModel {
    /// The base model on its own mesh and step: the truth.
    Fine,
    /// The coarse mesh with the base's material and damping.
    Untuned,
    /// One Lame pair (and damping) for the whole coarse mesh.
    Homogeneous,
    /// A Lame pair per region.
    PerRegion,
    /// A smooth field: weights of a few basis functions over the rest shape.
    Smooth,
    /// A Lame pair per coarse element.
    PerElement,
}

impl CoarseModel {
    /// Its name in reports.
    pub fn name(self) -> &'static str {
        match self {
            CoarseModel::Fine => "fine (truth)",
            CoarseModel::Untuned => "untuned coarse",
            CoarseModel::Homogeneous => "homogeneous fit",
            CoarseModel::PerRegion => "per-region fit",
            CoarseModel::Smooth => "smooth-field fit",
            CoarseModel::PerElement => "per-element fit",
        }
    }
}

/// What a fit took.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct FitSummary {
    /// Coefficients fitted (term coefficients and damping).
    pub coefficients: usize,
    /// Loss at the start and at the end.
    pub losses: (f64, f64),
    /// Loss evaluations (each one forward and one adjoint pass over the training data).
    pub evaluations: usize,
    /// Wall time, seconds (for the per-element fit: of all regularisation weights, fitted
    /// concurrently).
    pub seconds: f64,
    /// How the optimiser stopped (for the per-element fit: the chosen weight's).
    pub termination: Termination,
    /// Why the fitted model was rejected, when it was: its free rollout of a training or
    /// validation trajectory failed (for the per-element fit: every weight's did), and the
    /// row holds the model the fit started from instead (the untuned model for the
    /// homogeneous fit, the homogeneous fit for the others).
    #[serde(default)]
    pub unstable: Option<String>,
}

/// One model measured on the held-out motions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct CoarseRow {
    /// Which.
    pub model: CoarseModel,
    /// Mean test RMS position error at each coarse state (m); zeros for the fine model.
    pub errors: Vec<f64>,
    /// Wall time per simulated second of the test motions (s / s), the median of three
    /// rounds that time the fine model and every coarse one back to back.
    pub cost: f64,
    /// Rayleigh alpha and gamma.
    pub damping: (f64, f64),
    /// Newton's relative tolerance (the scene's, or the one chosen on validation).
    pub newton_rel: f64,
    /// The fit, for fitted models.
    pub fit: Option<FitSummary>,
}

impl CoarseRow {
    /// Mean over the predicted states of the test RMS error (m).
    pub fn mean_error(&self) -> f64 {
        mean_error(&self.errors)
    }

    /// The test RMS error at the last state (m).
    pub fn final_error(&self) -> f64 {
        self.errors.last().copied().unwrap_or(0.0)
    }
}

/// The coarse mesh at one time step.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct CoarsenCase {
    /// The coarse step over the base's.
    pub dt_factor: usize,
    /// The coarse step (s).
    pub dt: f64,
    /// Fine, untuned, homogeneous, per-region and per-element, in that order.
    pub rows: Vec<CoarseRow>,
    /// Validation error (m) of the per-element field at each regularisation weight tried.
    pub regularisation: Vec<(f64, f64)>,
    /// The chosen weight.
    pub chosen: f64,
    /// The per-element model's scene and its field for ParaView (relative to the results
    /// folder), when files are written.
    pub files: Vec<PathBuf>,
    /// The per-element field, one series per term (`mu`, `lambda`), at each element's
    /// position along the rest shape's longest axis (0 to 1).
    pub field: Vec<Series>,
    /// Where the per-region model's regions meet along that axis (0 to 1): none when they
    /// are not slabs along it.
    #[serde(default)]
    pub region_bounds: Vec<f64>,
}

impl CoarsenCase {
    /// The row of `model`.
    pub fn row(&self, model: CoarseModel) -> Option<&CoarseRow> {
        self.rows.iter().find(|r| r.model == model)
    }

    /// `a`'s mean test error over `b`'s.
    pub fn error_ratio(&self, a: CoarseModel, b: CoarseModel) -> Option<f64> {
        Some(self.row(a)?.mean_error() / self.row(b)?.mean_error())
    }

    /// `a`'s cost over `b`'s.
    pub fn cost_ratio(&self, a: CoarseModel, b: CoarseModel) -> Option<f64> {
        Some(self.row(a)?.cost / self.row(b)?.cost)
    }
}

/// What the coarse models learnt.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct CoarsenReport {
    /// How the coarse mesh sits in the fine one.
    pub mapping: Mapping,
    /// Simulated time of the held-out motions (s, all of them).
    pub test_seconds: f64,
    /// The fitted models' material, when it is not the base's.
    pub material: Option<MaterialSpec>,
    /// One per coarse step.
    pub cases: Vec<CoarsenCase>,
}

impl CoarsenReport {
    /// The summary line of the last case.
    pub fn headline(&self) -> String {
        let Some(c) = self.cases.last() else {
            return String::new();
        };
        use CoarseModel::*;
        let r = |a, b| c.error_ratio(a, b).unwrap_or(f64::NAN);
        format!(
            "{:.0}x fewer tets, {}x the step: {:.3}x cheaper than fine, per-element error {:.3}x untuned, {:.3}x homogeneous",
            self.mapping.ratio,
            c.dt_factor,
            1.0 / c.cost_ratio(PerElement, Fine).unwrap_or(f64::NAN),
            r(PerElement, Untuned),
            r(PerElement, Homogeneous)
        )
    }
}

impl CoarsenReport {
    /// `models.csv` (every row of every case) and `rollout_error_Kx_dt.csv` (the error
    /// series of case `K`).
    pub fn csv_files(&self) -> Vec<(String, String)> {
        let mut files = Vec::new();
        let mut csv = String::from(
            "dt_factor,model,mean_error,final_error,cost,alpha,gamma,newton_rel,coefficients,loss_before,loss_after,evaluations,fit_seconds,termination\n",
        );
        for c in &self.cases {
            for row in &c.rows {
                let fit = row.fit.as_ref().map_or(",,,,,".to_owned(), |f| {
                    let (l0, l1) = f.losses;
                    format!(
                        "{},{l0:e},{l1:e},{},{},\"{}\"",
                        f.coefficients,
                        f.evaluations,
                        f.seconds,
                        f.termination.describe()
                    )
                });
                let (alpha, gamma) = row.damping;
                let _ = writeln!(
                    csv,
                    "{},\"{}\",{:e},{:e},{:e},{alpha:e},{gamma:e},{:e},{fit}",
                    c.dt_factor,
                    row.model.name(),
                    row.mean_error(),
                    row.final_error(),
                    row.cost,
                    row.newton_rel
                );
            }
            let series: Vec<Series> = c
                .rows
                .iter()
                .map(|row| Series::new(row.model.name(), row.errors.clone()))
                .collect();
            let name = format!("rollout_error_{}x_dt.csv", c.dt_factor);
            files.push((name, crate::series::series_csv("coarse_step", &series)));
        }
        files.push(("models.csv".to_owned(), csv));
        files
    }
}

/// How coarse models are fitted ([`fit_coarse_models`]; the fields of [`Task::Coarsen`]).
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct CoarseSettings {
    /// Slabs of the per-region fit along the rest shape's longest axis (without `tags`).
    pub regions: u32,
    /// Region tags of the coarse elements, when given (else `regions` slabs).
    pub tags: Option<Vec<u32>>,
    /// Regularisation weights of the per-element field tried; the least validation error
    /// is kept.
    pub regularisation: Vec<f64>,
    /// Fit Rayleigh alpha and gamma with every field.
    pub damping: bool,
    /// Fit per-vertex mass scales with the per-element field.
    pub mass_scale: bool,
    /// Also fit a smooth field of hat functions with these node counts.
    pub smooth: Option<[usize; 3]>,
    /// The fitted models' material (`None`: the data's scene's).
    pub material: Option<MaterialSpec>,
    /// Newton tolerances tried for the fitted models after their fit.
    pub newton_rel: Vec<f64>,
    /// Newton's iteration cap in the fits (`None`: the scene's).
    pub fit_newton_iterations: Option<usize>,
    /// The scene's Newton iteration cap: the fitted models run with it, and their
    /// validation errors are measured under it.
    pub scene_newton_iterations: usize,
    /// Options of every output-error fit.
    pub options: OutputErrorOptions,
}

deform_setters::setters!(CoarseSettings {
    regions: u32,
    tags: Option<Vec<u32>>,
    regularisation: Vec<f64>,
    damping: bool,
    mass_scale: bool,
    smooth: Option<[usize; 3]>,
    material: Option<MaterialSpec>,
    newton_rel: Vec<f64>,
    fit_newton_iterations: Option<usize>,
    scene_newton_iterations: usize,
    options: OutputErrorOptions,
});

impl CoarseSettings {
    /// The settings of a coarse model whose scene has Newton cap `newton_iterations`:
    /// 8 slabs, weights 0, 1e-3 and 1e-2, damping fitted, nothing else, `options`.
    pub fn new(newton_iterations: usize, options: OutputErrorOptions) -> Self {
        Self {
            regions: 8,
            tags: None,
            regularisation: vec![0.0, 1e-3, 1e-2],
            damping: true,
            mass_scale: false,
            smooth: None,
            material: None,
            newton_rel: Vec::new(),
            fit_newton_iterations: None,
            scene_newton_iterations: newton_iterations,
            options,
        }
    }

    /// A field over `labels` (none: one set for the whole mesh), with damping as asked and
    /// without mass scales.
    fn field(&self, labels: Vec<u32>, regularisation: Regularisation) -> Field {
        Field::default()
            .labels(labels)
            .regularisation(regularisation)
            .damping(self.damping)
    }
}

/// Runs [`Task::Coarsen`]: the held-out motions first (the fine model's rollouts of them
/// are its cost), then one case per coarse step.
///
/// # Errors
/// [`LearnError`] naming the scene, trajectory or step.
pub fn run(
    cx: Context<'_>,
    observer: &mut dyn ExperimentObserver,
    files: &mut Vec<PathBuf>,
) -> Result<CoarsenReport, LearnError> {
    let Task::Coarsen {
        mesh,
        test,
        embedding,
        region_tags,
        dt_factors,
        regions,
        regularisation,
        damping,
        mass_scale,
        smooth,
        material,
        newton_rel,
        fit_newton_iterations,
        output_error,
    } = &cx.experiment.task
    else {
        unreachable!("dispatched on the task")
    };
    let origin = cx.origin();
    // The held-out motions: simulated by the base model, or the data's own test split.
    let test_data = match test {
        Some(spec) => {
            observer.start(Stage::Dataset, (spec.trajectories * spec.steps) as u64);
            let made = generate(&cx.base, origin, spec, |_, _| observer.advance(1))?;
            observer.finish();
            made
        }
        None => cx.data.only(Split::Test),
    };
    let steps: usize = test_data.trajectories.iter().map(Trajectory::steps).sum();
    let test_seconds = steps as f64 * test_data.meta.dt;
    // The fine model's cost as every coarse model's: its rollouts of the held-out motions,
    // timed in the same rounds as the coarse models' (for imported data, deform's model of
    // the fine body, the experiment's scene).
    let built = cx.base.build(origin)?;
    let (fine_mesh, mut fine) = (built.mesh, built.integrator);
    let fine_tests: Vec<&Trajectory> = test_data.trajectories.iter().collect();
    let coarse = cx.base.clone().name("coarse".into()).mesh(mesh.clone());
    let coarse_mesh = coarse.build_mesh(origin)?;
    let embedding = match embedding {
        Some(files) => Some(deform_learn::coarsen::read_embedding(
            &files.elements,
            &files.weights,
            &fine_mesh,
            coarse_mesh.num_vertices(),
        )?),
        None => None,
    };
    let tags = match region_tags {
        Some(file) => Some(read_tags(file, coarse_mesh.num_tets())?),
        None => None,
    };
    let settings = CoarseSettings {
        regions: *regions,
        tags,
        regularisation: regularisation.clone(),
        damping: *damping,
        mass_scale: *mass_scale,
        smooth: *smooth,
        material: material.clone(),
        newton_rel: newton_rel.clone(),
        fit_newton_iterations: *fit_newton_iterations,
        scene_newton_iterations: cx.base.integrator.newton.max_iterations,
        options: *output_error,
    };
    let mut cases = Vec::new();
    let mut mapping = None;
    for &k in dt_factors {
        let mut scene = coarse.clone();
        scene.integrator.dt *= k as f64;
        let map = |d: &Dataset| -> Result<(Dataset, Mapping), LearnError> {
            let e = embedding.as_ref();
            let (d, mapping) = coarsen_embedded(d, &scene, origin, Constraints::FromFine, e)?;
            let mut d = d.subsample(k);
            d.meta.scene.integrator.dt = scene.integrator.dt;
            Ok((d, mapping))
        };
        let (data, m) = map(&cx.data)?;
        let (tests, _) = map(&test_data)?;
        mapping = Some(m);
        let fine = (&mut fine, fine_tests.as_slice());
        let cased = run_case((&data, &tests, k), fine, &settings, origin, observer)?;
        let (mut case, fits, fine_cost) = cased;
        case.rows.insert(0, fine_row(&case, fine_cost, &cx.base));
        if let Some(out) = cx.out {
            let scene = data
                .meta
                .scene
                .clone()
                .material(material.clone().unwrap_or(data.meta.scene.material.clone()));
            case.files = save_case(&scene, &case, &fits, out)?;
            files.extend(case.files.iter().cloned());
        }
        cases.push(case);
    }
    Ok(CoarsenReport {
        mapping: mapping.expect("validated: at least one dt factor"),
        test_seconds,
        material: material.clone(),
        cases,
    })
}

/// The truth's row: no error, the cost of simulating the held-out motions (measured with
/// the coarse models', [`time_in_rounds`]).
fn fine_row(case: &CoarsenCase, cost: f64, base: &Scene) -> CoarseRow {
    let untuned = case.row(CoarseModel::Untuned).expect("measured first");
    CoarseRow {
        model: CoarseModel::Fine,
        errors: vec![0.0; untuned.errors.len()],
        cost,
        damping: (base.integrator.alpha, base.integrator.gamma),
        newton_rel: base.integrator.newton.rel,
        fit: None,
    }
}

/// A fitted model in an integrator: its materials, options and mass scales.
type FittedModel = (MaterialField, IntegratorOptions, Option<Vec<f64>>);

/// Puts a fitted model into `sim`.
fn restore(
    sim: &mut Integrator,
    (materials, options, mass): &FittedModel,
) -> Result<(), LearnError> {
    set_materials(sim, materials.clone())?;
    sim.set_options(options.clone())?;
    Ok(sim.set_mass_scale(mass.as_deref())?)
}

/// The fitted model in `sim`.
fn fitted_model(sim: &Integrator) -> FittedModel {
    let mass = sim.mass_scale().map(<[f64]>::to_vec);
    (
        sim.assembly().materials().clone(),
        sim.options().clone(),
        mass,
    )
}

/// One coarse model as fitted ([`fit_coarse_models`]): which, what its fit took, and the
/// model as it runs (materials, options with the fitted damping and chosen Newton
/// tolerance, mass scales).
#[derive(Debug, Clone)]
pub struct CoarseModelFit {
    /// Which model.
    pub model: CoarseModel,
    /// Its fit (none for the untuned model).
    pub fit: Option<FitSummary>,
    /// Its materials.
    pub materials: MaterialField,
    /// Its integrator options.
    pub options: IntegratorOptions,
    /// Its per-vertex mass scales, when fitted.
    pub mass_scale: Option<Vec<f64>>,
}

impl CoarseModelFit {
    /// Puts the model into `sim` (an integrator of the coarse scene).
    ///
    /// # Errors
    /// [`LearnError`] when the model does not fit `sim`.
    pub fn apply(&self, sim: &mut Integrator) -> Result<(), LearnError> {
        restore(sim, &self.as_tuple())
    }

    fn as_tuple(&self) -> FittedModel {
        let (m, o, s) = (&self.materials, &self.options, &self.mass_scale);
        (m.clone(), o.clone(), s.clone())
    }
}

/// What [`fit_coarse_models`] fitted.
#[derive(Debug, Clone)]
pub struct CoarseFits {
    /// The untuned model, then the homogeneous, per-region, smooth (when asked) and
    /// per-element fits, in that order, each as it runs.
    pub models: Vec<CoarseModelFit>,
    /// The validation error (m) of the per-element field at each regularisation weight.
    pub regularisation: Vec<(f64, f64)>,
    /// The chosen weight.
    pub chosen: f64,
    /// The per-element field's term coefficients (element, then term).
    pub coefficients: Vec<f64>,
    /// The coarse mesh.
    pub mesh: TetMesh,
}

/// Fits the coarse models of the coarse-data `data` (its scene is the coarse model; see
/// [`deform_learn::coarsen::coarsen_embedded`]) on its training trajectories, choosing on its
/// validation ones: homogeneous, per region (`settings.tags` or slabs), smooth (when
/// asked) and per element (each regularisation weight, concurrently; the least validation
/// error kept). Every fitted model must run freely over every training and validation
/// trajectory, or it is rejected for the model its fit started from
/// ([`FitSummary::unstable`]); each then takes the loosest of `settings.newton_rel` within
/// 2 % of its validation error. The library function behind [`Task::Coarsen`], for callers
/// without the runner.
///
/// # Errors
/// [`LearnError`] naming the scene, trajectory or step.
pub fn fit_coarse_models(
    data: &Dataset,
    origin: &Path,
    settings: &CoarseSettings,
    observer: &mut dyn ExperimentObserver,
) -> Result<CoarseFits, LearnError> {
    let built = data.meta.scene.build(origin)?;
    let (mesh, mut sim) = (built.mesh, built.integrator);
    let (train, validation) = (data.split(Split::Train), data.split(Split::Validation));
    let mut models = vec![(CoarseModel::Untuned, None, fitted_model(&sim))];
    if let Some(cap) = settings.fit_newton_iterations {
        let mut o = sim.options().clone();
        o.newton.max_iterations = cap;
        sim.set_options(o)?;
    }
    if let Some(m) = &settings.material {
        let model = m.build()?;
        set_materials(&mut sim, MaterialField::Uniform(model))?;
    }
    if settings.damping && sim.options().alpha == 0.0 {
        // The optimiser moves logarithms: a zero alpha would stay zero.
        let mut o = sim.options().clone();
        o.alpha = 1e-3;
        sim.set_options(o)?;
    }
    let field = |labels, regularisation| settings.field(labels, regularisation);
    let whole = field(Vec::new(), Regularisation::default());
    let sets = (train.as_slice(), validation.as_slice());
    // Of the row fits only the fit itself fails on a trajectory, one of the training set.
    let blame = data.blame(&[Split::Train]);
    let start = fitted_model(&sim);
    let (summary, homogeneous, tuned) =
        fit_row(&mut sim, sets, &whole, &start, settings, observer).map_err(&blame)?;
    models.push((CoarseModel::Homogeneous, Some(summary), tuned));
    let labels = settings.labels(&mesh);
    let regions = field(labels, Regularisation::default());
    let (summary, _, tuned) =
        fit_row(&mut sim, sets, &regions, &homogeneous, settings, observer).map_err(&blame)?;
    models.push((CoarseModel::PerRegion, Some(summary), tuned));
    if let Some(nodes) = settings.smooth {
        restore(&mut sim, &homogeneous)?;
        let smooth =
            field(Vec::new(), Regularisation::default()).basis(Some(Basis::hat(&mesh, nodes)?));
        let (summary, _, tuned) =
            fit_row(&mut sim, sets, &smooth, &homogeneous, settings, observer).map_err(&blame)?;
        models.push((CoarseModel::Smooth, Some(summary), tuned));
    }
    // Per element: each weight from the homogeneous fit; the best on validation is kept.
    let labels: Vec<u32> = (0..mesh.num_tets() as u32).collect();
    let per_element = PerElement {
        train: &train,
        validation: &validation,
        homogeneous: &homogeneous,
        neighbours: face_neighbours(&mesh, &labels),
        labels: &labels,
        settings,
    };
    let started = Instant::now();
    let fits = per_element.fit_every_weight(&mut sim, data, origin, observer)?;
    let tried = fits.iter().map(|f| (f.weight, f.validation)).collect();
    let evaluations = fits.iter().map(|f| f.summary.evaluations).sum();
    // The first least validation error: the serial order's choice.
    let best = fits.into_iter().reduce(|best, f| {
        if f.validation < best.validation {
            f
        } else {
            best
        }
    });
    let best = best.map(|f| (f.validation, f.weight, f.coefficients, f.summary, f.model));
    let seconds = started.elapsed().as_secs_f64();
    let (validated, chosen, mut c, mut summary, mut model) =
        best.expect("validated: at least one weight");
    (summary.evaluations, summary.seconds) = (evaluations, seconds);
    if validated.is_infinite() {
        // No weight gave a model that runs: the homogeneous fit, as a field, instead.
        let why = summary.unstable.take().unwrap_or_default();
        summary.unstable = Some(format!("at every weight; the chosen one's: {why}"));
        if let MaterialField::Uniform(m) = &homogeneous.0 {
            c = m.term_coefficients().repeat(labels.len());
        }
        model = homogeneous.clone();
    }
    let tuned = settings.loosest_newton(&mut sim, &validation, &model)?;
    models.push((CoarseModel::PerElement, Some(summary), tuned));
    // The term coefficients, without the mass scales, alpha and gamma.
    c.truncate(labels.len() * homogeneous.0.max_terms());
    let models =
        models.into_iter().map(
            |(model, fit, (materials, options, mass_scale))| CoarseModelFit {
                model,
                fit,
                materials,
                options,
                mass_scale,
            },
        );
    Ok(CoarseFits {
        models: models.collect(),
        regularisation: tried,
        chosen,
        coefficients: c,
        mesh,
    })
}

/// The rows of the fitted coarse models of `data` measured on the held-out `tests`, the
/// per-element model, and the cost of `fine` on its held-out motions.
fn run_case(
    (data, tests, dt_factor): (&Dataset, &Dataset, usize),
    fine: (&mut Integrator, &[&Trajectory]),
    settings: &CoarseSettings,
    origin: &Path,
    observer: &mut dyn ExperimentObserver,
) -> Result<(CoarsenCase, CoarseFits, f64), LearnError> {
    let fits = fit_coarse_models(data, origin, settings, observer)?;
    let mut sim = data.meta.scene.build(origin)?.integrator;
    let test: Vec<&Trajectory> = tests.trajectories.iter().collect();
    let models = fits
        .models
        .iter()
        .map(|m| (m.model, m.fit.clone(), m.as_tuple()))
        .collect();
    let (fine_cost, rows) = time_in_rounds(fine, (&mut sim, &test), models)?;
    let case = CoarsenCase {
        dt_factor,
        dt: sim.options().dt,
        rows,
        regularisation: fits.regularisation.clone(),
        chosen: fits.chosen,
        files: Vec::new(),
        field: field_series(&fits.mesh, &fits.coefficients),
        region_bounds: region_bounds(&fits.mesh, &settings.labels(&fits.mesh)),
    };
    Ok((case, fits, fine_cost))
}

/// Fits `field` from the model in `sim`, rejects the fitted model for `fallback` when it
/// does not run freely over every training and validation trajectory
/// ([`free_rollout_failure`]), and chooses its Newton tolerance: the row's summary, the
/// model kept (left in `sim`) and that model as it runs.
fn fit_row(
    sim: &mut Integrator,
    (train, validation): (&[&Trajectory], &[&Trajectory]),
    field: &Field,
    fallback: &FittedModel,
    settings: &CoarseSettings,
    observer: &mut dyn ExperimentObserver,
) -> Result<(FitSummary, FittedModel, FittedModel), LearnError> {
    let (_, mut summary) = fit(sim, train, field, settings, observer)?;
    let fitted = fitted_model(sim);
    let sets = [train, validation];
    let kept = settings.keep_stable(sim, &sets, fitted, fallback, &mut summary)?;
    let tuned = settings.loosest_newton(sim, validation, &kept)?;
    Ok((summary, kept, tuned))
}

impl CoarseSettings {
    /// The per-region model's region of each element of `mesh`: the given tags, or slabs.
    fn labels(&self, mesh: &TetMesh) -> Vec<u32> {
        match &self.tags {
            Some(tags) => tags.clone(),
            None => slabs(mesh, self.regions),
        }
    }

    /// `fitted` when it runs freely (as it runs: [`CoarseSettings::running`]) over every
    /// trajectory of `sets`, else `fallback` with the failure in `summary.unstable`; the
    /// model kept is left in `sim`.
    fn keep_stable(
        &self,
        sim: &mut Integrator,
        sets: &[&[&Trajectory]],
        fitted: FittedModel,
        fallback: &FittedModel,
        summary: &mut FitSummary,
    ) -> Result<FittedModel, LearnError> {
        restore(sim, &self.running(&fitted))?;
        let kept = match free_rollout_failure(sim, sets) {
            None => fitted,
            Some(why) => {
                summary.unstable = Some(why);
                fallback.clone()
            }
        };
        restore(sim, &kept)?;
        Ok(kept)
    }
}

/// How much more mean validation error a looser Newton tolerance may cost than the
/// scene's: a coarse model's error is its discretisation's, which a few per cent hide.
const NEWTON_SLACK: f64 = 0.02;

impl CoarseSettings {
    /// `fitted` as it runs: with the scene's Newton iteration cap, whatever the fits' was.
    fn running(&self, fitted: &FittedModel) -> FittedModel {
        let mut model = fitted.clone();
        model.1.newton.max_iterations = self.scene_newton_iterations;
        model
    }

    /// `fitted` with the scene's Newton iteration cap and the loosest of
    /// [`CoarseSettings::newton_rel`] whose mean validation rollout error is within
    /// [`NEWTON_SLACK`] of the model's own tolerance's (a tolerance under which a step fails
    /// is passed over). `sim` is left with `fitted`, so later fits start from what they
    /// would without the choice.
    fn loosest_newton(
        &self,
        sim: &mut Integrator,
        validation: &[&Trajectory],
        fitted: &FittedModel,
    ) -> Result<FittedModel, LearnError> {
        let model = self.running(fitted);
        let own = model.1.newton.rel;
        let mut chosen = model.clone();
        if self.newton_rel.iter().all(|&r| r <= own) {
            return Ok(chosen);
        }
        restore(sim, &model)?;
        let bound = (1.0 + NEWTON_SLACK) * mean_error(&mean_rollout_errors(sim, validation)?);
        for &rel in self.newton_rel.iter().filter(|&&r| r > own) {
            let mut candidate = model.clone();
            candidate.1.newton.rel = rel;
            restore(sim, &candidate)?;
            let within =
                mean_rollout_errors(sim, validation).is_ok_and(|e| mean_error(&e) <= bound);
            if within && rel > chosen.1.newton.rel {
                chosen = candidate;
            }
        }
        restore(sim, fitted)?;
        Ok(chosen)
    }
}

/// Rounds of timing behind each cost figure, the median reported: one timing of a model
/// varies by up to 1.5x between runs on this 2-core VM, and the machine's speed drifts
/// over minutes, so each round times every model once, back to back.
const COST_REPEATS: usize = 3;

/// The fine model's cost (wall time per simulated second of its rollouts of its held-out
/// motions) and each coarse model's row: its mean errors on `test` and its cost. The models
/// are timed in [`COST_REPEATS`] rounds of the fine one, then each coarse one; each cost is
/// the median of its rounds. `sim` keeps the last model.
fn time_in_rounds(
    (fine, fine_test): (&mut Integrator, &[&Trajectory]),
    (sim, test): (&mut Integrator, &[&Trajectory]),
    models: Vec<(CoarseModel, Option<FitSummary>, FittedModel)>,
) -> Result<(f64, Vec<CoarseRow>), LearnError> {
    let timed = |sim: &mut Integrator, test: &[&Trajectory]| {
        let steps: usize = test.iter().map(|t| t.steps()).sum();
        let simulated = steps as f64 * sim.options().dt;
        let started = Instant::now();
        let errors = mean_rollout_errors(sim, test)?;
        Ok::<_, LearnError>((errors, started.elapsed().as_secs_f64() / simulated))
    };
    let mut fine_costs = Vec::with_capacity(COST_REPEATS);
    let mut costs = vec![Vec::with_capacity(COST_REPEATS); models.len()];
    let mut errors = Vec::with_capacity(models.len());
    for round in 0..COST_REPEATS {
        fine_costs.push(timed(fine, fine_test)?.1);
        for (k, (_, _, model)) in models.iter().enumerate() {
            restore(sim, model)?;
            let (e, cost) = timed(sim, test)?;
            costs[k].push(cost);
            if round == 0 {
                errors.push(e);
            }
        }
    }
    let rows = models.into_iter().zip(errors).zip(costs);
    let rows = rows.map(
        |(((model, fit, (_, options, _)), errors), costs)| CoarseRow {
            model,
            errors,
            cost: median(costs),
            damping: (options.alpha, options.gamma),
            newton_rel: options.newton.rel,
            fit,
        },
    );
    Ok((median(fine_costs), rows.collect()))
}

fn save_case(
    scene: &Scene,
    case: &CoarsenCase,
    fits: &CoarseFits,
    out: &Path,
) -> Result<Vec<PathBuf>, LearnError> {
    fits.save(scene, &format!("coarse_{}x_dt", case.dt_factor), out)
}

/// A model's mean free-rollout position error (m) on the validation and the test
/// (held-out) trajectories; `None` for an empty split, infinite where a rollout failed.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct SplitErrors {
    /// On the validation trajectories (which chose among the models).
    pub validation: Option<f64>,
    /// On the test trajectories (seen by no fit and no choice).
    pub test: Option<f64>,
}

impl CoarseFits {
    /// Each model's [`SplitErrors`] on `data`, in `models`' order. `data` and `origin` are
    /// those the models were fitted with: how a caller tells which model is good.
    ///
    /// # Errors
    /// [`LearnError`] when a model does not fit the scene; a rollout that fails makes that
    /// figure infinite rather than an error (the model is no good there).
    pub fn split_errors(
        &self,
        data: &Dataset,
        origin: &Path,
    ) -> Result<Vec<SplitErrors>, LearnError> {
        let mut sim = data.meta.scene.build(origin)?.integrator;
        let (validation, test) = (data.split(Split::Validation), data.split(Split::Test));
        let error = |sim: &mut Integrator, set: &[&Trajectory]| {
            (!set.is_empty())
                .then(|| mean_rollout_errors(sim, set).map_or(f64::INFINITY, |e| mean_error(&e)))
        };
        let mut out = Vec::with_capacity(self.models.len());
        for m in &self.models {
            m.apply(&mut sim)?;
            out.push(SplitErrors {
                validation: error(&mut sim, &validation),
                test: error(&mut sim, &test),
            });
        }
        Ok(out)
    }

    /// Saves the per-element model as the scene `NAME.ron` over `scene` (the coarse model's
    /// mesh, material family and constraints), with its field beside it, and the field as
    /// cell data for ParaView (`NAME_field.vtu`); returns the files, relative to `out`.
    ///
    /// # Errors
    /// [`LearnError`] naming the file that could not be written.
    pub fn save(&self, scene: &Scene, name: &str, out: &Path) -> Result<Vec<PathBuf>, LearnError> {
        let per_element = self.models.last().expect("the per-element model is last");
        let model = scene
            .clone()
            .name(name.to_owned())
            .integrator(per_element.options.clone());
        let written = save_model(
            &model,
            &self.coefficients,
            per_element.mass_scale.as_deref(),
            out,
        )?;
        self.write_field(name, out, written)
    }

    /// Writes the per-element field as `NAME_field.vtu` and lists it after `written`,
    /// every file relative to `out`.
    fn write_field(
        &self,
        name: &str,
        out: &Path,
        written: Vec<PathBuf>,
    ) -> Result<Vec<PathBuf>, LearnError> {
        let mesh = &self.mesh;
        let terms = self.coefficients.len() / mesh.num_tets().max(1);
        let column = |j: usize| -> Vec<f64> {
            let c = self.coefficients.iter().skip(j).step_by(terms.max(1));
            c.copied().collect()
        };
        let columns: Vec<(String, Vec<f64>)> = term_names(terms)
            .into_iter()
            .enumerate()
            .map(|(j, n)| (n, column(j)))
            .collect();
        let mut vtu = Vtu::new(mesh);
        for (n, values) in &columns {
            vtu = vtu.cell_scalars(n, values);
        }
        let vtu_name = format!("{name}_field.vtu");
        let path = out.join(&vtu_name);
        vtu.write(&path).map_err(|e| LearnError::Io {
            path: path.clone(),
            source: std::io::Error::other(e.to_string()),
        })?;
        let relative = |p: &PathBuf| p.strip_prefix(out).unwrap_or(p).to_path_buf();
        let mut files: Vec<PathBuf> = written.iter().map(relative).collect();
        files.push(vtu_name.into());
        Ok(files)
    }
}

#[cfg(test)]
mod tests;
