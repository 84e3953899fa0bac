//! Datasets round-trip through disk, merge in order, and refuse empty and non-finite arrays.

mod common;

use common::*;
use std::path::Path;

use deform_learn::DatasetSpec;
use deform_learn::dataset::generate;
use deform_learn::import::{Velocities, import_trajectory};
use deform_learn::{Dataset, Split, Variations, npy};

#[test]
fn datasets_round_trip_through_disk_and_split_by_trajectory() {
    let s = scene("", "Beam(1)");
    let data = make(&s, 5, 4);
    let dir = tempfile::tempdir().unwrap();
    data.save(dir.path()).unwrap();
    let back = Dataset::load(dir.path()).unwrap();
    assert_eq!(back, data);
    let splits: Vec<Split> = data.meta.trajectories.iter().map(|t| t.split).collect();
    assert_eq!(
        splits,
        [
            Split::Train,
            Split::Train,
            Split::Train,
            Split::Validation,
            Split::Test
        ]
    );
    // numpy's layout: (steps + 1, vertices, 3).
    let x = npy::read(&dir.path().join("traj_000/x.npy")).unwrap();
    assert_eq!(x.shape, vec![5, data.meta.vertices, 3]);
    // Regeneration with the same seed is bit-identical; another seed differs.
    assert_eq!(make(&s, 5, 4), data);
    let other = generate(
        &s,
        Path::new("t"),
        &DatasetSpec::new(5, 4, 43)
            .variations(Variations::default())
            .split((0.6, 0.2)),
        |_, _| {},
    )
    .unwrap();
    assert_ne!(other.trajectories, data.trajectories);
    // A corrupted array is reported with its file.
    std::fs::write(
        dir.path().join("traj_001/v.npy"),
        b"\x93NUMPY\x01\x00garbage",
    )
    .unwrap();
    let e = Dataset::load(dir.path()).unwrap_err().to_string();
    assert!(e.contains("traj_001") && e.contains("v.npy"), "{e}");
}

#[test]
fn datasets_of_one_model_merge_in_order_and_others_are_refused() {
    let s = scene("", "Beam(1)");
    let part = |seed| {
        let spec = DatasetSpec::new(2, 3, seed);
        generate(&s, Path::new("test"), &spec, |_, _| {}).unwrap()
    };
    let (a, b) = (part(1), part(2));
    let merged = Dataset::merge(vec![a.clone(), b.clone()]).unwrap();
    assert_eq!(merged.trajectories.len(), 4);
    assert_eq!(&merged.trajectories[..2], &a.trajectories[..]);
    assert_eq!(&merged.trajectories[2..], &b.trajectories[..]);
    let names: Vec<&str> = merged
        .meta
        .trajectories
        .iter()
        .map(|m| m.name.as_str())
        .collect();
    assert_eq!(names, ["traj_000", "traj_001", "traj_002", "traj_003"]);
    assert_eq!(
        merged.meta.trajectories[2].initial,
        b.meta.trajectories[0].initial
    );
    // It saves and loads like any dataset.
    let dir = tempfile::tempdir().unwrap();
    merged.save(dir.path()).unwrap();
    assert_eq!(Dataset::load(dir.path()).unwrap(), merged);
    let mut other = scene("", "Beam(1)");
    other.density = 2000.0;
    let c = generate(
        &other,
        Path::new("test"),
        &DatasetSpec::new(1, 3, 3),
        |_, _| {},
    )
    .unwrap();
    let e = Dataset::merge(vec![a, c]).unwrap_err().to_string();
    assert!(e.contains("dataset 1") && e.contains("scene"), "{e}");
    assert!(Dataset::merge(Vec::new()).is_err());
}

#[test]
fn imports_and_loads_refuse_empty_and_non_finite_arrays() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("x.npy");
    // (3, 0, 3): no vertex (was a panic).
    npy::write(&p, &[3, 0, 3], &[]).unwrap();
    let e = import_trajectory(&p, Velocities::Derived, 0.01)
        .unwrap_err()
        .to_string();
    assert!(e.contains("x.npy") && e.contains("vertices"), "{e}");
    // A NaN position names the step and vertex.
    let mut data = vec![0.0; 3 * 2 * 3];
    data[3 * 2 + 4] = f64::NAN; // step 1, vertex 1
    npy::write(&p, &[3, 2, 3], &data).unwrap();
    let e = import_trajectory(&p, Velocities::Derived, 0.01)
        .unwrap_err()
        .to_string();
    assert!(e.contains("step 1, vertex 1"), "{e}");
    // A dataset whose metadata says zero vertices (was a panic).
    let s = scene("", "Beam(1)");
    let data = make(&s, 3, 2);
    data.save(dir.path()).unwrap();
    let meta = dir.path().join("meta.ron");
    let text = std::fs::read_to_string(&meta).unwrap();
    let vertices = format!("vertices: {}", data.meta.vertices);
    assert!(text.contains(&vertices), "{text}");
    std::fs::write(&meta, text.replace(&vertices, "vertices: 0")).unwrap();
    let e = Dataset::load(dir.path()).unwrap_err().to_string();
    assert!(e.contains("meta.ron") && e.contains("vertices"), "{e}");
}
