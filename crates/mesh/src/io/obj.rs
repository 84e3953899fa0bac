//! Wavefront `.obj` surfaces: the boundary surface written for Blender and other surface
//! tools, and surfaces read as contact obstacles.

use std::io::Write;

use nalgebra::Vector3;

use super::cursor::{Cursor, Parse, ParseError, show};
use crate::topology::boundary_faces;
use crate::{Surface, TetMesh};

/// Parses the vertices (`v x y z [w]`) and faces (`f`, each corner `i`, `i/t`, `i//n` or
/// `i/t/n`, 1-based or negative from the end) of an `.obj` file; polygons become fans of
/// triangles. Everything else (normals, texture coordinates, groups, materials, lines) is
/// skipped.
pub(crate) fn parse(data: &[u8]) -> Parse<Surface> {
    let mut c = Cursor::new(data, None);
    let mut s = Surface::default();
    while c.remaining() > 0 {
        let start = c.offset();
        let line = c.line();
        let line = line.split(|&b| b == b'#').next().unwrap_or_default();
        let mut tokens = line
            .split(|b| b.is_ascii_whitespace())
            .filter(|t| !t.is_empty());
        match tokens.next() {
            Some(b"v") => {
                let mut p = Vector3::zeros();
                for k in 0..3 {
                    let t = tokens.next().unwrap_or_default();
                    p[k] = std::str::from_utf8(t)
                        .ok()
                        .and_then(|t| t.parse::<f64>().ok())
                        .filter(|v| v.is_finite())
                        .ok_or_else(|| {
                            ParseError::expected(start, "a finite vertex coordinate", show(t))
                        })?;
                }
                s.positions.push(p);
            }
            Some(b"f") => {
                let corners = tokens
                    .map(|t| corner(t, s.positions.len(), start))
                    .collect::<Parse<Vec<usize>>>()?;
                if corners.len() < 3 {
                    return Err(ParseError::expected(
                        start,
                        "a face of at least 3 vertices",
                        format!("{} vertices", corners.len()),
                    ));
                }
                let mut distinct = corners.clone();
                distinct.sort_unstable();
                distinct.dedup();
                if distinct.len() < corners.len() {
                    return Err(ParseError::expected(
                        start,
                        "a face of distinct vertices",
                        show(line),
                    ));
                }
                for k in 1..corners.len() - 1 {
                    s.triangles.push([corners[0], corners[k], corners[k + 1]]);
                }
            }
            _ => {}
        }
    }
    Ok(s)
}

/// A face corner's vertex, 0-based, from its 1-based or negative (relative) index among the
/// `defined` vertices so far.
fn corner(token: &[u8], defined: usize, at: usize) -> Parse<usize> {
    let index = token.split(|&b| b == b'/').next().unwrap_or_default();
    let bad = || ParseError::expected(at, format!("a vertex index in 1..={defined}"), show(token));
    let i: i64 = std::str::from_utf8(index)
        .ok()
        .and_then(|t| t.parse().ok())
        .ok_or_else(bad)?;
    let resolved = if i < 0 { defined as i64 + i } else { i - 1 };
    usize::try_from(resolved)
        .ok()
        .filter(|&v| v < defined)
        .ok_or_else(bad)
}

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
