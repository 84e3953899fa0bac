//! Construction, validation, rest shape, mass, topology, selectors and quality of `TetMesh`.

use approx::assert_relative_eq;
use deform_mesh::generate::{BoxGrid, Split};
use deform_mesh::quality::{quality, rest_quality};
use deform_mesh::select::{Selector, select_by};
use deform_mesh::topology::{BlockPattern, VertexElements, edges, faces, surface_vertices};
use deform_mesh::{MeshError, MeshOptions, TetMesh, Unreferenced, Vector3};
use nalgebra::Matrix3;

fn unit_tet() -> (Vec<Vector3<f64>>, Vec<[usize; 4]>) {
    (
        vec![Vector3::zeros(), Vector3::x(), Vector3::y(), Vector3::z()],
        vec![[0, 1, 2, 3]],
    )
}

#[test]
fn validation_errors_name_the_culprit() {
    let (p, _) = unit_tet();
    assert_eq!(
        TetMesh::try_new(p.clone(), vec![]),
        Err(MeshError::NoElements)
    );
    assert_eq!(
        TetMesh::try_new(p.clone(), vec![[0, 1, 2, 3], [0, 1, 2, 9]]),
        Err(MeshError::IndexOutOfRange {
            element: 1,
            index: 9,
            num_vertices: 4
        })
    );
    assert_eq!(
        TetMesh::try_new(p.clone(), vec![[0, 1, 1, 3]]),
        Err(MeshError::RepeatedVertex {
            element: 0,
            vertex: 1
        })
    );
    let mut nan = p.clone();
    nan[2].y = f64::NAN;
    assert!(matches!(
        TetMesh::try_new(nan, vec![[0, 1, 2, 3]]),
        Err(MeshError::NonFiniteCoordinate {
            vertex: 2,
            axis: 1,
            ..
        })
    ));
    let mut flat = p.clone();
    flat[3] = Vector3::new(0.3, 0.3, 1e-14);
    assert!(matches!(
        TetMesh::try_new(flat, vec![[0, 1, 2, 3]]),
        Err(MeshError::DegenerateElement { element: 0, .. })
    ));
}

#[test]
fn negative_tets_are_reoriented_and_counted() {
    let (p, _) = unit_tet();
    let mesh = TetMesh::try_new(p, vec![[0, 2, 1, 3]]).unwrap();
    assert_eq!(mesh.build_report().reoriented, 1);
    assert_eq!(mesh.tets()[0], [0, 1, 2, 3]);
    assert_relative_eq!(mesh.volumes()[0], 1.0 / 6.0, max_relative = 1e-15);
}

#[test]
fn unreferenced_vertices_are_dropped_or_reported() {
    let (mut p, t) = unit_tet();
    p.insert(1, Vector3::new(5.0, 5.0, 5.0));
    let t: Vec<[usize; 4]> = t
        .iter()
        .map(|t| t.map(|i| if i >= 1 { i + 1 } else { i }))
        .collect();
    let mesh = TetMesh::try_new(p.clone(), t.clone()).unwrap();
    assert_eq!(mesh.num_vertices(), 4);
    assert_eq!(mesh.build_report().dropped_vertices, 1);
    assert_eq!(
        mesh.build_report().kept_vertices.as_deref(),
        Some(&[0, 2, 3, 4][..])
    );
    assert_eq!(mesh.rest_positions()[1], Vector3::x());
    let strict = MeshOptions::default().unreferenced(Unreferenced::Error);
    assert_eq!(
        TetMesh::try_with_options(p, t, None, &strict),
        Err(MeshError::UnreferencedVertices { count: 1, first: 1 })
    );
}

#[test]
fn deformation_gradient_of_an_affine_map_is_its_matrix() {
    let mesh = BoxGrid::new([2, 3, 2], [1.0, 2.0, 0.5])
        .origin([0.1, -0.2, 0.3])
        .split(Split::Five)
        .build()
        .unwrap();
    let a = Matrix3::new(1.1, 0.2, -0.3, 0.05, 0.9, 0.1, -0.2, 0.3, 1.3);
    let b = Vector3::new(0.3, -1.0, 2.0);
    let x: Vec<f64> = mesh
        .rest_positions()
        .iter()
        .flat_map(|p| (a * p + b).iter().copied().collect::<Vec<_>>())
        .collect();
    for e in 0..mesh.num_tets() {
        let f = mesh.deformation_gradient(e, &x);
        assert_relative_eq!(f, a, epsilon = 1e-12);
        let g = mesh.shape_gradients(e);
        let sum: Vector3<f64> = g.iter().sum();
        assert_relative_eq!(sum, Vector3::zeros(), epsilon = 1e-12);
        // F = sum_a x_a grad_a^T
        let t = mesh.tets()[e];
        let mut f2 = Matrix3::zeros();
        for k in 0..4 {
            let xa = Vector3::new(x[3 * t[k]], x[3 * t[k] + 1], x[3 * t[k] + 2]);
            f2 += xa * g[k].transpose();
        }
        assert_relative_eq!(f2, a, epsilon = 1e-12);
    }
}

