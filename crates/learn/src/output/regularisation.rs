//! Regularisation of coefficient fields: a weighted penalty on differences between
//! neighbouring elements (faces shared), and which vertices the data see.

use super::*;

/// A penalty on a coefficient field, in log-coefficients (the optimiser's own variables, so
/// it is scale-free): `towards` times the mean over groups of `sum_k (ln c_gk - ln b_k)^2`,
/// pulling every group towards the base material `b` (the homogeneous fit the field starts
/// from), plus `smooth` times the mean over `neighbours` (pairs of groups sharing a face) of
/// `sum_k (ln c_gk - ln c_hk)^2`. Both weights are chosen on validation data.
#[derive(Debug, Clone, PartialEq, Default)]
#[non_exhaustive]
pub struct Regularisation {
    /// Weight of the pull towards the base material.
    pub towards: f64,
    /// Weight of the differences across shared faces.
    pub smooth: f64,
    /// Pairs of neighbouring groups (see [`face_neighbours`]).
    pub neighbours: Vec<[usize; 2]>,
}

deform_setters::setters!(Regularisation { towards: f64, smooth: f64, neighbours: Vec<[usize; 2]> });

impl Regularisation {
    /// The penalty at `c` (terms per group `base.len()`); adds its gradient to `grad`.
    pub(super) fn add(&self, c: &[f64], base: &[f64], grad: &mut [f64]) -> f64 {
        let terms = base.len().max(1);
        let groups = c.len() / terms;
        let log = |i: usize| c[i].abs().ln();
        let mut penalty = 0.0;
        if self.towards > 0.0 && groups > 0 {
            let w = self.towards / groups as f64;
            for (i, gi) in grad.iter_mut().enumerate() {
                let d = log(i) - base[i % terms].abs().ln();
                penalty += w * d * d;
                *gi += 2.0 * w * d / c[i];
            }
        }
        if self.smooth > 0.0 && !self.neighbours.is_empty() {
            let w = self.smooth / self.neighbours.len() as f64;
            for [g, h] in &self.neighbours {
                for k in 0..terms {
                    let (i, j) = (g * terms + k, h * terms + k);
                    let d = log(i) - log(j);
                    penalty += w * d * d;
                    grad[i] += 2.0 * w * d / c[i];
                    grad[j] -= 2.0 * w * d / c[j];
                }
            }
        }
        penalty
    }
}

/// Pairs of groups (by position in increasing label) whose elements share a face, sorted and
/// without repeats: the neighbours of a field's smoothness penalty.
pub fn face_neighbours(mesh: &deform_mesh::TetMesh, labels: &[u32]) -> Vec<[usize; 2]> {
    let mut distinct = labels.to_vec();
    distinct.sort_unstable();
    distinct.dedup();
    let group = |e: usize| distinct.binary_search(&labels[e]).unwrap_or(0);
    let mut pairs: Vec<[usize; 2]> = deform_mesh::topology::faces(mesh)
        .interior
        .iter()
        .map(|&[a, b]| (group(a), group(b)))
        .filter(|(g, h)| g != h)
        .map(|(g, h)| [g.min(h), g.max(h)])
        .collect();
    pairs.sort_unstable();
    pairs.dedup();
    pairs
}

/// Per vertex, whether `t` observed it (every vertex of a wholly observed trajectory; the
/// vertex markers' of a partially observed one).
pub(super) fn seen_vertices(t: &Trajectory, vertices: usize) -> Vec<bool> {
    let Some(o) = &t.observed else {
        return vec![true; vertices];
    };
    let mut seen = vec![false; vertices];
    for m in &o.markers {
        if let crate::observe::Marker::Vertex(v) = *m {
            seen[v] = true;
        }
    }
    seen
}
