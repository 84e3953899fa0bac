//! `Model`: every energy model behind one enum (static dispatch, no boxing), the weighted
//! `Ensemble`, and the `Parametric` trait.

use nalgebra::{Matrix3, Vector3};

use crate::MaterialError;
use crate::isotropic::{self, Isotropic, SignedSvd};
use crate::lame::{Lame, invalid};
use crate::material::{Material, Matrix9, project_psd};
use crate::models::{
    CorotatedLinear, FixedCorotated, LinearElastic, NeoHookean, StVenantKirchhoff, StableNeoHookean,
};

/// Any of deform's energy models.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum Model {
    /// Linear isotropic elasticity.
    Linear(LinearElastic),
    /// Corotated linear elasticity.
    Corotated(CorotatedLinear),
    /// Fixed corotated.
    FixedCorotated(FixedCorotated),
    /// St. Venant-Kirchhoff.
    StVenantKirchhoff(StVenantKirchhoff),
    /// Neo-Hookean.
    NeoHookean(NeoHookean),
    /// Stable Neo-Hookean.
    StableNeoHookean(StableNeoHookean),
    /// A weighted sum of the above.
    Ensemble(Ensemble),
}

macro_rules! dispatch {
    ($self:expr, $m:ident => $e:expr) => {
        match $self {
            Model::Linear($m) => $e,
            Model::Corotated($m) => $e,
            Model::FixedCorotated($m) => $e,
            Model::StVenantKirchhoff($m) => $e,
            Model::NeoHookean($m) => $e,
            Model::StableNeoHookean($m) => $e,
            Model::Ensemble($m) => $e,
        }
    };
}

impl Model {
    /// The term coefficients, in the order of the assembly's parameter Jacobians:
    /// `[mu, lambda]` for a single model, each member's effective `w (mu, lambda)` for an
    /// ensemble (the energy is linear in them).
    pub fn term_coefficients(&self) -> Vec<f64> {
        match self {
            Model::Ensemble(e) => e
                .members
                .iter()
                .flat_map(|(w, m)| m.params().into_iter().map(move |p| w * p))
                .collect(),
            m => m.params(),
        }
    }

    /// The model with term coefficients `c` (an ensemble's weights become 1).
    ///
    /// # Errors
    /// [`MaterialError`] when `c` has the wrong length or holds an invalid pair.
    pub fn with_term_coefficients(&self, c: &[f64]) -> Result<Model, MaterialError> {
        let mut model = self.clone();
        match &mut model {
            Model::Ensemble(e) => {
                let mut p = vec![1.0; e.members.len()];
                p.extend_from_slice(c);
                model.set_params(&p)?;
            }
            m => m.set_params(c)?,
        }
        Ok(model)
    }

    /// The model as an isotropic energy of singular values, where it is one (every model
    /// but linear elasticity and the lagged-rotation corotated tangent).
    pub(crate) fn as_isotropic(&self) -> Option<&dyn Isotropic> {
        match self {
            Model::Linear(_) => None,
            Model::Corotated(m) if m.lagged_rotation => None,
            Model::Corotated(m) => Some(m),
            Model::FixedCorotated(m) => Some(m),
            Model::StVenantKirchhoff(m) => Some(m),
            Model::NeoHookean(m) => Some(m),
            Model::StableNeoHookean(m) => Some(m),
            Model::Ensemble(e) => e.isotropic.then_some(e as &dyn Isotropic),
        }
    }

    /// The Lame pair of a single model; `None` for an ensemble.
    pub fn lame(&self) -> Option<Lame> {
        match self {
            Model::Linear(m) => Some(m.lame),
            Model::Corotated(m) => Some(m.lame),
            Model::FixedCorotated(m) => Some(m.lame),
            Model::StVenantKirchhoff(m) => Some(m.lame),
            Model::NeoHookean(m) => Some(m.lame),
            Model::StableNeoHookean(m) => Some(m.lame),
            Model::Ensemble(_) => None,
        }
    }

