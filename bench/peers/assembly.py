"""Energy + gradient + sparse Hessian on the BENCHMARKS.md beam: deform vs pbatoolkit and
felupe, measured in the same run.

    python3 bench/peers/assembly.py --n 16 [--repeats 5]
"""

import argparse
import os
import tempfile

import meshio
import numpy as np

from common import beam_state, median_time, table, xtask


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    e_mod, nu = 1e6, 0.4
    mu, lam = e_mod / (2 * (1 + nu)), e_mod * nu / ((1 + nu) * (1 - 2 * nu))

    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "beam.msh")
        rows = []
        for model in ["NeoHookean", "StableNeoHookean"]:
            r = xtask("bench", "assembly", "--n", str(args.n), "--model", model,
                      "--repeats", str(args.repeats), "--export-mesh", path)[0]
            rows.append((f"deform {model}", r["seconds"], f"{r['tets_per_second'] / 1e6:.2f} M tets/s, {r['threads']} threads"))
        mesh = meshio.read(path)
    points = mesh.points.astype(np.float64)
    tets = mesh.cells_dict["tetra"].astype(np.int64)
    ntets = len(tets)
    x = beam_state(points)

    try:
        import pbatoolkit as pbat

        fem = pbat.pbat.fem
        X, E = points.T.copy(order="F"), tets.T.copy(order="F")
        el = fem.Element.Tetrahedron
        wg = fem.mesh_quadrature_weights(E, X, el, order=1, quadrature_order=1)
        eg = fem.mesh_quadrature_elements(E, wg)
        gne = fem.shape_function_gradients(E, X, element=el, order=1, dims=3, quadrature_order=1)
        mug, lamg = np.full(wg.size, mu), np.full(wg.size, lam)
        xf = x.T.ravel(order="F")
        flags = (fem.ElementElasticityComputationFlags.Potential
                 | fem.ElementElasticityComputationFlags.Gradient
                 | fem.ElementElasticityComputationFlags.Hessian)

        def pbat_run():
            return fem.hyper_elastic_potential(
                E=E, n_nodes=X.shape[1], eg=np.ravel(eg), wg=np.ravel(wg), GNeg=gne,
                mug=mug, lambdag=lamg, x=xf, energy=fem.HyperElasticEnergy.StableNeoHookean,
                flags=flags, spd_correction=fem.HyperElasticSpdCorrection.NoCorrection,
                element=el, order=1, dims=3)

        s = median_time(pbat_run, args.repeats)
        rows.append(("pbatoolkit StableNeoHookean", s, f"{ntets / s / 1e6:.3f} M tets/s"))
    except Exception as e:  # a peer that is missing or changed its API is reported, not fatal
        print(f"pbatoolkit skipped: {e}")

    try:
        import felupe as fe

        region = fe.RegionTetra(fe.Mesh(points, tets, "tetra"))
        field = fe.FieldContainer([fe.Field(region, dim=3)])
        field[0].values[:] = x - points
        solid = fe.SolidBody(fe.NeoHooke(mu=mu, bulk=lam + 2 * mu / 3), field)

        def felupe_run():
            solid.assemble.vector(field)
            solid.assemble.matrix(field)

        s = median_time(felupe_run, args.repeats)
        rows.append(("felupe NeoHooke (gradient + Hessian)", s, f"{ntets / s / 1e6:.3f} M tets/s"))
    except Exception as e:
        print(f"felupe skipped: {e}")

    print(f"beam n = {args.n}: {ntets} tets; energy + gradient + Hessian, median of {args.repeats}")
    table(rows, "deform NeoHookean")


if __name__ == "__main__":
    main()
