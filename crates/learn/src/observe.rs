//! Observations of part of the body, what a motion capture gives: the positions over time of
//! markers at vertices or inside elements (barycentric), and the estimate of the first state
//! the capture does not show.
//!
//! The output error and the rollout error compare a model's markers with the observed ones
//! ([`crate::Trajectory::observed`]); the rest of the state is the model's own, rolled out
//! from the trajectory's first state. Where that state is not known, [`estimate_start`] makes
//! it from the first frames: the least-strain shape through the markers (the elastic energy
//! at a minimum with the markers where they were seen, to rounding) moving with the
//! least-stiffness velocity through the markers' velocities. A fit with estimated starts
//! ([`crate::OutputErrorOptions::starts`]) then refines it with the material.

use deform_assembly::{StiffnessMatrix, Tangent};
use deform_integrator::{Conditions, Integrator, State};
use deform_solvers::{Cholesky, Indefinite, LinearOperator, LinearSolver, Ordering};

use crate::dataset::Trajectory;
pub use crate::markers::{Marker, ObserveError, Observed};

/// The penalty on the markers' distance, relative to the stiffness's mean diagonal: large
/// enough that each augmented-Lagrangian round shrinks the markers' misfit by about 1e-4.
const PENALTY: f64 = 1e4;

/// The first state of a partially observed trajectory `t` under its conditions, estimated
/// from its first frames (see the module docs): the least-strain shape through the markers
/// at frame 0, with the constrained vertices at their targets, and the least-stiffness
/// velocities through the markers' velocities (differenced from the first frames).
///
/// # Errors
/// [`ObserveError`] when `t` has no observations or they do not fit the model, or the
/// shape's Newton iteration fails.
pub fn estimate_start(sim: &mut Integrator, t: &Trajectory) -> Result<State, ObserveError> {
    let Some(observed) = &t.observed else {
        return Err(ObserveError::Frames(
            "the trajectory has no observations".into(),
        ));
    };
    let frames = observed.positions.len();
    observed.check(sim.assembly().num_vertices(), frames.max(1))?;
    t.under(sim, |sim| {
        let dt = sim.options().dt;
        let mut shape = Penalised::new(sim, &observed.markers, t.start_time)?;
        let x = shape.least_strain(sim, &observed.positions[0])?;
        let v = shape.least_stiffness(sim, &x, &observed.first_velocities(dt))?;
        Ok(State::new(x, v, t.start_time))
    })?
}

impl Trajectory {
    /// A trajectory of what a capture saw: `observed`'s frames under `conditions`, its first
    /// state estimated by [`estimate_start`] with `sim`'s material (every frame's positions
    /// and velocities hold that estimate; only the markers' positions are read after it).
    ///
    /// # Errors
    /// As [`estimate_start`].
    pub fn from_markers(
        sim: &mut Integrator,
        observed: Observed,
        conditions: Conditions,
    ) -> Result<Self, ObserveError> {
        let frames = observed.positions.len();
        let mut t = Self {
            conditions,
            observed: Some(observed),
            ..Default::default()
        };
        let first = estimate_start(sim, &t)?;
        t.x = vec![first.x; frames];
        t.v = vec![first.v; frames];
        Ok(t)
    }
}

/// The energy `E(x) + kappa/2 |P x - t|^2` of the markers `P` pulled towards targets `t` by
/// springs, minimised by Newton over the free DOFs; the targets are moved until the markers
/// sit where they were observed (augmented Lagrangian).
struct Penalised<'m> {
    markers: &'m [Marker],
    kappa: f64,
    k: StiffnessMatrix,
    /// `K + kappa P^T P`, whole, at the last factorised point.
    a: Option<sprs::CsMat<f64>>,
    solver: Cholesky,
    /// The rest shape with the constrained vertices at their targets at the first frame.
    start: State,
    /// The rest shape's bounding-box diagonal: the scale of positions.
    scale: f64,
}

/// Augmented-Lagrangian rounds before the markers' misfit must be at rounding.
const ROUNDS: usize = 12;
/// Newton iterations per round.
const NEWTON_ITERATIONS: usize = 100;

