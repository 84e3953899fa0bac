"""Experiments run from Python return deform's report as Python data."""

import re

import numpy as np
import pytest

import deform

SCENE = """Scene(
    name: "fit",
    mesh: Beam(1),
    material: NeoHookean(Young(e: {e}, nu: {nu})),
    density: 1000.0,
    constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
    integrator: (dt: 0.01, newton: (rel: 1e-11, abs: 1e-13)),
    steps: 1,
)"""


def record(sim, steps, kick):
    """A trajectory made in Python: a velocity kick, then free motion under gravity."""
    sim.v = kick
    xs, vs = [sim.x], [sim.v]
    for _ in range(steps):
        sim.step()
        xs.append(sim.x)
        vs.append(sim.v)
    return np.stack(xs), np.stack(vs)


def kicked_motion(truth, rng, steps):
    """From rest, a random velocity kick on the free vertices, then `steps` steps."""
    free = np.setdiff1d(np.arange(truth.x.shape[0]), truth.constrained)
    kick = np.zeros_like(truth.v)
    kick[free] = rng.normal(0, 0.5, (len(free), 3))
    truth.x = truth.mesh.vertices
    return record(truth, steps, kick)


def test_a_material_fit_on_data_made_in_python():
    truth = deform.Simulation(deform.Scene.from_ron(SCENE.format(e=1e5, nu=0.4)))
    rng = np.random.default_rng(3)
    trajectories = []
    for _ in range(3):
        x, v = kicked_motion(truth, rng, 8)
        trajectories.append(deform.Trajectory(x, 0.01, velocities=v))
    assert trajectories[0].steps == 8 and np.array_equal(trajectories[0].x[0], truth.mesh.vertices)
    guess = deform.Scene.from_ron(SCENE.format(e=3e5, nu=0.3))
    fit = deform.fit_material(guess, trajectories, rollout=4, max_iterations=20)
    assert abs(fit["E"] / 1e5 - 1) < 1e-6 and abs(fit["nu"] / 0.4 - 1) < 1e-6
    assert fit["stage1"]["relative_residual"] < 1e-6
    assert fit["stage2"]["loss"] <= fit["stage2"]["initial_loss"]
    # Stage 1 alone, and positions only (velocities derived, the first frame dropped).
    derived = deform.Trajectory(trajectories[0].x, 0.01)
    assert derived.steps == 7
    alone = deform.fit_material(guess, [derived], rollout=0)
    assert alone["stage2"] is None and abs(alone["E"] / 1e5 - 1) < 1e-3


def test_a_fit_stopped_on_its_cap_warns_and_starts_are_estimated_on_request():
    """Noisy positions: `starts=True` estimates the rollouts' first states (the fit reports
    their correction); a fit stopped by its iteration cap says so, as a UserWarning and in
    `termination` and `warnings`."""
    truth = deform.Simulation(deform.Scene.from_ron(SCENE.format(e=1e5, nu=0.4)))
    rng = np.random.default_rng(5)
    free = np.setdiff1d(np.arange(truth.x.shape[0]), truth.constrained)
    noisy = []
    for _ in range(2):
        x, _ = kicked_motion(truth, rng, 6)
        x[:, free] += rng.normal(0, 1e-4, x[:, free].shape)
        noisy.append(deform.Trajectory(x, 0.01))
    guess = deform.Scene.from_ron(SCENE.format(e=2e5, nu=0.3))
    with pytest.warns(UserWarning, match="stopped on its iteration cap"):
        fit = deform.fit_material(guess, noisy, rollout=5, max_iterations=1, starts=True)
    assert fit["termination"] == "iteration cap"
    assert any("iteration cap" in w for w in fit["warnings"])
    assert fit["stage2"]["start_correction"] is not None
    # Without starts, none are estimated; markers cannot go without them.
    with pytest.warns(UserWarning):
        plain = deform.fit_material(guess, noisy, rollout=5, max_iterations=1, starts=False)
    assert plain["stage2"]["start_correction"] is None


def test_states_of_another_mesh_are_refused_saying_what_they_have():
    scene = deform.Scene.from_ron(SCENE.format(e=1e5, nu=0.4))
    x = np.zeros((3, 5, 3))
    wrong = deform.Trajectory(x, 0.01, velocities=np.zeros_like(x))
    with pytest.raises(deform.LearnError, match=r"position state 0 has 15 values, expected \d+"):
        deform.fit_material(scene, [wrong], rollout=0)