#[test]
fn lumped_and_consistent_mass_agree_on_rigid_motion() {
    let mesh = BoxGrid::beam(2).build().unwrap();
    let rho = 1000.0;
    let total = rho * 0.25 * 0.25;
    let lumped = mesh.lumped_mass(rho);
    assert_relative_eq!(lumped.iter().sum::<f64>(), total, max_relative = 1e-12);
    let pattern = BlockPattern::new(&mesh);
    let m = mesh.consistent_mass(rho, &pattern);
    for (a, b) in m.row_sums(&pattern).iter().zip(&lumped) {
        assert_relative_eq!(a, b, max_relative = 1e-12);
    }
    // u^T M u for a unit translation is the total mass; M is symmetric.
    let u: Vec<f64> = (0..mesh.num_vertices())
        .flat_map(|_| [1.0, 0.0, 0.0])
        .collect();
    let mut mu = vec![0.0; u.len()];
    m.apply(&pattern, &u, &mut mu);
    let uu: f64 = u.iter().zip(&mu).map(|(a, b)| a * b).sum();
    assert_relative_eq!(uu, total, max_relative = 1e-12);
    for i in 0..pattern.num_rows() {
        for k in pattern.offsets()[i]..pattern.offsets()[i + 1] {
            let j = pattern.columns()[k];
            assert_eq!(m.values[k], m.values[pattern.find(j, i).unwrap()]);
        }
    }
}

#[test]
fn block_pattern_is_symmetric_and_covers_every_element_pair() {
    let mesh = BoxGrid::new([3, 2, 2], [1.0; 3])
        .split(Split::Five)
        .build()
        .unwrap();
    let p = BlockPattern::new(&mesh);
    assert_eq!(p.num_blocks(), mesh.num_vertices() + 2 * edges(&mesh).len());
    for i in 0..p.num_rows() {
        let row = &p.columns()[p.offsets()[i]..p.offsets()[i + 1]];
        assert!(
            row.windows(2).all(|w| w[0] < w[1]),
            "row {i} sorted and unique"
        );
        assert!(row.contains(&i));
        for &j in row {
            assert!(p.find(j, i).is_some(), "({j}, {i}) mirrors ({i}, {j})");
        }
    }
    let blocks = p.element_blocks(&mesh);
    for (t, b) in mesh.tets().iter().zip(&blocks) {
        for a in 0..4 {
            for c in 0..4 {
                assert_eq!(p.columns()[b[4 * a + c]], t[c]);
            }
        }
    }
    let (indptr, indices) = p.scalar_csr();
    assert_eq!(indptr.len(), 3 * mesh.num_vertices() + 1);
    assert_eq!(indices.len(), 9 * p.num_blocks());
    for i in 0..p.num_rows() {
        for k in p.offsets()[i]..p.offsets()[i + 1] {
            let j = p.columns()[k];
            for r in 0..3 {
                for c in 0..3 {
                    let s = p.scalar_index(i, k, r, c);
                    assert!(s >= indptr[3 * i + r] && s < indptr[3 * i + r + 1]);
                    assert_eq!(indices[s], 3 * j + c);
                }
            }
        }
    }
}

#[test]
fn vertex_elements_lists_every_use_once() {
    let mesh = BoxGrid::beam(1).build().unwrap();
    let adj = VertexElements::new(&mesh);
    let mut count = 0;
    for v in 0..mesh.num_vertices() {
        for &(e, a) in adj.of(v) {
            assert_eq!(mesh.tets()[e][a], v);
            count += 1;
        }
        assert!(adj.of(v).windows(2).all(|w| w[0].0 < w[1].0));
    }
    assert_eq!(count, 4 * mesh.num_tets());
}

