//! Readers and writers: real files from gmsh and TetGen, round trips, and bad files.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use approx::assert_relative_eq;
use base64::Engine;
use deform_mesh::generate::{BoxGrid, Split};
use deform_mesh::io::{self, MshFormat, MshVersion, Pvd, ReadError, Vtu};
use deform_mesh::{MeshError, MeshOptions, TetMesh};

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

fn asset(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../assets/meshes")
        .join(name)
}

fn read(path: &Path) -> TetMesh {
    io::read(path, &MeshOptions::default()).unwrap_or_else(|e| panic!("{e}"))
}

fn total_volume(mesh: &TetMesh) -> f64 {
    mesh.volumes().iter().sum()
}

fn region_set(mesh: &TetMesh) -> Vec<u32> {
    let mut r = mesh.regions().to_vec();
    r.sort_unstable();
    r.dedup();
    r
}

#[test]
fn gmsh_files_in_all_four_variants_read_identically() {
    let variants = [
        "two_boxes_22_ascii.msh",
        "two_boxes_22_binary.msh",
        "two_boxes_41_ascii.msh",
        "two_boxes_41_binary.msh",
    ];
    let meshes: Vec<TetMesh> = variants.iter().map(|v| read(&data(v))).collect();
    for (m, v) in meshes.iter().zip(variants) {
        // Counts and volume as reported by meshio for the files gmsh wrote (scripts/make_meshes.py).
        assert_eq!((m.num_vertices(), m.num_tets()), (428, 1455), "{v}");
        assert_relative_eq!(total_volume(m), 2.0, max_relative = 1e-12);
        assert_eq!(region_set(m), vec![7, 9], "{v}");
        // Every tet of region 7 lies in the left box x <= 1.
        for (t, r) in m.tets().iter().zip(m.regions()) {
            let cx: f64 = t.iter().map(|&i| m.rest_positions()[i].x).sum::<f64>() / 4.0;
            assert_eq!(*r == 7, cx < 1.0, "{v}");
        }
    }
    let names: BTreeMap<u32, String> = [(7, "left".to_owned()), (9, "right".to_owned())].into();
    assert_eq!(meshes[0].region_names(), &names);
    assert_eq!(meshes[3].region_names(), &names);
    for m in &meshes[1..] {
        // gmsh prints ASCII coordinates with 16 significant digits, binary ones exactly.
        for (a, b) in m.rest_positions().iter().zip(meshes[0].rest_positions()) {
            assert_relative_eq!(a, b, max_relative = 1e-15, epsilon = 1e-15);
        }
        assert_eq!(m.tets(), meshes[0].tets());
        assert_eq!(m.regions(), meshes[0].regions());
    }
}

#[test]
fn bundled_meshes_read_with_expected_counts_and_volumes() {
    // (file, vertices, tets, volume from meshio, regions)
    let cases: [(&str, usize, usize, f64, Vec<u32>); 5] = [
        ("beam.msh", 558, 1854, 0.0625, vec![1]),
        ("beam_fine.msh", 1299, 5083, 0.0625, vec![1]),
        ("beam_coarse.msh", 169, 412, 0.0625, vec![1]),
        ("bracket.msh", 588, 1700, 0.00626298309606, vec![1, 2]),
        ("block.node", 445, 1365, 0.1875, vec![5]),
    ];
    for (file, nv, nt, vol, regions) in cases {
        let m = read(&asset(file));
        assert_eq!((m.num_vertices(), m.num_tets()), (nv, nt), "{file}");
        assert_relative_eq!(total_volume(&m), vol, max_relative = 1e-11);
        assert_eq!(region_set(&m), regions, "{file}");
        assert_eq!(m.build_report().dropped_vertices, 0, "{file}");
    }
    assert_eq!(
        read(&asset("bracket.msh"))
            .region_names()
            .get(&2)
            .map(String::as_str),
        Some("wall")
    );
    // The .ele path and the stem read the same pair.
    assert_eq!(read(&asset("block.ele")), read(&asset("block.node")));
}

