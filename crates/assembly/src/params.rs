//! Parameter gradients through the materials' parameter split.
//!
//! Every model is `Psi = sum_k c_k Psi_k(F)` (for a single model `c = (mu, lambda)`), so the
//! forces are linear in the coefficients: `f = sum_k c_k f_k(x)` with
//! `f_k = -sum_e W_e dPsi_k/dF g_a`. The Jacobian `df/dc` is therefore the matrix of term
//! forces, exact and as cheap as one force evaluation per term. Coefficients can be shared
//! by all elements or be separate per group (region) of elements.

use deform_materials::{Material, Model, mat3, vec9};
use nalgebra::Vector3;
use rayon::prelude::*;

use crate::assembly::{
    admissible_gradient, check_len, check_positions, corners, for_each_element_with_model,
    vertex_chunks,
};
use crate::kernel::{corner_products, gradient};
use crate::{Assembly, AssemblyError};

/// Which elements share coefficients.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Grouping {
    group: Vec<u32>,
    labels: Vec<u32>,
}

impl Grouping {
    /// One group: global coefficients.
    pub fn global(asm: &Assembly) -> Self {
        Self {
            group: vec![0; asm.num_elements()],
            labels: vec![0],
        }
    }

    /// One group per mesh region, in increasing region tag.
    pub fn by_region(asm: &Assembly) -> Self {
        let mut labels = asm.geometry.regions.clone();
        labels.sort_unstable();
        labels.dedup();
        let group = asm
            .geometry
            .regions
            .iter()
            .map(|r| labels.binary_search(r).expect("every region is listed") as u32)
            .collect();
        Self { group, labels }
    }

    /// One group per element: a coefficient field over the mesh.
    pub fn per_element(asm: &Assembly) -> Self {
        let n = asm.num_elements() as u32;
        Self {
            group: (0..n).collect(),
            labels: (0..n).collect(),
        }
    }

    /// Groups given by a label per element (regions of a coarse mesh, clusters, ...): one
    /// group per distinct label, in increasing label.
    ///
    /// # Errors
    /// [`AssemblyError::DimensionMismatch`] when there is not one label per element.
    pub fn from_labels(asm: &Assembly, labels: &[u32]) -> Result<Self, AssemblyError> {
        check_len("labels", labels.len(), asm.num_elements())?;
        let mut distinct = labels.to_vec();
        distinct.sort_unstable();
        distinct.dedup();
        let group = labels
            .iter()
            .map(|l| distinct.binary_search(l).expect("every label is listed") as u32)
            .collect();
        Ok(Self {
            group,
            labels: distinct,
        })
    }

    /// The group of each element.
    pub fn groups(&self) -> &[u32] {
        &self.group
    }

    /// Number of groups.
    pub fn num_groups(&self) -> usize {
        self.labels.len()
    }

    /// The label of each group (region tags for [`Grouping::by_region`]).
    pub fn labels(&self) -> &[u32] {
        &self.labels
    }
}

/// A `3N x (groups * terms)` matrix, row-major; column `g * terms + k` belongs to term `k`
/// of group `g`.
#[derive(Debug, Clone, PartialEq)]
pub struct TermJacobian {
    /// Number of terms per group.
    pub terms: usize,
    /// Number of groups.
    pub groups: usize,
    /// Row-major values, `3N` rows of `groups * terms`.
    pub data: Vec<f64>,
}

impl TermJacobian {
    /// Number of columns.
    pub fn num_columns(&self) -> usize {
        self.terms * self.groups
    }

    /// Column `j` as a flat `3N` vector.
    pub fn column(&self, j: usize) -> Vec<f64> {
        self.data
            .iter()
            .skip(j)
            .step_by(self.num_columns())
            .copied()
            .collect()
    }
}

impl Assembly {
    /// `df/dc`: the forces of each term of each group at `x` (see the module docs).
    ///
    /// # Errors
    /// As [`Assembly::evaluate`]; [`AssemblyError::DimensionMismatch`] when the grouping was
    /// made for another mesh.
    pub fn term_forces(
        &self,
        x: &[f64],
        grouping: &Grouping,
    ) -> Result<TermJacobian, AssemblyError> {
        self.term_pass(x, None, grouping)
    }

    /// `d(K dx)/dc`: column `g * terms + k` is `K_{g,k}(x) dx`, the stiffness of term `k` on
    /// group `g` applied to `dx` (for derivatives of damping forces and of Newton residuals).
    ///
    /// # Errors
    /// As [`Assembly::term_forces`], plus checks of `dx`.
    pub fn term_stiffness_products(
        &self,
        x: &[f64],
        dx: &[f64],
        grouping: &Grouping,
    ) -> Result<TermJacobian, AssemblyError> {
        check_positions("dx", dx, self.num_dofs())?;
        self.term_pass(x, Some(dx), grouping)
    }

