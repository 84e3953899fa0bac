//! Vertex selectors for boundary conditions.
//!
//! A [`Selector`] is plain serde data so scenes can name vertex sets in RON, e.g.
//! `Plane(point: (0, 0, 0), normal: (-1, 0, 0))` for "the side x <= 0", or
//! `Box(min: (0.9, -1, -1), max: (1.1, 1, 1))`. [`select_by`] covers arbitrary predicates.
//! Every selection returns sorted, unique vertex indices.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::TetMesh;
use crate::topology::surface_vertices;

/// Default geometric tolerance of selectors, relative to the mesh's bounding-box diagonal.
pub const RELATIVE_TOLERANCE: f64 = 1e-9;

/// A set of vertices, described declaratively.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub enum Selector {
    /// Every vertex.
    All,
    /// Vertices inside the closed axis-aligned box `[min, max]` (grown by the tolerance).
    Box {
        /// Lower corner.
        min: [f64; 3],
        /// Upper corner.
        max: [f64; 3],
    },
    /// Vertices with `(X - point) . normal >= -tol`: the closed half-space the normal points into.
    /// With `normal = (-1, 0, 0)` and `point = (0, 0, 0)` this selects the side `x <= 0`.
    Plane {
        /// A point on the plane.
        point: [f64; 3],
        /// The side to keep (need not be unit length).
        normal: [f64; 3],
    },
    /// Vertices on the boundary surface.
    Surface,
    /// Explicit vertex indices.
    Indices(Vec<usize>),
    /// Vertex indices in an `.npy` file (any integer dtype, any shape: e.g. the int64 array
    /// of clamped vertex ids a numpy user has), relative to the scene file.
    File(std::path::PathBuf),
    /// Vertices selected by every one of these.
    And(Vec<Selector>),
    /// Vertices selected by any of these.
    Or(Vec<Selector>),
    /// Vertices not selected by this.
    Not(Box<Selector>),
}

/// Why a selector cannot be evaluated on a mesh.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum SelectError {
    /// An explicit index is out of range.
    #[error("selector index {index} is out of range for a mesh of {num_vertices} vertices")]
    IndexOutOfRange {
        /// The index.
        index: usize,
        /// Vertex count.
        num_vertices: usize,
    },
    /// A plane normal is zero or non-finite, or a coordinate is not finite.
    #[error("invalid selector geometry: {0}")]
    InvalidGeometry(String),
    /// An index file could not be read or holds something other than vertex ids.
    #[error("{}: {reason}", path.display())]
    File {
        /// The file.
        path: std::path::PathBuf,
        /// What is wrong.
        reason: String,
    },
}

impl Selector {
    /// Makes the relative paths of index files relative to `dir` (the scene file's folder).
    pub fn resolve_paths(&mut self, dir: &std::path::Path) {
        match self {
            Selector::File(path) if path.is_relative() => *path = dir.join(&*path),
            Selector::And(parts) | Selector::Or(parts) => {
                parts.iter_mut().for_each(|p| p.resolve_paths(dir));
            }
            Selector::Not(inner) => inner.resolve_paths(dir),
            _ => {}
        }
    }

    /// The selected vertices (sorted, unique), evaluated on rest positions.
    ///
    /// # Errors
    /// [`SelectError`] for out-of-range indices or invalid geometry.
    pub fn select(&self, mesh: &TetMesh) -> Result<Vec<usize>, SelectError> {
        let (lo, hi) = mesh.bounding_box();
        let tol = RELATIVE_TOLERANCE * (hi - lo).norm().max(f64::MIN_POSITIVE);
        let mut mask = vec![false; mesh.num_vertices()];
        self.mark(mesh, tol, &mut mask)?;
        Ok(mask_to_indices(&mask))
    }

    fn mark(&self, mesh: &TetMesh, tol: f64, mask: &mut [bool]) -> Result<(), SelectError> {
        let finite = |v: &[f64; 3], what: &str| {
            if v.iter().all(|c| c.is_finite()) {
                Ok(Vector3::from(*v))
            } else {
                Err(SelectError::InvalidGeometry(format!(
                    "{what} {v:?} is not finite"
                )))
            }
        };
        let rest = mesh.rest_positions();
        match self {
            Selector::All => mask.fill(true),
            Selector::Box { min, max } => {
                let (lo, hi) = (finite(min, "box min")?, finite(max, "box max")?);
                for (m, p) in mask.iter_mut().zip(rest) {
                    *m = (0..3).all(|a| p[a] >= lo[a] - tol && p[a] <= hi[a] + tol);
                }
            }
            Selector::Plane { point, normal } => {
                let (q, n) = (
                    finite(point, "plane point")?,
                    finite(normal, "plane normal")?,
                );
                let len = n.norm();
                if len == 0.0 {
                    return Err(SelectError::InvalidGeometry("plane normal is zero".into()));
                }
                let n = n / len;
                for (m, p) in mask.iter_mut().zip(rest) {
                    *m = (p - q).dot(&n) >= -tol;
                }
            }
            Selector::Surface => {
                mask.fill(false);
                for i in surface_vertices(mesh) {
                    mask[i] = true;
                }
            }
            Selector::Indices(indices) => mark_indices(indices, mask)?,
            Selector::File(path) => {
                let file_error = |reason: String| SelectError::File {
                    path: path.clone(),
                    reason,
                };
                let array = deform_fs::npy::read(path).map_err(|e| match e {
                    deform_fs::npy::NpyError::Io { error, .. } => file_error(error.to_string()),
                    deform_fs::npy::NpyError::Format { reason, .. } => file_error(reason),
                    other => file_error(other.to_string()),
                })?;
                let indices = array.indices().map_err(file_error)?;
                mark_indices(&indices, mask).map_err(|e| file_error(e.to_string()))?;
            }
            Selector::And(parts) | Selector::Or(parts) => {
                let is_and = matches!(self, Selector::And(_));
                mask.fill(is_and);
                let mut sub = vec![false; mask.len()];
                for part in parts {
                    part.mark(mesh, tol, &mut sub)?;
                    for (m, s) in mask.iter_mut().zip(&sub) {
                        *m = if is_and { *m && *s } else { *m || *s };
                    }
                }
            }
            Selector::Not(inner) => {
                inner.mark(mesh, tol, mask)?;
                for m in mask.iter_mut() {
                    *m = !*m;
                }
            }
        }
        Ok(())
    }
}

/// Marks exactly `indices` in `mask`.
fn mark_indices(indices: &[usize], mask: &mut [bool]) -> Result<(), SelectError> {
    let num_vertices = mask.len();
    mask.fill(false);
    for &index in indices {
        let slot = mask.get_mut(index).ok_or(SelectError::IndexOutOfRange {
            index,
            num_vertices,
        })?;
        *slot = true;
    }
    Ok(())
}

/// Vertices whose rest position satisfies `predicate(index, position)`, sorted.
pub fn select_by(
    mesh: &TetMesh,
    mut predicate: impl FnMut(usize, &Vector3<f64>) -> bool,
) -> Vec<usize> {
    mesh.rest_positions()
        .iter()
        .enumerate()
        .filter(|(i, p)| predicate(*i, p))
        .map(|(i, _)| i)
        .collect()
}

fn mask_to_indices(mask: &[bool]) -> Vec<usize> {
    mask.iter()
        .enumerate()
        .filter(|(_, m)| **m)
        .map(|(i, _)| i)
        .collect()
}