fn sample_mesh() -> TetMesh {
    let mesh = BoxGrid::new([3, 2, 2], [1.5, 1.0, 0.7])
        .origin([0.1, 0.2, -0.3])
        .split(Split::Five)
        .build()
        .unwrap();
    // Two regions so that tags round-trip too.
    let regions: Vec<u32> = (0..mesh.num_tets())
        .map(|e| if e % 3 == 0 { 4 } else { 2 })
        .collect();
    TetMesh::try_with_options(
        mesh.rest_positions().to_vec(),
        mesh.tets().to_vec(),
        Some(regions),
        &MeshOptions::default(),
    )
    .unwrap()
    .with_region_names(
        [
            (2, "soft".to_owned()),
            (4, "hard \"core\"".replace('"', "'")),
        ]
        .into(),
    )
}

#[test]
fn round_trips_preserve_topology_coordinates_and_regions() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = sample_mesh();
    for version in [MshVersion::V2_2, MshVersion::V4_1] {
        for binary in [false, true] {
            let path = dir.path().join(format!("m_{version:?}_{binary}.msh"));
            io::write_msh(&path, &mesh, MshFormat { version, binary }).unwrap();
            let back = read(&path);
            assert!(
                back == mesh,
                "{version:?} binary={binary}: {}",
                std::fs::read_to_string(&path)
                    .unwrap_or_default()
                    .lines()
                    .take(12)
                    .collect::<Vec<_>>()
                    .join("\n")
            );
        }
    }
    let stem = dir.path().join("m.node");
    io::write(&stem, &mesh).unwrap();
    let back = read(&stem);
    assert_eq!(back.rest_positions(), mesh.rest_positions());
    assert_eq!(back.tets(), mesh.tets());
    assert_eq!(back.regions(), mesh.regions());
}

/// Decodes one `format="binary"` DataArray of our VTU by name (UInt64 header + values).
fn vtu_array(xml: &str, name: &str) -> Vec<u8> {
    let start = xml
        .find(&format!("Name=\"{name}\""))
        .unwrap_or_else(|| panic!("array {name}"));
    let body_start = xml[start..].find('>').unwrap() + start + 1;
    let body_end = xml[body_start..].find("</DataArray>").unwrap() + body_start;
    let raw = base64::engine::general_purpose::STANDARD
        .decode(xml[body_start..body_end].trim())
        .unwrap();
    let len = u64::from_le_bytes(raw[..8].try_into().unwrap()) as usize;
    assert_eq!(len, raw.len() - 8, "header byte count of {name}");
    raw[8..].to_vec()
}

fn f64s(b: &[u8]) -> Vec<f64> {
    b.chunks_exact(8)
        .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
        .collect()
}

#[test]
fn vtu_frames_carry_positions_connectivity_and_fields() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = sample_mesh();
    let mut x = mesh.rest_positions_flat();
    for (k, v) in x.iter_mut().enumerate() {
        *v *= if k % 3 == 2 { 1.2 } else { 1.0 };
    }
    let path = dir.path().join("frame_0001.vtu");
    let vel = vec![0.5; x.len()];
    Vtu::deformed(&mesh, &x)
        .point_vectors("velocity", &vel)
        .write(&path)
        .unwrap();
    let xml = std::fs::read_to_string(&path).unwrap();
    assert_eq!(f64s(&vtu_array(&xml, "Points")), x);
    assert_eq!(f64s(&vtu_array(&xml, "velocity")), vel);
    let j = f64s(&vtu_array(&xml, "volume_ratio"));
    assert!(
        j.iter().all(|j| (j - 1.2).abs() < 1e-12),
        "uniform stretch of 1.2 in z"
    );
    let conn: Vec<i64> = vtu_array(&xml, "connectivity")
        .chunks_exact(8)
        .map(|c| i64::from_le_bytes(c.try_into().unwrap()))
        .collect();
    let expected: Vec<i64> = mesh.tets().iter().flatten().map(|&i| i as i64).collect();
    assert_eq!(conn, expected);
    assert_eq!(vtu_array(&xml, "types"), vec![10u8; mesh.num_tets()]);

    let mut pvd = Pvd::new(dir.path().join("series.pvd"));
    pvd.push(0.0, &path).unwrap();
    pvd.push(0.01, &dir.path().join("frame_0002.vtu")).unwrap();
    let text = std::fs::read_to_string(dir.path().join("series.pvd")).unwrap();
    assert!(
        text.contains(r#"timestep="0.01" group="" part="0" file="frame_0002.vtu""#),
        "{text}"
    );
    // No temporary files are left behind.
    let names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(names.iter().all(|n| !n.contains(".tmp")), "{names:?}");
}

