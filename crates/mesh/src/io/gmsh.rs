//! Gmsh `.msh` files, versions 2.2 and 4.1, ASCII and binary.
//!
//! Files may mix points, lines, triangles and tetrahedra: the 4-node tetrahedra (type 4)
//! are kept, the corner nodes of 10-node tetrahedra (type 11) too, everything else is
//! skipped. A tet's region is its first physical tag (2.2: the first element tag;
//! 4.1: the first physical tag of its volume entity), 0 when it has none.
//! Binary files in either byte order are read. `$PhysicalNames` become region names.

use std::collections::{BTreeMap, HashMap};
use std::io::Write;

use nalgebra::Vector3;

use super::RawMesh;
use super::cursor::{Cursor, Parse, ParseError, show};
use crate::TetMesh;

/// Which `.msh` variant to write.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct MshFormat {
    /// File format version.
    pub version: MshVersion,
    /// Binary (`file-type 1`) instead of ASCII.
    pub binary: bool,
}

/// Gmsh file format version.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MshVersion {
    /// The legacy 2.2 format, still the most widely read.
    V2_2,
    /// The current 4.1 format.
    #[default]
    V4_1,
}

const TET4: i64 = 4;
const TET10: i64 = 11;

/// Nodes per element of the Gmsh element types deform may meet (needed to skip binary blocks).
fn nodes_per_element(kind: i64) -> Option<usize> {
    Some(match kind {
        1 => 2,
        2 => 3,
        3 => 4,
        4 => 4,
        5 => 8,
        6 => 6,
        7 => 5,
        8 => 3,
        9 => 6,
        10 => 9,
        11 => 10,
        12 => 27,
        13 => 18,
        14 => 14,
        15 => 1,
        16 => 8,
        17 => 20,
        18 => 15,
        19 => 13,
        20 => 9,
        21 => 10,
        22 => 12,
        23 => 15,
        24 => 15,
        25 => 21,
        26 => 4,
        27 => 5,
        28 => 6,
        29 => 20,
        30 => 35,
        31 => 56,
        92 => 64,
        93 => 125,
        _ => return None,
    })
}

struct Header {
    version: MshVersion,
    binary: bool,
    size_t: usize,
}

#[derive(Default)]
struct Builder {
    positions: Vec<Vector3<f64>>,
    node_tags: Vec<u64>,
    node_index: HashMap<u64, usize>,
    tets: Vec<[usize; 4]>,
    regions: Vec<u32>,
    element_tags: Vec<u64>,
    names: BTreeMap<u32, String>,
    /// 4.1: physical tag of each volume entity.
    volume_physical: HashMap<i64, u32>,
}

impl Builder {
    fn node(&mut self, tag: u64, p: Vector3<f64>, at: usize) -> Parse<()> {
        if self.node_index.insert(tag, self.positions.len()).is_some() {
            return Err(ParseError::expected(
                at,
                "a unique node tag",
                format!("node {tag} defined twice"),
            ));
        }
        self.positions.push(p);
        self.node_tags.push(tag);
        Ok(())
    }

    fn tet(&mut self, tag: u64, nodes: &[u64], region: u32, at: usize) -> Parse<()> {
        let mut t = [0usize; 4];
        for (slot, node) in t.iter_mut().zip(nodes) {
            *slot = *self.node_index.get(node).ok_or_else(|| {
                ParseError::expected(
                    at,
                    "a node tag defined in $Nodes",
                    format!("element {tag} uses undefined node {node}"),
                )
            })?;
        }
        self.tets.push(t);
        self.regions.push(region);
        self.element_tags.push(tag);
        Ok(())
    }

    /// Orders the tets by their element tag (4.1 files group them by entity), so that
    /// the same mesh reads the same from every variant.
    fn finish(self) -> RawMesh {
        let mut order: Vec<usize> = (0..self.tets.len()).collect();
        order.sort_by_key(|&k| self.element_tags[k]);
        RawMesh {
            positions: self.positions,
            tets: order.iter().map(|&k| self.tets[k]).collect(),
            regions: order.iter().map(|&k| self.regions[k]).collect(),
            region_names: self.names,
            node_tags: self.node_tags,
            element_tags: order.iter().map(|&k| self.element_tags[k]).collect(),
        }
    }
}

fn region(tag: i64, at: usize) -> Parse<u32> {
    u32::try_from(tag)
        .map_err(|_| ParseError::expected(at, "a physical tag in 0..2^32", tag.to_string()))
}

