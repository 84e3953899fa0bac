//! Model selection (seed: "an ensemble ... learn the best configuration of the weights"):
//! a weighted sum of linear, corotated, fixed corotated, StVK, Neo-Hookean and stable
//! Neo-Hookean energies ([`Member`]),
//! fitted by the equation error with non-negative coefficients. Each member `m` contributes
//! the term pair `w_m (mu_m, lambda_m)`, so the fit finds every member's effective Lame pair
//! at once; a member the data do not support gets zero. Stage 2 ([`refine_ensemble`]) then
//! refines the kept members' pairs by the output error, as for a single model. The report gives each member's share
//! of the ensemble's elastic energy on given states.

use std::path::Path;

use deform_assembly::{Assembly, MaterialField};
use deform_integrator::Scene;
use deform_materials::{EnsembleMember, Lame, MaterialSpec, Model, Moduli};
use deform_mesh::TetMesh;
use serde::{Deserialize, Serialize};

use crate::dataset::Trajectory;
use crate::fit::{EquationErrorOptions, FitError, fit_equation_error};
use crate::output::{OutputErrorFit, OutputErrorOptions, fit_output_error, term_coefficients};

/// An ensemble member: one of deform's single energy models. In RON: `NeoHookean`, ...
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Member {
    /// Linear isotropic (small strain).
    LinearElastic,
    /// Corotated linear.
    CorotatedLinear,
    /// Fixed corotated (Stomakhin et al. 2012).
    FixedCorotated,
    /// St. Venant-Kirchhoff.
    StVenantKirchhoff,
    /// Neo-Hookean.
    NeoHookean,
    /// Stable Neo-Hookean (Smith et al. 2018).
    StableNeoHookean,
}

impl Member {
    /// Every member.
    pub const ALL: [Member; 6] = [
        Member::LinearElastic,
        Member::CorotatedLinear,
        Member::FixedCorotated,
        Member::StVenantKirchhoff,
        Member::NeoHookean,
        Member::StableNeoHookean,
    ];

    /// The member's material with the given moduli.
    pub fn spec(self, moduli: Moduli) -> MaterialSpec {
        match self {
            Member::LinearElastic => MaterialSpec::LinearElastic(moduli),
            Member::CorotatedLinear => MaterialSpec::CorotatedLinear {
                moduli,
                lagged_rotation: false,
            },
            Member::FixedCorotated => MaterialSpec::FixedCorotated(moduli),
            Member::StVenantKirchhoff => MaterialSpec::StVenantKirchhoff(moduli),
            Member::NeoHookean => MaterialSpec::NeoHookean(moduli),
            Member::StableNeoHookean => MaterialSpec::StableNeoHookean(moduli),
        }
    }
}

impl std::fmt::Display for Member {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        std::fmt::Debug::fmt(self, f)
    }
}

/// One fitted member.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct FittedMember {
    /// The model.
    pub model: Member,
    /// Effective `mu` (weight times the member's own).
    pub mu: f64,
    /// Effective `lambda`.
    pub lambda: f64,
    /// Share of the ensemble's elastic energy on the evaluation states (0 to 1).
    pub energy_share: f64,
}

impl FittedMember {
    /// Whether the member carries energy with a valid pair (and so appears in
    /// [`EnsembleFit::spec`]): a member with `mu = 0` and `lambda > 0` carries volume only,
    /// and is kept.
    pub fn kept(&self) -> bool {
        Lame::try_member(self.mu, self.lambda).is_ok()
    }
}

/// A candidate model left out of an ensemble because the data leave its domain.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct Excluded {
    /// The model.
    pub model: Member,
    /// Where first: trajectory (of the train, then the evaluation trajectories), step,
    /// element and its `det F` (e.g. an inverted element, which a log-barrier model's
    /// energy does not define).
    pub trajectory: usize,
    /// The step.
    pub step: usize,
    /// The element.
    pub element: usize,
    /// Its `det F`.
    pub det: f64,
}

/// The fitted ensemble.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct EnsembleFit {
    /// The members, in the order of `names` (without the excluded ones).
    pub members: Vec<FittedMember>,
    /// Relative equation-error residual.
    pub relative_residual: f64,
    /// Candidates whose energy the data leave undefined (they cannot have made the data).
    #[serde(default)]
    pub excluded: Vec<Excluded>,
}