#[test]
fn obj_surface_is_closed_and_outward() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = BoxGrid::beam(1).build().unwrap();
    let path = dir.path().join("s.obj");
    io::write(&path, &mesh).unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    let v: Vec<[f64; 3]> = text
        .lines()
        .filter_map(|l| l.strip_prefix("v "))
        .map(|l| {
            let c: Vec<f64> = l.split_whitespace().map(|s| s.parse().unwrap()).collect();
            [c[0], c[1], c[2]]
        })
        .collect();
    let f: Vec<[usize; 3]> = text
        .lines()
        .filter_map(|l| l.strip_prefix("f "))
        .map(|l| {
            let c: Vec<usize> = l
                .split_whitespace()
                .map(|s| s.parse::<usize>().unwrap() - 1)
                .collect();
            [c[0], c[1], c[2]]
        })
        .collect();
    assert_eq!(v.len(), 20); // all vertices of a 4 x 1 x 1 grid are on the surface
    assert_eq!(f.len(), 2 * 2 * (4 + 1 + 4));
    let p = |i: usize| nalgebra::Vector3::from(v[i]);
    let vol: f64 = f
        .iter()
        .map(|t| p(t[0]).dot(&p(t[1]).cross(&p(t[2]))) / 6.0)
        .sum();
    assert_relative_eq!(vol, 0.0625, max_relative = 1e-12);
}

#[test]
fn obj_surfaces_read_back_as_written_and_as_the_mesh_boundary() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = BoxGrid::beam(2).build().unwrap();
    let obj = dir.path().join("s.obj");
    let msh = dir.path().join("s.msh");
    io::write(&obj, &mesh).unwrap();
    io::write(&msh, &mesh).unwrap();
    let boundary = deform_mesh::Surface::boundary(&mesh);
    // The .obj written and the .msh's boundary both read as the boundary surface.
    assert_eq!(io::read_surface(&obj).unwrap(), boundary);
    assert_eq!(io::read_surface(&msh).unwrap(), boundary);
}

#[test]
fn obj_reader_takes_polygons_relative_indices_and_slashes() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("quad.obj");
    let text = "# a unit square and a triangle\no square\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n\
                vn 0 0 1\nvt 0 0\nusemtl x\nf 1/1/1 2//1 3/1 4\nv 0 0 1 1.0\nf -5 -4 -1 # relative\n";
    std::fs::write(&path, text).unwrap();
    let s = io::read_surface(&path).unwrap();
    assert_eq!(s.positions.len(), 5);
    assert_eq!(s.triangles, vec![[0, 1, 2], [0, 2, 3], [0, 1, 4]]);
}

