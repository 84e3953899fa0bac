//! Every parser of user input (meshes, scenes, experiments, `.npy` arrays), fed random and
//! mutated bytes of real files, returns `Ok` or a typed error and never panics (the
//! `cargo fuzz` targets in `fuzz/` do the same at scale).

use std::path::Path;

use deform_mesh::MeshOptions;
use deform_mesh::io::{ReadError, parse_msh, parse_tetgen};
use deform_tests::{asset, mesh_fixture};
use proptest::prelude::*;

fn msh_files() -> Vec<Vec<u8>> {
    let mut files: Vec<Vec<u8>> = [
        "two_boxes_22_ascii.msh",
        "two_boxes_22_binary.msh",
        "two_boxes_41_ascii.msh",
        "two_boxes_41_binary.msh",
    ]
    .iter()
    .map(|f| std::fs::read(mesh_fixture(f)).unwrap())
    .collect();
    files.push(std::fs::read(asset("meshes/bracket.msh")).unwrap());
    files
}

/// Parses and, when that succeeds, validates: both stages must stay panic-free.
fn check_msh(bytes: &[u8]) {
    let path = Path::new("fuzz.msh");
    match parse_msh(bytes, path) {
        Ok(raw) => {
            let _ = raw.into_mesh(path, &MeshOptions::default());
        }
        Err(ReadError::Parse { line, .. } | ReadError::Unsupported { line, .. }) => {
            assert!(line >= 1)
        }
        Err(e) => panic!("unexpected error kind: {e}"),
    }
}

fn check_tetgen(node: &[u8], ele: &[u8]) {
    let (np, ep) = (Path::new("f.node"), Path::new("f.ele"));
    if let Ok(raw) = parse_tetgen(node, ele, np, ep) {
        let _ = raw.into_mesh(ep, &MeshOptions::default());
    }
}

#[derive(Debug, Clone)]
enum Mutation {
    Truncate(usize),
    Flip(Vec<(usize, u8)>),
    Insert(usize, Vec<u8>),
    Delete(usize, usize),
    Digits(usize, Vec<u8>),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        any::<usize>().prop_map(Mutation::Truncate),
        prop::collection::vec((any::<usize>(), any::<u8>()), 1..8).prop_map(Mutation::Flip),
        (any::<usize>(), prop::collection::vec(any::<u8>(), 1..16))
            .prop_map(|(a, b)| Mutation::Insert(a, b)),
        (any::<usize>(), 1usize..64).prop_map(|(a, b)| Mutation::Delete(a, b)),
        (
            any::<usize>(),
            prop::collection::vec(prop::sample::select(b"0123456789-.e \n".to_vec()), 1..12)
        )
            .prop_map(|(a, b)| Mutation::Digits(a, b)),
    ]
}

