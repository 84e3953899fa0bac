//! Deterministic structured generators: boxes and beams of cubes split into tetrahedra.
//!
//! The numbering is documented exactly, so that anyone can rebuild the same mesh (it is
//! the benchmark family of deform's `BENCHMARKS.md`):
//!
//! - A grid of `nx x ny x nz` cells of size `size / (nx, ny, nz)`, lower corner `origin`.
//! - Vertex `(i, j, k)`, `0 <= i <= nx` etc., sits at `origin + (i hx, j hy, k hz)` and has
//!   index `(i (ny + 1) + j) (nz + 1) + k` (z fastest, x slowest).
//! - Cell `(ci, cj, ck)` has index `(ci ny + cj) nz + ck`; its local corner
//!   `l = a + 2 b + 4 c` (a, b, c in {0, 1}) is vertex `(ci + a, cj + b, ck + c)`.
//! - [`Split::Six`] (Kuhn split around the diagonal from corner 0 to corner 7): tet
//!   `6 cell + t` has local corners [`SIX_TETS`]`[t]`, each of volume `hx hy hz / 6`.
//! - [`Split::Five`]: a central tet and four corner tets, alternating with the parity of
//!   `ci + cj + ck` so that the face diagonals of neighbouring cells match: tet `5 cell + t`
//!   has local corners [`FIVE_TETS_EVEN`]`[t]` or [`FIVE_TETS_ODD`]`[t]`.
//!
//! All listed tets are positively oriented, so the generated mesh is exactly the tables.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::{MeshError, TetMesh};

/// Local corners of the six Kuhn tets of a cube (all positively oriented).
pub const SIX_TETS: [[usize; 4]; 6] = [
    [0, 1, 3, 7],
    [0, 5, 1, 7],
    [0, 3, 2, 7],
    [0, 2, 6, 7],
    [0, 4, 5, 7],
    [0, 6, 4, 7],
];

/// Local corners of the five tets of a cube whose `ci + cj + ck` is even; the last is central.
pub const FIVE_TETS_EVEN: [[usize; 4]; 5] = [
    [0, 1, 2, 4],
    [1, 3, 2, 7],
    [1, 4, 5, 7],
    [2, 6, 4, 7],
    [1, 2, 4, 7],
];

/// Local corners of the five tets of a cube whose `ci + cj + ck` is odd; the last is central.
pub const FIVE_TETS_ODD: [[usize; 4]; 5] = [
    [1, 0, 5, 3],
    [0, 3, 2, 6],
    [0, 6, 4, 5],
    [3, 6, 5, 7],
    [0, 5, 3, 6],
];

/// How each cube is split into tetrahedra.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum Split {
    /// Five tets per cube (alternating orientation, conforming).
    Five,
    /// Six Kuhn tets per cube, all congruent.
    #[default]
    Six,
}

/// A structured box of cells, see the module documentation for the exact numbering.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct BoxGrid {
    /// Cells along x, y, z.
    pub cells: [usize; 3],
    /// Edge lengths of the box.
    pub size: [f64; 3],
    /// Lower corner.
    #[serde(default)]
    pub origin: [f64; 3],
    /// Cube split.
    #[serde(default)]
    pub split: Split,
}

deform_setters::setters!(BoxGrid {
    cells: [usize; 3],
    size: [f64; 3],
    origin: [f64; 3],
    split: Split
});

impl BoxGrid {
    /// A box of `cells` cubes (or bricks) over `size`, its lower corner at the origin, Kuhn
    /// split.
    pub fn new(cells: [usize; 3], size: [f64; 3]) -> Self {
        let (origin, split) = ([0.0; 3], Split::Six);
        Self {
            cells,
            size,
            origin,
            split,
        }
    }

    /// The beam of size parameter `n` from `BENCHMARKS.md`: `4n x n x n` cubes of edge
    /// `1 / (4n)` on `[0, 1] x [0, 0.25] x [0, 0.25]`, Kuhn split.
    pub fn beam(n: usize) -> Self {
        Self {
            cells: [4 * n, n, n],
            size: [1.0, 0.25, 0.25],
            origin: [0.0; 3],
            split: Split::Six,
        }
    }

    /// Number of vertices the grid will have.
    pub fn num_vertices(&self) -> usize {
        // Saturating, so that a hostile grid is measured (and refused), not overflowed.
        let [nx, ny, nz] = self.cells.map(|c| c.saturating_add(1));
        nx.saturating_mul(ny).saturating_mul(nz)
    }

    /// Number of tetrahedra the grid will have.
    pub fn num_tets(&self) -> usize {
        let per_cell = match self.split {
            Split::Five => 5,
            Split::Six => 6,
        };
        self.cells
            .iter()
            .fold(per_cell, |n, c| n.saturating_mul(*c))
    }

