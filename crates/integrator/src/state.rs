//! The simulation state and boundary conditions.

use nalgebra::{Rotation3, Unit, Vector3};
use serde::{Deserialize, Serialize};

/// Positions and velocities (flat `3N`) at time `t`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct State {
    /// Positions.
    pub x: Vec<f64>,
    /// Velocities.
    pub v: Vec<f64>,
    /// Time.
    pub t: f64,
}

impl State {
    /// At rest at positions `x`, time 0.
    pub fn at_rest(x: Vec<f64>) -> Self {
        let v = vec![0.0; x.len()];
        Self::new(x, v, 0.0)
    }

    /// Positions `x`, velocities `v` (flat, 3 per vertex) at time `t`.
    pub fn new(x: Vec<f64>, v: Vec<f64>, t: f64) -> Self {
        Self { x, v, t }
    }
}

/// How constrained vertices move, as a function of time and their rest position `X`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub enum Motion {
    /// Held at the rest position.
    Fixed,
    /// `X + velocity t` (a scripted pull), for `t <= until` (then held).
    Translate {
        /// Velocity (m/s).
        velocity: [f64; 3],
        /// End of the motion (s); `None` moves forever.
        #[serde(default)]
        until: Option<f64>,
    },
    /// Rotation of `X` about an axis through `center` at `angular_velocity` rad/s, for
    /// `t <= until` (then held).
    Rotate {
        /// A point on the axis.
        center: [f64; 3],
        /// Axis direction (normalised here).
        axis: [f64; 3],
        /// Angular velocity (rad/s).
        angular_velocity: f64,
        /// End of the motion (s); `None` rotates forever.
        #[serde(default)]
        until: Option<f64>,
    },
}

impl Motion {
    fn active_time(t: f64, until: Option<f64>) -> f64 {
        until.map_or(t, |u| t.min(u))
    }

    /// Position at time `t` of the vertex whose rest position is `rest`.
    pub fn position(&self, rest: &Vector3<f64>, t: f64) -> Vector3<f64> {
        match self {
            Motion::Fixed => *rest,
            Motion::Translate { velocity, until } => {
                rest + Vector3::from(*velocity) * Self::active_time(t, *until)
            }
            Motion::Rotate {
                center,
                axis,
                angular_velocity,
                until,
            } => {
                let c = Vector3::from(*center);
                let angle = angular_velocity * Self::active_time(t, *until);
                let axis = Unit::new_normalize(Vector3::from(*axis));
                c + Rotation3::from_axis_angle(&axis, angle) * (rest - c)
            }
        }
    }

    /// Checks the parameters; the message names the field.
    pub(crate) fn validate(&self) -> Result<(), String> {
        let finite = |v: &[f64; 3]| v.iter().all(|x| x.is_finite());
        match self {
            Motion::Fixed => Ok(()),
            Motion::Translate { velocity, until } => {
                if !finite(velocity) {
                    return Err("velocity must be finite".into());
                }
                check_until(*until)
            }
            Motion::Rotate {
                center,
                axis,
                angular_velocity,
                until,
            } => {
                if !finite(center) {
                    return Err("center must be finite".into());
                }
                if !finite(axis) || Vector3::from(*axis).norm() == 0.0 {
                    return Err("axis must be finite and non-zero".into());
                }
                if !angular_velocity.is_finite() {
                    return Err("angular_velocity must be finite".into());
                }
                check_until(*until)
            }
        }
    }
}

fn check_until(until: Option<f64>) -> Result<(), String> {
    match until {
        Some(u) if !(u.is_finite() && u >= 0.0) => {
            Err(format!("until = {u} must be finite and >= 0"))
        }
        _ => Ok(()),
    }
}

/// A set of constrained vertices and their motion.
#[derive(Debug, Clone, PartialEq)]
pub struct Constraint {
    /// The vertices.
    pub vertices: Vec<usize>,
    /// Their motion.
    pub motion: Motion,
}
