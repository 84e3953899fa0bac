#!/usr/bin/env python3
"""Reads what deform writes with meshio, an independent reader, and compares.

    pip install "./crates/python[meshio]"
    python3 scripts/check_with_meshio.py

For every bundled mesh: `cargo xtask mesh convert` to .vtu, .msh (2.2/4.1, ASCII/binary),
.node/.ele and .obj; meshio reads each, and the counts, coordinates, connectivity and
volume must match the source as meshio reads it. Exits non-zero on any mismatch.
"""
import os
import subprocess
import sys
import tempfile

import meshio
import numpy as np

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
SOURCES = ["assets/meshes/beam.msh", "assets/meshes/bracket.msh", "assets/meshes/block.node"]


def tet_volume(points, tets):
    a, b, c, d = (points[tets[:, k]] for k in range(4))
    return np.abs(np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a)).sum() / 6


def xtask(*args):
    subprocess.run(["cargo", "xtask", "mesh", *args], cwd=ROOT, check=True, capture_output=True)


def main():
    failures = 0
    with tempfile.TemporaryDirectory() as tmp:
        for src in SOURCES:
            ref = meshio.read(os.path.join(ROOT, src)) if src.endswith(".msh") else None
            outputs = {
                "vtu": ("out.vtu", []),
                "msh41": ("out41.msh", []),
                "msh41b": ("out41b.msh", ["--binary"]),
                "msh22": ("out22.msh", ["--msh-version", "2.2"]),
                "msh22b": ("out22b.msh", ["--msh-version", "2.2", "--binary"]),
                "node": ("out.node", []),
            }
            results = {}
            for key, (name, extra) in outputs.items():
                path = os.path.join(tmp, name)
                xtask("convert", os.path.join(ROOT, src), path, *extra)
                m = meshio.read(path, file_format="tetgen" if name.endswith(".node") else None)
                tets = m.cells_dict["tetra"]
                results[key] = (m.points, tets)
            p0, t0 = results["vtu"]
            vol = tet_volume(p0, t0)
            for key, (p, t) in results.items():
                ok = p.shape == p0.shape and np.array_equal(t, t0) and np.allclose(p, p0, rtol=0, atol=1e-15)
                ok = ok and abs(tet_volume(p, t) - vol) <= 1e-12 * vol
                if ref is not None:
                    rt = ref.cells_dict["tetra"]
                    ok = ok and len(rt) == len(t) and abs(tet_volume(ref.points, rt) - vol) <= 1e-12 * vol
                print(f"{'ok  ' if ok else 'FAIL'} {src} -> {key}: {len(p)} points, {len(t)} tets, volume {vol:.12g}")
                failures += not ok
            obj = os.path.join(tmp, "out.obj")
            xtask("convert", os.path.join(ROOT, src), obj)
            s = meshio.read(obj)
            tri = s.cells_dict["triangle"]
            a, b, c = (s.points[tri[:, k]] for k in range(3))
            enclosed = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
            ok = abs(enclosed - vol) <= 1e-9 * vol
            print(f"{'ok  ' if ok else 'FAIL'} {src} -> obj: {len(tri)} triangles enclose {enclosed:.12g}")
            failures += not ok
    print(f"{failures} failed")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