/// Parses a whole `.msh` file.
pub(crate) fn parse(data: &[u8]) -> Parse<RawMesh> {
    let mut c = Cursor::new(data, None);
    let header = parse_header(&mut c)?;
    let mut b = Builder::default();
    let mut seen_nodes = false;
    while let Some(tok) = c.peek_token() {
        let at = c.here();
        let name = tok.to_vec();
        c.token("section")?;
        match name.as_slice() {
            b"$PhysicalNames" => parse_names(&mut c, &mut b)?,
            b"$Entities" if header.version == MshVersion::V4_1 => {
                if header.binary {
                    c.end_of_line()?;
                }
                parse_entities(&mut c, &header, &mut b)?;
                c.keyword("$EndEntities")?;
            }
            b"$Nodes" => {
                if header.binary && header.version == MshVersion::V4_1 {
                    c.end_of_line()?;
                }
                match header.version {
                    MshVersion::V2_2 => parse_nodes_22(&mut c, &header, &mut b)?,
                    MshVersion::V4_1 => parse_nodes_41(&mut c, &header, &mut b)?,
                }
                c.keyword("$EndNodes")?;
                seen_nodes = true;
            }
            b"$Elements" => {
                if !seen_nodes {
                    return Err(ParseError::expected(
                        at,
                        "$Nodes before $Elements",
                        "$Elements",
                    ));
                }
                if header.binary && header.version == MshVersion::V4_1 {
                    c.end_of_line()?;
                }
                match header.version {
                    MshVersion::V2_2 => parse_elements_22(&mut c, &header, &mut b)?,
                    MshVersion::V4_1 => parse_elements_41(&mut c, &header, &mut b)?,
                }
                c.keyword("$EndElements")?;
            }
            [b'$', rest @ ..] if !rest.starts_with(b"End") => {
                let end = format!("$End{}", String::from_utf8_lossy(rest));
                c.skip_to(&end)?;
            }
            _ => return Err(ParseError::expected(at, "a `$Section`", show(&name))),
        }
    }
    if !seen_nodes {
        return Err(ParseError::expected(
            data.len(),
            "a $Nodes section",
            "end of file",
        ));
    }
    Ok(b.finish())
}

fn parse_header(c: &mut Cursor) -> Parse<Header> {
    c.keyword("$MeshFormat")?;
    let at = c.here();
    let v: String = c.parse("format version")?;
    let version = match v.as_str() {
        "2" | "2.0" | "2.1" | "2.2" => MshVersion::V2_2,
        "4.1" => MshVersion::V4_1,
        other => {
            return Err(ParseError::unsupported(
                at,
                format!(
                    "MSH version {other} (deform reads 2.2 and 4.1; re-export with gmsh -format msh41)"
                ),
            ));
        }
    };
    let file_type: u8 = c.parse("file-type 0 (ASCII) or 1 (binary)")?;
    let at = c.here();
    let size_t: usize = c.parse("data-size")?;
    if file_type > 1 {
        return Err(ParseError::expected(
            at,
            "file-type 0 or 1",
            file_type.to_string(),
        ));
    }
    let binary = file_type == 1;
    if !(size_t == 8 || (size_t == 4 && version == MshVersion::V4_1)) {
        return Err(ParseError::unsupported(at, format!("data-size {size_t}")));
    }
    if binary {
        c.end_of_line()?;
        let at = c.offset();
        let one = c.bytes(4, "the binary integer 1")?;
        c.swap = match one {
            [1, 0, 0, 0] => false,
            [0, 0, 0, 1] => true,
            _ => {
                return Err(ParseError::expected(
                    at,
                    "the binary integer 1",
                    format!("{one:?}"),
                ));
            }
        };
    }
    c.keyword("$EndMeshFormat")?;
    Ok(Header {
        version,
        binary,
        size_t,
    })
}

fn parse_names(c: &mut Cursor, b: &mut Builder) -> Parse<()> {
    let n: usize = c.parse("number of physical names")?;
    c.line();
    for _ in 0..n {
        let at = c.here();
        let dim: u8 = c.parse("physical dimension")?;
        let tag: i64 = c.parse("physical tag")?;
        let rest = String::from_utf8_lossy(c.line()).trim().to_owned();
        let name = rest
            .strip_prefix('"')
            .and_then(|s| s.strip_suffix('"'))
            .ok_or_else(|| ParseError::expected(at, "a quoted name", rest.clone()))?;
        if dim == 3 {
            b.names.insert(region(tag, at)?, name.to_owned());
        }
    }
    c.keyword("$EndPhysicalNames")
}

