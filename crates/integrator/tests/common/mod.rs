//! Helpers shared by the contact integration tests, kept independent of the crate's own
//! collision code so that their checks stay exact and separate from what they test.
//! Each test binary uses a part of them.
#![allow(dead_code)]

use deform_integrator::{Integrator, State};
use nalgebra::Vector3;

/// Whether the segment `p q` crosses the triangle `t` (closed), exactly up to rounding:
/// the segment's end points lie on opposite sides of the triangle's plane and the crossing
/// point lies inside the triangle.
pub fn crosses(p: Vector3<f64>, q: Vector3<f64>, t: [Vector3<f64>; 3]) -> bool {
    let n = (t[1] - t[0]).cross(&(t[2] - t[0]));
    let (sp, sq) = ((p - t[0]).dot(&n), (q - t[0]).dot(&n));
    if sp * sq > 0.0 || sp == sq {
        return false;
    }
    let x = p + (q - p) * (sp / (sp - sq));
    (0..3).all(|i| {
        let (a, b) = (t[i], t[(i + 1) % 3]);
        (b - a).cross(&(x - a)).dot(&n) >= 0.0
    })
}

/// Kinetic, elastic, barrier and gravitational energy.
pub fn total_energy(sim: &mut Integrator, s: &State) -> f64 {
    let masses = sim.assembly().vertex_masses(sim.mass());
    let g = Vector3::from(sim.gravity());
    let mut elastic = 0.0;
    sim.assembly_mut()
        .evaluate(
            &s.x,
            deform_assembly::Outputs {
                energy: Some(&mut elastic),
                ..Default::default()
            },
        )
        .unwrap();
    let barrier = sim
        .contact()
        .unwrap()
        .evaluate(&s.x, None, None)
        .unwrap()
        .energy;
    let mut other = 0.0;
    for (v, m) in masses.iter().enumerate() {
        let (x, u) = (&s.x[3 * v..3 * v + 3], &s.v[3 * v..3 * v + 3]);
        other += 0.5 * m * u.iter().map(|u| u * u).sum::<f64>();
        other -= m * (g.x * x[0] + g.y * x[1] + g.z * x[2]);
    }
    elastic + barrier + other
}

/// The edges of `triangles`, each once, as sorted vertex pairs.
pub fn edges(triangles: &[[usize; 3]]) -> Vec<[usize; 2]> {
    let mut e: Vec<[usize; 2]> = triangles
        .iter()
        .flat_map(|f| [[f[0], f[1]], [f[1], f[2]], [f[2], f[0]]])
        .map(|[a, b]| [a.min(b), a.max(b)])
        .collect();
    e.sort_unstable();
    e.dedup();
    e
}

/// Whether an edge of one surface crosses a triangle of the other (`a` at `pa`, `b` at
/// `pb`).
pub fn surfaces_cross(
    (pa, a): (&[Vector3<f64>], &[[usize; 3]]),
    (pb, b): (&[Vector3<f64>], &[[usize; 3]]),
) -> bool {
    let one_way = |pa: &[Vector3<f64>], a: &[[usize; 3]], pb: &[Vector3<f64>], b: &[[usize; 3]]| {
        edges(a).iter().any(|e| {
            b.iter()
                .any(|t| crosses(pa[e[0]], pa[e[1]], t.map(|v| pb[v])))
        })
    };
    one_way(pa, a, pb, b) || one_way(pb, b, pa, a)
}
