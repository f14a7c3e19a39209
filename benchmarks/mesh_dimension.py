"""Mesh dimension (thesis Alg. 6) of 17-dimensional trajectories: hybridctl's vectorised box
count against the thesis' dict-of-tuples box count, measured in the same run. Prints one JSON
document.

    .venv/bin/python benchmarks/mesh_dimension.py [--quick] [--out FILE]

Trajectories (17 coordinates, the size of HalfCheetah's state without x):
``gait``: a noisy quasi-periodic signal (every coordinate a sum of two harmonics of one
base frequency with its own phases, plus 1 % white noise), the kind of set the thesis
meshes; ``random_walk``: a 17-D Gaussian random walk (no structure, the hardest case for
the count). Both at 1e4 and 1e5 states. Each entry: median wall seconds of
``mesh_dimension`` with ``method="vectorised"`` and ``method="dict"`` (the same curve,
checked), their ratio, the process-CPU seconds of both (steadier on a busy machine), the
number of meshes on the curve and the dimensions found.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import numpy as np  # noqa: E402

from common import emit, machine_info  # noqa: E402
from hybridctl.analysis import mesh_dimension  # noqa: E402

DIMS = 17


def gait(n: int, rng: np.random.Generator) -> np.ndarray:
    """Noisy quasi-periodic 17-D trajectory, 100 samples per cycle."""
    t = np.arange(n) * (2 * np.pi / 100)
    phase = rng.uniform(0, 2 * np.pi, size=(2, DIMS))
    amp = rng.uniform(0.5, 1.5, size=(2, DIMS))
    x = amp[0] * np.sin(t[:, None] + phase[0]) + 0.3 * amp[1] * np.sin(2 * t[:, None] + phase[1])
    return x + 0.01 * rng.normal(size=x.shape)


def random_walk(n: int, rng: np.random.Generator) -> np.ndarray:
    """17-D Gaussian random walk."""
    return rng.normal(size=(n, DIMS)).cumsum(axis=0)


def timed(fn, repeats: int) -> tuple[object, list[float], list[float]]:
    """Result of ``fn()``, and the wall and process-CPU seconds of ``repeats`` calls after a warm-up call.

    CPU seconds count every thread of this process and not other processes, so they move far less
    than wall seconds when the machine is busy (compare both with the load average).
    """
    result = fn()
    wall, cpu = [], []
    for _ in range(repeats):
        start, cpu_start = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - cpu_start)
    return result, wall, cpu


def bench_one(kind: str, n: int, repeats: int, dict_repeats: int) -> dict:
    """One trajectory: vectorised vs dict mesh dimension, same curve required."""
    states = {"gait": gait, "random_walk": random_walk}[kind](n, np.random.default_rng(0))
    fast, fast_times, fast_cpu = timed(lambda: mesh_dimension(states), repeats)
    slow, slow_times, slow_cpu = timed(lambda: mesh_dimension(states, method="dict"), dict_repeats)
    if not np.array_equal(fast.sizes, slow.sizes):
        raise AssertionError(f"{kind} n={n}: vectorised and dict mesh sizes differ")
    fast_s, slow_s = statistics.median(fast_times), statistics.median(slow_times)
    return {"trajectory": kind, "n_states": n, "n_dims": DIMS, "meshes_on_curve": int(len(fast.sizes)),
            "lower": fast.lower, "upper": fast.upper,
            "vectorised_s": fast_s, "vectorised_min_s": min(fast_times), "vectorised_max_s": max(fast_times),
            "dict_s": slow_s, "speedup_vs_dict": slow_s / fast_s,
            "vectorised_cpu_s": statistics.median(fast_cpu), "dict_cpu_s": statistics.median(slow_cpu),
            "repeats": {"vectorised": repeats, "dict": dict_repeats}}


def run(quick: bool) -> dict:
    """All entries and the machine record."""
    sizes = (10_000,) if quick else (10_000, 100_000)
    entries = []
    for kind in ("gait", "random_walk"):
        for n in sizes:
            entries.append(bench_one(kind, n, repeats=3 if quick else 15 if n <= 10_000 else 5,
                                     dict_repeats=1 if quick or n > 10_000 else 3))
    return {"benchmark": "mesh_dimension", "quick": quick, "command": sys.argv,
            "timestamp": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "machine": machine_info(),
            "settings": {"f": 1.5, "d0": 1e-2, "stop_fraction": 0.8, "d_min": 1e-9,
                         "normalisation": "the trajectory's own mean and std"},
            "peer": "mesh_dimension(method='dict'): Algorithm 6 with the thesis' dict-of-tuples box count",
            "entries": entries}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="1e4 states only, fewer repeats (for tests)")
    parser.add_argument("--out", type=Path, help="also write the JSON to this file")
    args = parser.parse_args(argv)
    emit(run(args.quick), args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