/// Volume element types other than the linear and quadratic tetrahedron (whose corners
/// deform keeps): a mesh with them would lose part of its volume without a word.
fn other_volume(kind: i64) -> bool {
    matches!(kind, 5..=7 | 12..=14 | 17..=19 | 29..=31 | 92 | 93)
}

/// The refusal of a non-tetrahedral volume element.
fn not_a_tet(at: usize, kind: i64) -> ParseError {
    ParseError::unsupported(
        at,
        format!(
            "volume element of Gmsh type {kind} (hexahedron, prism, pyramid or high-order tetrahedron): deform simulates linear tetrahedra, so mesh the volume with tetrahedra"
        ),
    )
}

/// The header's total against the sum of the blocks (4.1).
fn check_total(at: usize, header: usize, blocks: usize, what: &str) -> Parse<()> {
    if header == blocks {
        return Ok(());
    }
    Err(ParseError::expected(
        at,
        format!("{header} {what} (the header's total)"),
        format!("{blocks} in the blocks"),
    ))
}

/// Reads a count, either an ASCII token or a binary `size_t`.
fn count(c: &mut Cursor, h: &Header, what: &str) -> Parse<u64> {
    if h.binary {
        c.unsigned(h.size_t, what)
    } else {
        c.parse(what)
    }
}

fn int(c: &mut Cursor, h: &Header, what: &str) -> Parse<i64> {
    if h.binary {
        c.i32(what).map(i64::from)
    } else {
        c.parse(what)
    }
}

fn real(c: &mut Cursor, h: &Header, what: &str) -> Parse<f64> {
    if h.binary { c.f64(what) } else { c.parse(what) }
}

/// Rejects counts that the remaining bytes cannot possibly hold (hostile sizes).
fn plausible(c: &Cursor, n: u64, min_bytes_each: usize, what: &str) -> Parse<usize> {
    let n_usize = usize::try_from(n).unwrap_or(usize::MAX);
    if n_usize.saturating_mul(min_bytes_each) > c.remaining() {
        return Err(ParseError::expected(
            c.offset(),
            format!("{what} that fit in the file"),
            format!("a count of {n} with {} bytes left", c.remaining()),
        ));
    }
    Ok(n_usize)
}

fn parse_entities(c: &mut Cursor, h: &Header, b: &mut Builder) -> Parse<()> {
    let mut counts = [0usize; 4];
    for (d, slot) in counts.iter_mut().enumerate() {
        let n = count(c, h, "entity count")?;
        *slot = plausible(c, n, 2, if d == 0 { "points" } else { "entities" })?;
    }
    for (dim, &n) in counts.iter().enumerate() {
        for _ in 0..n {
            let tag = int(c, h, "entity tag")?;
            let coords = if dim == 0 { 3 } else { 6 };
            for _ in 0..coords {
                real(c, h, "entity bounding coordinate")?;
            }
            let at = c.offset();
            let nphys = count(c, h, "number of physical tags")?;
            let nphys = plausible(c, nphys, 1, "physical tags")?;
            let mut first = None;
            for _ in 0..nphys {
                let p = int(c, h, "physical tag")?;
                first.get_or_insert(p);
            }
            if dim == 3
                && let Some(p) = first
            {
                b.volume_physical.insert(tag, region(p, at)?);
            }
            if dim > 0 {
                let nb = count(c, h, "number of bounding entities")?;
                let nb = plausible(c, nb, 1, "bounding entities")?;
                for _ in 0..nb {
                    int(c, h, "bounding entity tag")?;
                }
            }
        }
    }
    Ok(())
}

fn parse_nodes_22(c: &mut Cursor, h: &Header, b: &mut Builder) -> Parse<()> {
    let n: u64 = c.parse("number of nodes")?;
    if h.binary {
        c.end_of_line()?;
    }
    let n = plausible(c, n, if h.binary { 28 } else { 8 }, "nodes")?;
    b.positions.reserve(n);
    for _ in 0..n {
        let at = c.offset();
        let tag = if h.binary {
            let t = c.i32("node tag")?;
            u64::try_from(t)
                .map_err(|_| ParseError::expected(at, "a positive node tag", t.to_string()))?
        } else {
            c.parse("node tag")?
        };
        let p = Vector3::new(real(c, h, "x")?, real(c, h, "y")?, real(c, h, "z")?);
        b.node(tag, p, at)?;
    }
    Ok(())
}

