"""Ray scaling of three parallel workloads on 1, 2 (and more) workers, in one run: a Drake balance map, a
reachable-mesh build and a fine-tuning update. Prints one JSON document.

    .venv/bin/python benchmarks/ray_scaling.py [--quick] [--repeats 2] [--workers 1 2 4] [--out FILE]

Each workload runs on a new local Ray instance (127.0.0.1) of as many CPUs as ``workers`` (1 and 2 by default;
more than the machine's cores oversubscribe it, which the record's machine section shows),
started before the clock starts and warmed by one untimed run (workers import hybridctl and build
their simulators once), so the times are the work and Ray's scheduling, not start-up. Every run
of a workload must give the same result on every worker count (the script fails otherwise);
``speedup`` is the 1-worker time over the 2-worker time and ``speedup_N`` over the N-worker time, measured in
the same run (the peer).

* ``balance_map``: the energy swing-up of the acrobot from a grid of rest states, Drake engine,
  chunks of starts as Ray tasks (:func:`hybridctl.experiments.balance_map`, ``backend="ray"``);
* ``mesh``: the rimless wheel's reachable mesh under 25 Gaussian slopes
  (:func:`hybridctl.analysis.build_mesh`, ``backend="ray"``), batches of states as tasks, or in process
  where a round's measured cost is under ``PARALLEL_MIN_ROUND_SECONDS`` (``rounds`` says where they ran);
* ``finetune_update``: one update of fine-tuning (thesis Ch. 6) of a linear Pendulum-v1 policy,
  2 x 8 perturbed rollouts in chunks as tasks.

``tasks_at_thesis_settings`` says how many tasks each workload makes at the thesis' settings, so
how far it can parallelise: a 41 x 41 map, the 64 directions of fine-tuning, the mesh's batches.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from common import emit, machine_info  # noqa: E402


def _balance_map(workers: int, grid: int):
    from hybridctl.experiments import balance_map

    result = balance_map("acrobot", "energy", grid=grid, duration=2.0, backend="ray", workers=workers,
                         progress=False)
    return result.balanced.tolist(), result.returns.round(12).tolist()


_ROUNDS: dict[int, dict] = {}
"""Where the mesh's rounds ran (``ReachableMesh.rounds``) per worker count, filled by :func:`_mesh`."""


def _mesh(workers: int, box: float):
    from hybridctl.analysis import build_mesh
    from hybridctl.analysis.poincare import GaussianDisturbance, RimlessWheel

    wheel = RimlessWheel()
    mesh = build_mesh(wheel, [[wheel.fixed_point(0.15)]], GaussianDisturbance(0.15, 0.06, 25), box,
                      backend="ray", workers=workers, batch_size=16, progress=False)
    summary = {k: v for k, v in mesh.summary().items() if k != "wall_time_s"}
    _ROUNDS[workers] = dict(mesh.rounds)
    return np.asarray(mesh.states).round(12).tolist(), summary


def _finetune(workers: int, directions: int):
    from hybridctl.learn import FineTune, FineTuneConfig

    policy = torch.nn.Linear(3, 1).double()
    with torch.no_grad():
        policy.weight.copy_(torch.tensor([[-1.0, 0.0, -0.1]]))
        policy.bias.zero_()
    config = FineTuneConfig(updates=1, n_directions=directions, episode_steps=200, backend="ray", workers=workers,
                            chunk_size=max(1, directions // 2), seed=0)
    tuner = FineTune("Pendulum-v1", policy, config)
    tuner.learn(progress=False)
    return tuner.theta.tolist()


WORKLOADS = {"balance_map": _balance_map, "mesh": _mesh, "finetune_update": _finetune}


def measure(name: str, size, repeats: int, worker_counts=(1, 2)) -> dict:
    """Seconds of ``name`` on a local Ray instance of each of ``worker_counts`` workers (median of ``repeats``)."""
    import ray

    from hybridctl.parallel import make_backend

    out, results = {}, {}
    _ROUNDS.clear()
    for workers in worker_counts:
        with make_backend("ray", workers=workers):     # a new local instance of `workers` CPUs
            WORKLOADS[name](workers, size)              # warm: workers import and build once
            times = []
            for _ in range(repeats):
                start = time.perf_counter()
                results[workers] = WORKLOADS[name](workers, size)
                times.append(time.perf_counter() - start)
            out[f"{workers}_worker_s"] = statistics.median(times)
        assert not ray.is_initialized()
    if any(results[w] != results[worker_counts[0]] for w in worker_counts):
        raise SystemExit(f"{name}: {', '.join(map(str, worker_counts))} workers gave different results")
    if 1 in worker_counts and 2 in worker_counts:
        out["speedup"] = out["1_worker_s"] / out["2_worker_s"]
    for w in worker_counts:
        if w > 2 and 1 in worker_counts:
            out[f"speedup_{w}"] = out["1_worker_s"] / out[f"{w}_worker_s"]
    out["same_result"] = True
    if _ROUNDS:
        out["rounds"] = {str(w): r for w, r in _ROUNDS.items()}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes (structure check)")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2],
                        help="worker counts, each a new local Ray instance of as many CPUs (default 1 2; 1 to 16)")
    args = parser.parse_args()
    if not (1 in args.workers and 2 in args.workers and all(1 <= w <= 16 for w in args.workers)):
        parser.error(f"--workers must include 1 and 2, each in [1, 16], got {args.workers}")
    workers = tuple(sorted(set(args.workers)))
    torch.set_num_threads(1)
    sizes = {"balance_map": 4 if args.quick else 8, "mesh": 2e-2 if args.quick else 5e-3,
             "finetune_update": 4 if args.quick else 16}
    repeats = 1 if args.quick else args.repeats
    report = {name: {"size": sizes[name], **measure(name, sizes[name], repeats, workers)} for name in WORKLOADS}
    report["balance_map"]["what"] = f"acrobot, energy swing-up, {sizes['balance_map']}^2 starts of 2 s, Drake"
    report["mesh"]["what"] = f"rimless wheel, 25 slopes, box {sizes['mesh']}"
    report["finetune_update"]["what"] = f"Pendulum-v1 linear policy, 2 x {sizes['finetune_update']} rollouts"
    report["tasks_at_thesis_settings"] = {
        "balance_map": "41 x 41 = 1,681 starts in chunks of <= 25: >= 68 tasks (4 per worker up to 17 workers)",
        "finetune_update": "2 x 64 = 128 rollouts in chunks of --chunk-size (default 64): 2 tasks per update",
        "mesh": "batch_size x workers states per round: as many tasks as workers while the frontier is large"}
    emit({"benchmark": "ray_scaling", "machine": machine_info(), "repeats": repeats, **report}, args.out)
    print(np.round([report[n]["speedup"] for n in WORKLOADS], 2), file=sys.stderr)


if __name__ == "__main__":
    main()
