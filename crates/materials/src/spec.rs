//! `MaterialSpec`: the serde (RON) description of any model, validated into a [`Model`].

use serde::{Deserialize, Serialize};

use crate::MaterialError;
use crate::lame::{Lame, Moduli};
use crate::model::{Ensemble, Model, prefix};
use crate::models::{
    CorotatedLinear, FixedCorotated, LinearElastic, NeoHookean, StVenantKirchhoff, StableNeoHookean,
};

/// A material as a configuration file states it. Unknown fields are rejected.
///
/// ```
/// use deform_materials::{MaterialSpec, Material};
/// let spec: MaterialSpec = ron::from_str("NeoHookean(Young(e: 1e6, nu: 0.4))").unwrap();
/// let model = spec.build().unwrap();
/// assert_eq!(model.psi(&nalgebra::Matrix3::identity()), 0.0);
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub enum MaterialSpec {
    /// Linear isotropic elasticity.
    LinearElastic(Moduli),
    /// Corotated linear elasticity, optionally with the lagged-rotation tangent.
    CorotatedLinear {
        /// Elastic moduli.
        moduli: Moduli,
        /// Hold the rotation fixed in the tangent ("warped stiffness").
        #[serde(default)]
        lagged_rotation: bool,
    },
    /// Fixed corotated (Stomakhin et al. 2012).
    FixedCorotated(Moduli),
    /// St. Venant-Kirchhoff.
    StVenantKirchhoff(Moduli),
    /// Neo-Hookean.
    NeoHookean(Moduli),
    /// Stable Neo-Hookean (Smith et al. 2018), with moduli of its small-strain limit.
    StableNeoHookean(Moduli),
    /// A weighted sum of single models.
    Ensemble(Vec<EnsembleMember>),
}

/// One member of an ensemble.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct EnsembleMember {
    /// Its weight (`>= 0`).
    pub weight: f64,
    /// Its model (not itself an ensemble).
    pub model: MaterialSpec,
}

impl EnsembleMember {
    /// `model` with `weight`.
    pub fn new(weight: f64, model: MaterialSpec) -> Self {
        Self { weight, model }
    }
}

impl MaterialSpec {
    /// The same single model with its moduli replaced (`None` for an ensemble, whose
    /// members each have their own).
    pub fn with_moduli(&self, moduli: Moduli) -> Option<MaterialSpec> {
        Some(match self {
            MaterialSpec::LinearElastic(_) => MaterialSpec::LinearElastic(moduli),
            MaterialSpec::CorotatedLinear {
                lagged_rotation, ..
            } => MaterialSpec::CorotatedLinear {
                moduli,
                lagged_rotation: *lagged_rotation,
            },
            MaterialSpec::FixedCorotated(_) => MaterialSpec::FixedCorotated(moduli),
            MaterialSpec::StVenantKirchhoff(_) => MaterialSpec::StVenantKirchhoff(moduli),
            MaterialSpec::NeoHookean(_) => MaterialSpec::NeoHookean(moduli),
            MaterialSpec::StableNeoHookean(_) => MaterialSpec::StableNeoHookean(moduli),
            MaterialSpec::Ensemble(_) => return None,
        })
    }

    /// Validates and builds the model. An ensemble member may carry volume only (`mu = 0`
    /// with Lame moduli; see [`Lame::try_member`]).
    ///
    /// # Errors
    /// [`MaterialError`] naming the invalid field (`members[1].nu`, `weights[0]`, ...).
    pub fn build(&self) -> Result<Model, MaterialError> {
        match self {
            MaterialSpec::Ensemble(members) => {
                let built = members
                    .iter()
                    .enumerate()
                    .map(|(k, m)| {
                        m.model
                            .build_single(Moduli::to_member_lame)
                            .map(|model| (m.weight, model))
                            .map_err(|e| prefix(e, &format!("members[{k}].")))
                    })
                    .collect::<Result<Vec<_>, _>>()?;
                Ok(Model::Ensemble(Ensemble::try_new(built)?))
            }
            single => single.build_single(Moduli::to_lame),
        }
    }

    /// A single model with its moduli validated by `lame`.
    fn build_single(
        &self,
        lame: fn(&Moduli) -> Result<Lame, MaterialError>,
    ) -> Result<Model, MaterialError> {
        Ok(match self {
            MaterialSpec::LinearElastic(m) => Model::Linear(LinearElastic { lame: lame(m)? }),
            MaterialSpec::CorotatedLinear {
                moduli,
                lagged_rotation,
            } => Model::Corotated(CorotatedLinear {
                lame: lame(moduli)?,
                lagged_rotation: *lagged_rotation,
            }),
            MaterialSpec::FixedCorotated(m) => {
                Model::FixedCorotated(FixedCorotated { lame: lame(m)? })
            }
            MaterialSpec::StVenantKirchhoff(m) => {
                Model::StVenantKirchhoff(StVenantKirchhoff { lame: lame(m)? })
            }
            MaterialSpec::NeoHookean(m) => Model::NeoHookean(NeoHookean { lame: lame(m)? }),
            MaterialSpec::StableNeoHookean(m) => {
                Model::StableNeoHookean(StableNeoHookean { lame: lame(m)? })
            }
            MaterialSpec::Ensemble(_) => {
                return Err(MaterialError::InvalidEnsemble("ensembles cannot be nested"));
            }
        })
    }
}