fn parse_nodes_41(c: &mut Cursor, h: &Header, b: &mut Builder) -> Parse<()> {
    let blocks = count(c, h, "number of node blocks")?;
    let blocks = plausible(c, blocks, 4, "node blocks")?;
    let total_at = c.offset();
    let n = count(c, h, "number of nodes")?;
    let n = plausible(c, n, 8, "nodes")?;
    let mut in_blocks = 0usize;
    count(c, h, "minimum node tag")?;
    count(c, h, "maximum node tag")?;
    b.positions.reserve(n);
    for _ in 0..blocks {
        let dim = int(c, h, "entity dimension")?;
        int(c, h, "entity tag")?;
        let at = c.offset();
        let parametric = int(c, h, "parametric flag")?;
        let extra = match parametric {
            0 => 0,
            1 => usize::try_from(dim).unwrap_or(0).min(3),
            other => {
                return Err(ParseError::expected(
                    at,
                    "parametric flag 0 or 1",
                    other.to_string(),
                ));
            }
        };
        let m = count(c, h, "nodes in block")?;
        let m = plausible(c, m, 8, "nodes in block")?;
        in_blocks = in_blocks.saturating_add(m);
        let tags_at = c.offset();
        let mut tags = Vec::with_capacity(m);
        for _ in 0..m {
            tags.push(count(c, h, "node tag")?);
        }
        for tag in tags {
            let at = if h.binary { tags_at } else { c.offset() };
            let p = Vector3::new(real(c, h, "x")?, real(c, h, "y")?, real(c, h, "z")?);
            for _ in 0..extra {
                real(c, h, "parametric coordinate")?;
            }
            b.node(tag, p, at)?;
        }
    }
    check_total(total_at, n, in_blocks, "nodes")
}

fn parse_elements_22(c: &mut Cursor, h: &Header, b: &mut Builder) -> Parse<()> {
    let n: u64 = c.parse("number of elements")?;
    let n = plausible(c, n, if h.binary { 12 } else { 6 }, "elements")?;
    if !h.binary {
        let mut nodes = Vec::new();
        for _ in 0..n {
            let at = c.here();
            let tag: u64 = c.parse("element tag")?;
            let kind: i64 = c.parse("element type")?;
            let ntags: usize = c.parse("number of element tags")?;
            let mut first_tag = 0;
            for k in 0..ntags {
                let t: i64 = c.parse("element tag value")?;
                if k == 0 {
                    first_tag = t;
                }
            }
            match nodes_per_element(kind) {
                Some(np) if kind == TET4 || kind == TET10 => {
                    nodes.clear();
                    for _ in 0..np {
                        nodes.push(c.parse::<u64>("node tag of the element")?);
                    }
                    b.tet(tag, &nodes[..4], region(first_tag, at)?, at)?;
                }
                _ if other_volume(kind) => return Err(not_a_tet(at, kind)),
                _ => {
                    c.line();
                }
            }
        }
        return Ok(());
    }
    c.end_of_line()?;
    let mut read = 0usize;
    let mut nodes = Vec::new();
    while read < n {
        let at = c.offset();
        let kind = i64::from(c.i32("element type")?);
        let follow = c.i32("number of elements following")?;
        let ntags = c.i32("number of tags")?;
        let (Ok(follow), Ok(ntags)) = (usize::try_from(follow), usize::try_from(ntags)) else {
            return Err(ParseError::expected(
                at,
                "non-negative element block counts",
                format!("{follow}, {ntags}"),
            ));
        };
        let np = nodes_per_element(kind)
            .ok_or_else(|| ParseError::unsupported(at, format!("binary element type {kind}")))?;
        if other_volume(kind) {
            return Err(not_a_tet(at, kind));
        }
        if follow == 0 || follow > n - read {
            return Err(ParseError::expected(
                at,
                format!("between 1 and {} elements in the block", n - read),
                follow.to_string(),
            ));
        }
        plausible(c, follow as u64, 4 * (1 + ntags + np), "elements in block")?;
        for _ in 0..follow {
            let at = c.offset();
            let tag = c.i32("element tag")?;
            let mut first_tag = 0;
            for k in 0..ntags {
                let t = c.i32("element tag value")?;
                if k == 0 {
                    first_tag = i64::from(t);
                }
            }
            nodes.clear();
            for _ in 0..np {
                let v = c.i32("node tag of the element")?;
                nodes.push(u64::try_from(v).unwrap_or(u64::MAX));
            }
            if kind == TET4 || kind == TET10 {
                let tag = u64::try_from(tag).unwrap_or(u64::MAX);
                b.tet(tag, &nodes[..4], region(first_tag, at)?, at)?;
            }
        }
        read += follow;
    }
    Ok(())
}

