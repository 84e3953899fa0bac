"""The Dask sweep: parts made on a 2-worker LocalCluster merge into what one process makes."""

import sys

import numpy as np
import pytest
from dask import distributed

import deform
from conftest import ROOT

sys.path.insert(0, str(ROOT / "python" / "examples"))
import sweep  # noqa: E402  (python/examples/sweep.py)

SCENE = """Scene(
    name: "sweep",
    mesh: Beam(1),
    material: NeoHookean(Young(e: 1e5, nu: 0.4)),
    density: 1000.0,
    constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
    steps: 1,
)"""


def test_a_sweep_on_a_local_cluster_equals_the_sequential_one(tmp_path):
    scenes = []
    for name, e in [("soft", 1e5), ("stiff", 4e5)]:
        path = tmp_path / f"{name}.ron"
        path.write_text(SCENE.replace("1e5", repr(e)))
        scenes.append(path)
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True)
    with distributed.Client(cluster) as client:
        merged = sweep.sweep(client, scenes, [1, 2, 3], trajectories=2, steps=5)
    cluster.close()
    assert set(merged) == {str(s) for s in scenes}
    for scene in scenes:
        alone = deform.Dataset.merge(
            [sweep.make_part(str(scene), seed, 2, 5) for seed in (1, 2, 3)]
        )
        got = merged[str(scene)]
        assert len(got) == 6
        for a, b in zip(got.trajectories, alone.trajectories):
            assert np.array_equal(a.x, b.x) and np.array_equal(a.v, b.v)
        assert [t["name"] for t in got.meta["trajectories"]] == [f"traj_{i:03}" for i in range(6)]
        # The merged dataset saves and loads.
        got.save(tmp_path / scene.stem)
        back = deform.Dataset.load(tmp_path / scene.stem)
        assert np.array_equal(back.trajectories[5].x, alone.trajectories[5].x)


def test_datasets_pickle_and_refuse_to_merge_across_scenes(tmp_path):
    import pickle

    a = deform.Dataset.generate(deform.Scene.from_ron(SCENE), 2, 3, seed=1)
    b = pickle.loads(pickle.dumps(a))
    assert len(b) == 2 and b.meta == a.meta
    assert all(np.array_equal(p.x, q.x) for p, q in zip(a.trajectories, b.trajectories))
    other = deform.Dataset.generate(deform.Scene.from_ron(SCENE.replace("1000.0", "900.0")), 1, 3, 2)
    with pytest.raises(deform.LearnError, match="scene"):
        deform.Dataset.merge([a, other])