/// A UTF-8 byte-order mark before the first line is no part of it: the first vertex is
/// read (it was dropped, its line unrecognised, and the face then named a missing vertex or
/// the wrong one).
#[test]
fn a_byte_order_mark_does_not_hide_the_first_line() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bom.obj");
    std::fs::write(
        &path,
        "\u{feff}v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\n",
    )
    .unwrap();
    let s = io::read_surface(&path).unwrap();
    assert_eq!(s.positions.len(), 4);
    assert_eq!(s.positions[0], nalgebra::Vector3::zeros());
    assert_eq!(s.triangles, vec![[0, 1, 2]]);
}

/// A surface in a format deform does not read is refused naming the formats it does,
/// `.obj` among them.
#[test]
fn an_unknown_surface_format_names_obj_among_those_read() {
    let e = io::read_surface(Path::new("ground.stl")).unwrap_err();
    assert!(matches!(e, ReadError::UnknownSurfaceFormat { .. }), "{e}");
    let text = e.to_string();
    assert!(
        text.contains("ground.stl") && text.contains(".obj"),
        "{text}"
    );
}

#[test]
fn bad_obj_files_name_the_file_and_line() {
    let dir = tempfile::tempdir().unwrap();
    let cases = [
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n",
            4,
            "a vertex index in 1..=3",
        ),
        ("v 0 0 0\nv 1 0 x\n", 2, "a finite vertex coordinate"),
        ("v 0 0 0\nv 1 0 nan\n", 2, "a finite vertex coordinate"),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\n\nf 1 2\n",
            5,
            "a face of at least 3 vertices",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 2\n",
            4,
            "a face of distinct vertices",
        ),
        ("v 0 0 0\nf 0 1 1\n", 2, "a vertex index in 1..=1"),
    ];
    for (k, (text, line, expected)) in cases.iter().enumerate() {
        let path = dir.path().join(format!("bad{k}.obj"));
        std::fs::write(&path, text).unwrap();
        match io::read_surface(&path) {
            Err(ReadError::Parse {
                path: p,
                line: l,
                expected: e,
                ..
            }) => {
                assert_eq!(
                    (p, l, e.as_str()),
                    (path.clone(), *line, *expected),
                    "{text:?}"
                );
            }
            other => panic!("{text:?}: {other:?}"),
        }
    }
    let empty = dir.path().join("empty.obj");
    std::fs::write(&empty, "v 0 0 0\n").unwrap();
    let e = io::read_surface(&empty).unwrap_err();
    assert!(matches!(e, ReadError::InvalidSurface { .. }), "{e}");
    assert!(e.to_string().contains("empty.obj"), "{e}");
}

fn parse_err(text: &str) -> ReadError {
    io::parse_msh(text.as_bytes(), Path::new("bad.msh"))
        .and_then(|raw| raw.into_mesh(Path::new("bad.msh"), &MeshOptions::default()))
        .expect_err("the file is bad")
}

const GOOD_22: &str = "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n4\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n$EndNodes\n$Elements\n2\n1 15 2 0 1 1\n2 4 2 3 1 1 2 3 4\n$EndElements\n";

