"""The Backward-Euler system K + M/dt^2 of the BENCHMARKS.md beam, exported by deform as
Matrix Market: deform's solvers vs scipy (SuperLU, CG) and MKL PARDISO, in the same run.

    python3 bench/peers/solvers.py --n 16 [--repeats 3] [--skip-splu] [--skip-general]
"""

import argparse
import os
import tempfile

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
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "system.mtx")
        for r in xtask("bench", "solvers", "--n", str(args.n), "--repeats", str(args.repeats), "--export", path):
            if r["solver"].startswith("direct"):
                rows.append((f"deform {r['solver']}", r["total"],
                             f"analyze {r['analyze']:.3f} + factorize {r['factorize']:.3f} + solve {r['solve']:.3f} s, nnz(L) {r['factor_nnz'] / 1e6:.1f} M, "
                             f"residual {r['relative_residual']:.1e} ({r['refinement_steps']} refinement steps)"))
            else:
                rows.append((f"deform {r['solver']}", r["seconds"],
                             f"{r['iterations']} iterations, {1e6 * r['seconds_per_iteration']:.1f} us/iteration"))
        a = scipy.io.mmread(path).tocsr()
    n = a.shape[0]
    b = ((np.arange(n) % 7) - 3.0) * 1e-3

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

    print(f"beam n = {args.n}: {n} free DOFs, {a.nnz} nonzeros; medians of {args.repeats}")
    table(rows, "deform direct")


if __name__ == "__main__":
    main()
