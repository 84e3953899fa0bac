//! Mesh files: readers, writers and atomic output.
//!
//! | format | read | write |
//! |---|---|---|
//! | Gmsh `.msh` 2.2 / 4.1, ASCII / binary | [`read_msh`] | [`write_msh`] |
//! | TetGen `.node` + `.ele` | [`read_tetgen`] | [`write_tetgen`] |
//! | VTK `.vtu` + `.pvd` (ParaView) | | [`Vtu`], [`Pvd`] |
//! | Wavefront `.obj` (surface) | [`read_surface`] | [`write_obj`] |
//!
//! [`read_arrays`] reads a mesh from numpy's `.npy` vertex and tet arrays. [`read`] and
//! [`write()`] pick the format from the extension. Readers never panic on any
//! input: every error names the file, the line (and byte offset) and what was expected.
//! Writers go through `deform_fs::write_atomic`: a temporary file in the same directory, synced,
//! then renamed over the target, so a crash never leaves a half-written file.

mod cursor;
mod gmsh;
mod obj;
mod tetgen;
mod vtu;

use std::collections::BTreeMap;
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use nalgebra::Vector3;
use thiserror::Error;

pub use gmsh::{MshFormat, MshVersion};
pub use vtu::{Pvd, Vtu, write_triangles};

use crate::{MeshError, MeshOptions, Surface, TetMesh};
use cursor::{ParseError, ParseErrorKind, line_of};

/// Why a mesh file could not be read.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum ReadError {
    /// The file could not be opened or read.
    #[error("{}: {error}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error (shown in the message, so not chained as a source).
        error: std::io::Error,
    },
    /// The file is malformed.
    #[error("{}:{line}: expected {expected}, found {found} (byte {offset})", path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// 1-based line of the failure (for binary data, the line the data starts on).
        line: usize,
        /// Byte offset of the failure.
        offset: usize,
        /// What the reader expected.
        expected: String,
        /// What it found.
        found: String,
    },
    /// The file is well-formed but uses a feature deform does not read.
    #[error("{}:{line}: unsupported: {what}", path.display())]
    Unsupported {
        /// The file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// The feature.
        what: String,
    },
    /// The file parsed but does not describe a valid mesh.
    #[error("{}: {}invalid mesh: {error}", path.display(), context.as_deref().map(|c| format!("{c}: ")).unwrap_or_default())]
    Invalid {
        /// The file.
        path: PathBuf,
        /// The file's own tag of the offending element or node, when there is one.
        context: Option<String>,
        /// The validation failure (indices in deform's numbering).
        error: MeshError,
    },
    /// An `.npy` array of vertices or tets has the wrong dtype, shape or values.
    #[error("{}: {reason}", path.display())]
    Array {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A surface file parsed but is no usable surface (no triangle).
    #[error("{}: invalid surface: {reason}", path.display())]
    InvalidSurface {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The extension names no mesh format deform reads.
    #[error("{}: unknown mesh format (expected .msh, .node or .ele)", path.display())]
    UnknownFormat {
        /// The file.
        path: PathBuf,
    },
    /// The extension names no surface format deform reads.
    #[error("{}: unknown surface format (expected .obj, or a tet mesh: .msh, .node or .ele)", path.display())]
    UnknownSurfaceFormat {
        /// The file.
        path: PathBuf,
    },
}

/// Why a file could not be written.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum WriteError {
    /// Writing, syncing or renaming failed.
    #[error("{}: {error}", path.display())]
    Io {
        /// The target file.
        path: PathBuf,
        /// The OS error (shown in the message, so not chained as a source).
        error: std::io::Error,
    },
    /// The extension names no format deform writes.
    #[error("{}: unknown output format (expected .msh, .vtu, .obj, .node or .ele)", path.display())]
    UnknownFormat {
        /// The target file.
        path: PathBuf,
    },
}