#[test]
fn bad_files_give_typed_errors_with_lines() {
    let ok = io::parse_msh(GOOD_22.as_bytes(), Path::new("good.msh")).unwrap();
    assert_eq!(ok.tets, vec![[0, 1, 2, 3]]);
    assert_eq!(ok.regions, vec![3]);

    // Truncated in the middle of the nodes: the announced count cannot fit.
    let cut = &GOOD_22[..GOOD_22.find("3 0 1 0").unwrap()];
    match parse_err(cut) {
        ReadError::Parse { line, found, .. } => {
            assert_eq!(line, 5);
            assert!(found.contains("bytes left"), "{found}");
        }
        e => panic!("{e}"),
    }
    // Truncated inside the last element.
    let cut = &GOOD_22[..GOOD_22.find("1 2 3 4\n").unwrap() + 5];
    match parse_err(cut) {
        ReadError::Parse {
            line,
            expected,
            found,
            ..
        } => {
            assert_eq!(line, 14);
            assert_eq!(expected, "node tag of the element");
            assert_eq!(found, "end of file");
        }
        e => panic!("{e}"),
    }
    // Wrong count: three elements announced, two present.
    match parse_err(&GOOD_22.replace("$Elements\n2", "$Elements\n3")) {
        ReadError::Parse { line, found, .. } => {
            assert_eq!(line, 15);
            assert!(found.contains("$EndElements"), "{found}");
        }
        e => panic!("{e}"),
    }
    // A tet refers to a node that does not exist.
    match parse_err(&GOOD_22.replace("1 2 3 4\n", "1 2 3 44\n")) {
        ReadError::Parse { line, found, .. } => {
            assert_eq!(line, 14);
            assert!(found.contains("undefined node 44"), "{found}");
        }
        e => panic!("{e}"),
    }
    // NaN coordinate: parsed, then rejected naming the file's node tag.
    match parse_err(&GOOD_22.replace("3 0 1 0", "3 0 nan 0")) {
        ReadError::Invalid {
            context,
            error: MeshError::NonFiniteCoordinate { vertex: 2, .. },
            ..
        } => {
            assert_eq!(context.as_deref(), Some("file node 3"));
        }
        e => panic!("{e}"),
    }
    // Degenerate tet (all four nodes in a plane).
    let e = parse_err(&GOOD_22.replace("4 0 0 1", "4 1 1 0"));
    assert!(
        matches!(
            e,
            ReadError::Invalid {
                error: MeshError::DegenerateElement { element: 0, .. },
                ..
            }
        ),
        "{e}"
    );
    assert!(e.to_string().contains("file element 2"), "{e}");
    assert!(e.to_string().starts_with("bad.msh:"), "{e}");
    // Repeated vertex.
    let e = parse_err(&GOOD_22.replace("1 2 3 4\n", "1 2 2 4\n"));
    assert!(
        matches!(
            e,
            ReadError::Invalid {
                error: MeshError::RepeatedVertex { .. },
                ..
            }
        ),
        "{e}"
    );
    // Unsupported version and bad header.
    assert!(matches!(
        parse_err(&GOOD_22.replace("2.2 0 8", "3.0 0 8")),
        ReadError::Unsupported { line: 2, .. }
    ));
    assert!(matches!(
        parse_err("hello"),
        ReadError::Parse { line: 1, .. }
    ));
    // A hostile count does not allocate: it is rejected against the file size.
    let e = parse_err(&GOOD_22.replace("$Nodes\n4", "$Nodes\n4000000000000"));
    assert!(matches!(e, ReadError::Parse { line: 5, .. }), "{e}");
}

#[test]
fn bad_tetgen_files_name_the_file_and_line() {
    let node = b"4 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0 # comment\n4 0 0 1\n";
    let ele = b"# tets\n1 4 0\n1 1 2 3 4\n";
    let (np, ep) = (Path::new("a.node"), Path::new("a.ele"));
    let raw = io::parse_tetgen(node, ele, np, ep).unwrap();
    assert_eq!(raw.tets, vec![[0, 1, 2, 3]]);
    let e = io::parse_tetgen(node, b"1 4 0\n1 1 2 3 0\n", np, ep).unwrap_err();
    assert!(
        matches!(&e, ReadError::Parse { path, line: 2, .. } if path == ep),
        "{e}"
    );
    let e = io::parse_tetgen(b"4 2 0 0\n", ele, np, ep).unwrap_err();
    assert!(
        matches!(&e, ReadError::Parse { path, line: 1, .. } if path == np),
        "{e}"
    );
    let e = io::parse_tetgen(b"4 3 0 0\n1 0 0 0\n2 1 0 0\n4 0 1 0\n", ele, np, ep).unwrap_err();
    assert!(matches!(&e, ReadError::Parse { line: 4, .. }), "{e}");
    // Out-of-range node index: caught by validation, naming the file's element index.
    let raw = io::parse_tetgen(node, b"1 4 0\n7 1 2 3 9\n", np, ep).unwrap();
    let e = raw.into_mesh(ep, &MeshOptions::default()).unwrap_err();
    assert!(
        matches!(
            e,
            ReadError::Invalid {
                error: MeshError::IndexOutOfRange { index: 8, .. },
                ..
            }
        ),
        "{e}"
    );
    assert!(e.to_string().contains("file element 7"), "{e}");
    let missing = io::read(Path::new("/nonexistent/x.msh"), &MeshOptions::default()).unwrap_err();
    assert!(matches!(missing, ReadError::Io { .. }));
    assert!(matches!(
        io::read(Path::new("x.stl"), &MeshOptions::default()),
        Err(ReadError::UnknownFormat { .. })
    ));
}

