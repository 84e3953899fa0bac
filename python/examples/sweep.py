"""Dataset sweeps on Dask distributed: scenes x seeds as independent tasks, merged per scene.

Every (scene, seed) part is one task (deform generates it with the GIL released); the
client merges each scene's parts in seed order, so the result does not depend on which
worker ran what. Datasets pickle, so parts travel between processes and machines.

    pip install "./crates/python[dask]"                              # deform with Dask
    python python/examples/sweep.py                                  # a LocalCluster here
    python python/examples/sweep.py --scheduler tcp://10.0.0.5:8786   # a running cluster

On a cluster, the scene files (and the meshes they name) must be readable by the workers
at the same paths (a shared file system), and deform installed on them.
"""

import argparse
import pathlib

from dask.distributed import Client, LocalCluster

import deform


def make_part(scene_path, seed, trajectories, steps):
    """One task: `trajectories` simulations of the scene from initial conditions of `seed`."""
    scene = deform.Scene.load(scene_path)
    return deform.Dataset.generate(scene, trajectories, steps, seed)


def sweep(client, scenes, seeds, trajectories, steps):
    """Runs every (scene, seed) part on `client`; returns {scene path: merged dataset}."""
    futures = {
        str(scene): [
            client.submit(make_part, str(scene), seed, trajectories, steps, pure=False)
            for seed in seeds
        ]
        for scene in scenes
    }
    return {scene: deform.Dataset.merge(client.gather(parts)) for scene, parts in futures.items()}


def main():
    root = pathlib.Path(__file__).resolve().parents[2]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scheduler", help="address of a running Dask scheduler")
    parser.add_argument("--workers", type=int, default=2, help="LocalCluster workers")
    parser.add_argument(
        "--scenes",
        nargs="+",
        default=[root / "assets" / "scenes" / "cantilever.ron"],
        type=pathlib.Path,
    )
    parser.add_argument("--seeds", type=int, default=4, help="seeds 1..N per scene")
    parser.add_argument("--trajectories", type=int, default=2, help="per seed")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--out", type=pathlib.Path, default=root / "target" / "deform" / "sweep")
    args = parser.parse_args()
    if args.scheduler:
        client = Client(args.scheduler)
    else:
        client = Client(LocalCluster(n_workers=args.workers, threads_per_worker=1))
    with client:
        merged = sweep(client, args.scenes, range(1, args.seeds + 1), args.trajectories, args.steps)
    for scene, dataset in merged.items():
        out = args.out / pathlib.Path(scene).stem
        dataset.save(out)
        print(f"{scene}: {len(dataset)} trajectories -> {out}")


if __name__ == "__main__":
    main()
