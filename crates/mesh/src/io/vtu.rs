//! VTK XML unstructured grids (`.vtu`) and `.pvd` time-series collections for ParaView.
//!
//! Arrays are written in VTK's inline `binary` encoding: base64 of a little-endian
//! `UInt64` byte count followed by the little-endian values. Every file carries the cell
//! data `region` (Int32); [`Vtu::deformed`] adds `displacement` (point vectors) and
//! `volume_ratio` (cell scalars, `J = det F`).

use std::io::Write;
use std::path::{Path, PathBuf};

use base64::Engine;

use super::{WriteError, write_atomic};
use crate::TetMesh;

/// VTK cell type of a linear tetrahedron.
const VTK_TETRA: u8 = 10;

/// Values of one data array.
#[derive(Debug, Clone, PartialEq)]
enum Field {
    Scalars(Vec<f64>),
    Vectors(Vec<f64>),
    Ints(Vec<i32>),
}

/// One `.vtu` frame: a mesh at some positions with point and cell data.
#[derive(Debug, Clone)]
pub struct Vtu<'a> {
    mesh: &'a TetMesh,
    positions: Vec<f64>,
    point_data: Vec<(String, Field)>,
    cell_data: Vec<(String, Field)>,
}

impl<'a> Vtu<'a> {
    /// The mesh at rest.
    pub fn new(mesh: &'a TetMesh) -> Self {
        let region = mesh
            .regions()
            .iter()
            .map(|&r| i32::try_from(r).unwrap_or(i32::MAX))
            .collect();
        Self {
            mesh,
            positions: mesh.rest_positions_flat(),
            point_data: Vec::new(),
            cell_data: vec![("region".to_owned(), Field::Ints(region))],
        }
    }

    /// The mesh at deformed positions `x` (flat `3N`), with `displacement` and `volume_ratio`.
    ///
    /// # Panics
    /// If `x.len() != 3N`.
    #[track_caller]
    pub fn deformed(mesh: &'a TetMesh, x: &[f64]) -> Self {
        assert_eq!(
            x.len(),
            3 * mesh.num_vertices(),
            "positions must have 3N entries"
        );
        let rest = mesh.rest_positions_flat();
        let u: Vec<f64> = x.iter().zip(&rest).map(|(a, b)| a - b).collect();
        let j: Vec<f64> = (0..mesh.num_tets())
            .map(|e| mesh.deformation_gradient(e, x).determinant())
            .collect();
        let mut out = Self::new(mesh);
        out.positions = x.to_vec();
        out.point_data
            .push(("displacement".to_owned(), Field::Vectors(u)));
        out.cell_data
            .push(("volume_ratio".to_owned(), Field::Scalars(j)));
        out
    }

    /// Adds a scalar per vertex.
    ///
    /// # Panics
    /// If `values.len() != N`.
    #[track_caller]
    pub fn point_scalars(mut self, name: &str, values: &[f64]) -> Self {
        assert_eq!(
            values.len(),
            self.mesh.num_vertices(),
            "one value per vertex"
        );
        self.point_data
            .push((name.to_owned(), Field::Scalars(values.to_vec())));
        self
    }

    /// Adds a 3-vector per vertex, given flat (`3N`), e.g. velocity or force.
    ///
    /// # Panics
    /// If `values.len() != 3N`.
    #[track_caller]
    pub fn point_vectors(mut self, name: &str, values: &[f64]) -> Self {
        assert_eq!(
            values.len(),
            3 * self.mesh.num_vertices(),
            "three values per vertex"
        );
        self.point_data
            .push((name.to_owned(), Field::Vectors(values.to_vec())));
        self
    }

    /// Adds a scalar per element.
    ///
    /// # Panics
    /// If `values.len()` is not the number of elements.
    #[track_caller]
    pub fn cell_scalars(mut self, name: &str, values: &[f64]) -> Self {
        assert_eq!(values.len(), self.mesh.num_tets(), "one value per element");
        self.cell_data
            .push((name.to_owned(), Field::Scalars(values.to_vec())));
        self
    }

    /// Writes the file atomically.
    ///
    /// # Errors
    /// [`WriteError`] naming the path.
    pub fn write(&self, path: &Path) -> Result<(), WriteError> {
        write_atomic(path, |w| self.write_to(w))
    }

