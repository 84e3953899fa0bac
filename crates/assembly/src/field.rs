//! Which material each element has.

use std::collections::BTreeMap;

use deform_materials::Model;
use deform_mesh::TetMesh;

use crate::AssemblyError;

/// The material of every element: one model for the whole mesh (no per-element lookup), or
/// a table of models and an index per element (regions, graded stiffness).
#[derive(Debug, Clone, PartialEq)]
pub enum MaterialField {
    /// One model everywhere.
    Uniform(Model),
    /// `models[index[e]]` for element `e`.
    PerElement {
        /// The distinct models.
        models: Vec<Model>,
        /// One index into `models` per element.
        index: Vec<u32>,
    },
}

impl MaterialField {
    /// `base` with term coefficients per group (see `Model::with_term_coefficients`):
    /// group `g` takes `c[g * terms..(g + 1) * terms]`, element `e` group `index[e]`.
    ///
    /// # Errors
    /// [`AssemblyError::MaterialField`] for a wrong length or an invalid set, naming the
    /// group.
    pub fn from_term_coefficients(
        base: &Model,
        index: Vec<u32>,
        c: &[f64],
    ) -> Result<Self, AssemblyError> {
        let terms = base.term_coefficients().len().max(1);
        let groups = index.iter().max().map_or(0, |m| *m as usize + 1);
        if c.len() != terms * groups {
            let expected = terms * groups;
            return Err(AssemblyError::MaterialField(format!(
                "{} coefficients, expected {expected}",
                c.len()
            )));
        }
        let models = c
            .chunks(terms)
            .enumerate()
            .map(|(g, c)| {
                base.with_term_coefficients(c)
                    .map_err(|e| AssemblyError::MaterialField(format!("group {g}: {e}")))
            })
            .collect::<Result<_, _>>()?;
        Ok(MaterialField::PerElement { models, index })
    }

    /// A model per mesh region (the region tags of the mesh file).
    ///
    /// # Errors
    /// [`AssemblyError::MaterialField`] naming a region of the mesh that has no model.
    pub fn by_region(mesh: &TetMesh, models: &BTreeMap<u32, Model>) -> Result<Self, AssemblyError> {
        let keys: Vec<u32> = models.keys().copied().collect();
        let index = mesh
            .regions()
            .iter()
            .enumerate()
            .map(|(e, r)| {
                keys.binary_search(r).map(|i| i as u32).map_err(|_| {
                    AssemblyError::MaterialField(format!(
                        "element {e} is in region {r}, which has no model"
                    ))
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self::PerElement {
            models: models.values().cloned().collect(),
            index,
        })
    }

    /// Checks the field against a mesh of `num_tets` elements.
    pub(crate) fn validate(&self, num_tets: usize) -> Result<(), AssemblyError> {
        if let Self::PerElement { models, index } = self {
            if index.len() != num_tets {
                return Err(AssemblyError::MaterialField(format!(
                    "{} indices for {num_tets} elements",
                    index.len()
                )));
            }
            if let Some(e) = index.iter().position(|&i| i as usize >= models.len()) {
                return Err(AssemblyError::MaterialField(format!(
                    "element {e} has model index {} but there are {} models",
                    index[e],
                    models.len()
                )));
            }
        }
        Ok(())
    }

    /// The model of element `e`.
    pub fn model(&self, e: usize) -> &Model {
        match self {
            Self::Uniform(m) => m,
            Self::PerElement { models, index } => &models[index[e] as usize],
        }
    }

    /// The largest number of parameter-split terms of any model.
    pub fn max_terms(&self) -> usize {
        use deform_materials::Material;
        match self {
            Self::Uniform(m) => m.num_terms(),
            Self::PerElement { models, .. } => {
                models.iter().map(Material::num_terms).max().unwrap_or(0)
            }
        }
    }
}
