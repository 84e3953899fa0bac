"""Helpers shared by the peer scripts: run deform's xtask, time Python callables."""

import json
import os
import statistics
import subprocess
import time

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))


def xtask(*args):
    """Runs `cargo xtask ARGS` at the repository root; returns its JSON lines."""
    out = subprocess.run(
        ["cargo", "xtask", *args], cwd=ROOT, check=True, capture_output=True, text=True
    ).stdout
    return [json.loads(line) for line in out.splitlines() if line.startswith("{")]


def median_time(f, repeats):
    """Median wall time of `f()` over `repeats` calls (after one warm-up call)."""
    f()
    samples = []
    for _ in range(repeats):
        t = time.perf_counter()
        f()
        samples.append(time.perf_counter() - t)
    return statistics.median(samples)


def beam_state(points):
    """The deformed state of BENCHMARKS.md: X + (0.01 x z, 0.005 sin 3x, -0.1 x^2)."""
    import numpy as np

    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    return np.stack([x + 0.01 * x * z, y + 0.005 * np.sin(3 * x), z - 0.1 * x * x], axis=1)


def table(rows, baseline):
    """Prints `(name, seconds, extra)` rows with the ratio to the `baseline` row."""
    base = dict((r[0], r[1]) for r in rows)[baseline]
    width = max(len(r[0]) for r in rows)
    for name, seconds, extra in rows:
        print(f"{name:<{width}}  {seconds:9.4f} s  {seconds / base:7.2f}x {baseline}  {extra}")