#[test]
fn tetgen_output_names_pair_up() {
    // TetGen writes `NAME.1.node` / `NAME.1.ele`; either file, or the stem, names the pair.
    let dir = tempfile::tempdir().unwrap();
    let mesh = deform_mesh::generate::BoxGrid::beam(1).build().unwrap();
    let stem = dir.path().join("slab.1");
    io::write_tetgen(&stem, &mesh).unwrap();
    assert!(dir.path().join("slab.1.node").exists() && dir.path().join("slab.1.ele").exists());
    for name in ["slab.1.ele", "slab.1.node", "slab.1"] {
        let back = io::read_tetgen(&dir.path().join(name), &Default::default())
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(back.num_tets(), mesh.num_tets(), "{name}");
    }
    let back = io::read(&dir.path().join("slab.1.ele"), &Default::default()).unwrap();
    assert_eq!(back.num_vertices(), mesh.num_vertices());
}

/// Two tets on either side of the face 1-2-3 (z = 0), Gmsh 4.1 ASCII.
const GOOD_41: &str = "$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n1 5 1 5\n3 1 0 5\n1\n2\n3\n4\n5\n0 0 0\n1 0 0\n0 1 0\n0 0 1\nNODE5\n$EndNodes\n$Elements\n1 2 1 2\n3 1 4 2\n1 1 2 3 4\n2 1 3 2 5\n$EndElements\n";

fn msh41(node5: &str, elements: &str) -> String {
    let good = GOOD_41.replace("NODE5", node5);
    let start = good.find("$Elements\n").unwrap();
    format!("{}$Elements\n{elements}$EndElements\n", &good[..start])
}

#[test]
fn duplicate_overlapping_and_nonmanifold_elements_are_refused_naming_them() {
    let good = GOOD_41.replace("NODE5", "0 0 -1");
    let mesh = io::parse_msh(good.as_bytes(), Path::new("a.msh"))
        .and_then(|raw| raw.into_mesh(Path::new("a.msh"), &MeshOptions::default()))
        .unwrap();
    assert_eq!(mesh.num_tets(), 2);
    // The element block doubled (as a copy-paste would): the same four nodes again.
    let doubled = msh41(
        "0 0 -1",
        "1 3 1 3\n3 1 4 3\n1 1 2 3 4\n2 1 3 2 5\n3 4 3 2 1\n",
    );
    let e = parse_err(&doubled);
    assert!(
        matches!(
            e,
            ReadError::Invalid {
                error: MeshError::DuplicateElement {
                    element: 2,
                    first: 0
                },
                ..
            }
        ),
        "{e}"
    );
    assert!(e.to_string().contains("file elements 1 and 3"), "{e}");
    // The second tet folded onto the first's side of their shared face.
    let e = parse_err(&msh41(
        "0.2 0.2 0.5",
        "1 2 1 2\n3 1 4 2\n1 1 2 3 4\n2 1 3 2 5\n",
    ));
    assert!(
        matches!(
            e,
            ReadError::Invalid {
                error: MeshError::OverlappingElements {
                    first: 0,
                    second: 1,
                    face: [0, 1, 2]
                },
                ..
            }
        ),
        "{e}"
    );
    assert!(e.to_string().contains("file elements 1 and 2"), "{e}");
    // Three tets on one face: refused by default, accepted when asked for.
    let three = GOOD_41
        .replace("NODE5", "0 0 -1\n0.3 0.3 2")
        .replace(
            "1 5 1 5\n3 1 0 5\n1\n2\n3\n4\n5\n",
            "1 6 1 6\n3 1 0 6\n1\n2\n3\n4\n5\n6\n",
        )
        .replace("1 2 1 2\n3 1 4 2\n", "1 3 1 3\n3 1 4 3\n")
        .replace("2 1 3 2 5\n", "2 1 3 2 5\n3 1 2 3 6\n");
    let e = parse_err(&three);
    assert!(
        matches!(&e, ReadError::Invalid { error: MeshError::NonManifoldFace { face: [0, 1, 2], elements }, .. } if elements == &[0, 1, 2]),
        "{e}"
    );
    assert!(e.to_string().contains("file elements 1, 2, 3"), "{e}");
    let allow = MeshOptions::default().allow_nonmanifold(true);
    let raw = io::parse_msh(three.as_bytes(), Path::new("a.msh")).unwrap();
    assert_eq!(
        raw.into_mesh(Path::new("a.msh"), &allow)
            .unwrap()
            .num_tets(),
        3
    );
}