    fn lame_mut(&mut self) -> Option<&mut Lame> {
        match self {
            Model::Linear(m) => Some(&mut m.lame),
            Model::Corotated(m) => Some(&mut m.lame),
            Model::FixedCorotated(m) => Some(&mut m.lame),
            Model::StVenantKirchhoff(m) => Some(&mut m.lame),
            Model::NeoHookean(m) => Some(&mut m.lame),
            Model::StableNeoHookean(m) => Some(&mut m.lame),
            Model::Ensemble(_) => None,
        }
    }
}

impl Material for Model {
    #[inline]
    fn name(&self) -> &'static str {
        dispatch!(self, m => m.name())
    }
    #[inline]
    fn psi(&self, f: &Matrix3<f64>) -> f64 {
        dispatch!(self, m => m.psi(f))
    }
    #[inline]
    fn first_piola(&self, f: &Matrix3<f64>) -> Matrix3<f64> {
        dispatch!(self, m => m.first_piola(f))
    }
    #[inline]
    fn dp_df(&self, f: &Matrix3<f64>) -> Matrix9 {
        dispatch!(self, m => m.dp_df(f))
    }
    #[inline]
    fn dp(&self, f: &Matrix3<f64>, df: &Matrix3<f64>) -> Matrix3<f64> {
        dispatch!(self, m => m.dp(f, df))
    }
    fn dp_df_projected(&self, f: &Matrix3<f64>) -> Matrix9 {
        dispatch!(self, m => m.dp_df_projected(f))
    }
    #[inline]
    fn first_piola_and_tangent(&self, f: &Matrix3<f64>, project: bool) -> (Matrix3<f64>, Matrix9) {
        dispatch!(self, m => m.first_piola_and_tangent(f, project))
    }
    #[inline]
    fn admissible(&self, f: &Matrix3<f64>) -> bool {
        dispatch!(self, m => m.admissible(f))
    }
    fn num_terms(&self) -> usize {
        dispatch!(self, m => m.num_terms())
    }
    fn coefficients(&self, out: &mut [f64]) {
        dispatch!(self, m => m.coefficients(out))
    }
    fn term_psi(&self, k: usize, f: &Matrix3<f64>) -> f64 {
        dispatch!(self, m => m.term_psi(k, f))
    }
    fn term_first_piola(&self, k: usize, f: &Matrix3<f64>) -> Matrix3<f64> {
        dispatch!(self, m => m.term_first_piola(k, f))
    }
    fn term_dp_df(&self, k: usize, f: &Matrix3<f64>) -> Matrix9 {
        dispatch!(self, m => m.term_dp_df(k, f))
    }
}

/// A weighted sum `Psi = sum_m w_m Psi_m` of single models (no nested ensembles), each
/// with its own Lame pair. Weights are non-negative; members with weight 0 are skipped,
/// so an inadmissible state of an unused member does not matter.
#[derive(Debug, Clone, PartialEq)]
pub struct Ensemble {
    members: Vec<(f64, Model)>,
    isotropic: bool,
}

impl Ensemble {
    /// Builds an ensemble from `(weight, model)` pairs.
    ///
    /// # Errors
    /// [`MaterialError::InvalidEnsemble`] when empty or nested;
    /// [`MaterialError::InvalidParameter`] naming `weights[m]` for a negative or non-finite weight.
    pub fn try_new(members: Vec<(f64, Model)>) -> Result<Self, MaterialError> {
        if members.is_empty() {
            return Err(MaterialError::InvalidEnsemble(
                "an ensemble needs at least one member",
            ));
        }
        for (m, (w, model)) in members.iter().enumerate() {
            if !(w.is_finite() && *w >= 0.0) {
                return Err(invalid(
                    &format!("weights[{m}]"),
                    *w,
                    "must be finite and >= 0",
                ));
            }
            if matches!(model, Model::Ensemble(_)) {
                return Err(MaterialError::InvalidEnsemble("ensembles cannot be nested"));
            }
        }
        let isotropic = members.iter().all(|(_, m)| m.as_isotropic().is_some());
        Ok(Self { members, isotropic })
    }

