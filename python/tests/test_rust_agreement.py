"""The Python module and deform's Rust API give the same numbers, bit for bit: the runner
(`cargo xtask simulate`, the library's `simulate`) and `deform.Simulation` on one scene."""

import os
import subprocess

import meshio
import numpy as np

import deform
from conftest import ROOT

SCENE = """Scene(
    name: "agree",
    mesh: Beam(1),
    material: StableNeoHookean(Young(e: 1e5, nu: 0.45)),
    density: 1000.0,
    constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
    integrator: (dt: 0.01, alpha: 0.2),
    initial: (angular_velocity: (0.0, 3.0, 0.0)),
    steps: 12,
)"""


def test_a_simulation_equals_the_rust_runners(tmp_path):
    scene_file = tmp_path / "agree.ron"
    scene_file.write_text(SCENE)
    cargo = os.environ.get("CARGO", "cargo")
    subprocess.run(
        [cargo, "xtask", "simulate", str(scene_file), "--out", str(tmp_path / "rust"), "--quiet"],
        cwd=ROOT,
        check=True,
        capture_output=True,
    )
    sim = deform.Simulation(deform.Scene.load(scene_file))
    sim.run(12)
    rust = meshio.read(tmp_path / "rust" / "frame_00012.vtu")
    assert np.array_equal(rust.points, sim.x)
    assert np.array_equal(rust.point_data["velocity"], sim.v)
    # The displacement field the runner writes is x minus the rest shape, exactly.
    assert np.array_equal(rust.point_data["displacement"], sim.x - sim.mesh.vertices)
