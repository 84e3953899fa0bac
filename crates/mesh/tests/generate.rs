//! Generated meshes: orientation, volume, closed manifold surface, conformity; proptest
//! over sizes and rigid motions.

use approx::assert_relative_eq;
use deform_mesh::generate::{BoxGrid, Split};
use deform_mesh::topology::{edges, faces};
use deform_mesh::{TetMesh, Vector3};
use nalgebra::{Rotation3, Unit};
use proptest::prelude::*;

fn surface_area(mesh: &TetMesh, p: &[Vector3<f64>]) -> f64 {
    faces(mesh)
        .boundary
        .iter()
        .map(|f| (p[f[1]] - p[f[0]]).cross(&(p[f[2]] - p[f[0]])).norm() / 2.0)
        .sum()
}

fn check_grid(grid: &BoxGrid) {
    let mesh = grid.build().unwrap();
    let [nx, ny, nz] = grid.cells;
    let per_cell = if grid.split == Split::Six { 6 } else { 5 };
    assert_eq!(mesh.num_tets(), per_cell * nx * ny * nz);
    assert_eq!(mesh.num_vertices(), (nx + 1) * (ny + 1) * (nz + 1));
    assert_eq!(
        mesh.build_report().reoriented,
        0,
        "the tables are positively oriented"
    );
    let volume = grid.size.iter().product::<f64>();
    assert_relative_eq!(
        mesh.volumes().iter().sum::<f64>(),
        volume,
        max_relative = 1e-12
    );
    assert!(mesh.volumes().iter().all(|&v| v > 0.0));

    let f = faces(&mesh);
    assert!(
        f.nonmanifold.is_empty(),
        "each face is shared by at most two tets"
    );
    // Closed 2-manifold: every surface edge is used by exactly two boundary triangles,
    // once in each direction (consistent outward orientation).
    let mut directed: Vec<(usize, usize)> = f
        .boundary
        .iter()
        .flat_map(|t| [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])])
        .collect();
    directed.sort_unstable();
    assert!(
        directed.windows(2).all(|w| w[0] != w[1]),
        "no directed edge repeats"
    );
    for &(a, b) in &directed {
        assert!(
            directed.binary_search(&(b, a)).is_ok(),
            "edge ({a},{b}) has its twin"
        );
    }
    let mut verts: Vec<usize> = f.boundary.iter().flatten().copied().collect();
    verts.sort_unstable();
    verts.dedup();
    let (v, e, fc) = (
        verts.len() as i64,
        directed.len() as i64 / 2,
        f.boundary.len() as i64,
    );
    assert_eq!(v - e + fc, 2, "Euler characteristic of the surface");
    // Boundary faces: 2 per boundary cell face; interior faces satisfy 4T = 2I + B.
    let cell_faces = 2 * (nx * ny + ny * nz + nx * nz);
    assert_eq!(f.boundary.len(), 2 * cell_faces);
    assert_eq!(4 * mesh.num_tets(), 2 * f.interior.len() + f.boundary.len());
    // Outward: the divergence theorem gives volume = 1/3 sum (centroid . n) area.
    let p = mesh.rest_positions();
    let flux: f64 = f
        .boundary
        .iter()
        .map(|t| {
            (p[t[0]] + p[t[1]] + p[t[2]]).dot(&(p[t[1]] - p[t[0]]).cross(&(p[t[2]] - p[t[0]])))
                / 18.0
        })
        .sum();
    assert_relative_eq!(flux, volume, max_relative = 1e-10);
    // Euler characteristic of the solid: V - E + F - T = 1.
    let interior_and_boundary = (f.interior.len() + f.boundary.len()) as i64;
    assert_eq!(
        mesh.num_vertices() as i64 - edges(&mesh).len() as i64 + interior_and_boundary
            - mesh.num_tets() as i64,
        1
    );
}

#[test]
fn benchmark_beams_match_the_published_counts() {
    for (n, tets, vertices) in [(1, 24, 20), (2, 192, 81), (4, 1536, 425)] {
        let mesh = BoxGrid::beam(n).build().unwrap();
        assert_eq!((mesh.num_tets(), mesh.num_vertices()), (tets, vertices));
        assert_eq!(
            mesh.rest_positions()[mesh.num_vertices() - 1],
            Vector3::new(1.0, 0.25, 0.25)
        );
        // Vertex (i, j, k) at (i h, j h, k h) with index (i (ny+1) + j)(nz+1) + k.
        let h = 1.0 / (4 * n) as f64;
        let idx = (n * (n + 1) + 1) * (n + 1) + 1;
        assert_relative_eq!(
            mesh.rest_positions()[idx],
            Vector3::new(n as f64 * h, h, h),
            epsilon = 1e-15
        );
        check_grid(&BoxGrid::beam(n));
    }
}

#[test]
fn invalid_grids_are_rejected_naming_the_field() {
    let ok = BoxGrid::new([1, 1, 1], [1.0; 3]).split(Split::Six);
    let cases = [
        (ok.cells([0, 1, 1]), "cells"),
        (ok.size([1.0, -1.0, 1.0]), "size"),
        (ok.origin([f64::NAN, 0.0, 0.0]).split(Split::Five), "origin"),
        (ok.cells([100_000, 100_000, 1000]), "cells"),
    ];
    for (grid, expected) in cases {
        match grid.build() {
            Err(deform_mesh::MeshError::InvalidParameter { field, .. }) => {
                assert_eq!(field, expected)
            }
            other => panic!("{grid:?}: expected an error naming {expected}, got {other:?}"),
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    #[test]
    fn generated_grids_are_valid(
        nx in 1usize..5, ny in 1usize..4, nz in 1usize..4,
        sx in 0.1f64..3.0, sy in 0.1f64..3.0, sz in 0.1f64..3.0,
        five in any::<bool>(),
    ) {
        check_grid(&BoxGrid::new([nx, ny, nz], [sx, sy, sz]).origin([0.5, -1.0, 2.0]).split(if five { Split::Five } else { Split::Six }));
    }

    #[test]
    fn volume_and_area_are_invariant_under_rigid_motion(
        axis in prop::array::uniform3(-1.0f64..1.0).prop_filter("non-zero axis", |a| a.iter().map(|c| c * c).sum::<f64>() > 1e-3),
        angle in -3.2f64..3.2,
        shift in prop::array::uniform3(-10.0f64..10.0),
        n in 1usize..3,
    ) {
        let mesh = BoxGrid::beam(n).build().unwrap();
        let r = Rotation3::from_axis_angle(&Unit::new_normalize(Vector3::from(axis)), angle);
        let moved: Vec<Vector3<f64>> = mesh.rest_positions().iter().map(|p| r * p + Vector3::from(shift)).collect();
        let rebuilt = TetMesh::try_new(moved.clone(), mesh.tets().to_vec()).unwrap();
        prop_assert_eq!(rebuilt.build_report().reoriented, 0);
        let (v0, v1): (f64, f64) = (mesh.volumes().iter().sum(), rebuilt.volumes().iter().sum());
        prop_assert!((v0 - v1).abs() < 1e-12 * v0);
        let (a0, a1) = (surface_area(&mesh, mesh.rest_positions()), surface_area(&rebuilt, &moved));
        prop_assert!((a0 - a1).abs() < 1e-11 * a0);
        let exact = 2.0 * (0.25 + 0.25 + 0.0625);
        prop_assert!((a0 - exact).abs() < 1e-12);
    }
}
