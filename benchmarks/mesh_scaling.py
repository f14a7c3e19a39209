"""States/s of a reachable-mesh build (thesis Alg. 7, ``build_mesh``) against worker processes,
with a projection to a cluster. Prints one JSON document; writes a PNG figure.

    .venv/bin/python benchmarks/mesh_scaling.py [--quick] [--workers 1 2] [--box-size 1.0]
                                                [--batch-size 4] [--out FILE] [--figure PNG]

The default section map is the Ch. 5 hopper (``HopperApexMap``: gymnasium Hopper-v5 under the
shipped ARS policy, 25 pushes along x in [-100, 100] N, boxes in the policy's observation
std, as :mod:`hybridctl.reproduce.hopper`). The same mesh is built once per worker count on the
``processes`` backend, in this one run, so ``ratio_vs_1_worker`` compares like with like;
every build must give the same mesh (the script fails otherwise). ``--quick`` uses the
rimless wheel (pure Python, a second per build) for the structure tests.

``projection`` scales the measured per-worker rate to the thesis' 275,658-state hopper mesh
on 16 workers (see benchmarks/README.md for what it assumes).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import os
import resource
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

from common import command_line, emit, machine_info  # noqa: E402
from hybridctl.analysis import build_mesh  # noqa: E402
from hybridctl.parallel import ProcessBackend  # noqa: E402

THESIS_STATES = 275_658       # the thesis' hopper mesh (Ch. 5)
CLUSTER_WORKERS = 16
DEFAULT_FIGURE = ROOT / "results" / "ch5" / "mesh_scaling.png"


def hopper_problem(box_size: float) -> dict:
    """The Ch. 5 hopper mesh problem of hybridctl.reproduce.hopper (its recorded settings)."""
    from hybridctl.envs.sections import HopperApexMap, x_pushes
    from hybridctl.learn.ars import ARS

    agent = ARS.load(str(ROOT / "models" / "policies" / "ars-hopper"), backend="serial")
    section = HopperApexMap(agent.frozen_policy())
    seeds = section.apex_states(steps=2000, skip=3, seed=0)
    return {"name": "hopper (HopperApexMap, Hopper-v5, ARS policy, 25 x-pushes in [-100, 100] N)",
            "section_map": section, "seeds": seeds, "disturbances": x_pushes(100.0, 25),
            "box_size": box_size, "mean": agent.stats.mean, "std": agent.stats.std}


def wheel_problem() -> dict:
    """The rimless wheel (thesis Ch. 5's analytic example): cheap, for --quick."""
    from hybridctl.analysis.poincare import GaussianDisturbance, RimlessWheel

    wheel = RimlessWheel()
    return {"name": "rimless wheel (25 Gaussian slopes)", "section_map": wheel,
            "seeds": [[wheel.fixed_point(0.15)]], "disturbances": GaussianDisturbance(0.15, 0.06, 25),
            "box_size": 1e-3, "mean": None, "std": None}


def worker_probe(task) -> dict:
    """In a worker: one section-map step (builds the simulator), then the process's peak RSS."""
    section_map, state, disturbance = task
    start = time.perf_counter()
    section_map.step(state, disturbance)
    return {"first_step_s": time.perf_counter() - start,
            "max_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def startup(problem: dict, workers: int) -> dict:
    """Seconds to spawn ``workers`` processes and take one step in each (imports, simulator, policy)."""
    state = np.atleast_2d(np.asarray(problem["seeds"], dtype=np.float64))[0]
    disturbance = list(problem["disturbances"].finite_set().values)[0]
    start = time.perf_counter()
    with ProcessBackend(workers) as pool:
        probes = pool.map(worker_probe, [(problem["section_map"], state, disturbance)] * workers)
    return {"seconds": time.perf_counter() - start, "worker_max_rss_mib": max(p["max_rss_mib"] for p in probes)}


def build(problem: dict, workers: int, batch_size: int) -> tuple[dict, object]:
    """One mesh build on ``workers`` processes; its wall time, rate and the load around it."""
    load_before = os.getloadavg()[0]
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    mesh = build_mesh(problem["section_map"], problem["seeds"], problem["disturbances"], problem["box_size"],
                      mean=problem["mean"], std=problem["std"], backend="processes", workers=workers,
                      batch_size=batch_size, progress=False)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)       # the pool's workers, joined at its close
    cpu = (after.ru_utime - children.ru_utime) + (after.ru_stime - children.ru_stime)
    expanded = int(mesh.successors.shape[0])
    return {"workers": workers, "wall_s": wall, "states": int(mesh.size), "expanded_states": expanded,
            "complete": bool(mesh.complete), "map_steps": expanded * int(mesh.successors.shape[1]),
            "states_per_s": expanded / wall, "worker_cpu_s": cpu,
            "states_per_worker_cpu_s": expanded / cpu if cpu > 0 else None, "load_average_1min": [load_before, os.getloadavg()[0]]}, mesh


def mesh_bytes(mesh) -> dict:
    """Bytes per mesh state held by the driver: arrays, plus the box-key dict (measured in one build)."""
    arrays = mesh.states.nbytes + mesh.successors.nbytes
    return {"array_bytes_per_state": arrays / max(mesh.size, 1)}


def figure(rows: list[dict], path: Path, title: str) -> None:
    """states/s against workers, with the ideal linear scaling from 1 worker."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    workers = [r["workers"] for r in rows]
    rates = [r["states_per_s"] for r in rows]
    base = rows[0]["states_per_s"] / rows[0]["workers"]
    fig, ax = plt.subplots(figsize=(4.5, 3.4), dpi=120)
    ax.plot(workers, [base * w for w in workers], "--", color="grey", label="linear from 1 worker")
    ax.plot(workers, rates, "o-", color="C0", label="measured (incl. start-up)")
    steady = [r["steady_states_per_s"] for r in rows]
    if all(s is not None for s in steady):
        ax.plot(workers, steady, "s:", color="C1", label="measured, start-up excluded")
    ax.set_xlabel("worker processes")
    ax.set_ylabel("mesh states expanded / s")
    ax.set_xticks(workers)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def run(quick: bool, workers: list[int], box_size: float, batch_size: int, figure_path: Path | None) -> dict:
    problem = wheel_problem() if quick else hopper_problem(box_size)
    rows, meshes = [], []
    for w in workers:
        spin = None if quick else startup(problem, w)      # --quick: spawning is most of the time anyway
        row, mesh = build(problem, w, batch_size)
        row["startup_s"] = spin["seconds"] if spin else None
        row["worker_max_rss_mib"] = spin["worker_max_rss_mib"] if spin else None
        # start-up (spawn, imports, simulator) measured on a separate pool: subtracted only where
        # the build is much longer than it, otherwise the difference is noise
        long_enough = spin is not None and row["wall_s"] > 3 * spin["seconds"]
        row["steady_states_per_s"] = row["expanded_states"] / (row["wall_s"] - spin["seconds"]) if long_enough else None
        rows.append(row)
        meshes.append(mesh)
    # Every worker count should build the same mesh. Recorded, not enforced: a section map whose
    # step depends on what its worker stepped before (MuJoCo's solver warm start carries over
    # between set_state calls: ~1e-14 differences that can move a state across a box edge)
    # builds slightly different meshes on different worker counts.
    for row, mesh in zip(rows, meshes):
        same = mesh.states.shape == meshes[0].states.shape and np.array_equal(mesh.states, meshes[0].states) \
            and np.array_equal(mesh.successors, meshes[0].successors)
        row["same_mesh_as_first"] = bool(same)
    one = rows[0]
    steady = all(r["steady_states_per_s"] is not None for r in rows)
    rate = "steady_states_per_s" if steady else "states_per_s"     # what the projection scales
    for row in rows:
        row["ratio_vs_1_worker"] = row["states_per_s"] / one["states_per_s"]
        row["steady_ratio_vs_1_worker"] = row["steady_states_per_s"] / one["steady_states_per_s"] if steady else None
        row["efficiency"] = row["ratio_vs_1_worker"] * one["workers"] / row["workers"]
    # per worker on a core of its own: states per CPU second of the workers (start-up included),
    # which other jobs on the machine barely change; the wall-clock rate is the fallback
    cpu_rates = [r["states_per_worker_cpu_s"] for r in rows]
    per_worker = statistics.median(cpu_rates) if all(cpu_rates) else one[rate] / one["workers"]
    best = max(rows, key=lambda r: r["workers"])
    efficiency = min(1.0, best[rate] / one[rate] * one["workers"] / best["workers"])
    memory = mesh_bytes(meshes[0])
    projection = {
        "states": THESIS_STATES, "workers": CLUSTER_WORKERS, "pushes_per_state": int(meshes[0].successors.shape[1]),
        "per_worker_states_per_s": per_worker,
        "efficiency_assumed": efficiency,
        "hours_at_measured_efficiency": THESIS_STATES / (CLUSTER_WORKERS * per_worker * efficiency) / 3600,
        "hours_at_linear_scaling": THESIS_STATES / (CLUSTER_WORKERS * per_worker) / 3600,
        "worker_hours": THESIS_STATES / per_worker / 3600,
        "driver_array_mib": THESIS_STATES * memory["array_bytes_per_state"] / 2 ** 20,
        "rate_used": "states_per_worker_cpu_s (median over builds)" if all(cpu_rates) else rate,
        "worker_rss_mib": one["worker_max_rss_mib"],
        "cluster_worker_rss_gib": CLUSTER_WORKERS * one["worker_max_rss_mib"] / 1024 if one["worker_max_rss_mib"] else None,
        "note": "per-worker rate: mesh states per CPU second of the worker processes (a dedicated core each); efficiency: the largest "
                "worker count's (at most 1), assumed to hold at 16 workers; arrays only "
                "(states + successors), the driver's box-key dict adds about as much again",
    }
    if figure_path is not None:
        loads = [v for r in rows for v in r["load_average_1min"]]
        figure(rows, figure_path, f"{problem['name'].split(' (')[0]} mesh, box {problem['box_size']:g}: "
                                  f"{one['expanded_states']} states\n{os.cpu_count()} cores, load average "
                                  f"{min(loads):.1f}-{max(loads):.1f} during the builds")
    return {"benchmark": "mesh_scaling",
            "timestamp": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "command": command_line(), "quick": quick, "machine": machine_info(),
            "problem": {"name": problem["name"], "box_size": problem["box_size"], "batch_size": batch_size,
                        "seeds": int(np.atleast_2d(problem["seeds"]).shape[0]), "backend": "processes"},
            "builds": rows, "memory": memory, "projection": projection,
            "figure": str(figure_path) if figure_path is not None else None}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="the rimless wheel, seconds (for tests)")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--box-size", type=float, default=1.0, help="hopper box size (policy std units)")
    parser.add_argument("--batch-size", type=int, default=4, help="states per task")
    parser.add_argument("--out", type=Path, help="also write the JSON to this file")
    parser.add_argument("--figure", type=Path, default=None,
                        help=f"PNG to write (default: {DEFAULT_FIGURE.relative_to(ROOT)} unless --quick)")
    args = parser.parse_args(argv)
    if any(w < 1 for w in args.workers) or sorted(set(args.workers)) != args.workers:
        parser.error("--workers must be increasing integers >= 1")
    if args.batch_size < 1 or not args.box_size > 0:
        parser.error("--batch-size must be >= 1 and --box-size > 0")
    figure_path = args.figure if args.figure is not None else (None if args.quick else DEFAULT_FIGURE)
    emit(run(args.quick, args.workers, args.box_size, args.batch_size, figure_path), args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
