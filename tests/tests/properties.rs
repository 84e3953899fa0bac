//! Property tests of the integrator and the learning layer over random models and states:
//! a converged Backward-Euler step satisfies the discrete equations of motion (seed Eq. 7-9,
//! checked with the assembly's forces, mass and K, independently of the Newton loop), and
//! the output-error loss's adjoint gradient equals its central finite differences.

use std::path::Path;

use deform_integrator::{Scene, StepError};
use deform_learn::{DatasetSpec, OutputError, OutputErrorOptions, Split, dataset::generate};
use deform_solvers::LinearOperator;
use proptest::prelude::*;

/// A clamped n = 1 beam (24 tets) of `model` with the given moduli, damping and initial
/// velocity, solved to `rel` without retries.
fn scene(model: &str, e: f64, nu: f64, damping: (f64, f64), velocity: [f64; 3]) -> Scene {
    let text = format!(
        r#"Scene(
            name: "property",
            mesh: Beam(1),
            material: {model}(Young(e: {e:e}, nu: {nu})),
            density: 1000.0,
            constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
            integrator: (dt: 0.01, alpha: {}, gamma: {}, max_retries: 0,
                newton: (rel: 1e-9, abs: 1e-12)),
            initial: (velocity: ({:e}, {:e}, {:e})),
            steps: 1,
        )"#,
        damping.0, damping.1, velocity[0], velocity[1], velocity[2]
    );
    ron::from_str(&text).unwrap_or_else(|e| panic!("{e}\n{text}"))
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|a| a * a).sum::<f64>().sqrt()
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]

    #[test]
    fn a_converged_backward_euler_step_solves_its_equations(
        model in prop::sample::select(vec!["NeoHookean", "StVenantKirchhoff", "FixedCorotated", "StableNeoHookean"]),
        e in 1e4f64..1e6,
        nu in 0.05f64..0.45,
        alpha in 0.0f64..2.0,
        gamma in 0.0f64..0.01,
        vx in -1.0f64..1.0, vy in -1.0f64..1.0, vz in -1.0f64..1.0,
    ) {
        let s = scene(model, e, nu, (alpha, gamma), [vx, vy, vz]);
        let mut built = s.build(Path::new(".")).unwrap();
        let (x0, v0) = (built.state.x.clone(), built.state.v.clone());
        let step = built.integrator.step(&mut built.state);
        // A step that cannot converge must say so, never return a wrong state.
        if let Err(err) = &step {
            prop_assert!(matches!(err, StepError::NotConverged { .. } | StepError::Assembly { .. }), "{err}");
        }
        prop_assume!(step.is_ok());
        let report = step.unwrap();
        let sim = &mut built.integrator;
        let (x1, v1) = (built.state.x.clone(), built.state.v.clone());
        let dt = 0.01;
        let n = x1.len();
        // Positions follow the velocities: x1 = x0 + dt v1 (constrained DOFs stay put).
        for i in 0..n {
            prop_assert!((x1[i] - (x0[i] + dt * v1[i])).abs() <= 1e-12 * (1.0 + x1[i].abs()));
        }
        // r = M (v1 - v0) - dt (f(x1) - alpha M v1 - gamma K(x1) v1 + M g), on the free DOFs.
        let mass = sim.mass().clone();
        let asm = sim.assembly_mut();
        let mut f = vec![0.0; n];
        asm.forces(&x1, &mut f).unwrap();
        let mut k = asm.stiffness_matrix();
        asm.stiffness(&x1, deform_assembly::Tangent::Exact, &mut k).unwrap();
        let mut kv = vec![0.0; n];
        k.apply(&v1, &mut kv);
        let dv: Vec<f64> = v1.iter().zip(&v0).map(|(a, b)| a - b).collect();
        let (mut m_dv, mut m_v, mut m_g) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
        asm.mass_apply(&mass, &dv, &mut m_dv).unwrap();
        asm.mass_apply(&mass, &v1, &mut m_v).unwrap();
        let g: Vec<f64> = (0..n).map(|i| if i % 3 == 2 { -9.81 } else { 0.0 }).collect();
        asm.mass_apply(&mass, &g, &mut m_g).unwrap();
        let r: Vec<f64> = (0..n)
            .map(|i| m_dv[i] - dt * (f[i] - alpha * m_v[i] - gamma * kv[i] + m_g[i]))
            .collect();
        let mut r_free = vec![0.0; sim.dofs().num_free()];
        sim.dofs().restrict(&r, &mut r_free).unwrap();
        let scale = norm(&m_dv) + dt * norm(&f) + dt * norm(&m_g);
        let bound = 1e-12f64.max(1e-9 * report.initial_residual) * 1.01 + 1e-13 * scale;
        prop_assert!(
            norm(&r_free) <= bound,
            "{model}: |r| = {:e} > {bound:e} after {} Newton iterations",
            norm(&r_free),
            report.newton_iterations()
        );
    }

    #[test]
    fn the_adjoint_gradient_equals_finite_differences(
        mu in 1.5e4f64..8e4,
        lambda in 3e4f64..3e5,
        rollout in 1usize..4,
        velocity_weight in 0.0f64..1.0,
        seed in 0u64..1000,
    ) {
        let s = scene("NeoHookean", 1e5, 0.4, (0.0, 0.0), [0.0, 0.0, 0.0]);
        let data = generate(
            &s,
            Path::new("."),
            &DatasetSpec::new(3, 4, seed).split((0.34, 0.33)),
            |_, _| {},
        )
        .unwrap();
        let train = data.split(Split::Train);
        let mut sim = s.build(Path::new(".")).unwrap().integrator;
        let options = OutputErrorOptions::default().rollout(rollout).velocity_weight(velocity_weight);
        let objective = OutputError::new(&mut sim, &train, options, |_, _| {}).unwrap();
        let c = [mu, lambda];
        let (loss, grad) = objective.evaluate(&c).unwrap();
        prop_assert!(loss.is_finite() && loss >= 0.0);
        let largest = grad.iter().fold(0.0f64, |m, g| m.max(g.abs()));
        for j in 0..2 {
            let h = 1e-4 * c[j];
            let (mut cp, mut cm) = (c, c);
            cp[j] += h;
            cm[j] -= h;
            let fd = (objective.evaluate(&cp).unwrap().0 - objective.evaluate(&cm).unwrap().0)
                / (2.0 * h);
            prop_assert!(
                (grad[j] - fd).abs() <= 1e-4 * (fd.abs() + 1e-2 * largest),
                "dL/dc[{j}] = {:e}, finite difference {fd:e} at c = {c:?}",
                grad[j]
            );
        }
    }
}
