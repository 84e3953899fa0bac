//! Data for learning solver policies (issue: solver selection): at every Newton iteration of
//! a scene, features of the situation and the outcome of every candidate solver
//! configuration run on the same linear system (counterfactual logging through
//! `Integrator::set_candidates`).
//!
//! On disk, like trajectory datasets: `meta.ron` (feature names, candidate configurations,
//! the scene) and `.npy` arrays numpy loads directly: `features.npy` (samples x features),
//! `flops.npy`, `setup_flops.npy`, `sweep_flops.npy` (the solves' sequential sweeps; read
//! as zeros when absent, from datasets written before it), `reused.npy` (1 when a stale
//! factor was reused),
//! `seconds.npy`, `ok.npy` (1 when the candidate met its tolerance),
//! `relative_residual.npy`, `iterations.npy` and `age.npy` (solves since the candidate's
//! preconditioner was set up afresh), each samples x candidates.

use std::path::{Path, PathBuf};

use deform_fs::write_atomic;
use deform_integrator::{
    IterationReport, OnStep, PolicyContext, RunOptions, Scene, State, StepReport, Termination,
};
use deform_solvers::SolverSpec;
use serde::{Deserialize, Serialize};

use crate::dataset::DatasetError;
use deform_fs::npy;

/// The features of a Newton iteration, in column order.
pub const FEATURES: [&str; 9] = [
    "step",
    "iteration",
    "log10_residual",
    "log10_residual_over_initial",
    "log10_residual_decrease",
    "dt",
    "log10_free_dofs",
    "log10_youngs_modulus",
    "previous_linear_iterations",
];

/// One candidate's outcome on one system.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct Outcome {
    /// Deterministic work: set-up plus solve flops.
    pub flops: f64,
    /// The set-up's share of `flops` (factorisation or preconditioner).
    pub setup_flops: f64,
    /// The solve's flops in sequential sweeps (see `deform_solvers::SolveStats::sweep_flops`).
    #[serde(default)]
    pub sweep_flops: f64,
    /// The set-up reused an earlier factor (stale Cholesky) instead of computing one.
    pub reused: bool,
    /// Wall time, set-up plus solve.
    pub seconds: f64,
    /// Whether it met its tolerance.
    pub ok: bool,
    /// Relative residual reached (on failure the last one; infinite when the solve never
    /// started, e.g. a failed factorisation).
    pub relative_residual: f64,
    /// Iterations of the solve (1 for a direct solve, the cap on failure).
    pub iterations: f64,
    /// Solves since the candidate's preconditioner was last set up afresh (0 when it was
    /// set up for this one): the age of a stale factor.
    pub age: f64,
}

deform_setters::setters!(Outcome {
    flops: f64,
    setup_flops: f64,
    sweep_flops: f64,
    reused: bool,
    seconds: f64,
    ok: bool,
    relative_residual: f64,
    iterations: f64,
    age: f64
});

/// The metadata of a solver dataset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct SolverMeta {
    /// Feature names (columns of `features.npy`).
    pub features: Vec<String>,
    /// Candidate configurations (columns of the outcome arrays).
    pub candidates: Vec<SolverSpec>,
    /// The scene the systems came from.
    pub scene: Scene,
    /// Steps simulated.
    pub steps: usize,
}

impl SolverMeta {
    /// Logs of `candidates` on `steps` steps of `scene`, each system described by the
    /// `features` named.
    pub fn new(
        features: Vec<String>,
        candidates: Vec<SolverSpec>,
        scene: Scene,
        steps: usize,
    ) -> Self {
        Self {
            features,
            candidates,
            scene,
            steps,
        }
    }
}

/// Samples: one per Newton iteration.
#[derive(Debug, Clone, PartialEq)]
pub struct SolverDataset {
    /// Metadata.
    pub meta: SolverMeta,
    /// Features per sample.
    pub features: Vec<Vec<f64>>,
    /// Outcomes per sample, one per candidate.
    pub outcomes: Vec<Vec<Outcome>>,
}

