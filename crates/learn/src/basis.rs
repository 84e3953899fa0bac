//! Smooth coefficient fields: a few basis functions over the rest shape.
//!
//! A field's value on element `e` is `c_e = sum_j B_ej w_j` (per term), with `B` the
//! trilinear hat functions of a lattice over the rest shape's bounding box evaluated at the
//! element centroids. They are non-negative and sum to one at every point, so positive
//! weights give positive coefficients (the output error's log-parametrisation keeps them so)
//! and equal weights give a uniform field, where a fit starts. The gradient in the weights is
//! `B^T` times the per-element gradient, so one adjoint pass still gives all of it.

use deform_mesh::TetMesh;

use crate::error::FitError;

/// Basis functions over a mesh's elements: row `e` lists the functions that are non-zero
/// on element `e` with their values.
#[derive(Debug, Clone, PartialEq)]
pub struct Basis {
    functions: usize,
    rows: Vec<Vec<(u32, f64)>>,
}

impl Basis {
    /// The trilinear hat functions of a lattice of `nodes[d]` nodes along each axis `d` of
    /// the rest shape's bounding box (one node: constant along that axis), at the element
    /// centroids: `nodes[0] * nodes[1] * nodes[2]` functions.
    ///
    /// # Errors
    /// [`FitError::Invalid`] for a mesh without elements or a zero node count.
    pub fn hat(mesh: &TetMesh, nodes: [usize; 3]) -> Result<Self, FitError> {
        if mesh.num_tets() == 0 {
            return Err(FitError::Invalid("a smooth field needs elements".into()));
        }
        if nodes.contains(&0) {
            return Err(FitError::Invalid(format!(
                "smooth field nodes {nodes:?}: at least one per axis"
            )));
        }
        let p = mesh.rest_positions();
        let (lo, hi) = p
            .iter()
            .fold((p[0], p[0]), |(lo, hi), q| (lo.inf(q), hi.sup(q)));
        let rows = mesh
            .tets()
            .iter()
            .map(|t| {
                let centroid = t.iter().map(|&v| p[v]).sum::<nalgebra::Vector3<f64>>() / 4.0;
                // Per axis: the two neighbouring nodes and their weights.
                let axis = |d: usize| -> [(usize, f64); 2] {
                    let n = nodes[d];
                    let extent = hi[d] - lo[d];
                    if n == 1 || extent <= 0.0 {
                        return [(0, 1.0), (0, 0.0)];
                    }
                    let s = ((centroid[d] - lo[d]) / extent).clamp(0.0, 1.0) * (n - 1) as f64;
                    let cell = (s.floor() as usize).min(n - 2);
                    let u = s - cell as f64;
                    [(cell, 1.0 - u), (cell + 1, u)]
                };
                let (ax, ay, az) = (axis(0), axis(1), axis(2));
                let mut row = Vec::with_capacity(8);
                for &(i, wx) in &ax {
                    for &(j, wy) in &ay {
                        for &(k, wz) in &az {
                            let w = wx * wy * wz;
                            if w > 0.0 {
                                let f = (k * nodes[1] + j) * nodes[0] + i;
                                row.push((f as u32, w));
                            }
                        }
                    }
                }
                row
            })
            .collect();
        Ok(Self {
            functions: nodes.iter().product(),
            rows,
        })
    }

    /// Number of basis functions.
    pub fn num_functions(&self) -> usize {
        self.functions
    }

    /// Number of elements it is defined on.
    pub fn num_elements(&self) -> usize {
        self.rows.len()
    }

    /// Each element's non-zero functions and their values.
    pub fn rows(&self) -> &[Vec<(u32, f64)>] {
        &self.rows
    }

    /// Per-element values (element-major, `terms` per element) of weights `w` (function-
    /// major, `terms` per function).
    pub fn expand(&self, w: &[f64], terms: usize) -> Vec<f64> {
        let mut c = vec![0.0; self.rows.len() * terms];
        for (ce, row) in c.chunks_mut(terms.max(1)).zip(&self.rows) {
            for &(j, b) in row {
                for (k, ck) in ce.iter_mut().enumerate() {
                    *ck += b * w[j as usize * terms + k];
                }
            }
        }
        c
    }

    /// The transpose of [`Basis::expand`]: a per-element gradient to the weights'.
    pub fn contract(&self, g: &[f64], terms: usize) -> Vec<f64> {
        let mut w = vec![0.0; self.functions * terms];
        for (ge, row) in g.chunks(terms.max(1)).zip(&self.rows) {
            for &(j, b) in row {
                for (k, gk) in ge.iter().enumerate() {
                    w[j as usize * terms + k] += b * gk;
                }
            }
        }
        w
    }
}

#[cfg(test)]
mod tests {
    use deform_mesh::generate::BoxGrid;

    use super::*;

    #[test]
    fn hat_functions_are_a_non_negative_partition_of_unity_and_contract_is_the_transpose() {
        let mesh = BoxGrid::beam(2).build().unwrap();
        let basis = Basis::hat(&mesh, [4, 2, 1]).unwrap();
        assert_eq!(basis.num_functions(), 8);
        for row in basis.rows() {
            assert!(row.iter().all(|&(j, b)| b > 0.0 && (j as usize) < 8));
            let sum: f64 = row.iter().map(|r| r.1).sum();
            assert!((sum - 1.0).abs() < 1e-14, "{sum}");
        }
        // Every function is used.
        let mut used = [false; 8];
        basis
            .rows()
            .iter()
            .flatten()
            .for_each(|r| used[r.0 as usize] = true);
        assert!(used.iter().all(|&u| u));
        // <B w, g> = <w, B^T g> for two terms.
        let w: Vec<f64> = (0..16).map(|i| (i as f64 * 0.37).sin()).collect();
        let g: Vec<f64> = (0..2 * mesh.num_tets())
            .map(|i| (i as f64 * 0.11).cos())
            .collect();
        let lhs: f64 = basis.expand(&w, 2).iter().zip(&g).map(|(a, b)| a * b).sum();
        let rhs: f64 = basis
            .contract(&g, 2)
            .iter()
            .zip(&w)
            .map(|(a, b)| a * b)
            .sum();
        assert!(
            (lhs - rhs).abs() <= 1e-12 * lhs.abs().max(1.0),
            "{lhs} vs {rhs}"
        );
        // Equal weights: a uniform field.
        let uniform = basis.expand(&[3.0, 5.0].repeat(8), 2);
        assert!(
            uniform
                .chunks(2)
                .all(|c| (c[0] - 3.0).abs() < 1e-12 && (c[1] - 5.0).abs() < 1e-12)
        );
        assert!(Basis::hat(&mesh, [0, 1, 1]).is_err());
    }
}