    /// `lambda^T df/dc`, or with `dx` `lambda^T d(K dx)/dc`: [`Assembly::term_forces`] and
    /// [`Assembly::term_stiffness_products`] applied to `lambda` from the left, in one pass
    /// over the elements without forming their `3N x columns` matrices, so that a
    /// coefficient per element costs about what one per mesh does. Entry `g * terms + k`
    /// belongs to term `k` of group `g`. Summed in element order: thread-count independent.
    ///
    /// # Errors
    /// As [`Assembly::term_stiffness_products`], plus checks of `lambda`.
    pub fn term_vjp(
        &self,
        x: &[f64],
        dx: Option<&[f64]>,
        lambda: &[f64],
        grouping: &Grouping,
    ) -> Result<Vec<f64>, AssemblyError> {
        check_positions("x", x, self.num_dofs())?;
        check_positions("lambda", lambda, self.num_dofs())?;
        if let Some(dx) = dx {
            check_positions("dx", dx, self.num_dofs())?;
        }
        check_len("grouping", grouping.group.len(), self.num_elements())?;
        let geo = &self.geometry;
        let terms = self.materials.max_terms();
        let mut per_element = vec![0.0; self.num_elements() * terms];
        if terms > 0 {
            let mut chunks: Vec<&mut [f64]> = per_element.chunks_mut(terms).collect();
            for_each_element_with_model(&self.materials, 0, &mut chunks, |e, out, m| {
                let (t, g) = (&geo.tets[e], &geo.grads[e]);
                let f = admissible_gradient(geo, x, e, m)?;
                let df = dx.map(|d| gradient(&corners(d, t), g));
                let l = corners(lambda, t);
                let w = geo.volumes[e];
                for k in 0..m.num_terms() {
                    let p = match &df {
                        None => -w * m.term_first_piola(k, &f),
                        Some(df) => w * mat3(&(m.term_dp_df(k, &f) * vec9(df))),
                    };
                    let c = corner_products(&p, g, 1.0);
                    out[k] = (0..4).map(|a| l[a].dot(&c[a])).sum();
                }
                Ok(())
            })?;
        }
        if let Some(i) = per_element.iter().position(|v| !v.is_finite()) {
            return Err(AssemblyError::NonFiniteElement {
                element: i / terms,
                what: "term vector-Jacobian product",
            });
        }
        let mut out = vec![0.0; terms * grouping.num_groups()];
        for (e, values) in per_element.chunks(terms.max(1)).enumerate() {
            let g = grouping.group[e] as usize;
            for (k, v) in values.iter().enumerate().take(terms) {
                out[g * terms + k] += v;
            }
        }
        Ok(out)
    }

    fn term_pass(
        &self,
        x: &[f64],
        dx: Option<&[f64]>,
        grouping: &Grouping,
    ) -> Result<TermJacobian, AssemblyError> {
        check_positions("x", x, self.num_dofs())?;
        check_len("grouping", grouping.group.len(), self.num_elements())?;
        let geo = &self.geometry;
        let terms = self.materials.max_terms();
        let cols = terms * grouping.num_groups();
        // Per element, per term: the four corner vectors.
        let mut corner = vec![[Vector3::zeros(); 4]; self.num_elements() * terms];
        let mut elements: Vec<&mut [[Vector3<f64>; 4]]> = corner.chunks_mut(terms.max(1)).collect();
        let body = |e: usize, out: &mut &mut [[Vector3<f64>; 4]], m: &Model| {
            let (t, g) = (&geo.tets[e], &geo.grads[e]);
            let f = admissible_gradient(geo, x, e, m)?;
            let df = dx.map(|d| gradient(&corners(d, t), g));
            let w = geo.volumes[e];
            for k in 0..m.num_terms() {
                // Forces carry -W; stiffness products +W.
                let p = match &df {
                    None => -w * m.term_first_piola(k, &f),
                    Some(df) => w * mat3(&(m.term_dp_df(k, &f) * vec9(df))),
                };
                out[k] = corner_products(&p, g, 1.0);
            }
            Ok(())
        };
        if terms > 0 {
            for_each_element_with_model(&self.materials, 0, &mut elements, body)?;
        }
        drop(elements);
        let mut data = vec![0.0; self.num_dofs() * cols];
        vertex_chunks(&mut data, |v| 3 * cols * v, geo.num_vertices)
            .into_par_iter()
            .for_each(|(v0, out)| {
                for (i, rows) in out.chunks_exact_mut(3 * cols.max(1)).enumerate() {
                    let v = v0 + i;
                    for &slot in &geo.vertex_slots[geo.vertex_ptr[v]..geo.vertex_ptr[v + 1]] {
                        let (e, a) = (slot as usize / 4, slot as usize % 4);
                        let g = grouping.group[e] as usize;
                        for k in 0..terms {
                            let c = corner[e * terms + k][a];
                            for r in 0..3 {
                                rows[r * cols + g * terms + k] += c[r];
                            }
                        }
                    }
                }
            });
        if let Some(i) = data.iter().position(|v| !v.is_finite()) {
            return Err(AssemblyError::NonFinite {
                what: "term Jacobian",
                vertex: i / (3 * cols),
            });
        }
        Ok(TermJacobian {
            terms,
            groups: grouping.num_groups(),
            data,
        })
    }
}
