"""Scenes and simulations: stepping, state as numpy arrays, callbacks, errors, threads."""

import threading

import numpy as np
import pytest

import deform

SCENE = """Scene(
    name: "py",
    mesh: Beam(1),
    material: NeoHookean(Young(e: 1e5, nu: 0.4)),
    density: 1000.0,
    constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
    integrator: (dt: 0.01),
    steps: 20,
)"""


def test_twenty_steps_under_gravity_sag_the_beam():
    sim = deform.Simulation(deform.Scene.from_ron(SCENE))
    x0 = sim.x
    seen = []
    summary = sim.run(20, callback=lambda r: seen.append(r["step"]))
    assert summary["steps"] == 20 and len(seen) == 20
    assert np.isclose(sim.t, 0.2)
    tip = x0[:, 0].argmax()
    assert sim.x[tip, 2] < x0[tip, 2] - 1e-3
    # Constrained vertices stay where they are.
    fixed = sim.constrained
    assert len(fixed) > 0 and np.array_equal(sim.x[fixed], x0[fixed])


def test_a_callback_stops_the_run_and_state_is_settable():
    sim = deform.Simulation(deform.Scene.from_ron(SCENE))
    summary = sim.run(10, callback=lambda r: r["step"] < 2)
    assert summary["steps"] == 3
    v = np.zeros_like(sim.v)
    v[:, 2] = 0.5
    sim.v = v
    assert np.array_equal(sim.v, v)
    sim.x = sim.mesh.vertices
    report = sim.step()
    assert report["converged"] and report["iterations"]
    with pytest.raises(deform.SimulationError, match="shape"):
        sim.x = np.zeros((3, 3))
    with pytest.raises(ValueError, match="non-finite"):
        sim.v = np.full_like(v, np.nan)


def test_same_scene_same_trajectory_from_python_threads():
    scene = deform.Scene.from_ron(SCENE)
    sims = [deform.Simulation(scene) for _ in range(2)]
    threads = [threading.Thread(target=s.run, args=(15,)) for s in sims]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    alone = deform.Simulation(scene)
    alone.run(15)
    for s in sims:
        assert np.array_equal(s.x, alone.x)


def test_bundled_scene_loads(assets):
    scene = deform.Scene.load(assets / "scenes" / "cantilever.ron")
    assert scene.mesh().num_tets == 1536
    assert "Scene" in scene.to_ron()


def test_bad_scenes_raise(tmp_path):
    with pytest.raises(deform.SceneError, match="density"):
        deform.Scene.from_ron(SCENE.replace("density: 1000.0", "density: -1.0"))
    with pytest.raises(deform.SceneError, match="colour"):
        deform.Scene.from_ron(SCENE.replace("steps: 20,", "steps: 20, colour: 3,"))
    with pytest.raises(deform.SceneError):
        deform.Scene.load(tmp_path / "missing.ron")


POLICIES = [
    "Fixed(Pcg(preconditioner: Ic0, tolerance: (rel: 1e-12)))",
    "Schedule(iterations: [Direct()], otherwise: Pcg(preconditioner: StaleCholesky(max_age: 10), tolerance: (rel: 1e-12)))",
    "EisenstatWalker(solver: Pcg(preconditioner: Jacobi, tolerance: (rel: 1e-8)))",
    "StaleFactor(solver: Pcg(preconditioner: StaleCholesky(max_age: 1000), tolerance: (rel: 1e-12)), refactor_above: 6)",
    "Fixed(MatrixFree(Pcg(preconditioner: BlockJacobi, tolerance: (rel: 1e-12))))",
]


@pytest.mark.parametrize("policy", POLICIES)
def test_every_solver_policy_gives_the_direct_solvers_trajectory(policy):
    def run(text):
        sim = deform.Simulation(deform.Scene.from_ron(text))
        summary = sim.run(5)
        return sim.x, summary

    reference, _ = run(SCENE.replace("steps: 20,", "policy: Fixed(Direct()), steps: 20,"))
    x, summary = run(SCENE.replace("steps: 20,", f"policy: {policy}, steps: 20,"))
    assert summary["steps"] == 5
    assert np.abs(x - reference).max() < 1e-6


DROP = """Scene(
    name: "drop",
    mesh: Generate((cells: (2, 2, 2), size: (0.1, 0.1, 0.1), origin: (0.0, 0.0, 0.01))),
    material: NeoHookean(Young(e: 1e5, nu: 0.4)),
    density: 1000.0,
    contact: Some((obstacles: [Plane(point: (0.0, 0.0, 0.0), normal: (0.0, 0.0, 1.0))])),
    integrator: (dt: 0.005),
    initial: (velocity: (0.0, 0.0, -1.0)),
    steps: 40,
)"""


def test_a_body_dropped_on_the_ground_never_goes_through_it():
    sim = deform.Simulation(deform.Scene.from_ron(DROP))
    lowest, active = [], []

    def seen(report):
        lowest.append(sim.x[:, 2].min())
        active.append(report["contact"]["active"])

    sim.run(40, callback=seen)
    assert min(lowest) > 0.0
    assert max(active) > 0
    # A state set inside the ground is refused by the next step, naming the vertex.
    x = sim.x
    x[0, 2] = -0.01
    sim.x = x
    with pytest.raises(deform.SimulationError, match="vertex 0 is inside obstacle 0"):
        sim.step()
