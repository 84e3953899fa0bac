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
    /// Two tetrahedra have the same four vertices.
    #[error("element {element} has the same four vertices as element {first}")]
    DuplicateElement {
        /// The later element.
        element: usize,
        /// The earlier one.
        first: usize,
    },
    /// Two tetrahedra share a face and lie on the same side of it, so they overlap.
    #[error(
        "elements {first} and {second} share the face {face:?} and lie on the same side of it: they overlap"
    )]
    OverlappingElements {
        /// The smaller element index.
        first: usize,
        /// The larger one.
        second: usize,
        /// The shared face's vertices, sorted.
        face: [usize; 3],
    },
    /// More than two tetrahedra share a face (rejected unless
    /// [`crate::MeshOptions::allow_nonmanifold`]).
    #[error("the face {face:?} is shared by {} elements ({elements:?}); a solid's face has at most two", elements.len())]
    NonManifoldFace {
        /// The face's vertices, sorted.
        face: [usize; 3],
        /// The elements sharing it, ascending.
        elements: Vec<usize>,
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
