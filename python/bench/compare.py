"""deform from Python against pbatoolkit, in one Python process, on the BENCHMARKS.md beam.

    python python/bench/compare.py --n 16 [--repeats 5]

Needs the deform module (`maturin develop --release -m crates/python/Cargo.toml` in a
virtual environment) and pbatoolkit (`pip install pbatoolkit`; pypardiso optional). Prints
JSON lines and a table:

- energy + gradient + Hessian (to scipy CSR) of Stable Neo-Hookean at the benchmark state:
  deform's one-pass `Assembly.evaluate` from Python, pbatoolkit's `hyper_elastic_potential`
  from Python, and deform's Rust figure (`cargo xtask bench assembly`, the same work without
  the Python boundary), so the boundary's cost is the Python figure over the Rust one;
- one Backward-Euler step from rest under gravity (dt = 0.01 s, clamped at x = 0, Newton
  to a relative residual of 1e-8, the direct solver): deform's `Simulation.step` from Python
  and a Newton loop on pbatoolkit's gradient and Hessian with scipy's (or pypardiso's)
  sparse direct solver, against deform's Rust figure (`cargo xtask bench step`).
"""

import argparse
import json
import os
import sys
import time

import numpy as np
import scipy.sparse
import scipy.sparse.linalg

import deform

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
# The peer scripts' helpers: deform's runner, median timing, the benchmark state.
sys.path.insert(0, os.path.join(ROOT, "bench", "peers"))
from common import beam_state, median_time, xtask  # noqa: E402

E_MOD, NU, RHO, DT = 1e6, 0.4, 1000.0, 0.01
MU, LAM = E_MOD / (2 * (1 + NU)), E_MOD * NU / ((1 + NU) * (1 - 2 * NU))


class Pbat:
    """pbatoolkit's Stable Neo-Hookean energy, gradient and Hessian on a mesh."""

    def __init__(self, points, tets):
        import pbatoolkit as pbat

        self.fem = pbat.pbat.fem
        fem = self.fem
        self.X, self.E = points.T.copy(order="F"), tets.T.copy(order="F")
        self.el = fem.Element.Tetrahedron
        wg = fem.mesh_quadrature_weights(self.E, self.X, self.el, order=1, quadrature_order=1)
        self.eg = np.ravel(fem.mesh_quadrature_elements(self.E, wg))
        self.wg = np.ravel(wg)
        self.gne = fem.shape_function_gradients(
            self.E, self.X, element=self.el, order=1, dims=3, quadrature_order=1
        )
        self.mug, self.lamg = np.full(self.wg.size, MU), np.full(self.wg.size, LAM)

    def evaluate(self, x):
        """(energy, gradient, Hessian as scipy CSR) at positions x (V, 3)."""
        fem = self.fem
        flags = (
            fem.ElementElasticityComputationFlags.Potential
            | fem.ElementElasticityComputationFlags.Gradient
            | fem.ElementElasticityComputationFlags.Hessian
        )
        u, g, h = fem.hyper_elastic_potential(
            E=self.E, n_nodes=self.X.shape[1], eg=self.eg, wg=self.wg, GNeg=self.gne,
            mug=self.mug, lambdag=self.lamg, x=x.ravel(), energy=fem.HyperElasticEnergy.StableNeoHookean,
            flags=flags, spd_correction=fem.HyperElasticSpdCorrection.NoCorrection,
            element=self.el, order=1, dims=3,
        )
        return u, g, scipy.sparse.csr_matrix(h)


def sparse_solve():
    try:
        import pypardiso

        return "pypardiso", pypardiso.spsolve
    except ImportError:
        return "scipy spsolve", scipy.sparse.linalg.spsolve


def pbat_step(pb, mesh, masses, fixed):
    """One Backward-Euler step from rest with Newton on pbatoolkit's derivatives."""
    name, solve = sparse_solve()
    x0 = mesh.vertices.copy()
    g = np.zeros_like(x0)
    g[:, 2] = -9.81
    target = (x0 + DT * DT * g).ravel()
    m = np.repeat(masses, 3)
    free = np.setdiff1d(np.arange(x0.size), (3 * fixed[:, None] + np.arange(3)).ravel())
    x = x0.ravel().copy()
    r0 = None
    for it in range(20):
        _, grad, hess = pb.evaluate(x.reshape(-1, 3))
        r = (m * (x - target) / (DT * DT) + grad)[free]
        norm = np.linalg.norm(r)
        r0 = norm if r0 is None else r0
        if norm <= 1e-8 * r0 and it > 0:
            break
        a = (hess + scipy.sparse.diags(m / (DT * DT))).tocsr()[free][:, free]
        x[free] -= solve(a, r)
    return name, it


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    mesh = deform.beam(args.n)
    x = beam_state(mesh.vertices)
    rows = []

    def row(what, impl, seconds, **extra):
        r = {"what": what, "impl": impl, "tets": mesh.num_tets, "seconds": seconds, **extra}
        print(json.dumps(r))
        rows.append(r)

    rust = xtask("bench", "assembly", "--n", str(args.n), "--model", "StableNeoHookean",
                 "--repeats", str(args.repeats))[0]
    row("assembly", "deform (Rust)", rust["seconds"])
    asm = deform.Assembly(mesh, deform.Material("stable_neo_hookean", mu=MU, lam=LAM))
    row("assembly", "deform (Python)", median_time(lambda: asm.evaluate(x), args.repeats))
    pb = Pbat(mesh.vertices, mesh.tets)
    row("assembly", "pbatoolkit (Python)", median_time(lambda: pb.evaluate(x), args.repeats))

    steps = xtask("bench", "step", "--n", str(args.n))
    direct = next(s for s in steps if s["policy"] == "direct")
    row("step", "deform (Rust)", direct["seconds"], newton=direct["newton"])
    scene = deform.Scene.from_ron(f"""Scene(
        name: "bench", mesh: Beam({args.n}),
        material: NeoHookean(Young(e: {E_MOD}, nu: {NU})), density: {RHO},
        constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
        integrator: (dt: {DT}), policy: Fixed(Direct()), steps: 1)""")
    sim = deform.Simulation(scene)
    t = time.perf_counter()
    report = sim.step()
    row("step", "deform (Python)", time.perf_counter() - t, newton=len(report["iterations"]))
    masses = asm.lumped_mass(RHO)
    t = time.perf_counter()
    solver, newton = pbat_step(pb, mesh, masses, sim.constrained)
    row("step", f"pbatoolkit + {solver} (Python)", time.perf_counter() - t, newton=newton)

    print(f"\nbeam n = {args.n}: {mesh.num_tets} tets")
    for what in ("assembly", "step"):
        base = next(r for r in rows if r["what"] == what and r["impl"] == "deform (Rust)")
        for r in rows:
            if r["what"] == what:
                print(f"{what:9} {r['impl']:34} {r['seconds']:9.4f} s  {r['seconds'] / base['seconds']:6.2f}x")


if __name__ == "__main__":
    main()
