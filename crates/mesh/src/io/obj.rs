//! Wavefront `.obj` of the boundary surface, for Blender and other surface tools.

use std::io::Write;

use nalgebra::Vector3;

use crate::TetMesh;
use crate::topology::boundary_faces;

/// Writes the outward-oriented boundary triangles at `positions`, with only the surface
/// vertices (renumbered in increasing order of their mesh index, 1-based as OBJ wants).
pub(crate) fn write(
    w: &mut dyn Write,
    mesh: &TetMesh,
    positions: &[Vector3<f64>],
) -> std::io::Result<()> {
    let faces = boundary_faces(mesh);
    let mut local = vec![0usize; mesh.num_vertices()];
    let mut used: Vec<usize> = faces.iter().flatten().copied().collect();
    used.sort_unstable();
    used.dedup();
    writeln!(
        w,
        "# deform-mesh surface: {} vertices, {} triangles",
        used.len(),
        faces.len()
    )?;
    for (k, &i) in used.iter().enumerate() {
        local[i] = k + 1;
        let p = positions[i];
        writeln!(w, "v {:?} {:?} {:?}", p.x, p.y, p.z)?;
    }
    for f in faces {
        writeln!(w, "f {} {} {}", local[f[0]], local[f[1]], local[f[2]])?;
    }
    Ok(())
}