    /// Builds the mesh.
    ///
    /// # Errors
    /// [`MeshError::InvalidParameter`] for a zero cell count, a non-positive or non-finite
    /// size, a non-finite origin, or a grid too large to index.
    pub fn build(&self) -> Result<TetMesh, MeshError> {
        let [nx, ny, nz] = self.cells;
        if nx == 0 || ny == 0 || nz == 0 {
            return Err(MeshError::InvalidParameter {
                field: "cells",
                reason: format!("every count must be at least 1, got {:?}", self.cells),
            });
        }
        if !self.size.iter().all(|s| s.is_finite() && *s > 0.0) {
            return Err(MeshError::InvalidParameter {
                field: "size",
                reason: format!(
                    "every edge must be finite and positive, got {:?}",
                    self.size
                ),
            });
        }
        if !self.origin.iter().all(|s| s.is_finite()) {
            return Err(MeshError::InvalidParameter {
                field: "origin",
                reason: format!("must be finite, got {:?}", self.origin),
            });
        }
        let per_cell = match self.split {
            Split::Five => 5,
            Split::Six => 6,
        };
        let too_big = (nx + 1)
            .checked_mul(ny + 1)
            .and_then(|v| v.checked_mul(nz + 1))
            .and_then(|v| v.checked_mul(per_cell))
            .is_none_or(|v| v > u32::MAX as usize);
        if too_big {
            return Err(MeshError::InvalidParameter {
                field: "cells",
                reason: format!("grid {:?} is too large", self.cells),
            });
        }
        let tets = self.num_tets();
        crate::memory::check_fits(crate::memory::mesh_bytes(self.num_vertices(), tets)).map_err(
            |reason| MeshError::InvalidParameter {
                field: "cells",
                reason: format!("a grid of {tets} tets {reason}"),
            },
        )?;
        let h = Vector3::new(
            self.size[0] / nx as f64,
            self.size[1] / ny as f64,
            self.size[2] / nz as f64,
        );
        let o = Vector3::from(self.origin);
        let vid = |i: usize, j: usize, k: usize| (i * (ny + 1) + j) * (nz + 1) + k;
        let mut rest = Vec::with_capacity(self.num_vertices());
        for i in 0..=nx {
            for j in 0..=ny {
                for k in 0..=nz {
                    // Exact at the far faces: i == nx gives origin + size, not a rounded sum.
                    let c = |n: usize, m: usize, a: usize| {
                        if n == m {
                            self.size[a]
                        } else {
                            n as f64 * h[a]
                        }
                    };
                    rest.push(o + Vector3::new(c(i, nx, 0), c(j, ny, 1), c(k, nz, 2)));
                }
            }
        }
        let mut tets = Vec::with_capacity(per_cell * nx * ny * nz);
        for ci in 0..nx {
            for cj in 0..ny {
                for ck in 0..nz {
                    let corner =
                        |l: usize| vid(ci + (l & 1), cj + ((l >> 1) & 1), ck + ((l >> 2) & 1));
                    let table: &[[usize; 4]] = match self.split {
                        Split::Six => &SIX_TETS,
                        Split::Five if (ci + cj + ck) % 2 == 0 => &FIVE_TETS_EVEN,
                        Split::Five => &FIVE_TETS_ODD,
                    };
                    tets.extend(table.iter().map(|t| t.map(corner)));
                }
            }
        }
        TetMesh::try_new(rest, tets)
    }
}

/// Several boxes in one mesh, numbered one after another (the vertices and tets of
/// `grids[1]` after all of `grids[0]`'s, and so on): one body of separate parts, such as a
/// cube resting on a slab in self-contact. Overlapping boxes are not merged.
///
/// # Errors
/// As [`BoxGrid::build`] for each box, or [`MeshError::NoElements`] for no box.
pub fn boxes(grids: &[BoxGrid]) -> Result<TetMesh, MeshError> {
    let (mut rest, mut tets) = (Vec::new(), Vec::new());
    for grid in grids {
        let mesh = grid.build()?;
        let first = rest.len();
        rest.extend_from_slice(mesh.rest_positions());
        tets.extend(mesh.tets().iter().map(|t| t.map(|v| v + first)));
    }
    TetMesh::try_new(rest, tets)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn boxes_number_their_parts_one_after_another() {
        let grid = |cells, origin| BoxGrid {
            cells,
            size: [0.1; 3],
            origin,
            split: Split::default(),
        };
        let (a, b) = (grid([1, 1, 1], [0.0; 3]), grid([2, 1, 1], [0.0, 0.0, 1.0]));
        let mesh = boxes(&[a, b]).unwrap();
        let (ma, mb) = (a.build().unwrap(), b.build().unwrap());
        assert_eq!(mesh.num_vertices(), ma.num_vertices() + mb.num_vertices());
        assert_eq!(&mesh.rest_positions()[8..], mb.rest_positions());
        assert_eq!(mesh.tets()[6], mb.tets()[0].map(|v| v + 8));
        assert!(matches!(boxes(&[]), Err(MeshError::NoElements)));
    }
}