impl<'m> Penalised<'m> {
    fn new(sim: &mut Integrator, markers: &'m [Marker], time: f64) -> Result<Self, ObserveError> {
        let mut start = sim.rest_state();
        for (v, p) in sim.constrained_targets(time) {
            start.x[3 * v..3 * v + 3].copy_from_slice(&p);
        }
        start.t = time;
        let mut k = sim.assembly().stiffness_matrix();
        sim.assembly_mut()
            .stiffness(&start.x, Tangent::Projected, &mut k)?;
        let free = sim.dofs().free_dofs();
        let csr = k.csr();
        let mean_diagonal = free
            .iter()
            .map(|&i| csr.get(i, i).copied().unwrap_or(0.0).abs())
            .sum::<f64>()
            / free.len().max(1) as f64;
        let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        for p in start.x.chunks(3) {
            for d in 0..3 {
                (lo[d], hi[d]) = (lo[d].min(p[d]), hi[d].max(p[d]));
            }
        }
        let scale = (0..3).map(|d| (hi[d] - lo[d]).powi(2)).sum::<f64>().sqrt();
        Ok(Self {
            markers,
            kappa: PENALTY * mean_diagonal.max(f64::MIN_POSITIVE),
            k,
            a: None,
            solver: Cholesky::new(Ordering::Auto, Indefinite::Ldlt),
            start,
            scale: scale.max(f64::MIN_POSITIVE),
        })
    }

    /// The markers' misfit `P x - p`, flat `3M`.
    fn misfit(&self, x: &[f64], p: &[f64]) -> Vec<f64> {
        self.markers
            .iter()
            .zip(p.chunks(3))
            .flat_map(|(m, p)| {
                let q = m.position(x);
                [q[0] - p[0], q[1] - p[1], q[2] - p[2]]
            })
            .collect()
    }

    /// `kappa P^T e` added to `g` for the misfit `e`.
    fn spread(&self, e: &[f64], g: &mut [f64]) {
        for (m, e) in self.markers.iter().zip(e.chunks(3)) {
            for (v, w) in m.terms() {
                for d in 0..3 {
                    g[3 * v + d] += self.kappa * w * e[d];
                }
            }
        }
    }

    /// `E(x) + kappa/2 |P x - t|^2` and, when asked, its gradient; `None` where the energy is
    /// not defined (an inverted element).
    fn energy(
        &self,
        sim: &mut Integrator,
        x: &[f64],
        t: &[f64],
        gradient: Option<&mut Vec<f64>>,
    ) -> Option<f64> {
        let e = self.misfit(x, t);
        let springs = 0.5 * self.kappa * e.iter().map(|a| a * a).sum::<f64>();
        let elastic = match gradient {
            None => sim.assembly_mut().energy(x).ok()?,
            Some(g) => {
                let mut energy = 0.0;
                g.iter_mut().for_each(|v| *v = 0.0);
                let out = deform_assembly::Outputs {
                    energy: Some(&mut energy),
                    forces: Some(g),
                    ..Default::default()
                };
                sim.assembly_mut().evaluate(x, out).ok()?;
                g.iter_mut().for_each(|v| *v = -*v);
                self.spread(&e, g);
                energy
            }
        };
        Some(elastic + springs).filter(|v| v.is_finite())
    }

    /// `K + kappa P^T P` at `x` (`K` projected to positive semi-definite), factorised on the
    /// free DOFs; returns its free block.
    fn factorise(
        &mut self,
        sim: &mut Integrator,
        x: &[f64],
    ) -> Result<deform_assembly::ReducedMatrix, ObserveError> {
        sim.assembly_mut()
            .stiffness(x, Tangent::Projected, &mut self.k)?;
        let mut a = self.k.csr().clone();
        for m in self.markers {
            for (i, wi) in m.terms() {
                for (j, wj) in m.terms() {
                    for d in 0..3 {
                        // Corners of one element: K's pattern holds the entry.
                        if let Some(value) = a.get_mut(3 * i + d, 3 * j + d) {
                            *value += self.kappa * wi * wj;
                        }
                    }
                }
            }
        }
        let reduced = sim.dofs().reduced_matrix(&a)?;
        self.solver.factorize(&reduced.matrix)?;
        self.a = Some(a);
        Ok(reduced)
    }

    /// Solves the factorised system for the full right-hand side `b` (restricted to the free
    /// DOFs), scattered into a full vector with zeros on the constrained DOFs.
    fn solve(
        &mut self,
        sim: &Integrator,
        reduced: &deform_assembly::ReducedMatrix,
        b: &[f64],
    ) -> Result<Vec<f64>, ObserveError> {
        let dofs = sim.dofs();
        let mut b_free = vec![0.0; dofs.num_free()];
        dofs.restrict(b, &mut b_free)?;
        let mut y = vec![0.0; b_free.len()];
        self.solver.solve(&reduced.matrix, &b_free, &mut y)?;
        let mut full = vec![0.0; b.len()];
        dofs.scatter(&y, &mut full)?;
        Ok(full)
    }

