//! Errors of mesh construction (validation). Reader and writer errors live in [`crate::io`].

use thiserror::Error;

/// Why a set of positions and tetrahedra is not a valid [`crate::TetMesh`].
#[derive(Debug, Clone, PartialEq, Error)]
#[non_exhaustive]
pub enum MeshError {
    /// The mesh has no tetrahedra.
    #[error("the mesh has no tetrahedra")]
    NoElements,
    /// A vertex coordinate is NaN or infinite.
    #[error("vertex {vertex} has a non-finite coordinate {value} (axis {axis})")]
    NonFiniteCoordinate {
        /// Vertex index (as given to the constructor).
        vertex: usize,
        /// Axis 0, 1 or 2.
        axis: usize,
        /// The offending value.
        value: f64,
    },
    /// A tetrahedron refers to a vertex that does not exist.
    #[error(
        "element {element} refers to vertex {index}, but there are only {num_vertices} vertices"
    )]
    IndexOutOfRange {
        /// Element index.
        element: usize,
        /// The offending vertex index.
        index: usize,
        /// Number of vertices.
        num_vertices: usize,
    },
    /// A tetrahedron lists the same vertex twice.
    #[error("element {element} lists vertex {vertex} more than once")]
    RepeatedVertex {
        /// Element index.
        element: usize,
        /// The repeated vertex.
        vertex: usize,
    },
    /// A tetrahedron has (nearly) zero volume relative to its longest edge.
    #[error(
        "element {element} is degenerate: volume {volume:e} is below {tolerance:e} x (longest edge)^3 = {threshold:e}"
    )]
    DegenerateElement {
        /// Element index.
        element: usize,
        /// Its unsigned volume.
        volume: f64,
        /// The relative tolerance in force.
        tolerance: f64,
        /// The absolute threshold the volume was compared with.
        threshold: f64,
    },
    /// Vertices not used by any tetrahedron, with [`crate::Unreferenced::Error`].
    #[error("{count} vertices are not used by any element (first: {first})")]
    UnreferencedVertices {
        /// How many.
        count: usize,
        /// The smallest such index.
        first: usize,
    },
    /// A per-element array has the wrong length.
    #[error("{what} has {found} entries, expected {expected}")]
    LengthMismatch {
        /// Which array.
        what: &'static str,
        /// Its length.
        found: usize,
        /// The expected length.
        expected: usize,
    },
    /// An option or parameter is out of its valid range.
    #[error("invalid {field}: {reason}")]
    InvalidParameter {
        /// The field's name.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
}
