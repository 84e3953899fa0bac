//! What observations are: markers at vertices or inside elements (barycentric), the marker
//! positions a trajectory carries ([`Observed`]), and why an observation is refused
//! ([`ObserveError`]). A type module: datasets store them and [`crate::observe`] estimates
//! from them, so neither imports the other.

use deform_integrator::IntegratorError;
use deform_mesh::TetMesh;
use deform_solvers::SolverError;
use serde::{Deserialize, Serialize};

/// A point of the body that observations follow.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Marker {
    /// A vertex.
    Vertex(usize),
    /// A point inside a tetrahedron: its corners and their barycentric weights (summing to 1).
    Inside {
        /// The element's vertices.
        vertices: [usize; 4],
        /// Their weights.
        weights: [f64; 4],
    },
}

impl Marker {
    /// The point of `element` with barycentric `weights` (one per corner, in the element's
    /// order), used as given: weights slightly outside `[0, 1]` (a point just outside a
    /// faceted surface) are kept.
    ///
    /// # Errors
    /// [`ObserveError::Marker`] (index 0: the caller's numbering is its own) for an element
    /// out of range or weights that are not finite or do not sum to 1 within 1e-6.
    pub fn in_element(
        mesh: &TetMesh,
        element: usize,
        weights: [f64; 4],
    ) -> Result<Self, ObserveError> {
        let bad = |reason: String| ObserveError::Marker { marker: 0, reason };
        let Some(&vertices) = mesh.tets().get(element) else {
            return Err(bad(format!(
                "element {element} is out of range for {} elements",
                mesh.num_tets()
            )));
        };
        let sum: f64 = weights.iter().sum();
        if weights.iter().any(|w| !w.is_finite()) || (sum - 1.0).abs() > 1e-6 {
            return Err(bad(format!(
                "weights {weights:?} of element {element} must be finite and sum to 1"
            )));
        }
        Ok(Self::Inside { vertices, weights })
    }

    /// Points inside `elements` with `weights` (four per point, flat), as
    /// [`Marker::in_element`]; an error names the marker.
    ///
    /// # Errors
    /// [`ObserveError::Marker`] naming the first bad one.
    pub fn in_elements(
        mesh: &TetMesh,
        elements: &[usize],
        weights: &[f64],
    ) -> Result<Vec<Self>, ObserveError> {
        let rows = elements.iter().zip(weights.chunks(4)).enumerate();
        rows.map(|(marker, (&e, w))| {
            Self::in_element(mesh, e, [w[0], w[1], w[2], w[3]]).map_err(|err| match err {
                ObserveError::Marker { reason, .. } => ObserveError::Marker { marker, reason },
                other => other,
            })
        })
        .collect()
    }

    /// The vertices and weights whose sum is the marker.
    pub fn terms(&self) -> impl Iterator<Item = (usize, f64)> + '_ {
        let (vertices, weights): (&[usize], &[f64]) = match self {
            Self::Vertex(v) => (std::slice::from_ref(v), &[1.0]),
            Self::Inside { vertices, weights } => (vertices, weights),
        };
        vertices.iter().copied().zip(weights.iter().copied())
    }

    /// The marker's position in the flat `3N` positions `x`.
    pub fn position(&self, x: &[f64]) -> [f64; 3] {
        let mut p = [0.0; 3];
        for (v, w) in self.terms() {
            for (d, pd) in p.iter_mut().enumerate() {
                *pd += w * x[3 * v + d];
            }
        }
        p
    }
}

/// What a capture saw: markers and their positions per frame.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Observed {
    /// The markers.
    pub markers: Vec<Marker>,
    /// Their positions per frame (the trajectory's frames), flat `3M` each.
    pub positions: Vec<Vec<f64>>,
}

impl Observed {
    /// `markers` seen at the flat positions `positions` (frame-major, `3M` per frame).
    pub fn from_flat(markers: Vec<Marker>, positions: &[f64]) -> Self {
        let width = 3 * markers.len().max(1);
        let positions = positions.chunks(width).map(<[f64]>::to_vec).collect();
        Self { markers, positions }
    }

