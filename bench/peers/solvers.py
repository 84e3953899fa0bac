"""The Backward-Euler system K + M/dt^2 of the BENCHMARKS.md beam, exported by deform as
Matrix Market: deform's solvers vs scipy (SuperLU, CG), MKL PARDISO and pyamg's smoothed
aggregation (with the rigid-body modes of the free vertices as B), in the same run.

    python3 bench/peers/solvers.py --n 16 [--repeats 3] [--skip-splu] [--skip-general] [--no-direct]
"""

import argparse
import os
import tempfile
import time

import numpy as np
import scipy.io
import scipy.sparse
import scipy.sparse.linalg as sla

from common import median_time, table, xtask


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--skip-splu", action="store_true", help="SuperLU takes tens of seconds at n = 16")
    ap.add_argument("--skip-general", action="store_true", help="PARDISO's unsymmetric mode (minutes at n = 32)")
    ap.add_argument("--no-direct", action="store_true", help="no direct solvers (deform's, PARDISO, SuperLU)")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "system.mtx")
        points_path = os.path.join(tmp, "coordinates.npy")
        extra = ["--no-direct"] if args.no_direct else []
        for r in xtask("bench", "solvers", "--n", str(args.n), "--repeats", str(args.repeats), "--export", path,
                       "--export-coordinates", points_path, *extra):
            if r["solver"].startswith("direct"):
                rows.append((f"deform {r['solver']}", r["total"],
                             f"analyze {r['analyze']:.3f} + factorize {r['factorize']:.3f} + solve {r['solve']:.3f} s, nnz(L) {r['factor_nnz'] / 1e6:.1f} M, "
                             f"residual {r['relative_residual']:.1e} ({r['refinement_steps']} refinement steps)"))
            else:
                rows.append((f"deform {r['solver']}", r["seconds"],
                             f"{r['iterations']} iterations, set-up {r['setup']:.3f} s, {1e6 * r['seconds_per_iteration']:.1f} us/iteration"))
        a = scipy.io.mmread(path).tocsr()
        points = np.load(points_path)
    n = a.shape[0]
    b = ((np.arange(n) % 7) - 3.0) * 1e-3

    rows.extend(pyamg_rows(a, b, points, args.repeats))
    if args.no_direct:
        return report(args, n, a, rows)
    try:
        import pypardiso

        upper = scipy.sparse.triu(a, format="csr")

        def pardiso_spd():
            # Real symmetric positive definite: PARDISO reads the upper triangle.
            solver = pypardiso.PyPardisoSolver(mtype=2)
            return solver.solve(upper, b)

        s = median_time(pardiso_spd, args.repeats)
        x = pardiso_spd()
        res = np.linalg.norm(b - a @ x) / np.linalg.norm(b)
        rows.append(("PARDISO SPD (pypardiso, analyze+factor+solve)", s, f"residual {res:.1e}"))
        # pypardiso.spsolve keeps its factorisation between calls: a new solver each time.
        if not args.skip_general:
            s = median_time(lambda: pypardiso.PyPardisoSolver().solve(a, b), args.repeats)
            rows.append(("PARDISO general (pypardiso default, unsymmetric)", s, ""))
    except Exception as e:
        print(f"pypardiso skipped: {e}")

    if not args.skip_splu:
        s = median_time(lambda: sla.splu(a.tocsc()).solve(b), 1)
        rows.append(("scipy splu (SuperLU)", s, ""))

    for rel in [1e-6]:
        count = [0]

        def cb(_):
            count[0] += 1

        def cg(m=None):
            count[0] = 0
            sla.cg(a, b, rtol=rel, maxiter=100000, M=m, callback=cb)

        s = median_time(cg, args.repeats)
        rows.append((f"scipy cg_{rel:g}", s, f"{count[0]} iterations, {1e6 * s / max(count[0], 1):.1f} us/iteration"))
        d = sla.LinearOperator(a.shape, matvec=lambda v: v / a.diagonal())
        s = median_time(lambda: cg(d), args.repeats)
        rows.append((f"scipy pcg_jacobi_{rel:g}", s, f"{count[0]} iterations, {1e6 * s / max(count[0], 1):.1f} us/iteration"))

    report(args, n, a, rows)


def report(args, n, a, rows):
    print(f"beam n = {args.n}: {n} free DOFs, {a.nnz} nonzeros; medians of {args.repeats}")
    table(rows, "deform pcg_ic0_1e-6")


def rigid_body_modes(points):
    """The six rigid-body modes of the points (translations, rotations about the centroid),
    one row per DOF: what pyamg takes as B for elasticity."""
    p = (points - points.mean(axis=0)) / np.abs(points - points.mean(axis=0)).max()
    n = len(p)
    b = np.zeros((3 * n, 6))
    for c in range(3):
        b[c::3, c] = 1.0
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    # Rotations about x, y and z: omega x p.
    b[1::3, 3], b[2::3, 3] = -z, y
    b[0::3, 4], b[2::3, 4] = z, -x
    b[0::3, 5], b[1::3, 5] = -y, x
    return b


def pyamg_rows(a, b, points, repeats):
    """pyamg's smoothed aggregation with B = rigid-body modes on the 3x3-block matrix, as CG's
    preconditioner to 1e-6: its defaults otherwise (symmetric strength, standard aggregation,
    Jacobi-smoothed P, symmetric block Gauss-Seidel smoothing)."""
    try:
        import pyamg
    except ImportError as e:
        print(f"pyamg skipped: {e}")
        return []
    bsr = a.tobsr(blocksize=(3, 3))
    modes = rigid_body_modes(points)
    out = []
    for name, kwargs in [
        ("pyamg SA (defaults, B = rigid modes)", {}),
        ("pyamg SA (Chebyshev-like: Jacobi smoother)", {
            "presmoother": ("jacobi", {"omega": 4.0 / 3.0, "iterations": 2}),
            "postsmoother": ("jacobi", {"omega": 4.0 / 3.0, "iterations": 2})}),
    ]:
        stats = {}

        def run():
            t = time.perf_counter()
            ml = pyamg.smoothed_aggregation_solver(bsr, B=modes, symmetry="hermitian", **kwargs)
            stats["setup"] = time.perf_counter() - t
            residuals = []
            x = ml.solve(b, tol=1e-6, accel="cg", maxiter=1000, residuals=residuals)
            stats["iterations"] = len(residuals) - 1
            stats["residual"] = np.linalg.norm(b - a @ x) / np.linalg.norm(b)
            stats["levels"] = [lv.A.shape[0] for lv in ml.levels]

        s = median_time(run, repeats)
        out.append((name, s, f"{stats['iterations']} iterations, set-up {stats['setup']:.3f} s, "
                             f"residual {stats['residual']:.1e}, levels {stats['levels']}"))
    return out


if __name__ == "__main__":
    main()