fn parse_elements_41(c: &mut Cursor, h: &Header, b: &mut Builder) -> Parse<()> {
    let blocks = count(c, h, "number of element blocks")?;
    let blocks = plausible(c, blocks, 4, "element blocks")?;
    let total_at = c.offset();
    let n = count(c, h, "number of elements")?;
    let n = plausible(c, n, 4, "elements")?;
    let mut in_blocks = 0usize;
    count(c, h, "minimum element tag")?;
    count(c, h, "maximum element tag")?;
    let mut nodes = Vec::new();
    for _ in 0..blocks {
        let dim = int(c, h, "entity dimension")?;
        let entity = int(c, h, "entity tag")?;
        let at = c.offset();
        let kind = int(c, h, "element type")?;
        let m = count(c, h, "elements in block")?;
        let m = plausible(c, m, 4, "elements in block")?;
        in_blocks = in_blocks.saturating_add(m);
        let reg = b.volume_physical.get(&entity).copied().unwrap_or(0);
        let keep = kind == TET4 || kind == TET10;
        if dim == 3 && !keep && m > 0 {
            return Err(not_a_tet(at, kind));
        }
        match nodes_per_element(kind) {
            Some(np) => {
                for _ in 0..m {
                    let at = c.offset();
                    let tag = count(c, h, "element tag")?;
                    nodes.clear();
                    for _ in 0..np {
                        nodes.push(count(c, h, "node tag of the element")?);
                    }
                    if keep {
                        b.tet(tag, &nodes[..4], reg, at)?;
                    }
                }
            }
            None if !h.binary => {
                c.line();
                for _ in 0..m {
                    c.line();
                }
            }
            None => {
                return Err(ParseError::unsupported(
                    at,
                    format!("binary element type {kind}"),
                ));
            }
        }
    }
    check_total(total_at, n, in_blocks, "elements")
}

/// Writes `mesh` as `.msh` in `format`. Regions become physical groups (4.1: one volume
/// entity per region), with their names when the mesh has them.
pub(crate) fn write(w: &mut dyn Write, mesh: &TetMesh, format: MshFormat) -> std::io::Result<()> {
    let bin = format.binary;
    let version = match format.version {
        MshVersion::V2_2 => "2.2",
        MshVersion::V4_1 => "4.1",
    };
    writeln!(w, "$MeshFormat\n{version} {} 8", u8::from(bin))?;
    if bin {
        w.write_all(&1i32.to_le_bytes())?;
        writeln!(w)?;
    }
    writeln!(w, "$EndMeshFormat")?;
    let mut regions: Vec<u32> = mesh.regions().to_vec();
    regions.sort_unstable();
    regions.dedup();
    if !mesh.region_names().is_empty() {
        writeln!(w, "$PhysicalNames\n{}", mesh.region_names().len())?;
        for (tag, name) in mesh.region_names() {
            writeln!(w, "3 {tag} \"{name}\"")?;
        }
        writeln!(w, "$EndPhysicalNames")?;
    }
    match format.version {
        MshVersion::V2_2 => write_v22(w, mesh, bin, &regions),
        MshVersion::V4_1 => write_v41(w, mesh, bin, &regions),
    }
}