/// A mesh as a file states it, before validation, with the file's own node and element tags.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RawMesh {
    /// Node positions, in file order.
    pub positions: Vec<Vector3<f64>>,
    /// Tetrahedra as 0-based indices into `positions`.
    pub tets: Vec<[usize; 4]>,
    /// Region tag per tetrahedron (0 for none).
    pub regions: Vec<u32>,
    /// Names of region tags.
    pub region_names: BTreeMap<u32, String>,
    /// The file's tag of each node.
    pub node_tags: Vec<u64>,
    /// The file's tag of each tetrahedron.
    pub element_tags: Vec<u64>,
}

impl RawMesh {
    /// Validates into a [`TetMesh`]; errors name the file's element or node tag.
    ///
    /// # Errors
    /// [`ReadError::Invalid`] with `path` and the file's tag of what is wrong.
    pub fn into_mesh(self, path: &Path, options: &MeshOptions) -> Result<TetMesh, ReadError> {
        let Self {
            positions,
            tets,
            regions,
            region_names,
            node_tags,
            element_tags,
        } = self;
        TetMesh::try_with_options(positions, tets, Some(regions), options)
            .map(|m| m.with_region_names(region_names))
            .map_err(|error| {
                let context = match &error {
                    MeshError::IndexOutOfRange { element, .. }
                    | MeshError::RepeatedVertex { element, .. }
                    | MeshError::DegenerateElement { element, .. } => element_tags
                        .get(*element)
                        .map(|t| format!("file element {t}")),
                    MeshError::DuplicateElement {
                        element: b,
                        first: a,
                    }
                    | MeshError::OverlappingElements {
                        first: a,
                        second: b,
                        ..
                    } => {
                        let (a, b) = (element_tags.get(*a), element_tags.get(*b));
                        a.zip(b).map(|(a, b)| format!("file elements {a} and {b}"))
                    }
                    MeshError::NonManifoldFace { elements, .. } => {
                        let tags: Option<Vec<String>> = elements
                            .iter()
                            .map(|e| element_tags.get(*e).map(u64::to_string))
                            .collect();
                        tags.map(|t| format!("file elements {}", t.join(", ")))
                    }
                    MeshError::NonFiniteCoordinate { vertex, .. } => {
                        node_tags.get(*vertex).map(|t| format!("file node {t}"))
                    }
                    _ => None,
                };
                ReadError::Invalid {
                    path: path.to_owned(),
                    context,
                    error,
                }
            })
    }
}

fn parse_failure(path: &Path, data: &[u8], e: ParseError) -> ReadError {
    let line = line_of(data, e.offset);
    match e.kind {
        ParseErrorKind::Expected { expected, found } => ReadError::Parse {
            path: path.to_owned(),
            line,
            offset: e.offset,
            expected,
            found,
        },
        ParseErrorKind::Unsupported(what) => ReadError::Unsupported {
            path: path.to_owned(),
            line,
            what,
        },
    }
}

/// A file's bytes, without a UTF-8 byte-order mark (editors on Windows write one; left in,
/// it hid the first line of an `.obj`, which then went unread).
fn read_bytes(path: &Path) -> Result<Vec<u8>, ReadError> {
    let mut data = fs::read(path).map_err(|error| ReadError::Io {
        path: path.to_owned(),
        error,
    })?;
    if data.starts_with(b"\xEF\xBB\xBF") {
        data.drain(..3);
    }
    Ok(data)
}

/// Parses `.msh` bytes without validation; `path` only labels errors.
///
/// # Errors
/// [`ReadError::Parse`] or [`ReadError::Unsupported`].
pub fn parse_msh(data: &[u8], path: &Path) -> Result<RawMesh, ReadError> {
    gmsh::parse(data).map_err(|e| parse_failure(path, data, e))
}

/// Parses TetGen `.node` and `.ele` bytes without validation; the paths label errors.
///
/// # Errors
/// [`ReadError::Parse`] naming whichever file is malformed.
pub fn parse_tetgen(
    node: &[u8],
    ele: &[u8],
    node_path: &Path,
    ele_path: &Path,
) -> Result<RawMesh, ReadError> {
    tetgen::parse(node, ele).map_err(|(in_node, e)| {
        if in_node {
            parse_failure(node_path, node, e)
        } else {
            parse_failure(ele_path, ele, e)
        }
    })
}