    /// The least-strain shape whose markers are at `p`, from the rest shape.
    fn least_strain(&mut self, sim: &mut Integrator, p: &[f64]) -> Result<Vec<f64>, ObserveError> {
        let mut x = self.start.x.clone();
        let mut t = p.to_vec();
        for _ in 0..ROUNDS {
            self.minimise(sim, &mut x, &t)?;
            let e = self.misfit(&x, p);
            if e.iter().all(|v| v.abs() <= 1e-10 * self.scale) {
                return Ok(x);
            }
            t.iter_mut().zip(&e).for_each(|(t, e)| *t -= e);
        }
        let worst = self
            .misfit(&x, p)
            .iter()
            .fold(0.0f64, |m, v| m.max(v.abs()));
        Err(ObserveError::NotConverged(format!(
            "a marker is still {worst:.3e} m from where it was seen after {ROUNDS} rounds"
        )))
    }

    /// Newton with a backtracking line search on the penalised energy, from `x`.
    fn minimise(
        &mut self,
        sim: &mut Integrator,
        x: &mut [f64],
        t: &[f64],
    ) -> Result<(), ObserveError> {
        let mut g = vec![0.0; x.len()];
        for _ in 0..NEWTON_ITERATIONS {
            let energy = self.energy(sim, x, t, Some(&mut g)).ok_or_else(|| {
                ObserveError::NotConverged("the energy is not finite at an iterate".into())
            })?;
            let reduced = self.factorise(sim, x)?;
            let minus_g: Vec<f64> = g.iter().map(|v| -v).collect();
            let d = self.solve(sim, &reduced, &minus_g)?;
            // A Newton step at rounding: done (the energy's differences are rounding there).
            if d.iter().all(|v| v.abs() <= 1e-11 * self.scale) {
                x.iter_mut().zip(&d).for_each(|(x, d)| *x += d);
                return Ok(());
            }
            let slope: f64 = g.iter().zip(&d).map(|(a, b)| a * b).sum();
            if -slope <= 1e-12 * energy.abs() {
                // The Newton decrement: the step's predicted decrease is at the energy's
                // rounding (soft modes of few markers reach it before the step is small).
                x.iter_mut().zip(&d).for_each(|(x, d)| *x += d);
                return Ok(());
            }
            let mut step = 1.0;
            loop {
                let trial: Vec<f64> = x.iter().zip(&d).map(|(x, d)| x + step * d).collect();
                match self.energy(sim, &trial, t, None) {
                    Some(e) if e <= energy + 1e-4 * step * slope.min(0.0) => {
                        x.copy_from_slice(&trial);
                        break;
                    }
                    _ if step < 1e-12 && -slope <= 1e-9 * energy.abs() => return Ok(()),
                    _ if step < 1e-12 => {
                        return Err(ObserveError::NotConverged(
                            "the line search found no lower energy".into(),
                        ));
                    }
                    _ => step *= 0.5,
                }
            }
        }
        Err(ObserveError::NotConverged(format!(
            "Newton did not converge in {NEWTON_ITERATIONS} iterations"
        )))
    }

    /// The velocities at shape `x` whose markers move at `q` and whose constrained vertices
    /// move with their targets, least stiff otherwise (`v^T K v` at a minimum).
    fn least_stiffness(
        &mut self,
        sim: &mut Integrator,
        x: &[f64],
        q: &[f64],
    ) -> Result<Vec<f64>, ObserveError> {
        let reduced = self.factorise(sim, x)?;
        let a = self.a.take().expect("factorised above");
        // The constrained vertices' velocities: their targets' over the model's step.
        let dt = sim.options().dt;
        let mut fixed = vec![0.0; x.len()];
        let time = self.start.t;
        for ((v, p0), (_, p1)) in sim
            .constrained_targets(time)
            .into_iter()
            .zip(sim.constrained_targets(time + dt))
        {
            for d in 0..3 {
                fixed[3 * v + d] = (p1[d] - p0[d]) / dt;
            }
        }
        let mut coupling = vec![0.0; x.len()];
        LinearOperator::apply(&a, &fixed, &mut coupling);
        let scale = q
            .iter()
            .fold(0.0f64, |m, v| m.max(v.abs()))
            .max(f64::MIN_POSITIVE);
        let mut t = q.to_vec();
        let mut v = fixed.clone();
        for _ in 0..ROUNDS {
            let mut b: Vec<f64> = coupling.iter().map(|c| -c).collect();
            self.spread(&t, &mut b);
            let free = self.solve(sim, &reduced, &b)?;
            v.iter_mut()
                .zip(&free)
                .zip(&fixed)
                .for_each(|((v, f), c)| *v = f + c);
            let e = self.misfit(&v, q);
            if e.iter().all(|e| e.abs() <= 1e-10 * scale) {
                break;
            }
            t.iter_mut().zip(&e).for_each(|(t, e)| *t -= e);
        }
        Ok(v)
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use deform_integrator::Scene;
    use deform_mesh::select::Selector;

    use super::*;

    fn free_beam() -> deform_integrator::scene::Built {
        let text = r#"Scene(
            name: "free",
            mesh: Beam(2),
            material: NeoHookean(Young(e: 1e5, nu: 0.4)),
            density: 1000.0,
            integrator: (dt: 0.01),
            steps: 1,
        )"#;
        let origin = Path::new("free.ron");
        Scene::parse(text, origin).unwrap().build(origin).unwrap()
    }

