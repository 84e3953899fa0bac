//! Triangle surfaces: the boundary of a tet mesh, or a surface read from a file, as the
//! obstacles of contact are given.

use nalgebra::Vector3;

use crate::TetMesh;
use crate::topology::boundary_faces;

/// A triangle surface: positions and triangles indexing them (0-based).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Surface {
    /// Vertex positions.
    pub positions: Vec<Vector3<f64>>,
    /// Triangles as indices into `positions`.
    pub triangles: Vec<[usize; 3]>,
}

impl Surface {
    /// The outward-oriented boundary of `mesh` at rest, with only the vertices it uses
    /// (renumbered in increasing order of their mesh index).
    pub fn boundary(mesh: &TetMesh) -> Self {
        let faces = boundary_faces(mesh);
        let mut used: Vec<usize> = faces.iter().flatten().copied().collect();
        used.sort_unstable();
        used.dedup();
        let mut local = vec![usize::MAX; mesh.num_vertices()];
        for (k, &v) in used.iter().enumerate() {
            local[v] = k;
        }
        let rest = mesh.rest_positions();
        Self {
            positions: used.iter().map(|&v| rest[v]).collect(),
            triangles: faces.iter().map(|f| f.map(|v| local[v])).collect(),
        }
    }

    /// The same surface moved by `offset`.
    pub fn translated(mut self, offset: Vector3<f64>) -> Self {
        for p in &mut self.positions {
            *p += offset;
        }
        self
    }

    /// Checks that the surface has a triangle, finite positions, and triangles of three
    /// distinct vertices that exist; the error names the first triangle or vertex that is
    /// not.
    ///
    /// # Errors
    /// A message naming the triangle or vertex (0-based).
    pub fn check(&self) -> Result<(), String> {
        if self.triangles.is_empty() {
            return Err("has no triangle".into());
        }
        if let Some(v) = self
            .positions
            .iter()
            .position(|p| !p.iter().all(|c| c.is_finite()))
        {
            return Err(format!("vertex {v} has a non-finite coordinate"));
        }
        let n = self.positions.len();
        for (i, t) in self.triangles.iter().enumerate() {
            if t.iter().any(|&v| v >= n) {
                return Err(format!(
                    "triangle {i} {t:?} names a vertex beyond the {n} given"
                ));
            }
            if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
                return Err(format!("triangle {i} {t:?} repeats a vertex"));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::generate::BoxGrid;

    #[test]
    fn boundary_of_a_box_is_closed_and_uses_only_surface_vertices() {
        let mesh = BoxGrid::beam(2).build().unwrap();
        let s = Surface::boundary(&mesh);
        s.check().unwrap();
        assert_eq!(
            s.positions.len(),
            crate::topology::surface_vertices(&mesh).len()
        );
        // A closed surface: every edge is shared by exactly two triangles.
        let mut edges = std::collections::HashMap::new();
        for t in &s.triangles {
            for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                *edges.entry((a.min(b), a.max(b))).or_insert(0) += 1;
            }
        }
        assert!(edges.values().all(|&c| c == 2));
        // Outward: the enclosed volume by the divergence theorem is the mesh's.
        let volume: f64 = s
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|v| s.positions[v]);
                a.dot(&b.cross(&c)) / 6.0
            })
            .sum();
        let expected: f64 = mesh.volumes().iter().sum();
        assert!(
            (volume - expected).abs() < 1e-12 * expected.max(1.0),
            "{volume} {expected}"
        );
    }

    #[test]
    fn check_names_what_is_wrong() {
        let p = vec![Vector3::zeros(), Vector3::x(), Vector3::y()];
        let ok = Surface {
            positions: p.clone(),
            triangles: vec![[0, 1, 2]],
        };
        ok.check().unwrap();
        let far = Surface {
            positions: p.clone(),
            triangles: vec![[0, 1, 3]],
        };
        assert!(far.check().unwrap_err().contains("triangle 0"));
        let repeated = Surface {
            positions: p.clone(),
            triangles: vec![[0, 1, 1]],
        };
        assert!(repeated.check().unwrap_err().contains("repeats"));
        let mut nan = ok.clone();
        nan.positions[2].z = f64::NAN;
        assert!(nan.check().unwrap_err().contains("vertex 2"));
        assert!(Surface::default().check().is_err());
    }
}
