//! Cost per evaluation of `P + dP/dF` (plain and SPD-projected) for every model, on a
//! batch of 1024 deformation gradients (moderate stretch, random rotations).
//!
//! `cargo bench -p deform-materials`; criterion reports elements (evaluations) per second.

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use deform_materials::{
    CorotatedLinear, Ensemble, FixedCorotated, Lame, LinearElastic, Material, Model, NeoHookean,
    StVenantKirchhoff, StableNeoHookean,
};
use nalgebra::{Matrix3, Rotation3, Vector3};

/// Deterministic pseudo-random gradients (an LCG: no dependency, same batch every run).
fn batch(n: usize) -> Vec<Matrix3<f64>> {
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut next = move || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    (0..n)
        .map(|_| {
            let r =
                Rotation3::from_euler_angles(6.0 * next(), 6.0 * next(), 6.0 * next()).into_inner();
            let s = Vector3::new(0.8 + 0.4 * next(), 0.8 + 0.4 * next(), 0.8 + 0.4 * next());
            r * Matrix3::from_diagonal(&s)
        })
        .collect()
}

fn benches(c: &mut Criterion) {
    let l = Lame::from_young(1e6, 0.4).unwrap();
    let models = [
        ("linear", Model::Linear(LinearElastic { lame: l })),
        (
            "corotated",
            Model::Corotated(CorotatedLinear {
                lame: l,
                lagged_rotation: false,
            }),
        ),
        (
            "corotated_lagged",
            Model::Corotated(CorotatedLinear {
                lame: l,
                lagged_rotation: true,
            }),
        ),
        (
            "fixed_corotated",
            Model::FixedCorotated(FixedCorotated { lame: l }),
        ),
        (
            "stvk",
            Model::StVenantKirchhoff(StVenantKirchhoff { lame: l }),
        ),
        ("neo_hookean", Model::NeoHookean(NeoHookean { lame: l })),
        (
            "stable_neo_hookean",
            Model::StableNeoHookean(StableNeoHookean { lame: l }),
        ),
        (
            "ensemble4",
            Model::Ensemble(
                Ensemble::try_new(vec![
                    (
                        0.25,
                        Model::Corotated(CorotatedLinear {
                            lame: l,
                            lagged_rotation: false,
                        }),
                    ),
                    (0.25, Model::Linear(LinearElastic { lame: l })),
                    (
                        0.25,
                        Model::StVenantKirchhoff(StVenantKirchhoff { lame: l }),
                    ),
                    (0.25, Model::NeoHookean(NeoHookean { lame: l })),
                ])
                .unwrap(),
            ),
        ),
    ];
    let fs = batch(1024);
    let mut g = c.benchmark_group("materials");
    g.throughput(Throughput::Elements(fs.len() as u64));
    for (name, m) in &models {
        g.bench_function(format!("{name}/P+tangent"), |b| {
            b.iter(|| {
                fs.iter()
                    .map(|f| m.first_piola_and_tangent(black_box(f), false).1[(4, 4)])
                    .sum::<f64>()
            })
        });
        g.bench_function(format!("{name}/P+projected"), |b| {
            b.iter(|| {
                fs.iter()
                    .map(|f| m.first_piola_and_tangent(black_box(f), true).1[(4, 4)])
                    .sum::<f64>()
            })
        });
    }
    // The concrete type, without the enum dispatch, for the Neo-Hookean target.
    let nh = NeoHookean { lame: l };
    g.bench_function("neo_hookean_concrete/P+tangent", |b| {
        b.iter(|| {
            fs.iter()
                .map(|f| nh.first_piola_and_tangent(black_box(f), false).1[(4, 4)])
                .sum::<f64>()
        })
    });
    g.finish();
}

criterion_group!(material_benches, benches);
criterion_main!(material_benches);