    /// An affine motion of a body is its least-strain shape and least-stiffness velocity
    /// through its surface: the estimate from the surface vertices and one point inside an
    /// element gives it back everywhere (the interior too), to rounding.
    #[test]
    fn an_affine_motion_is_found_from_the_surface() {
        let mut built = free_beam();
        let rest = built.mesh.rest_positions_flat();
        let (c, s) = (0.3f64.cos(), 0.3f64.sin());
        // A stretch and a rotation about z; a spin and a stretching rate.
        let a = [
            [1.05 * c, -0.97 * s, 0.0],
            [1.05 * s, 0.97 * c, 0.0],
            [0.0, 0.0, 1.02],
        ];
        let w = [[0.1, -2.0, 0.0], [2.0, 0.05, 0.3], [0.0, -0.3, -0.1]];
        let map = |m: &[[f64; 3]; 3], shift: f64| -> Vec<f64> {
            rest.chunks(3)
                .flat_map(|p| {
                    (0..3).map(move |i| shift + (0..3).map(|j| m[i][j] * p[j]).sum::<f64>())
                })
                .collect()
        };
        let (x, v) = (map(&a, 0.2), map(&w, -0.5));
        let dt = built.integrator.options().dt;
        // Frames of the constant-velocity motion, so the difference gives `v` exactly.
        let frames: Vec<Vec<f64>> = (0..3)
            .map(|k| {
                x.iter()
                    .zip(&v)
                    .map(|(x, v)| x + k as f64 * dt * v)
                    .collect()
            })
            .collect();
        let surface = Selector::Surface.select(&built.mesh).unwrap();
        let mut observed = Observed::vertices(&frames, &surface);
        let inside = Marker::in_element(&built.mesh, 3, [0.1, 0.2, 0.3, 0.4]).unwrap();
        observed.markers.push(inside);
        for f in &mut observed.positions {
            // The frame's positions are those `observed` was made from, by construction.
            let k = f.len() / 3 - surface.len();
            assert_eq!(k, 0);
        }
        for (f, frame) in observed.positions.iter_mut().zip(&frames) {
            f.extend(inside.position(frame));
        }
        let t = Trajectory::from_markers(&mut built.integrator, observed, Conditions::default())
            .unwrap();
        let far = |a: &[f64], b: &[f64]| {
            a.iter()
                .zip(b)
                .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()))
        };
        assert!(
            far(&t.x[0], &x) < 1e-9,
            "positions off by {:.3e}",
            far(&t.x[0], &x)
        );
        assert!(
            far(&t.v[0], &v) < 1e-7,
            "velocities off by {:.3e}",
            far(&t.v[0], &v)
        );
        assert_eq!(t.steps(), 2);
    }

    #[test]
    fn bad_markers_are_named() {
        let built = free_beam();
        let e = Marker::in_element(&built.mesh, 10_000, [0.25; 4]).unwrap_err();
        assert!(e.to_string().contains("element 10000"), "{e}");
        let e = Marker::in_element(&built.mesh, 0, [0.5; 4]).unwrap_err();
        assert!(e.to_string().contains("sum to 1"), "{e}");
        let observed = Observed {
            markers: vec![Marker::Vertex(0), Marker::Vertex(99_999)],
            positions: vec![vec![0.0; 6]],
        };
        let e = observed.check(built.mesh.num_vertices(), 1).unwrap_err();
        assert!(e.to_string().starts_with("marker 1: vertex 99999"), "{e}");
        let short = Observed {
            markers: vec![Marker::Vertex(0)],
            positions: vec![vec![0.0; 3], vec![f64::NAN; 3]],
        };
        let e = short.check(built.mesh.num_vertices(), 2).unwrap_err();
        assert!(e.to_string().contains("frame 1, marker 0"), "{e}");
        let e = short.check(built.mesh.num_vertices(), 3).unwrap_err();
        assert!(e.to_string().contains("2 frames"), "{e}");
    }
}