impl EnsembleFit {
    /// The fitted ensemble as a material specification (members with zero coefficients
    /// left out).
    pub fn spec(&self) -> Option<MaterialSpec> {
        let members: Vec<EnsembleMember> = self
            .members
            .iter()
            .filter(|m| m.kept())
            .map(|m| {
                let lame = Moduli::Lame {
                    mu: m.mu,
                    lambda: m.lambda,
                };
                EnsembleMember::new(1.0, m.model.spec(lame))
            })
            .collect();
        (!members.is_empty()).then_some(MaterialSpec::Ensemble(members))
    }
}

/// The candidates among `names` whose domain the states of `trajectories` leave, each
/// with where it first happens (each element's `F` computed once for all candidates).
fn outside_domains(
    mesh: &TetMesh,
    names: &[Member],
    trajectories: &[&Trajectory],
) -> Result<Vec<Excluded>, FitError> {
    let models: Vec<Option<Model>> = names.iter().map(|&n| model_of(n, 1.0, 1.0)).collect();
    let mut found: Vec<Option<Excluded>> = vec![None; names.len()];
    for (trajectory, t) in trajectories.iter().enumerate() {
        for (step, x) in t.x.iter().enumerate() {
            if x.len() != 3 * mesh.num_vertices() {
                return Err(FitError::Data {
                    index: trajectory,
                    reason: format!(
                        "position state {step} has {} values, expected {} (3 per vertex of the scene's {} vertices)",
                        x.len(),
                        3 * mesh.num_vertices(),
                        mesh.num_vertices()
                    ),
                });
            }
            for element in 0..mesh.num_tets() {
                let f = mesh.deformation_gradient(element, x);
                for (m, model) in models.iter().enumerate() {
                    let Some(model) = model else { continue };
                    if found[m].is_none() && !deform_materials::Material::admissible(model, &f) {
                        found[m] = Some(Excluded {
                            model: names[m],
                            trajectory,
                            step,
                            element,
                            det: f.determinant(),
                        });
                    }
                }
            }
        }
    }
    Ok(found.into_iter().flatten().collect())
}

/// Fits an ensemble of the models `names` to `train` with the equation
/// error, using `scene`'s mesh, constraints and integrator options; reports energy shares on
/// the states of `evaluate`. A candidate whose energy the data leave undefined (a
/// log-barrier model on data with an inverted element) cannot have made them: it is left
/// out and listed in [`EnsembleFit::excluded`].
///
/// # Errors
/// [`FitError`], numbering the trajectories of `train` then those of `evaluate`;
/// [`FitError::Invalid`] when every candidate is excluded.
pub fn fit_ensemble(
    scene: &Scene,
    origin: &Path,
    names: &[Member],
    train: &[&Trajectory],
    evaluate: &[&Trajectory],
) -> Result<EnsembleFit, FitError> {
    let mesh = scene.build_mesh(origin)?;
    let all: Vec<&Trajectory> = train.iter().chain(evaluate).copied().collect();
    let excluded = outside_domains(&mesh, names, &all)?;
    let kept: Vec<Member> = names
        .iter()
        .copied()
        .filter(|n| !excluded.iter().any(|e| e.model == *n))
        .collect();
    if let (true, Some(first)) = (kept.is_empty(), excluded.first()) {
        return Err(FitError::Invalid(format!(
            "no candidate model can have made the data: each one's energy is undefined on them (first: {} at trajectory {}, step {}, element {}, det F = {:.3e})",
            first.model, first.trajectory, first.step, first.element, first.det
        )));
    }
    let names = &kept[..];
    // Any positive starting moduli: the equation error only uses the term split.
    let start = Moduli::Lame {
        mu: 1.0,
        lambda: 1.0,
    };
    let mut variant = scene.clone();
    variant.material = MaterialSpec::Ensemble(
        names
            .iter()
            .map(|n| EnsembleMember::new(1.0, n.spec(start)))
            .collect(),
    );
    let built = variant.build(origin)?;
    let fit = fit_equation_error(&built.integrator, train, EquationErrorOptions::default())?;
    let mut members: Vec<FittedMember> = names
        .iter()
        .enumerate()
        .map(|(m, n)| FittedMember {
            model: *n,
            mu: fit.coefficients[2 * m],
            lambda: fit.coefficients[2 * m + 1],
            energy_share: 0.0,
        })
        .collect();
    energy_shares(&built.mesh, &mut members, evaluate)
        .map_err(|e| after_training(e, train.len()))?;
    Ok(EnsembleFit {
        members,
        relative_residual: fit.relative_residual,
        excluded,
    })
}