#[test]
fn selectors_pick_the_expected_vertices() {
    let mesh = BoxGrid::beam(2).build().unwrap();
    let clamp = Selector::Plane {
        point: [0.0; 3],
        normal: [-1.0, 0.0, 0.0],
    }
    .select(&mesh)
    .unwrap();
    let by_pred = select_by(&mesh, |_, p| p.x == 0.0);
    assert_eq!(clamp, by_pred);
    assert_eq!(clamp.len(), 3 * 3);
    let tip = Selector::Box {
        min: [1.0, -1.0, -1.0],
        max: [2.0, 1.0, 1.0],
    }
    .select(&mesh)
    .unwrap();
    assert_eq!(tip, select_by(&mesh, |_, p| p.x == 1.0));
    let surface = Selector::Surface.select(&mesh).unwrap();
    // 9 x 3 x 3 grid: all but the (9-2) x 1 x 1 interior vertices.
    assert_eq!(surface.len(), mesh.num_vertices() - 7);
    assert_eq!(surface, surface_vertices(&mesh));
    let both = Selector::Or(vec![
        Selector::Plane {
            point: [0.0; 3],
            normal: [-1.0, 0.0, 0.0],
        },
        Selector::Indices(vec![5]),
    ])
    .select(&mesh)
    .unwrap();
    assert_eq!(both.len(), 9);
    let interior = Selector::Not(Box::new(Selector::Surface))
        .select(&mesh)
        .unwrap();
    assert_eq!(interior.len(), 7);
    let none = Selector::And(vec![
        Selector::Surface,
        Selector::Not(Box::new(Selector::Surface)),
    ])
    .select(&mesh)
    .unwrap();
    assert!(none.is_empty());
    assert!(Selector::Indices(vec![10_000]).select(&mesh).is_err());
    assert!(
        Selector::Plane {
            point: [0.0; 3],
            normal: [0.0; 3]
        }
        .select(&mesh)
        .is_err()
    );
}

#[test]
fn quality_of_a_regular_tet_and_of_an_inverted_configuration() {
    let s = 1.0 / 2f64.sqrt();
    let p = vec![
        Vector3::new(1.0, 0.0, -s),
        Vector3::new(-1.0, 0.0, -s),
        Vector3::new(0.0, 1.0, s),
        Vector3::new(0.0, -1.0, s),
    ];
    let mesh = TetMesh::try_new(p.clone(), vec![[0, 1, 2, 3]]).unwrap();
    let q = rest_quality(&mesh);
    let regular = (1.0f64 / 3.0).acos().to_degrees();
    assert_relative_eq!(q.min_dihedral_deg, regular, epsilon = 1e-9);
    assert_relative_eq!(q.max_dihedral_deg, regular, epsilon = 1e-9);
    assert_relative_eq!(q.max_aspect_ratio, 1.0, epsilon = 1e-12);
    assert_eq!(q.inverted, 0);
    let mut flipped: Vec<Vector3<f64>> = mesh.rest_positions().to_vec();
    flipped[3] = 2.0 * Vector3::new(0.0, 0.0, -s) - flipped[3];
    let q = quality(&mesh, &flipped);
    assert_eq!(q.inverted, 1);
    assert!(q.min_volume < 0.0);
    let beam = rest_quality(&BoxGrid::beam(1).build().unwrap());
    // The Kuhn simplex has dihedral angles of 45, 60 and 90 degrees.
    assert_relative_eq!(beam.min_dihedral_deg, 45.0, epsilon = 1e-9);
    assert_relative_eq!(beam.max_dihedral_deg, 90.0, epsilon = 1e-9);
}

#[test]
fn faces_classify_boundary_and_interior() {
    let (p, _) = unit_tet();
    let mut p = p;
    p.push(Vector3::new(1.0, 1.0, 1.0));
    let mesh = TetMesh::try_new(p, vec![[0, 1, 2, 3], [1, 2, 3, 4]]).unwrap();
    let f = faces(&mesh);
    assert_eq!(f.boundary.len(), 6);
    assert_eq!(f.interior, vec![[0, 1]]);
    assert!(f.nonmanifold.is_empty());
}

#[test]
fn the_summary_counts_the_beam() {
    let mesh = deform_mesh::generate::BoxGrid::beam(1).build().unwrap();
    let info = deform_mesh::MeshInfo::of(&mesh);
    assert_eq!((info.vertices, info.tets), (20, 24));
    // 18 unit squares of surface, two triangles each; every face used once or twice.
    assert_eq!(info.boundary_faces, 36);
    assert_eq!(info.nonmanifold_faces, 0);
    assert_eq!(4 * info.tets, info.boundary_faces + 2 * info.interior_faces);
    assert!((info.quality.total_volume - 0.0625).abs() < 1e-15);
    let text = info.to_string();
    assert!(
        text.contains("tets            24") && text.contains("region"),
        "{text}"
    );
}

