//! A mesh's summary, as `cargo xtask mesh info` prints it: counts, surface, volume, bounding
//! box, element quality, what validation changed and the regions.

use std::fmt;

use crate::TetMesh;
use crate::quality::{Quality, rest_quality};
use crate::topology::{edges, faces};

/// Summary of a mesh ([`MeshInfo::of`]); `Display` prints one labelled line per figure.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct MeshInfo {
    /// Vertices.
    pub vertices: usize,
    /// Tetrahedra.
    pub tets: usize,
    /// Edges.
    pub edges: usize,
    /// Boundary triangles.
    pub boundary_faces: usize,
    /// Faces shared by two tets.
    pub interior_faces: usize,
    /// Faces shared by more than two tets.
    pub nonmanifold_faces: usize,
    /// Bounding box `(lo, hi)`.
    pub bounding_box: ([f64; 3], [f64; 3]),
    /// Rest-shape element quality.
    pub quality: Quality,
    /// Elements reoriented at validation (negatively oriented in the file).
    pub reoriented: usize,
    /// Unreferenced vertices dropped at validation.
    pub dropped_vertices: usize,
    /// `(region tag, name, tets)` in tag order.
    pub regions: Vec<(u32, Option<String>, usize)>,
}

impl MeshInfo {
    /// The summary of `mesh`.
    pub fn of(mesh: &TetMesh) -> Self {
        let f = faces(mesh);
        let (lo, hi) = mesh.bounding_box();
        let report = mesh.build_report();
        let mut tags: Vec<u32> = mesh.regions().to_vec();
        tags.sort_unstable();
        tags.dedup();
        let regions = tags
            .into_iter()
            .map(|r| {
                let count = mesh.regions().iter().filter(|&&x| x == r).count();
                (r, mesh.region_names().get(&r).cloned(), count)
            })
            .collect();
        Self {
            vertices: mesh.num_vertices(),
            tets: mesh.num_tets(),
            edges: edges(mesh).len(),
            boundary_faces: f.boundary.len(),
            interior_faces: f.interior.len(),
            nonmanifold_faces: f.nonmanifold.len(),
            bounding_box: ([lo.x, lo.y, lo.z], [hi.x, hi.y, hi.z]),
            quality: rest_quality(mesh),
            reoriented: report.reoriented,
            dropped_vertices: report.dropped_vertices,
            regions,
        }
    }
}

impl fmt::Display for MeshInfo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let q = &self.quality;
        let (lo, hi) = self.bounding_box;
        writeln!(f, "vertices        {}", self.vertices)?;
        writeln!(f, "tets            {}", self.tets)?;
        writeln!(f, "edges           {}", self.edges)?;
        writeln!(
            f,
            "surface         {} triangles, {} interior faces, {} non-manifold faces",
            self.boundary_faces, self.interior_faces, self.nonmanifold_faces
        )?;
        writeln!(f, "volume          {:.9e}", q.total_volume)?;
        writeln!(
            f,
            "bounding box    [{:.6}, {:.6}, {:.6}] - [{:.6}, {:.6}, {:.6}]",
            lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]
        )?;
        writeln!(
            f,
            "element volume  {:.3e} .. {:.3e}",
            q.min_volume, q.max_volume
        )?;
        writeln!(
            f,
            "dihedral angle  {:.2} .. {:.2} deg",
            q.min_dihedral_deg, q.max_dihedral_deg
        )?;
        writeln!(
            f,
            "aspect ratio    max {:.3}, mean {:.3} (1 = regular)",
            q.max_aspect_ratio, q.mean_aspect_ratio
        )?;
        writeln!(f, "inverted        {}", q.inverted)?;
        writeln!(
            f,
            "reoriented      {} (negatively oriented in the file)",
            self.reoriented
        )?;
        writeln!(
            f,
            "dropped         {} unreferenced vertices",
            self.dropped_vertices
        )?;
        for (r, name, count) in &self.regions {
            let name = name
                .as_ref()
                .map(|n| format!(" \"{n}\""))
                .unwrap_or_default();
            writeln!(f, "region {r}{name:<10} {count} tets")?;
        }
        Ok(())
    }
}