/// Reads and validates a Gmsh `.msh` file (2.2 or 4.1, ASCII or binary).
///
/// # Errors
/// Any [`ReadError`], naming the file and line.
pub fn read_msh(path: &Path, options: &MeshOptions) -> Result<TetMesh, ReadError> {
    let data = read_bytes(path)?;
    parse_msh(&data, path)?.into_mesh(path, options)
}

/// The `.node` and `.ele` files of a TetGen pair named by either file or by their stem. Only
/// the last extension is replaced, so TetGen's own names (`slab.1.node`, `slab.1.ele`) pair
/// up.
fn tetgen_pair(path: &Path) -> (PathBuf, PathBuf) {
    match path.extension().and_then(|e| e.to_str()) {
        Some("node" | "ele") => (path.with_extension("node"), path.with_extension("ele")),
        _ => {
            let with = |ext: &str| {
                let mut name = path.as_os_str().to_owned();
                name.push(ext);
                PathBuf::from(name)
            };
            (with(".node"), with(".ele"))
        }
    }
}

/// Reads and validates a TetGen pair; `path` may name the `.node`, the `.ele` or their
/// common stem.
///
/// # Errors
/// Any [`ReadError`], naming the file and line.
pub fn read_tetgen(path: &Path, options: &MeshOptions) -> Result<TetMesh, ReadError> {
    let (node_path, ele_path) = tetgen_pair(path);
    let node = read_bytes(&node_path)?;
    let ele = read_bytes(&ele_path)?;
    parse_tetgen(&node, &ele, &node_path, &ele_path)?.into_mesh(&ele_path, options)
}

/// Reads and validates a mesh given as two `.npy` arrays, as numpy users have one: rest
/// `vertices` of shape (V, 3) and `tets` of shape (T, 4) (any integer dtype, 0-based). Errors
/// name the file, and a mesh error the row ("file element" `k` is row `k` of `tets`).
///
/// # Errors
/// [`ReadError::Io`], [`ReadError::Array`] (dtype, shape, a non-integer or negative index) or
/// [`ReadError::Invalid`].
pub fn read_arrays(
    vertices: &Path,
    tets: &Path,
    options: &MeshOptions,
) -> Result<TetMesh, ReadError> {
    let read = |path: &Path, columns: usize| {
        let array = deform_fs::npy::read(path).map_err(|e| match e {
            deform_fs::npy::NpyError::Io { path, error } => ReadError::Io { path, error },
            other => ReadError::Array {
                path: path.to_owned(),
                reason: other.to_string(),
            },
        })?;
        if array.shape.len() != 2 || array.shape[1] != columns || array.shape[0] == 0 {
            return Err(ReadError::Array {
                path: path.to_owned(),
                reason: format!("shape {:?}, expected (rows >= 1, {columns})", array.shape),
            });
        }
        Ok(array)
    };
    let v = read(vertices, 3)?;
    let t = read(tets, 4)?;
    let corners = t.indices().map_err(|reason| ReadError::Array {
        path: tets.to_owned(),
        reason,
    })?;
    let raw = RawMesh {
        positions: v.data.chunks(3).map(Vector3::from_column_slice).collect(),
        tets: corners
            .chunks(4)
            .map(|c| [c[0], c[1], c[2], c[3]])
            .collect(),
        regions: vec![0; t.shape[0]],
        region_names: BTreeMap::new(),
        node_tags: (0..v.shape[0] as u64).collect(),
        element_tags: (0..t.shape[0] as u64).collect(),
    };
    raw.into_mesh(tets, options)
}