#[test]
fn nested_grids_embed_exactly_and_outside_points_go_to_the_nearest_element() {
    use deform_mesh::embed::Embedding;
    for (fine_n, coarse_n) in [(4, 2), (4, 1), (8, 2)] {
        let fine = BoxGrid::beam(fine_n).build().unwrap();
        let coarse = BoxGrid::beam(coarse_n).build().unwrap();
        let e = Embedding::locate(&fine, coarse.rest_positions());
        assert!(e.outside.is_empty() && e.max_distance == 0.0);
        // Every coarse vertex is a fine vertex: its weights pick that vertex alone.
        for (i, (t, w)) in e.element.iter().zip(&e.weights).enumerate() {
            let k = (0..4).max_by(|a, b| w[*a].total_cmp(&w[*b])).unwrap();
            assert!((w[k] - 1.0).abs() < 1e-12, "vertex {i}: {w:?}");
            let v = fine.tets()[*t][k];
            assert!((fine.rest_positions()[v] - coarse.rest_positions()[i]).norm() < 1e-14);
        }
        // So any fine state maps to the fine values at those vertices.
        let x: Vec<f64> = (0..3 * fine.num_vertices())
            .map(|i| (i as f64 * 0.37).sin())
            .collect();
        let mapped = e.interpolate(&fine, &x);
        for (i, (t, w)) in e.element.iter().zip(&e.weights).enumerate() {
            let k = (0..4).max_by(|a, b| w[*a].total_cmp(&w[*b])).unwrap();
            let v = fine.tets()[*t][k];
            for d in 0..3 {
                assert!((mapped[3 * i + d] - x[3 * v + d]).abs() < 1e-12);
            }
        }
    }
    // Linear fields are reproduced anywhere inside; a point outside is counted and snapped.
    let fine = BoxGrid::beam(2).build().unwrap();
    let inside = Vector3::new(0.313, 0.071, 0.2);
    let outside = Vector3::new(1.5, 0.1, 0.1);
    let e = Embedding::locate(&fine, &[inside, outside]);
    assert_eq!(e.outside, vec![1]);
    assert!((e.max_distance - 0.5).abs() < 1e-12, "{}", e.max_distance);
    let linear: Vec<f64> = fine
        .rest_positions()
        .iter()
        .flat_map(|p| [2.0 * p.x - p.y, p.z + 1.0, 3.0 * p.y])
        .collect();
    let at = e.interpolate(&fine, &linear);
    let want = [2.0 * inside.x - inside.y, inside.z + 1.0, 3.0 * inside.y];
    for d in 0..3 {
        assert!((at[d] - want[d]).abs() < 1e-12);
    }
    // The outside point carries the value at its closest point, (1.0, 0.1, 0.1).
    assert!((at[3] - (2.0 - 0.1)).abs() < 1e-12, "{}", at[3]);
}

#[test]
fn gmsh_meshes_of_one_shape_at_two_resolutions_embed() {
    use deform_mesh::embed::Embedding;
    let read = |name: &str| {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../assets/meshes")
            .join(name);
        deform_mesh::io::read(&path, &MeshOptions::default()).unwrap()
    };
    let (fine, coarse) = (read("beam_fine.msh"), read("beam_coarse.msh"));
    assert!(fine.num_tets() >= 8 * coarse.num_tets());
    let e = Embedding::locate(&fine, coarse.rest_positions());
    // The same box: every coarse vertex lies in (or on) the fine mesh, to rounding.
    assert!(
        e.max_distance < 1e-12,
        "{} outside, up to {}",
        e.outside.len(),
        e.max_distance
    );
    let linear: Vec<f64> = fine
        .rest_positions()
        .iter()
        .flat_map(|p| [p.x - 2.0 * p.z, 0.5 * p.y, p.x * 3.0 + p.y])
        .collect();
    let at = e.interpolate(&fine, &linear);
    for (i, p) in coarse.rest_positions().iter().enumerate() {
        let want = [p.x - 2.0 * p.z, 0.5 * p.y, p.x * 3.0 + p.y];
        for d in 0..3 {
            assert!((at[3 * i + d] - want[d]).abs() < 1e-12);
        }
    }
}

#[test]
fn a_sparse_mesh_gets_a_bounded_grid_and_still_locates_points() {
    use deform_mesh::embed::Embedding;
    // Two unit cubes 100 m apart: the bounding box is a million times their volume.
    let cube = BoxGrid::beam(1).build().unwrap();
    let far = Vector3::repeat(100.0);
    let n = cube.num_vertices();
    let rest: Vec<Vector3<f64>> = cube
        .rest_positions()
        .iter()
        .copied()
        .chain(cube.rest_positions().iter().map(|p| p + far))
        .collect();
    let tets: Vec<[usize; 4]> = cube
        .tets()
        .iter()
        .copied()
        .chain(cube.tets().iter().map(|t| t.map(|v| v + n)))
        .collect();
    let mesh = TetMesh::try_new(rest, tets).unwrap();
    let inside = far + Vector3::new(0.5, 0.1, 0.1);
    let e = Embedding::locate(&mesh, &[inside, Vector3::new(50.0, 50.0, 50.0)]);
    assert!(e.element[0] >= cube.num_tets());
    assert_eq!(e.outside, vec![1]);
    let at = e.interpolate(&mesh, &mesh.rest_positions_flat());
    assert!((Vector3::new(at[0], at[1], at[2]) - inside).norm() < 1e-12);
}
