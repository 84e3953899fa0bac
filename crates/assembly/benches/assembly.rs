//! Assembly throughput on the beam family of `docs/benchmarks.md` (Neo-Hookean,
//! E = 1e6, nu = 0.4, deformed state `X + (0.01 x z, 0.005 sin 3x, -0.1 x^2)`): pattern build,
//! energy, forces, K fill (exact and projected), energy + forces + K in one pass, and the
//! matrix-free differential. Criterion reports elements (tets) per second.
//!
//! `cargo bench -p deform-assembly --bench assembly` (all sizes) or append
//! `-- 'n=16'` for one size. The thread count is rayon's default (all cores); set
//! `RAYON_NUM_THREADS=1` for single-core figures.

use std::hint::black_box;
use std::time::Duration;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use deform_assembly::{Assembly, MaterialField, Outputs, Tangent};
use deform_materials::MaterialSpec;
use deform_mesh::generate::BoxGrid;

fn benchmark_state(mesh: &deform_mesh::TetMesh) -> Vec<f64> {
    mesh.rest_positions()
        .iter()
        .flat_map(|p| {
            [
                p.x + 0.01 * p.x * p.z,
                p.y + 0.005 * (3.0 * p.x).sin(),
                p.z - 0.1 * p.x * p.x,
            ]
        })
        .collect()
}

fn benches(c: &mut Criterion) {
    let model = ron::from_str::<MaterialSpec>("NeoHookean(Young(e: 1e6, nu: 0.4))")
        .unwrap()
        .build()
        .unwrap();
    let sizes: Vec<usize> = match std::env::var("DEFORM_BENCH_SIZES") {
        Ok(s) => s.split(',').filter_map(|v| v.trim().parse().ok()).collect(),
        Err(_) => vec![4, 8, 16, 32],
    };
    let mut group = c.benchmark_group("assembly");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_millis(500));
    for n in sizes {
        let mesh = BoxGrid::beam(n).build().unwrap();
        let x = benchmark_state(&mesh);
        let tets = mesh.num_tets() as u64;
        let id = |what: &str| BenchmarkId::new(what, format!("n={n}"));
        group.throughput(Throughput::Elements(tets));
        group.measurement_time(Duration::from_secs(if n >= 32 { 20 } else { 4 }));
        group.bench_function(id("pattern"), |b| {
            b.iter(|| {
                Assembly::new(black_box(&mesh), MaterialField::Uniform(model.clone())).unwrap()
            })
        });
        let mut asm = Assembly::new(&mesh, MaterialField::Uniform(model.clone())).unwrap();
        let mut f = vec![0.0; x.len()];
        let mut k = asm.stiffness_matrix();
        group.bench_function(id("energy"), |b| {
            b.iter(|| asm.energy(black_box(&x)).unwrap())
        });
        group.bench_function(id("forces"), |b| {
            b.iter(|| asm.forces(black_box(&x), &mut f).unwrap())
        });
        group.bench_function(id("k_fill"), |b| {
            b.iter(|| {
                asm.stiffness(black_box(&x), Tangent::Exact, &mut k)
                    .unwrap()
            })
        });
        group.bench_function(id("k_fill_projected"), |b| {
            b.iter(|| {
                asm.stiffness(black_box(&x), Tangent::Projected, &mut k)
                    .unwrap()
            })
        });
        group.bench_function(id("energy_forces_k"), |b| {
            b.iter(|| {
                let mut e = 0.0;
                asm.evaluate(
                    black_box(&x),
                    Outputs {
                        energy: Some(&mut e),
                        forces: Some(&mut f),
                        stiffness: Some(&mut k),
                        tangent: Tangent::Exact,
                        ..Outputs::default()
                    },
                )
                .unwrap();
                e
            })
        });
        let dx: Vec<f64> = (0..x.len()).map(|i| (i as f64).sin()).collect();
        group.bench_function(id("force_differential"), |b| {
            b.iter(|| asm.force_differential(black_box(&x), &dx, &mut f).unwrap())
        });
        let tangents = asm.tangents(&x, Tangent::Exact).unwrap();
        group.bench_function(id("tangent_apply"), |b| {
            b.iter(|| tangents.apply(black_box(&dx), &mut f))
        });
    }
    group.finish();
}

criterion_group!(assembly, benches);
criterion_main!(assembly);