/// The feature vector (in [`FEATURES`] order) of the Newton iteration a policy sees, for a
/// material of Young's modulus `young`.
pub fn feature_vector(c: &PolicyContext<'_>, young: f64) -> Vec<f64> {
    let tiny = f64::MIN_POSITIVE;
    let previous = c.history.last();
    let r = c.residual.max(tiny);
    let decrease = previous.map_or(1.0, |p| r / p.residual.max(tiny));
    vec![
        c.step as f64,
        c.iteration as f64,
        r.log10(),
        (r / c.initial_residual.max(tiny)).log10(),
        decrease.log10(),
        c.dt,
        (c.num_free.max(1) as f64).log10(),
        young.max(tiny).log10(),
        previous.map_or(0, |p| p.solve.iterations) as f64,
    ]
}

/// Features of iteration `k` of a step, from the step's iterations so far.
fn features(
    step: usize,
    history: &[IterationReport],
    k: usize,
    dt: f64,
    num_free: usize,
    young: f64,
) -> Vec<f64> {
    let context = PolicyContext {
        step,
        iteration: k,
        dt,
        num_free,
        residual: history[k].residual,
        initial_residual: history[0].residual,
        history: &history[..k],
    };
    feature_vector(&context, young)
}

/// Simulates `steps` steps of `scene` with every candidate logged at every Newton iteration.
///
/// # Errors
/// [`DatasetError`] when the scene does not build or a step fails.
pub fn collect(
    scene: &Scene,
    origin: &Path,
    candidates: &[SolverSpec],
    steps: usize,
    mut progress: impl FnMut(usize),
) -> Result<SolverDataset, DatasetError> {
    let built = scene.build(origin)?;
    let (mut sim, mut state) = (built.integrator, built.state);
    sim.set_candidates(candidates)
        .map_err(|e| DatasetError::Inconsistent(format!("candidates: {e}")))?;
    let young = scene
        .material
        .build()
        .ok()
        .and_then(|m| m.lame())
        .map_or(f64::NAN, |l| l.to_young().0);
    let (dt, free) = (sim.options().dt, sim.dofs().num_free());
    let mut data = SolverDataset {
        meta: SolverMeta {
            features: FEATURES.iter().map(|s| (*s).to_owned()).collect(),
            candidates: candidates.to_vec(),
            scene: scene.clone(),
            steps,
        },
        features: Vec::new(),
        outcomes: Vec::new(),
    };
    let mut ages = vec![0usize; candidates.len()];
    let mut record = |report: &StepReport| {
        let step = report.step;
        for k in 0..report.iterations.len() {
            data.features
                .push(features(step, &report.iterations, k, dt, free, young));
            data.outcomes.push(
                report.iterations[k]
                    .candidates
                    .iter()
                    .zip(&mut ages)
                    .map(|(c, age)| {
                        let reused = c.setup.is_some_and(|s| s.reused);
                        *age = if reused { *age + 1 } else { 0 };
                        (c, reused, *age)
                    })
                    .map(|(c, reused, age)| Outcome {
                        flops: (c.setup.map_or(0, |s| s.flops)
                            + c.solve.as_ref().map_or(0, |s| s.flops))
                            as f64,
                        setup_flops: c.setup.map_or(0, |s| s.flops) as f64,
                        sweep_flops: c.solve.as_ref().map_or(0, |s| s.sweep_flops) as f64,
                        reused,
                        seconds: c.setup.map_or(0.0, |s| s.seconds)
                            + c.solve.as_ref().map_or(0.0, |s| s.seconds),
                        ok: c.error.is_none(),
                        relative_residual: c
                            .solve
                            .as_ref()
                            .map_or(f64::INFINITY, |s| s.relative_residual()),
                        iterations: c.solve.as_ref().map_or(0, |s| s.iterations) as f64,
                        age: age as f64,
                    })
                    .collect(),
            );
        }
        progress(step);
    };
    let summary = sim.run(
        &mut state,
        &RunOptions::steps(steps),
        &mut OnStep(|report: &StepReport, _: &State| record(report)),
    );
    if let Termination::Failed { step, error } = summary.termination {
        return Err(DatasetError::Step {
            trajectory: 0,
            step,
            source: error,
        });
    }
    Ok(data)
}