def test_a_capture_of_markers_gives_the_material():
    """Only markers seen (4 vertices, 2 points inside elements): the first state estimated,
    stage 1 skipped, stage 2 over whole trajectories refining their starts."""
    truth = deform.Simulation(deform.Scene.from_ron(SCENE.format(e=1e5, nu=0.4)))
    free = np.setdiff1d(np.arange(truth.x.shape[0]), truth.constrained)
    vertices = free[::3][:4]
    elements, weights = np.array([7, 19]), np.array([[0.1, 0.2, 0.3, 0.4], [0.25] * 4])
    tets = truth.mesh.tets
    rng = np.random.default_rng(4)
    guess = deform.Scene.from_ron(SCENE.format(e=1.3e5, nu=0.35))
    captures = []
    for _ in range(3):
        kick = np.zeros_like(truth.v)
        kick[free] = rng.normal(0, 0.5, (len(free), 3))
        truth.x = truth.mesh.vertices
        x, _ = record(truth, 15, kick)
        inside = np.einsum("mk,fmkd->fmd", weights, x[:, tets[elements]])
        captures.append(deform.Trajectory.from_markers(guess, x[:, vertices], 0.01, vertices=vertices))
        captures.append(
            deform.Trajectory.from_markers(guess, inside, 0.01, elements=elements, weights=weights)
        )
    assert captures[1].markers.shape == (16, 2, 3) and captures[1].x.shape == x.shape
    fit = deform.fit_material(guess, captures, max_iterations=150)
    assert fit["stage1"] is None
    assert abs(fit["E"] / 1e5 - 1) < 0.01 and abs(fit["nu"] / 0.4 - 1) < 0.01, fit["E"]
    with pytest.raises(deform.LearnError, match="marker 0"):
        deform.Trajectory.from_markers(guess, inside, 0.01, elements=elements, weights=2 * weights)


def test_model_selection_finds_the_model_that_made_the_data():
    stvk = SCENE.format(e=1e5, nu=0.4).replace("NeoHookean(Young", "StVenantKirchhoff(Young")
    scene = deform.Scene.from_ron(stvk)
    data = deform.Dataset.generate(scene, 3, 6, seed=5, speed=2.0, spin=4.0, stretch=0.3)
    fit = deform.fit_ensemble(scene, data.trajectories)
    shares = {m["model"]: m["energy_share"] for m in fit["members"]}
    assert shares["StVenantKirchhoff"] > 0.99, shares
    # Refined by output error from the kept members.
    refined = deform.fit_ensemble(
        scene, data.trajectories, models=["stvk", "neo_hookean"], rollout=3, max_iterations=5
    )
    assert "refined" in refined
    with pytest.raises(deform.MaterialError, match="unknown model"):
        deform.fit_ensemble(scene, data.trajectories, models=["rubber"])


def test_bad_trajectories_raise():
    x = np.zeros((3, 4, 3))
    with pytest.raises(deform.LearnError, match="positions: shape"):
        deform.Trajectory(x[:, :, :2], 0.01)
    x[1, 2, 0] = np.nan
    with pytest.raises(deform.LearnError, match="step 1, vertex 2"):
        deform.Trajectory(x, 0.01)
    with pytest.raises(deform.LearnError, match="v0: shape"):
        deform.Trajectory(np.zeros((3, 4, 3)), 0.01, v0=np.zeros((5, 3)))
    with pytest.raises(deform.LearnError, match="dt"):
        deform.Trajectory(np.zeros((3, 4, 3)), -1.0)


