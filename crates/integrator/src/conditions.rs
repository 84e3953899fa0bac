//! The conditions of one motion of a body: gravity, the constrained vertices' motions and
//! external loads. A scene states its own; a trajectory of a dataset may override any of them
//! ([`Conditions`]), so that one model is fitted to motions made under different forcing
//! (released under gravity, kicked without it, pulled at another speed).

use serde::{Deserialize, Serialize};

use crate::Motion;
use deform_mesh::select::Selector;

/// A load's force history: `force` (N) in total on its vertices while `t <= until` (for
/// ever without `until`), spread over them in proportion to their lumped masses (the mesh's
/// own, not learned mass scales), so that the same load carries over between a fine mesh and
/// a coarse one of the same body.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct LoadForce {
    /// The total force (N).
    pub force: [f64; 3],
    /// End of the load (s); `None` acts for ever.
    #[serde(default)]
    pub until: Option<f64>,
}

crate::setters!(LoadForce { force: [f64; 3], until: Option<f64> });

impl LoadForce {
    /// The total `force` (N), acting for ever ([`LoadForce::until`] ends it).
    pub fn new(force: [f64; 3]) -> Self {
        let until = None;
        Self { force, until }
    }
}

impl LoadForce {
    /// Whether the load acts at `t` (`slack` absorbs the rounding of accumulated time steps).
    pub fn active(&self, t: f64, slack: f64) -> bool {
        self.until.is_none_or(|u| t <= u + slack)
    }

    /// Checks the values; the message names the field.
    pub(crate) fn validate(&self) -> Result<(), String> {
        if !self.force.iter().all(|f| f.is_finite()) {
            return Err(format!("force {:?} must be finite", self.force));
        }
        match self.until {
            Some(u) if !(u.is_finite() && u >= 0.0) => {
                Err(format!("until = {u} must be finite and >= 0"))
            }
            _ => Ok(()),
        }
    }
}

/// An external load in a scene: a total force on the selected vertices ([`LoadForce`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct LoadSpec {
    /// Which vertices.
    pub select: Selector,
    /// The total force (N).
    pub force: [f64; 3],
    /// End of the load (s); `None` acts for ever.
    #[serde(default)]
    pub until: Option<f64>,
}

crate::setters!(LoadSpec { select: Selector, force: [f64; 3], until: Option<f64> });

impl LoadSpec {
    /// The total `force` (N) on the vertices `select`, acting for ever.
    pub fn new(select: Selector, force: [f64; 3]) -> Self {
        let until = None;
        Self {
            select,
            force,
            until,
        }
    }
}

impl LoadSpec {
    /// Its force history.
    pub fn load_force(&self) -> LoadForce {
        LoadForce {
            force: self.force,
            until: self.until,
        }
    }
}

/// A load on a set of vertices, as an integrator holds it.
#[derive(Debug, Clone, PartialEq)]
pub struct Load {
    /// The vertices.
    pub vertices: Vec<usize>,
    /// The force history.
    pub force: LoadForce,
}

/// Conditions of one motion that override a model's own (`None` keeps the model's): what a
/// trajectory of a dataset made under other forcing than the scene's states. The default
/// overrides nothing.
///
/// ```
/// use deform_integrator::Conditions;
///
/// // Released without gravity, the scene's constraints and loads unchanged.
/// let c: Conditions = ron::from_str("(gravity: Some((0.0, 0.0, 0.0)))").unwrap();
/// assert_eq!(c.gravity, Some([0.0; 3]));
/// assert!(c.motions.is_none() && !c.is_default() && Conditions::default().is_default());
/// ```
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
#[non_exhaustive]
pub struct Conditions {
    /// Gravity (m/s^2).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gravity: Option<[f64; 3]>,
    /// The motion of each of the model's constraints, in their order.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub motions: Option<Vec<Motion>>,
    /// The force of each of the model's loads, in their order.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub loads: Option<Vec<LoadForce>>,
}

crate::setters!(Conditions {
    gravity: Option<[f64; 3]>,
    motions: Option<Vec<Motion>>,
    loads: Option<Vec<LoadForce>>,
});

impl Conditions {
    /// Whether it overrides nothing.
    pub fn is_default(&self) -> bool {
        *self == Self::default()
    }

    /// Checks the values against a model of `constraints` constraints and `loads` loads; the
    /// message names the field.
    ///
    /// # Errors
    /// `(field, reason)` of the first bad value.
    pub fn validate(&self, constraints: usize, loads: usize) -> Result<(), (String, String)> {
        if let Some(g) = self.gravity
            && !g.iter().all(|g| g.is_finite())
        {
            return Err(("gravity".into(), format!("{g:?} must be finite")));
        }
        if let Some(m) = &self.motions {
            if m.len() != constraints {
                let reason = format!("{} motions for {constraints} constraints", m.len());
                return Err(("motions".into(), reason));
            }
            for (i, m) in m.iter().enumerate() {
                m.validate().map_err(|r| (format!("motions[{i}]"), r))?;
            }
        }
        if let Some(l) = &self.loads {
            if l.len() != loads {
                return Err((
                    "loads".into(),
                    format!("{} forces for {loads} loads", l.len()),
                ));
            }
            for (i, l) in l.iter().enumerate() {
                l.validate().map_err(|r| (format!("loads[{i}]"), r))?;
            }
        }
        Ok(())
    }
}
