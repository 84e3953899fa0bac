//! TetGen `.node` / `.ele` pairs.
//!
//! `.node`: `<points> <dimension = 3> <attributes> <boundary markers 0|1>`, then one line
//! per point `<index> <x> <y> <z> [attributes] [marker]`. `.ele`: `<tets> <nodes per tet = 4|10>
//! <attributes>`, then `<index> <n1> ... [attributes]`. `#` starts a comment. Numbering
//! starts at 0 or 1, as the first point says; indices must be consecutive. The first
//! element attribute (TetGen's region attribute) becomes the region tag; of 10-node
//! tets the four corners are kept.

use std::io::Write;

use nalgebra::Vector3;

use super::RawMesh;
use super::cursor::{Cursor, Parse, ParseError, show};
use crate::TetMesh;

/// Parses a `.node` file: positions, and the index base (0 or 1).
pub(crate) fn parse_node(data: &[u8]) -> Parse<(Vec<Vector3<f64>>, u64)> {
    let mut c = Cursor::new(data, Some(b'#'));
    let n: u64 = c.parse("number of points")?;
    let at = c.here();
    let dim: u32 = c.parse("dimension")?;
    if dim != 3 {
        return Err(ParseError::expected(at, "dimension 3", dim.to_string()));
    }
    let attributes: usize = c.parse("number of point attributes")?;
    let at = c.here();
    let markers: u8 = c.parse("boundary marker flag")?;
    if markers > 1 {
        return Err(ParseError::expected(
            at,
            "boundary marker flag 0 or 1",
            markers.to_string(),
        ));
    }
    let per_line = 4usize
        .saturating_add(attributes)
        .saturating_add(usize::from(markers));
    let n = usize::try_from(n).unwrap_or(usize::MAX);
    if n.saturating_mul(per_line) > c.remaining() {
        return Err(ParseError::expected(
            c.offset(),
            format!("{n} points"),
            "a shorter file",
        ));
    }
    let mut positions = Vec::with_capacity(n);
    let mut base = 0;
    for i in 0..n {
        let at = c.here();
        let index: u64 = c.parse("point index")?;
        if i == 0 {
            if index > 1 {
                return Err(ParseError::expected(
                    at,
                    "first point index 0 or 1",
                    index.to_string(),
                ));
            }
            base = index;
        } else if index != base + i as u64 {
            return Err(ParseError::expected(
                at,
                format!("point index {}", base + i as u64),
                index.to_string(),
            ));
        }
        positions.push(Vector3::new(c.parse("x")?, c.parse("y")?, c.parse("z")?));
        for _ in 0..attributes + usize::from(markers) {
            c.parse::<f64>("point attribute or marker")?;
        }
    }
    end_after(&mut c, n, "points")?;
    Ok((positions, base))
}

/// Refuses lines after the header's count of records: a header that undercounts would
/// otherwise drop the rest silently.
fn end_after(c: &mut Cursor, n: usize, what: &str) -> Parse<()> {
    match c.peek_token() {
        None => Ok(()),
        Some(t) => Err(ParseError::expected(
            c.here(),
            format!("end of file after the header's {n} {what}"),
            show(t),
        )),
    }
}

/// Parses an `.ele` file against a point numbering starting at `base`.
/// Returns tets (0-based), regions and file element indices.
/// Tets (0-based), region per tet, and the file's element index per tet.
type Elements = (Vec<[usize; 4]>, Vec<u32>, Vec<u64>);

pub(crate) fn parse_ele(data: &[u8], base: u64) -> Parse<Elements> {
    let mut c = Cursor::new(data, Some(b'#'));
    let n: u64 = c.parse("number of tetrahedra")?;
    let at = c.here();
    let per: usize = c.parse("nodes per tetrahedron")?;
    if per != 4 && per != 10 {
        return Err(ParseError::expected(
            at,
            "4 or 10 nodes per tetrahedron",
            per.to_string(),
        ));
    }
    let attributes: usize = c.parse("number of element attributes")?;
    let n = usize::try_from(n).unwrap_or(usize::MAX);
    if n.saturating_mul(2 * (1 + per + attributes.min(1 << 20))) > c.remaining() {
        return Err(ParseError::expected(
            c.offset(),
            format!("{n} tetrahedra"),
            "a shorter file",
        ));
    }
    let (mut tets, mut regions, mut ids) = (
        Vec::with_capacity(n),
        Vec::with_capacity(n),
        Vec::with_capacity(n),
    );
    for _ in 0..n {
        let id: u64 = c.parse("tetrahedron index")?;
        let mut t = [0usize; 4];
        for k in 0..per {
            let at = c.here();
            let v: u64 = c.parse("node index")?;
            let v0 = v.checked_sub(base).ok_or_else(|| {
                ParseError::expected(at, format!("a node index >= {base}"), v.to_string())
            })?;
            if k < 4 {
                t[k] = usize::try_from(v0).unwrap_or(usize::MAX);
            }
        }
        let mut region = 0;
        for k in 0..attributes {
            let at = c.here();
            let a: f64 = c.parse("element attribute")?;
            if k == 0 {
                if !(a >= 0.0 && a <= f64::from(u32::MAX) && a.fract() == 0.0) {
                    return Err(ParseError::expected(
                        at,
                        "a non-negative integer region attribute",
                        a.to_string(),
                    ));
                }
                region = a as u32;
            }
        }
        tets.push(t);
        regions.push(region);
        ids.push(id);
    }
    end_after(&mut c, n, "tetrahedra")?;
    Ok((tets, regions, ids))
}

pub(crate) fn parse(node: &[u8], ele: &[u8]) -> Result<RawMesh, (bool, ParseError)> {
    let (positions, base) = parse_node(node).map_err(|e| (true, e))?;
    let (tets, regions, element_tags) = parse_ele(ele, base).map_err(|e| (false, e))?;
    let node_tags = (0..positions.len() as u64).map(|i| i + base).collect();
    Ok(RawMesh {
        positions,
        tets,
        regions,
        region_names: Default::default(),
        node_tags,
        element_tags,
    })
}

pub(crate) fn write_node(w: &mut dyn Write, mesh: &TetMesh) -> std::io::Result<()> {
    writeln!(w, "# written by deform-mesh\n{} 3 0 0", mesh.num_vertices())?;
    for (i, p) in mesh.rest_positions().iter().enumerate() {
        writeln!(w, "{i} {:?} {:?} {:?}", p.x, p.y, p.z)?;
    }
    Ok(())
}

pub(crate) fn write_ele(w: &mut dyn Write, mesh: &TetMesh) -> std::io::Result<()> {
    writeln!(w, "# written by deform-mesh\n{} 4 1", mesh.num_tets())?;
    for (e, (t, r)) in mesh.tets().iter().zip(mesh.regions()).enumerate() {
        writeln!(w, "{e} {} {} {} {} {r}", t[0], t[1], t[2], t[3])?;
    }
    Ok(())
}