def test_an_experiment_returns_its_report(assets, tmp_path):
    e = deform.Experiment.load(assets / "experiments" / "fit_material.ron")
    assert e.name == "fit_material"
    report = e.run(out=tmp_path)
    assert report["material"] == {"NeoHookean": {"Young": {"e": 1e5, "nu": 0.4}}}
    rows = {r["estimate"]: r for r in report["task"]["FitMaterial"]["rows"]}
    # Stage 2 recovers E and nu from data with 1 % position noise (the Rust test suite
    # checks the same figure on the same experiment).
    fit = rows["OutputError"]
    assert abs(fit["young"] / 1e5 - 1) < 0.01 and abs(fit["poisson"] / 0.4 - 1) < 0.01
    # The dataset is written where asked.
    assert report["files"] and all((tmp_path / f).exists() for f in report["files"])
    # And the report, rendered as the runner renders it: report.md and every plot it lists.
    markdown = (tmp_path / "report.md").read_text()
    assert markdown.startswith("# Experiment `fit_material`")
    pngs = sorted(p.name for p in tmp_path.glob("*.png"))
    assert pngs and sorted(p.name for p in tmp_path.glob("*.svg")) == [
        n.replace(".png", ".svg") for n in pngs
    ]
    # Every plot is embedded, and every file the report names exists.
    for svg in tmp_path.glob("*.svg"):
        assert f"]({svg.name})" in markdown
    files = next(line for line in markdown.splitlines() if line.startswith("Files: "))
    named = re.findall(r"`([^`]+)`", files)
    assert named and all((tmp_path / n).exists() for n in named), files


def test_bad_experiments_raise(tmp_path):
    with pytest.raises(deform.LearnError):
        deform.Experiment.load(tmp_path / "missing.ron")
    bad = tmp_path / "bad.ron"
    bad.write_text("Experiment(name: 1)")
    with pytest.raises(deform.LearnError, match="bad.ron"):
        deform.Experiment.load(bad)


def test_the_solver_policy_pipeline_runs_from_python():
    # Logging every candidate on the training Newton systems, learning the policy and
    # measuring it against the fixed solvers, Eisenstat-Walker and the hand schedule.
    from conftest import ROOT

    e = deform.Experiment.load(ROOT / "crates" / "studies" / "tests" / "data" / "select_solver.ron")
    rows = e.run()["task"]["SelectSolver"]["cases"][0]["rows"]
    contenders = [r["contender"] if isinstance(r["contender"], str) else next(iter(r["contender"])) for r in rows]
    assert "Learned" in contenders and "EisenstatWalker" in contenders
    learned = rows[contenders.index("Learned")]["measured"]
    assert not learned["failed"] and learned["deterministic"] and learned["error"] < 1e-6
    fixed = [r["measured"]["work"] for r, c in zip(rows, contenders) if c == "Fixed"]
    assert learned["work"] <= min(fixed)


def test_a_policy_learned_in_python_drives_a_simulation(tmp_path):
    scene = deform.Scene.from_ron(SCENE.format(e=1e5, nu=0.4))
    candidates = [
        "Direct()",
        "Pcg(preconditioner: Ic0, tolerance: (rel: 1e-10))",
        "Cg(tolerance: (rel: 1e-10, max_iterations: 2000))",
    ]
    data = deform.SolverData.collect(scene, candidates, steps=6)
    assert len(data) >= 6
    data.save(tmp_path / "solver_data")
    assert len(deform.SolverData.load(tmp_path / "solver_data")) == len(data)
    policy = deform.LearnedPolicy.train(data, young=1e5)
    assert policy.name.startswith("learned")
    learned, direct = (deform.Simulation(scene) for _ in range(2))
    learned.set_policy(policy)
    report = learned.step()
    assert report["policy"].startswith("learned")
    learned.run(4)
    direct.run(5)
    assert np.abs(learned.x - direct.x).max() < 1e-6
    with pytest.raises(deform.LearnError, match="candidate"):
        deform.SolverData.collect(scene, ["Gauss()"], steps=1)


FINE = """Scene(
    name: "fine",
    mesh: Beam(2),
    material: NeoHookean(Young(e: 1e5, nu: 0.4)),
    density: 1000.0,
    constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
    integrator: (dt: 0.01, gravity: {gravity}, newton: (rel: 1e-10, abs: 1e-12)),
    steps: 1,
)"""


def barycentric_embedding(fine, points):
    """Each point's fine element and barycentric weights, found by brute force in numpy
    (as a user's own mesher would give them)."""
    x, tets = fine.vertices, fine.tets
    elements, weights = [], []
    for p in points:
        for t, tet in enumerate(tets):
            d = np.stack([x[tet[1]] - x[tet[0]], x[tet[2]] - x[tet[0]], x[tet[3]] - x[tet[0]]], 1)
            l = np.linalg.solve(d, p - x[tet[0]])
            w = np.array([1.0 - l.sum(), *l])
            if w.min() >= -1e-9:
                elements.append(t)
                weights.append(w)
                break
    return np.array(elements), np.array(weights)