    /// The `(weight, model)` pairs.
    pub fn members(&self) -> &[(f64, Model)] {
        &self.members
    }

    /// Replaces the weights (validated as in [`Ensemble::try_new`]).
    ///
    /// # Errors
    /// As [`Ensemble::try_new`], or [`MaterialError::ParameterCount`].
    pub fn set_weights(&mut self, weights: &[f64]) -> Result<(), MaterialError> {
        if weights.len() != self.members.len() {
            return Err(MaterialError::ParameterCount {
                expected: self.members.len(),
                found: weights.len(),
            });
        }
        for (m, w) in weights.iter().enumerate() {
            if !(w.is_finite() && *w >= 0.0) {
                return Err(invalid(
                    &format!("weights[{m}]"),
                    *w,
                    "must be finite and >= 0",
                ));
            }
        }
        for ((w, _), new) in self.members.iter_mut().zip(weights) {
            *w = *new;
        }
        Ok(())
    }

    fn active(&self) -> impl Iterator<Item = (f64, &Model)> {
        self.members
            .iter()
            .filter(|(w, _)| *w != 0.0)
            .map(|(w, m)| (*w, m))
    }

    /// Member and term of split term `k` (two terms per member).
    fn term(&self, k: usize) -> (f64, &Model, usize) {
        let (w, m) = &self.members[k / 2];
        (*w, m, k % 2)
    }
}

impl Isotropic for Ensemble {
    fn psi_s(&self, s: &Vector3<f64>) -> f64 {
        self.active()
            .map(|(w, m)| w * m.as_isotropic().map_or(0.0, |i| i.psi_s(s)))
            .sum()
    }
    fn grad_s(&self, s: &Vector3<f64>) -> Vector3<f64> {
        self.active()
            .map(|(w, m)| m.as_isotropic().map_or(Vector3::zeros(), |i| i.grad_s(s)) * w)
            .sum()
    }
    fn hess_s(&self, s: &Vector3<f64>) -> Matrix3<f64> {
        self.active()
            .map(|(w, m)| m.as_isotropic().map_or(Matrix3::zeros(), |i| i.hess_s(s)) * w)
            .sum()
    }
    fn pair(&self, s: &Vector3<f64>, i: usize, j: usize, k: usize) -> (f64, f64) {
        self.active().fold((0.0, 0.0), |(a, b), (w, m)| {
            let (x, y) = m
                .as_isotropic()
                .map_or((0.0, 0.0), |iso| iso.pair(s, i, j, k));
            (a + w * x, b + w * y)
        })
    }
}

impl Material for Ensemble {
    fn name(&self) -> &'static str {
        "ensemble"
    }
    fn psi(&self, f: &Matrix3<f64>) -> f64 {
        self.active().map(|(w, m)| w * m.psi(f)).sum()
    }
    fn first_piola(&self, f: &Matrix3<f64>) -> Matrix3<f64> {
        self.active().map(|(w, m)| m.first_piola(f) * w).sum()
    }
    fn dp(&self, f: &Matrix3<f64>, df: &Matrix3<f64>) -> Matrix3<f64> {
        self.active().map(|(w, m)| m.dp(f, df) * w).sum()
    }
    fn dp_df(&self, f: &Matrix3<f64>) -> Matrix9 {
        self.active().map(|(w, m)| m.dp_df(f) * w).sum()
    }
    /// The projection of the sum (not the sum of projections): analytic when every member
    /// is isotropic, numeric otherwise.
    fn dp_df_projected(&self, f: &Matrix3<f64>) -> Matrix9 {
        if self.isotropic {
            isotropic::tangent(self, &SignedSvd::new(f), true)
        } else {
            project_psd(&self.dp_df(f))
        }
    }
    fn admissible(&self, f: &Matrix3<f64>) -> bool {
        self.active().all(|(_, m)| m.admissible(f))
    }
    fn num_terms(&self) -> usize {
        2 * self.members.len()
    }
    fn coefficients(&self, out: &mut [f64]) {
        for (k, (w, m)) in self.members.iter().enumerate() {
            m.coefficients(&mut out[2 * k..2 * k + 2]);
            out[2 * k] *= w;
            out[2 * k + 1] *= w;
        }
    }
    fn term_psi(&self, k: usize, f: &Matrix3<f64>) -> f64 {
        let (_, m, t) = self.term(k);
        m.term_psi(t, f)
    }
    fn term_first_piola(&self, k: usize, f: &Matrix3<f64>) -> Matrix3<f64> {
        let (_, m, t) = self.term(k);
        m.term_first_piola(t, f)
    }
    fn term_dp_df(&self, k: usize, f: &Matrix3<f64>) -> Matrix9 {
        let (_, m, t) = self.term(k);
        m.term_dp_df(t, f)
    }
}

