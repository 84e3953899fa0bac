//! The per-element coarse model: its regularisation weight chosen on validation, the fits of
//! several weights run concurrently, each in an integrator of its own.

use super::*;

/// The per-element fit at one regularisation weight.
pub(super) struct WeightFit {
    pub(super) weight: f64,
    /// Mean validation rollout error (m).
    pub(super) validation: f64,
    pub(super) coefficients: Vec<f64>,
    pub(super) summary: FitSummary,
    pub(super) model: FittedModel,
}

/// What every per-element fit shares.
pub(super) struct PerElement<'d> {
    pub(super) train: &'d [&'d Trajectory],
    pub(super) validation: &'d [&'d Trajectory],
    pub(super) homogeneous: &'d FittedModel,
    pub(super) neighbours: Vec<[usize; 2]>,
    pub(super) labels: &'d [u32],
    pub(super) settings: &'d CoarseSettings,
}

impl PerElement<'_> {
    /// The fit at weight `w` from the homogeneous model, left in `sim`.
    pub(super) fn fit(
        &self,
        sim: &mut Integrator,
        w: f64,
        observer: &mut dyn ExperimentObserver,
    ) -> Result<WeightFit, LearnError> {
        restore(sim, self.homogeneous)?;
        let regularisation = Regularisation::default()
            .towards(w)
            .smooth(w)
            .neighbours(self.neighbours.clone());
        let field = self
            .settings
            .field(self.labels.to_vec(), regularisation)
            .mass(self.settings.mass_scale);
        let (coefficients, mut summary) = fit(sim, self.train, &field, self.settings, observer)?;
        let model = fitted_model(sim);
        restore(sim, &self.settings.running(&model))?;
        // A model that does not run freely is not chosen.
        let validation = match free_rollout_failure(sim, &[self.train]) {
            Some(why) => Err(why),
            None => mean_rollout_errors(sim, self.validation)
                .map(|e| mean_error(&e))
                .map_err(|e| e.to_string()),
        };
        let validation = validation.unwrap_or_else(|why| {
            summary.unstable = Some(why);
            f64::INFINITY
        });
        restore(sim, &model)?;
        Ok(WeightFit {
            weight: w,
            validation,
            coefficients,
            summary,
            model,
        })
    }

    /// Every weight's fit, in the order of the weights. They are independent: the first
    /// runs in `sim` with the observer, each other one in a thread of its own with an
    /// integrator built from the data's scene, so the results do not depend on how many
    /// run at once. On one thread (`RAYON_NUM_THREADS=1`) they run one after another, each
    /// in an integrator of its own as well.
    pub(super) fn fit_every_weight(
        &self,
        sim: &mut Integrator,
        data: &Dataset,
        origin: &Path,
        observer: &mut dyn ExperimentObserver,
    ) -> Result<Vec<WeightFit>, LearnError> {
        let (&first, rest) = self
            .settings
            .regularisation
            .split_first()
            .expect("validated: at least one weight");
        let fit_alone = |w: f64| -> Result<WeightFit, LearnError> {
            let mut sim = data.meta.scene.build(origin)?.integrator;
            self.fit(&mut sim, w, &mut crate::NoProgress)
        };
        if rayon::current_num_threads() < 2 {
            let mut fits = vec![self.fit(sim, first, observer)?];
            for &w in rest {
                fits.push(fit_alone(w)?);
            }
            return Ok(fits);
        }
        std::thread::scope(|scope| {
            let others: Vec<_> = rest
                .iter()
                .map(|&w| scope.spawn(move || fit_alone(w)))
                .collect();
            let mut fits = vec![self.fit(sim, first, observer)?];
            for handle in others {
                let fit = handle
                    .join()
                    .unwrap_or_else(|p| std::panic::resume_unwind(p));
                fits.push(fit?);
            }
            Ok(fits)
        })
    }
}

pub(super) fn set_materials(
    sim: &mut Integrator,
    materials: MaterialField,
) -> Result<(), LearnError> {
    let result = sim.assembly_mut().set_materials(materials);
    Ok(result.map_err(deform_learn::fit::FitError::from)?)
}

/// Fits `field` on `train` from the model in `sim`, which keeps the result; the fitted
/// coefficients and what the fit took.
pub(super) fn fit(
    sim: &mut Integrator,
    train: &[&Trajectory],
    field: &Field,
    settings: &CoarseSettings,
    observer: &mut dyn ExperimentObserver,
) -> Result<(Vec<f64>, FitSummary), LearnError> {
    observer.start(Stage::Fit, settings.options.max_evaluations as u64);
    let started = Instant::now();
    let fit = fit_output_error_field(sim, train, field, settings.options, |k, loss| {
        observer.advance(1);
        observer.message(&format!("evaluation {k}, loss {loss:.3e}"));
    })?;
    observer.finish();
    let summary = FitSummary {
        coefficients: fit.coefficients.len(),
        losses: (fit.initial_loss, fit.loss),
        evaluations: fit.evaluations,
        seconds: started.elapsed().as_secs_f64(),
        termination: fit.termination,
        unstable: None,
    };
    Ok((fit.coefficients, summary))
}
