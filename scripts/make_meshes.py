#!/usr/bin/env python3
"""Regenerates the bundled meshes with real meshers (gmsh, TetGen).

    pip install "./crates/python[mesh]" && apt-get install tetgen
    python3 scripts/make_meshes.py

Writes:
  assets/meshes/beam.msh             gmsh, MSH 4.1 ASCII: the 1 x 0.25 x 0.25 m cantilever, unstructured
  assets/meshes/beam_{fine,coarse}.msh
                                     gmsh, MSH 4.1 binary: the same cantilever at two resolutions
                                     (mesh sizes 0.04 and 0.125), for coarse-from-fine data
  assets/meshes/bracket.msh          gmsh, MSH 2.2 binary: an L bracket with a bolt hole, two regions
  assets/meshes/torus.msh            gmsh, MSH 4.1 binary: a torus (R 0.2, r 0.06) centred at z = 0.3
  assets/meshes/tube.msh             gmsh, MSH 4.1 binary: a tube (radii 0.1 and 0.085, length 0.3) on the ground
  assets/meshes/block.node/.ele      TetGen 1.5 from a PLC of a notched block (1-based, region attribute)
  crates/mesh/tests/data/two_boxes_{22,41}_{ascii,binary}.msh
                                     one small two-region mesh in all four MSH variants
and prints counts and volumes that the Rust tests check against.
"""
import os
import sys
import subprocess
import tempfile

import gmsh
import meshio
import numpy as np

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
ASSETS = os.path.join(ROOT, "assets", "meshes")
DATA = os.path.join(ROOT, "crates", "mesh", "tests", "data")


def summary(path):
    m = meshio.read(path)
    tets = m.cells_dict["tetra"]
    p = m.points
    a, b, c, d = (p[tets[:, k]] for k in range(4))
    vol = np.abs(np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a)).sum() / 6
    used = np.unique(tets)
    print(f"{os.path.relpath(path, ROOT)}: {len(used)} vertices, {len(tets)} tets, volume {vol:.12g}")


def save(path, version, binary):
    gmsh.option.setNumber("Mesh.MshFileVersion", version)
    gmsh.option.setNumber("Mesh.Binary", 1 if binary else 0)
    gmsh.option.setNumber("Mesh.SaveAll", 0)
    gmsh.write(path)


def beam():
    gmsh.model.add("beam")
    gmsh.model.occ.addBox(0, 0, 0, 1, 0.25, 0.25)
    gmsh.model.occ.synchronize()
    gmsh.model.addPhysicalGroup(3, [1], 1, name="beam")
    gmsh.model.addPhysicalGroup(2, [1], 2, name="clamp")  # the face x = 0
    gmsh.option.setNumber("Mesh.MeshSizeMax", 0.06)
    gmsh.model.mesh.generate(3)
    path = os.path.join(ASSETS, "beam.msh")
    save(path, 4.1, False)
    gmsh.model.remove()
    summary(path)


def beam_pair():
    """One shape at two resolutions (coarse-from-fine data): the cantilever box, unstructured."""
    for name, size in [("beam_fine", 0.04), ("beam_coarse", 0.125)]:
        gmsh.model.add(name)
        gmsh.model.occ.addBox(0, 0, 0, 1, 0.25, 0.25)
        gmsh.model.occ.synchronize()
        gmsh.model.addPhysicalGroup(3, [1], 1, name="beam")
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.model.mesh.generate(3)
        path = os.path.join(ASSETS, f"{name}.msh")
        save(path, 4.1, True)
        gmsh.model.remove()
        summary(path)


def bracket():
    gmsh.model.add("bracket")
    occ = gmsh.model.occ
    base = occ.addBox(0, 0, 0, 0.4, 0.2, 0.05)
    wall = occ.addBox(0, 0, 0.05, 0.05, 0.2, 0.25)
    hole = occ.addCylinder(0.25, 0.1, -0.01, 0, 0, 0.07, 0.04)
    base2, _ = occ.cut([(3, base)], [(3, hole)])
    out, _ = occ.fragment(base2, [(3, wall)])
    occ.synchronize()
    vols = [t for d, t in gmsh.model.getEntities(3)]
    # The wall is the volume whose centre of mass has the largest z.
    com = {t: occ.getCenterOfMass(3, t) for t in vols}
    wall_tag = max(vols, key=lambda t: com[t][2])
    gmsh.model.addPhysicalGroup(3, [t for t in vols if t != wall_tag], 1, name="base")
    gmsh.model.addPhysicalGroup(3, [wall_tag], 2, name="wall")
    gmsh.option.setNumber("Mesh.MeshSizeMax", 0.03)
    gmsh.model.mesh.generate(3)
    path = os.path.join(ASSETS, "bracket.msh")
    save(path, 2.2, True)
    gmsh.model.remove()
    summary(path)
    print("  exact volume", 0.4 * 0.2 * 0.05 - np.pi * 0.04**2 * 0.05 + 0.05 * 0.2 * 0.25)


def one_solid(name, size, exact_volume):
    """Meshes the one solid just built as physical group 1 named `name`, saves it as
    assets/meshes/`name`.msh (MSH 4.1 binary) and prints its counts and exact volume."""
    gmsh.model.occ.synchronize()
    gmsh.model.addPhysicalGroup(3, [1], 1, name=name)
    gmsh.option.setNumber("Mesh.MeshSizeMax", size)
    gmsh.model.mesh.generate(3)
    path = os.path.join(ASSETS, f"{name}.msh")
    save(path, 4.1, True)
    gmsh.model.remove()
    summary(path)
    print("  exact volume", exact_volume)