/// A model with a named, validated parameter vector (what deform-learn fits).
pub trait Parametric {
    /// The current parameters.
    fn params(&self) -> Vec<f64>;
    /// Their names, as in the configuration (`mu`, `lambda`, `weights[1]`, `members[1].mu`).
    fn param_names(&self) -> Vec<String>;
    /// Sets all parameters, validating them.
    ///
    /// # Errors
    /// [`MaterialError`] naming the first invalid parameter; nothing changes then.
    fn set_params(&mut self, params: &[f64]) -> Result<(), MaterialError>;
}

impl Parametric for Model {
    /// Single models: `[mu, lambda]`. Ensembles: the weights, then each member's `mu, lambda`.
    fn params(&self) -> Vec<f64> {
        match self {
            Model::Ensemble(e) => {
                let mut p: Vec<f64> = e.members.iter().map(|(w, _)| *w).collect();
                p.extend(e.members.iter().flat_map(|(_, m)| m.params()));
                p
            }
            m => {
                let l = m.lame().expect("single model");
                vec![l.mu, l.lambda]
            }
        }
    }

    fn param_names(&self) -> Vec<String> {
        match self {
            Model::Ensemble(e) => {
                let n = e.members.len();
                let mut names: Vec<String> = (0..n).map(|m| format!("weights[{m}]")).collect();
                for m in 0..n {
                    names.push(format!("members[{m}].mu"));
                    names.push(format!("members[{m}].lambda"));
                }
                names
            }
            _ => vec!["mu".to_owned(), "lambda".to_owned()],
        }
    }

    fn set_params(&mut self, params: &[f64]) -> Result<(), MaterialError> {
        let expected = self.params().len();
        if params.len() != expected {
            return Err(MaterialError::ParameterCount {
                expected,
                found: params.len(),
            });
        }
        match self {
            Model::Ensemble(e) => {
                let n = e.members.len();
                let lames = (0..n)
                    .map(|m| {
                        Lame::try_member(params[n + 2 * m], params[n + 2 * m + 1])
                            .map_err(|err| prefix(err, &format!("members[{m}].")))
                    })
                    .collect::<Result<Vec<_>, _>>()?;
                e.set_weights(&params[..n])?;
                for ((_, member), lame) in e.members.iter_mut().zip(lames) {
                    *member.lame_mut().expect("members are single models") = lame;
                }
                Ok(())
            }
            m => {
                let lame = Lame::try_new(params[0], params[1])?;
                *m.lame_mut().expect("single model") = lame;
                Ok(())
            }
        }
    }
}

/// Prefixes the field name of an `InvalidParameter` error (for nested configuration).
pub(crate) fn prefix(err: MaterialError, prefix: &str) -> MaterialError {
    match err {
        MaterialError::InvalidParameter {
            field,
            value,
            reason,
        } => MaterialError::InvalidParameter {
            field: format!("{prefix}{field}"),
            value,
            reason,
        },
        other => other,
    }
}