fn apply(mut bytes: Vec<u8>, m: &Mutation) -> Vec<u8> {
    let n = bytes.len().max(1);
    match m {
        Mutation::Truncate(at) => bytes.truncate(at % n),
        Mutation::Flip(flips) => {
            for (at, v) in flips {
                let k = at % n;
                if k < bytes.len() {
                    bytes[k] ^= v | 1;
                }
            }
        }
        Mutation::Insert(at, b) => {
            let k = at % n;
            bytes.splice(k..k, b.iter().copied());
        }
        Mutation::Delete(at, len) => {
            let k = at % n;
            let end = (k + len).min(bytes.len());
            bytes.drain(k..end);
        }
        Mutation::Digits(at, b) => {
            let k = at % n;
            let end = (k + b.len()).min(bytes.len());
            bytes.splice(k..end, b.iter().copied());
        }
    }
    bytes
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn msh_parser_survives_mutated_real_files(file in 0usize..5, muts in prop::collection::vec(mutation(), 1..4)) {
        let files = msh_files();
        let bytes = muts.iter().fold(files[file].clone(), apply);
        check_msh(&bytes);
    }

    #[test]
    fn msh_parser_survives_random_bytes(
        header in prop::sample::select(vec!["", "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n", "$MeshFormat\n4.1 1 8\n\x01\0\0\0\n$EndMeshFormat\n$Nodes\n", "$MeshFormat\n2.2 1 8\n\x01\0\0\0\n$EndMeshFormat\n$Nodes\n3\n"]),
        body in prop::collection::vec(any::<u8>(), 0..512),
    ) {
        let mut bytes = header.as_bytes().to_vec();
        bytes.extend(body);
        check_msh(&bytes);
    }

    #[test]
    fn tetgen_parser_survives_mutated_real_files(in_node in any::<bool>(), muts in prop::collection::vec(mutation(), 1..4)) {
        let node = std::fs::read(asset("meshes/block.node")).unwrap();
        let ele = std::fs::read(asset("meshes/block.ele")).unwrap();
        let (node, ele) = if in_node {
            (muts.iter().fold(node, apply), ele)
        } else {
            (node, muts.iter().fold(ele, apply))
        };
        check_tetgen(&node, &ele);
    }

    #[test]
    fn tetgen_parser_survives_random_bytes(node in prop::collection::vec(any::<u8>(), 0..256), ele in prop::collection::vec(any::<u8>(), 0..256)) {
        check_tetgen(&node, &ele);
        check_tetgen(b"4 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n", &ele);
    }
}

/// Every bundled file of `folder` (scenes or experiments).
fn ron_files(folder: &str) -> Vec<Vec<u8>> {
    let mut files: Vec<_> = std::fs::read_dir(asset(folder))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "ron"))
        .collect();
    files.sort();
    files.iter().map(|p| std::fs::read(p).unwrap()).collect()
}

/// A valid `.npy` of shape (3, 2, 3).
fn npy_file() -> Vec<u8> {
    let header = "{'descr': '<f8', 'fortran_order': False, 'shape': (3, 2, 3), }";
    let header = format!("{header:<117}\n");
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend((header.len() as u16).to_le_bytes());
    bytes.extend(header.as_bytes());
    for i in 0..18 {
        bytes.extend((i as f64).to_le_bytes());
    }
    bytes
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn scene_parser_survives_mutated_bundled_scenes(file in any::<prop::sample::Index>(), muts in prop::collection::vec(mutation(), 1..4)) {
        let files = ron_files("scenes");
        let bytes = muts.iter().fold(files[file.index(files.len())].clone(), apply);
        let _ = deform_integrator::Scene::parse(&String::from_utf8_lossy(&bytes), Path::new("f.ron"));
    }

    #[test]
    fn experiment_parser_survives_mutated_bundled_experiments(file in any::<prop::sample::Index>(), muts in prop::collection::vec(mutation(), 1..4)) {
        let files = ron_files("experiments");
        let bytes = muts.iter().fold(files[file.index(files.len())].clone(), apply);
        let text = String::from_utf8_lossy(&bytes);
        let _ = deform_studies::Experiment::parse(&text, Path::new("f.ron"));
    }

    #[test]
    fn npy_parser_survives_mutated_arrays(muts in prop::collection::vec(mutation(), 1..4)) {
        let bytes = muts.iter().fold(npy_file(), apply);
        let _ = deform_learn::npy::parse(&bytes);
    }
}

#[test]
fn the_unmutated_files_parse() {
    for (i, f) in ron_files("scenes").iter().enumerate() {
        let text = String::from_utf8_lossy(f);
        deform_integrator::Scene::parse(&text, Path::new("f.ron"))
            .unwrap_or_else(|e| panic!("scene {i}: {e}"));
    }
    for (i, f) in ron_files("experiments").iter().enumerate() {
        let text = String::from_utf8_lossy(f);
        deform_studies::Experiment::parse(&text, Path::new("f.ron"))
            .unwrap_or_else(|e| panic!("experiment {i}: {e}"));
    }
    let a = deform_learn::npy::parse(&npy_file()).unwrap();
    assert_eq!(a.shape, vec![3, 2, 3]);
}
