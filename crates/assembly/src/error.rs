//! Errors of the assembly: they name the vertex or element at fault.

use thiserror::Error;

/// Why an evaluation failed. No output buffer holds NaN after an error is returned: the
/// caller must not use them.
#[derive(Debug, Clone, PartialEq, Error)]
#[non_exhaustive]
pub enum AssemblyError {
    /// A vector or matrix has the wrong size.
    #[error("{what} has length {found}, expected {expected}")]
    DimensionMismatch {
        /// Which argument.
        what: &'static str,
        /// Expected length.
        expected: usize,
        /// Actual length.
        found: usize,
    },
    /// A position is NaN or infinite.
    #[error("{what}: vertex {vertex} has a non-finite coordinate")]
    NonFinite {
        /// Which argument.
        what: &'static str,
        /// The vertex.
        vertex: usize,
    },
    /// An element is outside its model's domain (e.g. inverted for Neo-Hookean).
    #[error("element {element}: det F = {det:e} is outside the domain of {model}")]
    Inadmissible {
        /// The element.
        element: usize,
        /// `det F` of the element.
        det: f64,
        /// The model's name.
        model: &'static str,
    },
    /// An element produced a non-finite energy, force or tangent.
    #[error("element {element}: non-finite {what}")]
    NonFiniteElement {
        /// The element.
        element: usize,
        /// What was non-finite.
        what: &'static str,
    },
    /// A matrix passed for refilling does not have this mesh's pattern.
    #[error("the matrix does not have this mesh's stiffness pattern")]
    PatternMismatch,
    /// A material field does not match the mesh.
    #[error("material field: {0}")]
    MaterialField(String),
    /// A constrained vertex is out of range.
    #[error("constrained vertex {vertex} is out of range (the mesh has {num_vertices})")]
    VertexOutOfRange {
        /// The vertex.
        vertex: usize,
        /// Number of vertices.
        num_vertices: usize,
    },
    /// The mesh is too large for the 32-bit scatter maps: the count of elements (above 200
    /// million) or of matrix entries (above 2^32) that is too many.
    #[error("the mesh is too large for the 32-bit scatter maps ({0} elements or matrix entries)")]
    TooLarge(usize),
}