    /// The given `vertices` of whole `frames` (flat `3N` each): a capture of those vertices.
    pub fn vertices(frames: &[Vec<f64>], vertices: &[usize]) -> Self {
        let markers: Vec<Marker> = vertices.iter().map(|&v| Marker::Vertex(v)).collect();
        let positions = frames
            .iter()
            .map(|x| markers.iter().flat_map(|m| m.position(x)).collect())
            .collect();
        Self { markers, positions }
    }

    /// Whether the markers and positions fit a body of `vertices` vertices over `frames`
    /// frames: a reason when they do not.
    pub fn check(&self, vertices: usize, frames: usize) -> Result<(), ObserveError> {
        if self.markers.is_empty() {
            return Err(ObserveError::Frames("no marker is observed".into()));
        }
        for (marker, m) in self.markers.iter().enumerate() {
            let bad = |reason: String| Err(ObserveError::Marker { marker, reason });
            if let Some((v, _)) = m.terms().find(|&(v, _)| v >= vertices) {
                return bad(format!("vertex {v} is out of range for {vertices}"));
            }
            let sum: f64 = m.terms().map(|(_, w)| w).sum();
            if m.terms().any(|(_, w)| !w.is_finite()) || (sum - 1.0).abs() > 1e-6 {
                return bad("its weights must be finite and sum to 1".into());
            }
        }
        if self.positions.len() != frames {
            return Err(ObserveError::Frames(format!(
                "{} frames of marker positions for {frames} frames",
                self.positions.len()
            )));
        }
        let width = 3 * self.markers.len();
        for (frame, p) in self.positions.iter().enumerate() {
            if p.len() != width {
                return Err(ObserveError::Frames(format!(
                    "frame {frame} has {} values for {} markers (3 each)",
                    p.len(),
                    self.markers.len()
                )));
            }
            if let Some(i) = p.iter().position(|v| !v.is_finite()) {
                return Err(ObserveError::Frames(format!(
                    "frame {frame}, marker {}: a non-finite position",
                    i / 3
                )));
            }
        }
        Ok(())
    }

    /// The root-mean-square distance of the markers in positions `x` from those observed at
    /// `frame`.
    pub fn rms_distance(&self, x: &[f64], frame: usize) -> f64 {
        let sq: f64 = self
            .markers
            .iter()
            .zip(self.positions[frame].chunks(3))
            .map(|(m, p)| {
                let q = m.position(x);
                (0..3).map(|d| (q[d] - p[d]).powi(2)).sum::<f64>()
            })
            .sum();
        (sq / self.markers.len().max(1) as f64).sqrt()
    }

    /// The markers' velocities at frame 0 from the first frames `dt` apart: the one-sided
    /// second-order difference with three frames (exact under constant acceleration), the
    /// first-order one with two, zero with one.
    pub(crate) fn first_velocities(&self, dt: f64) -> Vec<f64> {
        let p = &self.positions;
        match p.len() {
            0 | 1 => vec![0.0; p.first().map_or(0, Vec::len)],
            2 => (0..p[0].len()).map(|i| (p[1][i] - p[0][i]) / dt).collect(),
            _ => (0..p[0].len())
                .map(|i| (-3.0 * p[0][i] + 4.0 * p[1][i] - p[2][i]) / (2.0 * dt))
                .collect(),
        }
    }
}

/// Why a first state could not be estimated or observations do not fit.
#[derive(Debug, thiserror::Error)]
pub enum ObserveError {
    /// A marker is malformed.
    #[error("marker {marker}: {reason}")]
    Marker {
        /// Its index.
        marker: usize,
        /// Why.
        reason: String,
    },
    /// The positions do not fit the markers or the frames.
    #[error("{0}")]
    Frames(String),
    /// The trajectory's conditions do not fit the model.
    #[error(transparent)]
    Conditions(#[from] IntegratorError),
    /// The assembly failed.
    #[error(transparent)]
    Assembly(#[from] deform_assembly::AssemblyError),
    /// A linear solve failed.
    #[error(transparent)]
    Solve(#[from] SolverError),
    /// The least-strain shape was not found.
    #[error("the least-strain shape through the markers was not found: {0}")]
    NotConverged(String),
}