/// One simulation to log: the scene, the folder its paths are relative to, and its steps.
pub type Run<'a> = (Scene, &'a Path, usize);

/// Logs several simulations into one dataset (its metadata names the first scene);
/// `progress` sees each finished step. Below `lanes::SIDE_BY_SIDE_MAX_DOFS` (20,000) free
/// DOFs the simulations run side by side (`lanes::side_by_side`); the logged
/// flops and iterations are the same bits either way, the logged seconds one core's.
///
/// # Errors
/// [`DatasetError`] as [`collect`]; `Inconsistent` when `runs` is empty.
pub fn collect_runs(
    runs: &[Run<'_>],
    candidates: &[SolverSpec],
    mut progress: impl FnMut(usize),
) -> Result<SolverDataset, DatasetError> {
    let log = |_: &mut (), k: usize, step: &mut dyn FnMut(usize)| {
        let (scene, origin, steps) = &runs[k];
        collect(scene, origin, candidates, *steps, step)
    };
    let mut free = 0;
    for (scene, origin, _) in runs {
        free = free.max(scene.build(origin)?.integrator.dofs().num_free());
    }
    let logs = if crate::lanes::worth_it(runs.len(), free) {
        let mut lanes = vec![(); rayon::current_num_threads().min(runs.len())];
        crate::lanes::side_by_side(&mut lanes, runs.len(), &log, &mut |_, s| progress(s))?
    } else {
        (0..runs.len())
            .map(|k| log(&mut (), k, &mut progress))
            .collect::<Result<Vec<_>, _>>()?
    };
    let mut logs = logs.into_iter();
    let mut all = logs
        .next()
        .ok_or_else(|| DatasetError::Inconsistent("no simulation to log".into()))?;
    for d in logs {
        all.features.extend(d.features);
        all.outcomes.extend(d.outcomes);
    }
    Ok(all)
}

impl SolverDataset {
    /// Number of samples.
    pub fn len(&self) -> usize {
        self.features.len()
    }

    /// Whether there are no samples.
    pub fn is_empty(&self) -> bool {
        self.features.is_empty()
    }

    /// Writes `meta.ron` and the arrays (atomically) into `dir`.
    ///
    /// # Errors
    /// [`DatasetError`] naming the file.
    pub fn save(&self, dir: &Path) -> Result<(), DatasetError> {
        std::fs::create_dir_all(dir).map_err(|e| DatasetError::Meta {
            path: dir.to_owned(),
            reason: e.to_string(),
        })?;
        let (n, f, c) = (
            self.len(),
            self.meta.features.len(),
            self.meta.candidates.len(),
        );
        npy::write(&dir.join("features.npy"), &[n, f], &self.features.concat())?;
        let column = |g: &dyn Fn(&Outcome) -> f64| -> Vec<f64> {
            self.outcomes.iter().flatten().map(g).collect()
        };
        npy::write(&dir.join("flops.npy"), &[n, c], &column(&|o| o.flops))?;
        npy::write(&dir.join("seconds.npy"), &[n, c], &column(&|o| o.seconds))?;
        npy::write(
            &dir.join("setup_flops.npy"),
            &[n, c],
            &column(&|o| o.setup_flops),
        )?;
        npy::write(
            &dir.join("sweep_flops.npy"),
            &[n, c],
            &column(&|o| o.sweep_flops),
        )?;
        npy::write(
            &dir.join("reused.npy"),
            &[n, c],
            &column(&|o| f64::from(u8::from(o.reused))),
        )?;
        npy::write(
            &dir.join("ok.npy"),
            &[n, c],
            &column(&|o| f64::from(u8::from(o.ok))),
        )?;
        // Infinite residuals (failures) are stored as NaN-free large numbers for numpy users.
        npy::write(
            &dir.join("relative_residual.npy"),
            &[n, c],
            &column(&|o| o.relative_residual.min(f64::MAX)),
        )?;
        npy::write(
            &dir.join("iterations.npy"),
            &[n, c],
            &column(&|o| o.iterations),
        )?;
        npy::write(&dir.join("age.npy"), &[n, c], &column(&|o| o.age))?;
        let path: PathBuf = dir.join("meta.ron");
        let text = ron::ser::to_string_pretty(&self.meta, ron::ser::PrettyConfig::default())
            .map_err(|e| DatasetError::Meta {
                path: path.clone(),
                reason: e.to_string(),
            })?;
        write_atomic(&path, |w| w.write_all(text.as_bytes())).map_err(|e| DatasetError::Meta {
            path: path.clone(),
            reason: e.to_string(),
        })
    }

    /// Reads a folder written by [`SolverDataset::save`].
    ///
    /// # Errors
    /// [`DatasetError`] naming the file and what does not match.
    pub fn load(dir: &Path) -> Result<Self, DatasetError> {
        let path = dir.join("meta.ron");
        let text = std::fs::read_to_string(&path).map_err(|e| DatasetError::Meta {
            path: path.clone(),
            reason: e.to_string(),
        })?;
        let meta: SolverMeta = ron::from_str(&text).map_err(|e| DatasetError::Meta {
            path: path.clone(),
            reason: e.to_string(),
        })?;
        let (f, c) = (meta.features.len(), meta.candidates.len());
        let read = |name: &str, cols: usize| -> Result<Vec<Vec<f64>>, DatasetError> {
            let p = dir.join(name);
            let a = npy::read(&p)?;
            if a.shape.len() != 2 || a.shape[1] != cols {
                return Err(DatasetError::Inconsistent(format!(
                    "{}: shape {:?}, meta.ron says (samples, {cols})",
                    p.display(),
                    a.shape
                )));
            }
            Ok(a.data.chunks(cols.max(1)).map(<[f64]>::to_vec).collect())
        };
        let features = read("features.npy", f)?;
        let (flops, seconds, ok, res) = (
            read("flops.npy", c)?,
            read("seconds.npy", c)?,
            read("ok.npy", c)?,
            read("relative_residual.npy", c)?,
        );
        let (setup, reused) = (read("setup_flops.npy", c)?, read("reused.npy", c)?);
        let sweep = if dir.join("sweep_flops.npy").exists() {
            read("sweep_flops.npy", c)?
        } else {
            vec![vec![0.0; c]; features.len()]
        };
        let (iterations, age) = (read("iterations.npy", c)?, read("age.npy", c)?);
        if [
            flops.len(),
            seconds.len(),
            ok.len(),
            res.len(),
            setup.len(),
            sweep.len(),
            reused.len(),
            iterations.len(),
            age.len(),
        ]
        .iter()
        .any(|&l| l != features.len())
        {
            return Err(DatasetError::Inconsistent(format!(
                "{}: arrays disagree on the number of samples",
                dir.display()
            )));
        }
        let outcomes = (0..features.len())
            .map(|i| {
                (0..c)
                    .map(|j| Outcome {
                        flops: flops[i][j],
                        setup_flops: setup[i][j],
                        sweep_flops: sweep[i][j],
                        reused: reused[i][j] != 0.0,
                        seconds: seconds[i][j],
                        ok: ok[i][j] != 0.0,
                        relative_residual: if res[i][j] >= f64::MAX {
                            f64::INFINITY
                        } else {
                            res[i][j]
                        },
                        iterations: iterations[i][j],
                        age: age[i][j],
                    })
                    .collect()
            })
            .collect();
        Ok(Self {
            meta,
            features,
            outcomes,
        })
    }
}