    /// Writes the XML to any writer.
    ///
    /// # Errors
    /// The writer's I/O errors.
    pub fn write_to(&self, w: &mut dyn Write) -> std::io::Result<()> {
        let (nv, ne) = (self.mesh.num_vertices(), self.mesh.num_tets());
        writeln!(w, r#"<?xml version="1.0"?>"#)?;
        writeln!(
            w,
            r#"<VTKFile type="UnstructuredGrid" version="1.0" byte_order="LittleEndian" header_type="UInt64">"#
        )?;
        writeln!(
            w,
            "<UnstructuredGrid>\n<Piece NumberOfPoints=\"{nv}\" NumberOfCells=\"{ne}\">"
        )?;
        writeln!(w, "<PointData>")?;
        for (name, f) in &self.point_data {
            array(w, name, f)?;
        }
        writeln!(w, "</PointData>\n<CellData>")?;
        for (name, f) in &self.cell_data {
            array(w, name, f)?;
        }
        writeln!(w, "</CellData>\n<Points>")?;
        array(w, "Points", &Field::Vectors(self.positions.clone()))?;
        writeln!(w, "</Points>\n<Cells>")?;
        let conn: Vec<i64> = self
            .mesh
            .tets()
            .iter()
            .flatten()
            .map(|&i| i as i64)
            .collect();
        let offsets: Vec<i64> = (1..=ne as i64).map(|k| 4 * k).collect();
        raw(
            w,
            "connectivity",
            "Int64",
            1,
            &bytes_of(&conn, |v| v.to_le_bytes()),
        )?;
        raw(
            w,
            "offsets",
            "Int64",
            1,
            &bytes_of(&offsets, |v| v.to_le_bytes()),
        )?;
        raw(w, "types", "UInt8", 1, &vec![VTK_TETRA; ne])?;
        writeln!(w, "</Cells>\n</Piece>\n</UnstructuredGrid>\n</VTKFile>")
    }
}

/// VTK cell type of a triangle.
const VTK_TRIANGLE: u8 = 5;

/// Writes a triangle surface (flat `3V` positions, vertex triples) as a `.vtu`: obstacles
/// and other surfaces shown beside a simulation's frames.
///
/// # Errors
/// [`WriteError`] naming the file; `InvalidInput` when a triangle names a vertex beyond
/// the positions.
pub fn write_triangles(
    path: &Path,
    positions: &[f64],
    triangles: &[[usize; 3]],
) -> Result<(), WriteError> {
    write_atomic(path, |w| {
        let (nv, nt) = (positions.len() / 3, triangles.len());
        if triangles.iter().flatten().any(|&i| i >= nv) {
            return Err(std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                format!("a triangle names a vertex beyond the {nv} given"),
            ));
        }
        writeln!(w, r#"<?xml version="1.0"?>"#)?;
        writeln!(
            w,
            r#"<VTKFile type="UnstructuredGrid" version="1.0" byte_order="LittleEndian" header_type="UInt64">"#
        )?;
        writeln!(
            w,
            "<UnstructuredGrid>\n<Piece NumberOfPoints=\"{nv}\" NumberOfCells=\"{nt}\">\n<Points>"
        )?;
        array(w, "Points", &Field::Vectors(positions[..3 * nv].to_vec()))?;
        writeln!(w, "</Points>\n<Cells>")?;
        let conn: Vec<i64> = triangles.iter().flatten().map(|&i| i as i64).collect();
        let offsets: Vec<i64> = (1..=nt as i64).map(|k| 3 * k).collect();
        raw(
            w,
            "connectivity",
            "Int64",
            1,
            &bytes_of(&conn, |v| v.to_le_bytes()),
        )?;
        raw(
            w,
            "offsets",
            "Int64",
            1,
            &bytes_of(&offsets, |v| v.to_le_bytes()),
        )?;
        raw(w, "types", "UInt8", 1, &vec![VTK_TRIANGLE; nt])?;
        writeln!(w, "</Cells>\n</Piece>\n</UnstructuredGrid>\n</VTKFile>")
    })
}

fn bytes_of<T: Copy, const N: usize>(v: &[T], f: impl Fn(T) -> [u8; N]) -> Vec<u8> {
    v.iter().flat_map(|x| f(*x)).collect()
}

fn array(w: &mut dyn Write, name: &str, f: &Field) -> std::io::Result<()> {
    match f {
        Field::Scalars(v) => raw(w, name, "Float64", 1, &bytes_of(v, f64::to_le_bytes)),
        Field::Vectors(v) => raw(w, name, "Float64", 3, &bytes_of(v, f64::to_le_bytes)),
        Field::Ints(v) => raw(w, name, "Int32", 1, &bytes_of(v, i32::to_le_bytes)),
    }
}

fn raw(
    w: &mut dyn Write,
    name: &str,
    kind: &str,
    components: usize,
    data: &[u8],
) -> std::io::Result<()> {
    let mut block = (data.len() as u64).to_le_bytes().to_vec();
    block.extend_from_slice(data);
    let name = xml_escape(name);
    writeln!(
        w,
        r#"<DataArray type="{kind}" Name="{name}" NumberOfComponents="{components}" format="binary">"#
    )?;
    writeln!(
        w,
        "{}",
        base64::engine::general_purpose::STANDARD.encode(&block)
    )?;
    writeln!(w, "</DataArray>")
}

fn xml_escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// A ParaView `.pvd` collection: a list of `(time, file)` datasets, rewritten atomically
/// after every added frame so that an interrupted run still leaves a readable series.
#[derive(Debug, Clone)]
pub struct Pvd {
    path: PathBuf,
    entries: Vec<(f64, String)>,
}

impl Pvd {
    /// A new, empty collection at `path` (written on the first [`Pvd::push`]).
    pub fn new(path: impl Into<PathBuf>) -> Self {
        Self {
            path: path.into(),
            entries: Vec::new(),
        }
    }

    /// Adds `file` at `time` and rewrites the collection. `file` is stored relative to the
    /// collection's directory when it lies inside it.
    ///
    /// # Errors
    /// [`WriteError`] naming the collection's path.
    pub fn push(&mut self, time: f64, file: &Path) -> Result<(), WriteError> {
        let dir = self.path.parent().unwrap_or(Path::new(""));
        let rel = file.strip_prefix(dir).unwrap_or(file);
        self.entries
            .push((time, rel.to_string_lossy().into_owned()));
        write_atomic(&self.path, |w| {
            writeln!(w, r#"<?xml version="1.0"?>"#)?;
            writeln!(
                w,
                r#"<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">"#
            )?;
            writeln!(w, "<Collection>")?;
            for (t, f) in &self.entries {
                writeln!(
                    w,
                    r#"<DataSet timestep="{t:?}" group="" part="0" file="{}"/>"#,
                    xml_escape(f)
                )?;
            }
            writeln!(w, "</Collection>\n</VTKFile>")
        })
    }

    /// The `(time, file)` entries so far.
    pub fn entries(&self) -> &[(f64, String)] {
        &self.entries
    }
}
