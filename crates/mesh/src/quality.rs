//! Element quality statistics, for a rest mesh or any deformed configuration.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::TetMesh;
use crate::topology::TET_FACES;

/// Summary statistics of element quality.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct Quality {
    /// Smallest dihedral angle over all elements, degrees (70.53 for a regular tet).
    pub min_dihedral_deg: f64,
    /// Largest dihedral angle, degrees.
    pub max_dihedral_deg: f64,
    /// Largest aspect ratio `L_max / (2 sqrt(6) r_in)` (1 for a regular tet, grows without bound for slivers).
    pub max_aspect_ratio: f64,
    /// Mean aspect ratio.
    pub mean_aspect_ratio: f64,
    /// Smallest signed element volume.
    pub min_volume: f64,
    /// Largest signed element volume.
    pub max_volume: f64,
    /// Sum of signed volumes.
    pub total_volume: f64,
    /// Elements with signed volume `<= 0` (inverted or flat).
    pub inverted: usize,
}

/// Quality of the rest configuration.
pub fn rest_quality(mesh: &TetMesh) -> Quality {
    quality(mesh, mesh.rest_positions())
}

/// Quality of `mesh`'s connectivity at `positions` (one per vertex).
///
/// # Panics
/// If `positions` has fewer entries than the mesh has vertices.
#[track_caller]
pub fn quality(mesh: &TetMesh, positions: &[Vector3<f64>]) -> Quality {
    assert!(
        positions.len() >= mesh.num_vertices(),
        "one position per vertex"
    );
    let mut q = Quality {
        min_dihedral_deg: f64::INFINITY,
        max_dihedral_deg: f64::NEG_INFINITY,
        max_aspect_ratio: 0.0,
        mean_aspect_ratio: 0.0,
        min_volume: f64::INFINITY,
        max_volume: f64::NEG_INFINITY,
        total_volume: 0.0,
        inverted: 0,
    };
    let mut aspect_sum = 0.0;
    for t in mesh.tets() {
        let p = t.map(|i| positions[i]);
        let volume = (p[1] - p[0]).cross(&(p[2] - p[0])).dot(&(p[3] - p[0])) / 6.0;
        q.min_volume = q.min_volume.min(volume);
        q.max_volume = q.max_volume.max(volume);
        q.total_volume += volume;
        if !(volume > 0.0) {
            q.inverted += 1;
        }
        // Area-weighted outward normals of the four faces (outward for positive volume).
        let normals = TET_FACES.map(|f| (p[f[1]] - p[f[0]]).cross(&(p[f[2]] - p[f[0]])));
        let area_sum: f64 = normals.iter().map(|n| n.norm() / 2.0).sum();
        for i in 0..4 {
            for j in i + 1..4 {
                let (a, b) = (normals[i], normals[j]);
                let cos = (a.dot(&b) / (a.norm() * b.norm())).clamp(-1.0, 1.0);
                let angle = 180.0 - cos.acos().to_degrees();
                if angle.is_finite() {
                    q.min_dihedral_deg = q.min_dihedral_deg.min(angle);
                    q.max_dihedral_deg = q.max_dihedral_deg.max(angle);
                }
            }
        }
        let longest = crate::mesh::longest_edge(positions, t);
        let inradius = 3.0 * volume.abs() / area_sum;
        let aspect = longest / (2.0 * 6f64.sqrt() * inradius);
        let aspect = if aspect.is_finite() {
            aspect
        } else {
            f64::INFINITY
        };
        q.max_aspect_ratio = q.max_aspect_ratio.max(aspect);
        aspect_sum += aspect;
    }
    q.mean_aspect_ratio = aspect_sum / mesh.num_tets() as f64;
    q
}