/// Reads any supported mesh file, chosen by extension (`.msh`, `.node`, `.ele`).
///
/// # Errors
/// Any [`ReadError`]; [`ReadError::UnknownFormat`] for another extension.
pub fn read(path: &Path, options: &MeshOptions) -> Result<TetMesh, ReadError> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("msh") => read_msh(path, options),
        Some("node" | "ele") => read_tetgen(path, options),
        _ => Err(ReadError::UnknownFormat {
            path: path.to_owned(),
        }),
    }
}

/// Reads a triangle surface: an `.obj` file's vertices and faces (polygons as fans of
/// triangles), or the outward boundary of a tet mesh in any format [`read`] takes (`.msh`,
/// `.node`, `.ele`), as [`Surface::boundary`] gives it.
///
/// # Errors
/// Any [`ReadError`] naming the file and line; [`ReadError::InvalidSurface`] for a file with
/// no triangle, [`ReadError::UnknownSurfaceFormat`] for another extension.
pub fn read_surface(path: &Path) -> Result<Surface, ReadError> {
    let surface = match path.extension().and_then(|e| e.to_str()) {
        Some("obj") => {
            let data = read_bytes(path)?;
            obj::parse(&data).map_err(|e| parse_failure(path, &data, e))?
        }
        Some("msh" | "node" | "ele") => Surface::boundary(&read(path, &MeshOptions::default())?),
        _ => {
            return Err(ReadError::UnknownSurfaceFormat {
                path: path.to_owned(),
            });
        }
    };
    surface
        .check()
        .map_err(|reason| ReadError::InvalidSurface {
            path: path.to_owned(),
            reason,
        })?;
    Ok(surface)
}

/// [`deform_fs::write_atomic`] with the mesh writers' error.
fn write_atomic(
    path: &Path,
    body: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> Result<(), WriteError> {
    deform_fs::write_atomic(path, body).map_err(|e| WriteError::Io {
        path: e.path,
        error: e.error,
    })
}

/// Writes a Gmsh `.msh` file.
///
/// # Errors
/// [`WriteError`] naming the path.
pub fn write_msh(path: &Path, mesh: &TetMesh, format: MshFormat) -> Result<(), WriteError> {
    write_atomic(path, |w| gmsh::write(w, mesh, format))
}

/// Writes a TetGen pair `stem.node` + `stem.ele` (0-based, region as the element attribute).
///
/// # Errors
/// [`WriteError`] naming the path.
pub fn write_tetgen(stem: &Path, mesh: &TetMesh) -> Result<(), WriteError> {
    let (node_path, ele_path) = tetgen_pair(stem);
    write_atomic(&node_path, |w| tetgen::write_node(w, mesh))?;
    write_atomic(&ele_path, |w| tetgen::write_ele(w, mesh))
}

/// Writes the boundary surface at `positions` as Wavefront `.obj`.
///
/// # Errors
/// [`WriteError`] naming the path.
///
/// # Panics
/// If `positions` has fewer entries than the mesh has vertices.
#[track_caller]
pub fn write_obj(
    path: &Path,
    mesh: &TetMesh,
    positions: &[Vector3<f64>],
) -> Result<(), WriteError> {
    assert!(
        positions.len() >= mesh.num_vertices(),
        "one position per vertex"
    );
    write_atomic(path, |w| obj::write(w, mesh, positions))
}

/// Writes the rest mesh in the format its extension names: `.msh` (4.1 ASCII), `.vtu`,
/// `.obj`, `.node`/`.ele` (both files).
///
/// # Errors
/// [`WriteError::UnknownFormat`] for another extension, else I/O errors naming the path.
pub fn write(path: &Path, mesh: &TetMesh) -> Result<(), WriteError> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("msh") => write_msh(path, mesh, MshFormat::default()),
        Some("vtu") => Vtu::new(mesh).write(path),
        Some("obj") => write_obj(path, mesh, mesh.rest_positions()),
        Some("node" | "ele") => write_tetgen(path, mesh),
        _ => Err(WriteError::UnknownFormat {
            path: path.to_owned(),
        }),
    }
}
