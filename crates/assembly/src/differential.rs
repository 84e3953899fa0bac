//! Force differentials without assembling K (the seed's Section 1.4): element by element,
//! `df(x; dx) = -K(x) dx`.

use deform_materials::{Material, Matrix9, mat3, vec9};
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use crate::assembly::{
    Geometry, Tangent, admissible_gradient, check_len, check_positions, corners, finite9,
    for_each_element_with_model, gather_vertex_vectors,
};
use crate::kernel::{corner_products, gradient, stiffness_blocks};
use crate::{Assembly, AssemblyError};

/// The element tangents `W_e dP/dF(F_e)` at one configuration: a matrix-free `K`.
///
/// `apply` costs one 9x9 product per element and no matrix storage beyond the tangents;
/// results are summed per vertex in element order (independent of the thread count).
#[derive(Debug, Clone)]
pub struct ElementTangents<'a> {
    geometry: &'a Geometry,
    tangents: Vec<Matrix9>,
}

impl Assembly {
    /// The element tangents at `x`, for matrix-free products with `K(x)`.
    ///
    /// # Errors
    /// As [`Assembly::evaluate`].
    pub fn tangents(
        &self,
        x: &[f64],
        tangent: Tangent,
    ) -> Result<ElementTangents<'_>, AssemblyError> {
        check_positions("x", x, self.num_dofs())?;
        let geo = &self.geometry;
        let mut tangents = vec![Matrix9::zeros(); self.num_elements()];
        let project = tangent == Tangent::Projected;
        let body = |e: usize, out: &mut Matrix9, m: &deform_materials::Model| {
            let f = admissible_gradient(geo, x, e, m)?;
            let c = if project {
                m.dp_df_projected(&f)
            } else {
                m.dp_df(&f)
            };
            if !finite9(&c) {
                return Err(AssemblyError::NonFiniteElement {
                    element: e,
                    what: "tangent",
                });
            }
            *out = c * geo.volumes[e];
            Ok(())
        };
        for_each_element_with_model(&self.materials, 0, &mut tangents, body)?;
        Ok(ElementTangents {
            geometry: geo,
            tangents,
        })
    }

    /// `df = -K(x) dx` element by element with each material's `dP(F; dF)`, without forming
    /// any tangent matrix.
    ///
    /// # Errors
    /// As [`Assembly::evaluate`], plus a check of `dx` and `df`.
    pub fn force_differential(
        &self,
        x: &[f64],
        dx: &[f64],
        df: &mut [f64],
    ) -> Result<(), AssemblyError> {
        check_positions("x", x, self.num_dofs())?;
        check_positions("dx", dx, self.num_dofs())?;
        check_len("df", df.len(), self.num_dofs())?;
        let geo = &self.geometry;
        let mut corner_forces = vec![[Vector3::zeros(); 4]; self.num_elements()];
        let body = |e: usize, out: &mut [Vector3<f64>; 4], m: &deform_materials::Model| {
            let (t, g) = (&geo.tets[e], &geo.grads[e]);
            let f = admissible_gradient(geo, x, e, m)?;
            let dp = m.dp(&f, &gradient(&corners(dx, t), g));
            *out = corner_products(&dp, g, -geo.volumes[e]);
            Ok(())
        };
        for_each_element_with_model(&self.materials, 0, &mut corner_forces, body)?;
        gather_vertex_vectors(geo, |slot| corner_forces[slot / 4][slot % 4], df);
        finite_or_first_vertex(df)
    }
}

fn finite_or_first_vertex(v: &[f64]) -> Result<(), AssemblyError> {
    match v.iter().position(|x| !x.is_finite()) {
        Some(i) => Err(AssemblyError::NonFinite {
            what: "force differential",
            vertex: i / 3,
        }),
        None => Ok(()),
    }
}

impl ElementTangents<'_> {
    /// Number of rows, `3N`.
    pub fn num_dofs(&self) -> usize {
        3 * self.geometry.num_vertices
    }

    /// `y = K dx`.
    ///
    /// # Panics
    /// If the lengths are not `3N`.
    pub fn apply(&self, dx: &[f64], y: &mut [f64]) {
        assert_eq!(dx.len(), self.num_dofs(), "dx has the wrong length");
        assert_eq!(y.len(), self.num_dofs(), "y has the wrong length");
        let geo = self.geometry;
        let corner_forces: Vec<[Vector3<f64>; 4]> = (0..self.tangents.len())
            .into_par_iter()
            .with_min_len(crate::assembly::CHUNK)
            .map(|e| {
                let g = &geo.grads[e];
                let df = gradient(&corners(dx, &geo.tets[e]), g);
                corner_products(&mat3(&(self.tangents[e] * vec9(&df))), g, 1.0)
            })
            .collect();
        gather_vertex_vectors(geo, |slot| corner_forces[slot / 4][slot % 4], y);
    }

    /// Floating-point operations of one `apply` (the deterministic work count).
    pub fn apply_flops(&self) -> u64 {
        // dF (27 mul-add), 9x9 product (81), four corner products (3 x 15 + 9), gather (12).
        self.tangents.len() as u64 * 2 * (27 + 81 + 27 + 12)
    }

    /// The 3x3 diagonal blocks of K, one per vertex.
    ///
    /// # Panics
    /// If `out` does not have one block per vertex.
    pub fn block_diagonal(&self, out: &mut [Matrix3<f64>]) {
        let geo = self.geometry;
        assert_eq!(out.len(), geo.num_vertices, "one block per vertex");
        let diag: Vec<[Matrix3<f64>; 4]> = (0..self.tangents.len())
            .into_par_iter()
            .with_min_len(crate::assembly::CHUNK)
            .map(|e| {
                let mut blocks = [Matrix3::zeros(); 10];
                stiffness_blocks(&self.tangents[e], &geo.grads[e], 1.0, &mut blocks);
                [blocks[0], blocks[4], blocks[7], blocks[9]]
            })
            .collect();
        out.par_iter_mut().enumerate().for_each(|(v, b)| {
            let mut acc = Matrix3::zeros();
            for &slot in &geo.vertex_slots[geo.vertex_ptr[v]..geo.vertex_ptr[v + 1]] {
                let slot = slot as usize;
                acc += diag[slot / 4][slot % 4];
            }
            *b = acc;
        });
    }

    /// The diagonal of K.
    ///
    /// # Panics
    /// If `out` is not `3N` long.
    pub fn diagonal(&self, out: &mut [f64]) {
        let mut blocks = vec![Matrix3::zeros(); self.geometry.num_vertices];
        self.block_diagonal(&mut blocks);
        assert_eq!(out.len(), self.num_dofs(), "out has the wrong length");
        for (v, b) in blocks.iter().enumerate() {
            for r in 0..3 {
                out[3 * v + r] = b[(r, r)];
            }
        }
    }
}