/// The `$Nodes` and `$Elements` blocks of format 2.2.
fn write_v22(w: &mut dyn Write, mesh: &TetMesh, bin: bool, regions: &[u32]) -> std::io::Result<()> {
    // Elementary entity of a region: its position in the sorted region list, from 1.
    let entity = |r: u32| regions.binary_search(&r).map_or(1, |k| k as i32 + 1);
    let nv = mesh.num_vertices();
    let ne = mesh.num_tets();
    writeln!(w, "$Nodes\n{nv}")?;
    for (i, p) in mesh.rest_positions().iter().enumerate() {
        if bin {
            w.write_all(&(i as i32 + 1).to_le_bytes())?;
            for c in p.iter() {
                w.write_all(&c.to_le_bytes())?;
            }
        } else {
            writeln!(w, "{} {:?} {:?} {:?}", i + 1, p.x, p.y, p.z)?;
        }
    }
    if bin {
        writeln!(w)?;
    }
    writeln!(w, "$EndNodes\n$Elements\n{ne}")?;
    if bin {
        for v in [4i32, ne as i32, 2] {
            w.write_all(&v.to_le_bytes())?;
        }
    }
    for (e, (t, r)) in mesh.tets().iter().zip(mesh.regions()).enumerate() {
        if bin {
            let vals = [e as i32 + 1, *r as i32, entity(*r)];
            for v in vals.into_iter().chain(t.iter().map(|&i| i as i32 + 1)) {
                w.write_all(&v.to_le_bytes())?;
            }
        } else {
            writeln!(
                w,
                "{} 4 2 {} {} {} {} {} {}",
                e + 1,
                r,
                entity(*r),
                t[0] + 1,
                t[1] + 1,
                t[2] + 1,
                t[3] + 1
            )?;
        }
    }
    if bin {
        writeln!(w)?;
    }
    writeln!(w, "$EndElements")?;
    Ok(())
}

/// The `$Entities`, `$Nodes` and `$Elements` blocks of format 4.1.
fn write_v41(w: &mut dyn Write, mesh: &TetMesh, bin: bool, regions: &[u32]) -> std::io::Result<()> {
    // Elementary entity of a region: its position in the sorted region list, from 1.
    let entity = |r: u32| regions.binary_search(&r).map_or(1, |k| k as i32 + 1);
    let nv = mesh.num_vertices();
    let ne = mesh.num_tets();
    let sz = |v: usize, w: &mut dyn Write| -> std::io::Result<()> {
        if bin {
            w.write_all(&(v as u64).to_le_bytes())
        } else {
            write!(w, "{v} ")
        }
    };
    let int = |v: i32, w: &mut dyn Write| -> std::io::Result<()> {
        if bin {
            w.write_all(&v.to_le_bytes())
        } else {
            write!(w, "{v} ")
        }
    };
    let end = |w: &mut dyn Write| -> std::io::Result<()> { if bin { Ok(()) } else { writeln!(w) } };
    writeln!(w, "$Entities")?;
    for v in [0, 0, 0, regions.len()] {
        sz(v, w)?;
    }
    end(w)?;
    let (lo, hi) = mesh.bounding_box();
    for &r in regions {
        int(entity(r), w)?;
        for c in lo.iter().chain(hi.iter()) {
            if bin {
                w.write_all(&c.to_le_bytes())?
            } else {
                write!(w, "{c:?} ")?
            }
        }
        sz(usize::from(r > 0), w)?;
        if r > 0 {
            int(r as i32, w)?;
        }
        sz(0, w)?;
        end(w)?;
    }
    if bin {
        writeln!(w)?;
    }
    writeln!(w, "$EndEntities\n$Nodes")?;
    for v in [1, nv, 1, nv] {
        sz(v, w)?;
    }
    end(w)?;
    let first_entity = entity(regions.first().copied().unwrap_or(1));
    for v in [3, first_entity, 0] {
        int(v, w)?;
    }
    sz(nv, w)?;
    end(w)?;
    for i in 0..nv {
        sz(i + 1, w)?;
        end(w)?;
    }
    for p in mesh.rest_positions() {
        for c in p.iter() {
            if bin {
                w.write_all(&c.to_le_bytes())?
            } else {
                write!(w, "{c:?} ")?
            }
        }
        end(w)?;
    }
    if bin {
        writeln!(w)?;
    }
    writeln!(w, "$EndNodes\n$Elements")?;
    for v in [regions.len(), ne, 1, ne] {
        sz(v, w)?;
    }
    end(w)?;
    for &r in regions {
        let members: Vec<usize> = (0..ne).filter(|&e| mesh.regions()[e] == r).collect();
        for v in [3, entity(r), 4] {
            int(v, w)?;
        }
        sz(members.len(), w)?;
        end(w)?;
        for e in members {
            sz(e + 1, w)?;
            for &i in &mesh.tets()[e] {
                sz(i + 1, w)?;
            }
            end(w)?;
        }
    }
    if bin {
        writeln!(w)?;
    }
    writeln!(w, "$EndElements")?;
    Ok(())
}
