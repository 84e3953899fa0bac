//! The beam, materials and helpers shared by the integrator and Newton tests.
#![allow(dead_code, unused_imports)]

use deform_solvers::WorkWeights;
use std::ops::ControlFlow;

use deform_assembly::MaterialField;
use deform_integrator::{
    Constraint, Integrator, IntegratorError, IntegratorOptions, IterationReport, Motion,
    NewtonOptions, NoObserver, Observer, PolicySpec, RunOptions, State, StepError, StepReport,
    Termination, Until,
};
use deform_materials::MaterialSpec;
use deform_mesh::TetMesh;
use deform_mesh::generate::BoxGrid;

pub fn material(spec: &str) -> MaterialField {
    MaterialField::Uniform(
        ron::from_str::<MaterialSpec>(spec)
            .unwrap()
            .build()
            .unwrap(),
    )
}

pub const NH: &str = "NeoHookean(Young(e: 1e5, nu: 0.4))";

pub fn beam() -> TetMesh {
    BoxGrid::beam(1).build().unwrap()
}

pub fn clamp(mesh: &TetMesh) -> Vec<Constraint> {
    vec![Constraint {
        vertices: (0..mesh.num_vertices())
            .filter(|&v| mesh.rest_positions()[v].x < 1e-9)
            .collect(),
        motion: Motion::Fixed,
    }]
}

pub fn policy(ron_text: &str) -> Box<dyn deform_integrator::SolverPolicy> {
    ron::from_str::<PolicySpec>(ron_text)
        .unwrap()
        .build()
        .unwrap()
}

pub fn sim(
    mesh: &TetMesh,
    constraints: Vec<Constraint>,
    options: IntegratorOptions,
    p: &str,
) -> Integrator {
    Integrator::builder(mesh, material(NH))
        .density(1000.0)
        .constraints(constraints)
        .options(options)
        .policy(policy(p))
        .build()
        .unwrap()
}

pub fn momentum(sim: &Integrator, v: &[f64]) -> [f64; 3] {
    let m = sim.assembly().vertex_masses(sim.mass());
    let mut p = [0.0; 3];
    for (i, vi) in v.iter().enumerate() {
        p[i % 3] += m[i / 3] * vi;
    }
    p
}

/// Total energy: kinetic + elastic + gravitational (`-x . M g`).
pub fn total_energy(s: &mut Integrator, st: &State) -> f64 {
    let m = s.assembly().vertex_masses(s.mass());
    let kinetic: f64 =
        st.v.iter()
            .enumerate()
            .map(|(i, v)| 0.5 * m[i / 3] * v * v)
            .sum();
    let gravity: f64 = -st
        .x
        .iter()
        .zip(s.gravity_forces())
        .map(|(x, g)| x * g)
        .sum::<f64>();
    kinetic + s.assembly_mut().energy(&st.x).unwrap() + gravity
}

/// The residual of Backward Euler at `(x1, v1)` from `(x0, v0)`, assembled from scratch.
pub fn residual_norm(s: &mut Integrator, start: &State, end: &State) -> f64 {
    let o = s.options().clone();
    let n = end.x.len();
    let mut k = s.assembly().stiffness_matrix();
    let mut f = vec![0.0; n];
    let asm = s.assembly_mut();
    asm.forces(&end.x, &mut f).unwrap();
    asm.stiffness(&end.x, deform_assembly::Tangent::Exact, &mut k)
        .unwrap();
    let (mut fd, mut r) = (vec![0.0; n], vec![0.0; n]);
    let dv: Vec<f64> = end.v.iter().zip(&start.v).map(|(a, b)| a - b).collect();
    let asm = s.assembly();
    asm.damping_forces(o.alpha, o.gamma, s.mass(), &k, &end.v, &mut fd)
        .unwrap();
    asm.mass_apply(s.mass(), &dv, &mut r).unwrap();
    let g = s.gravity_forces();
    for i in 0..n {
        r[i] -= o.dt * (f[i] + fd[i] + g[i]);
    }
    let mut free = vec![0.0; s.dofs().num_free()];
    s.dofs().restrict(&r, &mut free).unwrap();
    free.iter().map(|v| v * v).sum::<f64>().sqrt()
}
