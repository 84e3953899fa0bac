//! Lumped and consistent mass of linear tetrahedra.

use crate::TetMesh;
use crate::topology::BlockPattern;

impl TetMesh {
    /// Lumped mass per vertex for a uniform density: each element gives `rho W / 4` to each
    /// of its vertices. The same mass applies to all three degrees of freedom of a vertex.
    pub fn lumped_mass(&self, density: f64) -> Vec<f64> {
        let mut m = vec![0.0; self.num_vertices()];
        for (t, w) in self.tets().iter().zip(self.volumes()) {
            for &i in t {
                m[i] += density * w / 4.0;
            }
        }
        m
    }

    /// Consistent mass on `pattern` (which must be this mesh's [`BlockPattern`]).
    ///
    /// For a linear tetrahedron, `M_ab = rho W (1 + delta_ab) / 20` times the 3x3 identity.
    ///
    /// # Panics
    /// If `pattern` is not the pattern of this mesh.
    #[track_caller]
    pub fn consistent_mass(&self, density: f64, pattern: &BlockPattern) -> ConsistentMass {
        let mut values = vec![0.0; pattern.num_blocks()];
        for (t, w) in self.tets().iter().zip(self.volumes()) {
            for a in 0..4 {
                for b in 0..4 {
                    let k = pattern
                        .find(t[a], t[b])
                        .expect("pattern must be the mesh's own BlockPattern");
                    let factor = if a == b { 2.0 } else { 1.0 };
                    values[k] += density * w * factor / 20.0;
                }
            }
        }
        ConsistentMass { values }
    }
}

/// A consistent mass matrix stored as one scalar per block of a [`BlockPattern`]:
/// block `(i, j)` of the `3N x 3N` matrix is `values[k] * I3`.
#[derive(Debug, Clone, PartialEq)]
pub struct ConsistentMass {
    /// Scalar per block, aligned with the pattern's columns.
    pub values: Vec<f64>,
}

impl ConsistentMass {
    /// `y = M x` for flat `3N` vectors.
    ///
    /// # Panics
    /// If the lengths do not match the pattern.
    #[track_caller]
    pub fn apply(&self, pattern: &BlockPattern, x: &[f64], y: &mut [f64]) {
        let n = pattern.num_rows();
        assert_eq!(x.len(), 3 * n, "x has the wrong length");
        assert_eq!(y.len(), 3 * n, "y has the wrong length");
        for i in 0..n {
            let mut acc = [0.0; 3];
            for k in pattern.offsets()[i]..pattern.offsets()[i + 1] {
                let j = pattern.columns()[k];
                for c in 0..3 {
                    acc[c] += self.values[k] * x[3 * j + c];
                }
            }
            y[3 * i..3 * i + 3].copy_from_slice(&acc);
        }
    }

    /// Row sums: the lumped mass obtained by row-sum lumping (equal to [`TetMesh::lumped_mass`]).
    pub fn row_sums(&self, pattern: &BlockPattern) -> Vec<f64> {
        (0..pattern.num_rows())
            .map(|i| {
                self.values[pattern.offsets()[i]..pattern.offsets()[i + 1]]
                    .iter()
                    .sum()
            })
            .collect()
    }
}
