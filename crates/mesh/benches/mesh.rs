//! Mesh-side costs that every run pays once: generation, validation, topology, the
//! stiffness pattern, reading a real `.msh`, and writing a `.vtu` frame.
//!
//! `cargo bench -p deform-mesh` (beam family of BENCHMARKS.md, n = 8 and 16).

use std::hint::black_box;
use std::path::Path;

use criterion::{Criterion, criterion_group, criterion_main};
use deform_mesh::generate::BoxGrid;
use deform_mesh::io::{MshFormat, Vtu, parse_msh};
use deform_mesh::topology::{BlockPattern, faces};
use deform_mesh::{MeshOptions, TetMesh};

fn benches(c: &mut Criterion) {
    let mut g = c.benchmark_group("mesh");
    g.sample_size(10);
    for n in [8usize, 16] {
        let mesh = BoxGrid::beam(n).build().unwrap();
        let tets = mesh.num_tets();
        g.bench_function(format!("generate+validate/beam{n} ({tets} tets)"), |b| {
            b.iter(|| BoxGrid::beam(black_box(n)).build().unwrap())
        });
        g.bench_function(format!("faces/beam{n}"), |b| {
            b.iter(|| faces(black_box(&mesh)))
        });
        g.bench_function(format!("block_pattern/beam{n}"), |b| {
            b.iter(|| BlockPattern::new(black_box(&mesh)))
        });
        let pattern = BlockPattern::new(&mesh);
        g.bench_function(format!("scalar_csr/beam{n}"), |b| {
            b.iter(|| pattern.scalar_csr())
        });
        g.bench_function(format!("element_blocks/beam{n}"), |b| {
            b.iter(|| pattern.element_blocks(&mesh))
        });
        let x = mesh.rest_positions_flat();
        g.bench_function(format!("vtu_to_memory/beam{n}"), |b| {
            b.iter(|| {
                let mut out = Vec::new();
                Vtu::deformed(&mesh, &x).write_to(&mut out).unwrap();
                out
            })
        });
        for binary in [false, true] {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("m.msh");
            deform_mesh::io::write_msh(
                &path,
                &mesh,
                MshFormat {
                    binary,
                    ..Default::default()
                },
            )
            .unwrap();
            let bytes = std::fs::read(&path).unwrap();
            let label = if binary { "binary" } else { "ascii" };
            g.bench_function(format!("read_msh41_{label}/beam{n}"), |b| {
                b.iter(|| {
                    let raw = parse_msh(black_box(&bytes), Path::new("m.msh")).unwrap();
                    TetMesh::try_with_options(
                        raw.positions,
                        raw.tets,
                        Some(raw.regions),
                        &MeshOptions::default(),
                    )
                    .unwrap()
                })
            });
        }
    }
    g.finish();
}

criterion_group!(mesh_benches, benches);
criterion_main!(mesh_benches);