def test_coarsening_outside_data_of_mixed_conditions_with_a_given_embedding(tmp_path):
    # Motions made elsewhere: two under gravity, two without, each kicked.
    rng = np.random.default_rng(5)
    trajectories = []
    for k in range(4):
        gravity = "(0.0, 0.0, -9.81)" if k % 2 == 0 else "(0.0, 0.0, 0.0)"
        sim = deform.Simulation(deform.Scene.from_ron(FINE.format(gravity=gravity)))
        free = np.setdiff1d(np.arange(sim.x.shape[0]), sim.constrained)
        kick = np.zeros_like(sim.v)
        kick[free] = rng.normal(0, 0.3, (len(free), 3))
        x, v = record(sim, 6, kick)
        conditions = None if k % 2 == 0 else {"gravity": [0.0, 0.0, 0.0]}
        trajectories.append(deform.Trajectory(x, 0.01, velocities=v, conditions=conditions))
    assert trajectories[1].conditions == {"gravity": (0.0, 0.0, 0.0)}
    fine_scene = deform.Scene.from_ron(FINE.format(gravity="(0.0, 0.0, -9.81)"))
    data = deform.Dataset.from_trajectories(fine_scene, trajectories, split=(0.5, 0.25))
    coarse_scene = deform.Scene.from_ron(
        FINE.format(gravity="(0.0, 0.0, -9.81)").replace("Beam(2)", "Beam(1)")
    )
    fine_mesh, coarse_mesh = deform.beam(2), deform.beam(1)
    elements, weights = barycentric_embedding(fine_mesh, coarse_mesh.vertices)
    coarse, mapping = data.coarsen(coarse_scene, elements=elements, weights=weights)
    assert mapping["vertices"] == coarse_mesh.vertices.shape[0]
    # Every coarse state is the fine one at the given places, conditions kept.
    for fine_t, coarse_t in zip(data.trajectories, coarse.trajectories):
        expected = np.einsum("pa,spad->spd", weights, fine_t.x[:, fine_mesh.tets[elements]])
        np.testing.assert_allclose(coarse_t.x, expected, atol=1e-12)
        assert coarse_t.conditions == fine_t.conditions
    # The coarse model's material fitted to the carried data of all four motions at once.
    fit = deform.fit_material(coarse_scene, coarse.trajectories, rollout=3, max_iterations=10)
    assert np.isfinite(fit["E"]) and fit["stage2"]["loss"] < fit["stage2"]["initial_loss"]
    # The coarsening study's fits on them: homogeneous, per region, per element, saved.
    # max_iterations=3 stops the fits on their cap: each one says so.
    with pytest.warns(UserWarning, match="iteration cap"):
        fits = coarse.fit_coarse(regions=2, regularisation=[0.0], rollout=6, max_iterations=3,
                                 save=str(tmp_path), name="learned")
    names = [m["name"] for m in fits["models"]]
    assert names == ["untuned coarse", "homogeneous fit", "per-region fit", "per-element fit"]
    # Each model's validation and held-out errors, so the user can tell which is good; the
    # split (0.5, 0.25) of four motions leaves one of each.
    for m in fits["models"]:
        assert m["validation_error"] > 0 and np.isfinite(m["validation_error"]), m
        assert m["test_error"] > 0 and np.isfinite(m["test_error"]), m
    untuned, homogeneous = fits["models"][0], fits["models"][1]
    assert homogeneous["validation_error"] != untuned["validation_error"]
    per_element = fits["models"][-1]["fit"]
    assert per_element["losses"][1] < per_element["losses"][0]
    learned = deform.Scene.load(str(tmp_path / "learned.ron"))
    deform.Simulation(learned).run(2)
    # Conditions that do not fit the scene are refused when the dataset is made.
    bad = deform.Trajectory(trajectories[0].x, 0.01, velocities=trajectories[0].v,
                            conditions={"motions": []})
    with pytest.raises(deform.LearnError, match="motions"):
        deform.Dataset.from_trajectories(fine_scene, [bad])
    with pytest.raises(deform.LearnError, match="weights"):
        data.coarsen(coarse_scene, elements=elements, weights=weights * 2.0)