#[test]
fn header_counts_must_match_what_follows() {
    // Gmsh 4.1: the header's totals against the blocks.
    let good = GOOD_41.replace("NODE5", "0 0 -1");
    let e = parse_err(&good.replace("1 5 1 5\n", "1 6 1 6\n"));
    assert!(
        matches!(&e, ReadError::Parse { line: 5, expected, .. } if expected.contains("6 nodes (the header's total)")),
        "{e}"
    );
    let e = parse_err(&good.replace("1 2 1 2\n", "1 1 1 2\n"));
    assert!(
        matches!(&e, ReadError::Parse { line: 19, found, .. } if found == "2 in the blocks"),
        "{e}"
    );
    // TetGen: a header that undercounts would drop the rest.
    let node = "5 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n5 0 0 -1\n";
    let (np, ep) = (Path::new("a.node"), Path::new("a.ele"));
    let e =
        io::parse_tetgen(node.as_bytes(), b"1 4 0\n1 1 2 3 4\n2 1 3 2 5\n", np, ep).unwrap_err();
    assert!(
        matches!(&e, ReadError::Parse { path, line: 3, .. } if path == ep),
        "{e}"
    );
    assert!(
        e.to_string().contains("after the header's 1 tetrahedra"),
        "{e}"
    );
    let e = io::parse_tetgen(
        node.replace("5 3 0 0", "4 3 0 0").as_bytes(),
        b"1 4 0\n1 1 2 3 4\n",
        np,
        ep,
    );
    assert!(matches!(&e, Err(ReadError::Parse { line: 6, .. })), "{e:?}");
}

#[test]
fn non_tetrahedral_volume_elements_are_refused_not_dropped() {
    // A hexahedron block beside the tets (4.1) and a prism (2.2): part of the volume.
    let hex = msh41(
        "0 0 -1",
        "2 3 1 3\n3 1 4 2\n1 1 2 3 4\n2 1 3 2 5\n3 2 5 1\n3 1 2 3 4 5 1 2 3\n",
    );
    let e = parse_err(&hex);
    assert!(
        matches!(&e, ReadError::Unsupported { line: 23, what, .. } if what.contains("type 5")),
        "{e}"
    );
    let prism = GOOD_22.replace("$Elements\n2\n", "$Elements\n3\n3 6 2 0 1 1 2 3 1 2 4\n");
    let e = parse_err(&prism);
    assert!(
        matches!(&e, ReadError::Unsupported { line: 13, what, .. } if what.contains("type 6")),
        "{e}"
    );
}