def torus():
    gmsh.model.add("torus")
    gmsh.model.occ.addTorus(0, 0, 0.3, 0.2, 0.06)
    one_solid("torus", 0.04, 2 * np.pi**2 * 0.2 * 0.06**2)


def tube():
    # A thin-walled tube lying along x, 2 mm above the ground: soft enough, it collapses
    # under its own weight until its inner wall meets itself (self-contact).
    gmsh.model.add("tube")
    outer = gmsh.model.occ.addCylinder(0, 0, 0.102, 0.3, 0, 0, 0.1)
    inner = gmsh.model.occ.addCylinder(0, 0, 0.102, 0.3, 0, 0, 0.085)
    gmsh.model.occ.cut([(3, outer)], [(3, inner)])
    one_solid("tube", 0.011, np.pi * (0.1**2 - 0.085**2) * 0.3)


def two_boxes():
    gmsh.model.add("two_boxes")
    occ = gmsh.model.occ
    a = occ.addBox(0, 0, 0, 1, 1, 1)
    b = occ.addBox(1, 0, 0, 1, 1, 1)
    occ.fragment([(3, a)], [(3, b)])
    occ.synchronize()
    gmsh.model.addPhysicalGroup(3, [a], 7, name="left")
    gmsh.model.addPhysicalGroup(3, [b], 9, name="right")
    gmsh.model.addPhysicalGroup(2, [1], 3, name="a face")
    gmsh.option.setNumber("Mesh.MeshSizeMax", 0.5)
    gmsh.model.mesh.generate(3)
    for version, tag in ((2.2, "22"), (4.1, "41")):
        for binary in (False, True):
            path = os.path.join(DATA, f"two_boxes_{tag}_{'binary' if binary else 'ascii'}.msh")
            save(path, version, binary)
            summary(path)
    gmsh.model.remove()


def block():
    # A 1 x 0.5 x 0.5 block with a 0.5 x 0.5 x 0.25 notch cut from its top, as a TetGen PLC.
    pts = [
        (0, 0, 0), (1, 0, 0), (1, 0.5, 0), (0, 0.5, 0),
        (0, 0, 0.5), (0.25, 0, 0.5), (0.25, 0, 0.25), (0.75, 0, 0.25), (0.75, 0, 0.5), (1, 0, 0.5),
        (0, 0.5, 0.5), (0.25, 0.5, 0.5), (0.25, 0.5, 0.25), (0.75, 0.5, 0.25), (0.75, 0.5, 0.5), (1, 0.5, 0.5),
    ]
    front = [0, 1, 9, 8, 7, 6, 5, 4]
    back = [3, 2, 15, 14, 13, 12, 11, 10]
    facets = [front, back[::-1], [0, 3, 2, 1], [0, 4, 10, 3], [1, 2, 15, 9],
              [4, 5, 11, 10], [5, 6, 12, 11], [6, 7, 13, 12], [7, 8, 14, 13], [8, 9, 15, 14]]
    with tempfile.TemporaryDirectory() as tmp:
        poly = os.path.join(tmp, "block.poly")
        with open(poly, "w") as f:
            f.write(f"# notched block\n{len(pts)} 3 0 0\n")
            for i, p in enumerate(pts):
                f.write(f"{i + 1} {p[0]} {p[1]} {p[2]}\n")
            f.write(f"{len(facets)} 0\n")
            for fa in facets:
                f.write(f"1\n{len(fa)} " + " ".join(str(i + 1) for i in fa) + "\n")
            f.write("0\n1\n1 0.5 0.25 0.1 5 -1\n")
        subprocess.run(["tetgen", "-pq1.3Aa0.0005", poly], check=True, capture_output=True)
        for ext in ("node", "ele"):
            with open(os.path.join(tmp, f"block.1.{ext}")) as src:
                text = src.read()
            with open(os.path.join(ASSETS, f"block.{ext}"), "w") as dst:
                dst.write(text)
    path = os.path.join(ASSETS, "block.ele")
    lines = [l.split() for l in open(path) if l.strip() and not l.startswith("#")]
    nodes = [l.split() for l in open(os.path.join(ASSETS, "block.node")) if l.strip() and not l.startswith("#")]
    p = np.array([[float(v) for v in n[1:4]] for n in nodes[1:]])
    t = np.array([[int(v) - 1 for v in l[1:5]] for l in lines[1:]])
    a, b, c, d = (p[t[:, k]] for k in range(4))
    vol = np.abs(np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a)).sum() / 6
    signed = np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a)
    print(f"assets/meshes/block.node/.ele: {len(p)} vertices, {len(t)} tets, volume {vol:.12g}, "
          f"negative orientation {int((signed < 0).sum())}; exact {1 * 0.5 * 0.5 - 0.5 * 0.5 * 0.25}")


if __name__ == "__main__":
    os.makedirs(ASSETS, exist_ok=True)
    os.makedirs(DATA, exist_ok=True)
    only = sys.argv[1:]  # e.g. `torus` to make one mesh; all when empty
    gmsh.initialize()
    gmsh.option.setNumber("General.Terminal", 0)
    for make in [beam, beam_pair, bracket, torus, tube, two_boxes]:
        if not only or make.__name__ in only:
            make()
    gmsh.finalize()
    if not only or "block" in only:
        block()