/// Stage 2 for an ensemble: the output error refines every kept member's effective pair
/// (members stage 1 dropped stay dropped), starting from `fit`; the energy shares are
/// recomputed on `evaluate`. When stage 1 kept no member (noisy positions swamp the
/// accelerations its equations need), every member starts from an equal share of the
/// scene's own Lame pair, as a single model's stage 2 starts from the scene's guess.
/// `progress(evaluation, loss)` sees every loss evaluation.
///
/// # Errors
/// [`FitError`], numbering the trajectories of `train` then those of `evaluate`;
/// [`FitError::Invalid`] when `fit` kept no member and the scene's material has no single
/// Lame pair to start from.
pub fn refine_ensemble(
    fit: &EnsembleFit,
    scene: &Scene,
    origin: &Path,
    train: &[&Trajectory],
    evaluate: &[&Trajectory],
    options: OutputErrorOptions,
    progress: impl FnMut(usize, f64),
) -> Result<(EnsembleFit, OutputErrorFit), FitError> {
    let guessed;
    let fit = if fit.spec().is_some() {
        fit
    } else {
        guessed = from_scene_guess(fit, scene)?;
        &guessed
    };
    let spec = fit.spec().ok_or(FitError::NoData)?;
    let kept: Vec<usize> = (0..fit.members.len())
        .filter(|&m| fit.members[m].kept())
        .collect();
    let mut variant = scene.clone();
    variant.material = spec;
    let mut built = variant.build(origin)?;
    let MaterialField::Uniform(model) = built.integrator.assembly().materials() else {
        unreachable!("an ensemble specification builds one uniform model")
    };
    let start = term_coefficients(model);
    let stage2 = fit_output_error(&mut built.integrator, train, &start, options, progress)?;
    let mut refined = fit.clone();
    for (k, &m) in kept.iter().enumerate() {
        refined.members[m].mu = stage2.coefficients[2 * k];
        refined.members[m].lambda = stage2.coefficients[2 * k + 1];
    }
    energy_shares(&built.mesh, &mut refined.members, evaluate)
        .map_err(|e| after_training(e, train.len()))?;
    Ok((refined, stage2))
}

/// An error about trajectory `k` of `evaluate` as one about trajectory `train + k`: the
/// ensemble fits number the trajectories of `train` then those of `evaluate`.
fn after_training(e: FitError, train: usize) -> FitError {
    match e.trajectory() {
        Some(k) => e.renumbered(train + k),
        None => e,
    }
}

/// `fit` with every member at an equal share of `scene`'s Lame pair (see
/// [`refine_ensemble`]).
fn from_scene_guess(fit: &EnsembleFit, scene: &Scene) -> Result<EnsembleFit, FitError> {
    let lame = scene
        .material
        .build()
        .ok()
        .and_then(|m| m.lame())
        .ok_or_else(|| {
            FitError::Invalid(format!(
                "stage 1 kept no member (relative residual {:.3}: the data do not determine them; noisy positions?) and the scene's material {:?} has no single Lame pair to start stage 2 from",
                fit.relative_residual, scene.material
            ))
        })?;
    let share = 1.0 / fit.members.len().max(1) as f64;
    let mut guessed = fit.clone();
    for m in &mut guessed.members {
        (m.mu, m.lambda) = (share * lame.mu, share * lame.lambda);
    }
    Ok(guessed)
}

/// Each member's share of the ensemble's elastic energy summed over the states of
/// `evaluate`.
fn energy_shares(
    mesh: &TetMesh,
    members: &mut [FittedMember],
    evaluate: &[&Trajectory],
) -> Result<(), FitError> {
    let mut energy = vec![0.0; members.len()];
    for (m, member) in members.iter().enumerate() {
        let Some(model) = model_of(member.model, member.mu, member.lambda) else {
            continue;
        };
        let mut asm = Assembly::new(mesh, MaterialField::Uniform(model))?;
        for (ti, t) in evaluate.iter().enumerate() {
            for (step, x) in t.x.iter().enumerate() {
                energy[m] += asm.energy(x).map_err(|source| FitError::Assembly {
                    trajectory: ti,
                    step,
                    source,
                })?;
            }
        }
    }
    let total: f64 = energy.iter().sum();
    for (member, e) in members.iter_mut().zip(&energy) {
        member.energy_share = if total > 0.0 { e / total } else { 0.0 };
    }
    Ok(())
}

/// A member with its effective Lame pair (as an ensemble of one, so a volume-only pair is
/// valid), or `None` when the pair is not a member's ([`Lame::try_member`]).
fn model_of(member: Member, mu: f64, lambda: f64) -> Option<Model> {
    let spec = MaterialSpec::Ensemble(vec![EnsembleMember::new(
        1.0,
        member.spec(Moduli::Lame { mu, lambda }),
    )]);
    spec.build().ok()
}
