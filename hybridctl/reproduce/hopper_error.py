"""Where the hopper mesh's MFPT error comes from: an error decomposition.

``hopper.json`` has the mesh MFPT at half the Monte Carlo value (58.4 at box size 0.35
against 114.6 [101.7, 127.5]). The mesh differs from the true apex map in three ways:

1. **box lumping** (the Markov assumption): the next box is taken to depend on the box only;
2. **the representative**: each box is expanded from one state, the first that reached it,
   whatever state of that box the true process is in;
3. **transients near the seeds** (the seeds' boxes are reached once at the start).

The disturbance set is not among them: mesh and Monte Carlo draw from the same 25 pushes.

This script measures them per box size against one recorded Monte Carlo run of the true map
(an independent stream: seed 2; ``hopper.json``'s Monte Carlo is seed 1).

- Lumping alone costs nothing: the box chain estimated from recorded complete runs (each
  box's row from the states the process really visits there) has exactly the runs' mean
  first passage as its MFPT, at any box size (the maximum-likelihood chain keeps the visit
  counts). So the mesh's error lies in how it estimates each box's row.
- ``decomposition`` (exact; see :func:`decompose`): the mesh's per-step failure rate
  1 / MFPT minus the true one splits into an **occupancy** term (the mesh chain spends its
  steps in other boxes than the true process) and a **representative** term (on the boxes
  the true process visits, the representative fails more or less often than the visits).
  Also: total-variation distance of the two occupancies, the mesh's occupancy in boxes the
  true process never visited, the normalised distance from a visit to its representative.
- ``jitter``: Monte Carlo on the true map with every apex state moved by a uniform random
  offset of up to half a box (policy std units; all coordinates but the apex' vertical
  velocity) after each step: how sensitive the map is to a box-sized state error.
- transients (3): ``mesh_mfpt_seeds`` (from the seeds) against ``mesh_mfpt_quasi_stationary``.

```text
usage: python -m hybridctl.reproduce.hopper_error [--box-sizes 1 0.7 0.5 0.35 0.25]
       [--episodes 200] [--jitter-episodes 100] [--keep-rows]
``--keep-rows --box-sizes 0.18`` adds a finer row to the record and keeps the others.
Checkpoints (meshes, recorded runs) go to ``--work`` (runs/ch5/error) and are reused.
Writes ``results/ch5/hopper_error.json`` and ``.png`` (``--out``); reads ``hopper.json`` beside it.
The meshes run on --backend/--workers/--address (default: serial, in this process).
```
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import torch

from hybridctl.analysis import build_mesh
from hybridctl.analysis.markov import _krylov_solve
from hybridctl.analysis.mesh import box_keys
from hybridctl.analysis.reachable import ReachableMesh
from hybridctl.envs.sections import HopperApexMap, x_pushes
from hybridctl.io import atomic_write, atomic_write_text
from hybridctl.learn.ars import ARS
from hybridctl.reproduce.common import (RESULTS, add_backend_flags, backend_options, check_backend_flags, command_line,
                                       machine_info, recorded_path, shipped_policy)

VZ_INDEX = 6     # section state: qpos[1:] (5 numbers) then qvel; qvel[1] (vertical) is index 6, ~0 at an apex


def record_runs(section, seeds, pushes, episodes: int, max_hops: int, seed: int, jitter=None) -> dict:
    """Monte Carlo on the true map, all episodes stepped together; every transition recorded.

    ``jitter``: None, or half-widths (per coordinate, in state units) of a uniform offset
    added to each successor state (the representative's error modelled as noise).
    Returns arrays ``start`` (first state per episode), ``src`` (state before each
    transition), ``dst`` (state after it; NaN row = failure), ``episode``, ``steps``
    (first passage per episode), ``push`` (index into the push set per transition), ``censored``.
    """
    rng = np.random.default_rng(seed)
    values = np.asarray(pushes.values, dtype=np.float64)
    x = seeds[rng.integers(0, len(seeds), size=episodes)].copy()
    start = x.copy()
    alive = np.ones(episodes, dtype=bool)
    steps = np.zeros(episodes, dtype=np.int64)
    src, dst, ep, push = [], [], [], []
    for _ in range(max_hops):
        idx = np.flatnonzero(alive)
        if idx.size == 0:
            break
        which = rng.integers(0, len(values), size=idx.size)
        push.append(which)
        nxt = section.step_many(x[idx], values[which])
        ok = ~np.isnan(nxt).any(axis=1)
        if jitter is not None:
            nxt[ok] += rng.uniform(-1.0, 1.0, size=(int(ok.sum()), x.shape[1])) * jitter
        src.append(x[idx].copy()), dst.append(nxt), ep.append(idx)
        steps[idx] += 1             # the failing step counts: first passage = successes + 1
        x[idx[ok]] = nxt[ok]
        alive[idx[~ok]] = False
    return {"start": start, "src": np.concatenate(src), "dst": np.concatenate(dst), "episode": np.concatenate(ep),
            "push": np.concatenate(push), "steps": steps, "censored": int(alive.sum())}


def cached_runs(path: Path, **kwargs) -> tuple[dict, float]:
    """``record_runs`` once; later calls with the same settings read ``path``."""
    tag = json.dumps({k: v for k, v in kwargs.items() if k in ("episodes", "max_hops", "seed")} |
                     {"jitter": None if kwargs.get("jitter") is None else list(map(float, kwargs["jitter"]))})
    if path.is_file():
        data = dict(np.load(path, allow_pickle=False))
        if str(data.pop("tag")) == tag:
            wall = float(data.pop("wall_s"))
            data["censored"] = int(data["censored"])
            return data, wall
    t0 = time.perf_counter()
    data = record_runs(**kwargs)
    wall = time.perf_counter() - t0
    atomic_write(path, lambda f: np.savez(f, tag=tag, wall_s=wall, **data))
    return data, wall


def interval(steps: np.ndarray) -> dict:
    """Mean first passage with a normal 95 % interval."""
    half = 1.96 * steps.std(ddof=1) / np.sqrt(steps.size)
    return {"mean": float(steps.mean()), "interval95": [float(steps.mean() - half), float(steps.mean() + half)],
            "episodes": int(steps.size)}


def box_ids(states: np.ndarray, d: float, mean, std, ids: dict) -> np.ndarray:
    """Mesh id (1-based) of each state's box; 0 where the mesh has no such box."""
    keys = np.ascontiguousarray(box_keys(states, d, mean, std))
    return np.array([ids.get(k.tobytes(), 0) for k in keys], dtype=np.int64)


def mesh_occupancy(mesh: ReachableMesh) -> np.ndarray:
    """Expected visits to each mesh state (index id - 1) before failure, from the seeds:
    solves (I - Q)^T n = s0. Their sum is the mesh MFPT from the seeds."""
    T = mesh.transition_matrix()
    Q = T[1:, 1:]
    s0 = mesh.seed_distribution()[1:]
    # Krylov, as the mesh's own MFPT solve: sparse LU did not finish in 10 min on the 34,155-state mesh
    occupancy, _ = _krylov_solve((sp.identity(Q.shape[0], format="csr") - Q.T).tocsr(), s0, rtol=1e-10)
    return occupancy


def decompose(mesh: ReachableMesh, runs: dict, d: float, mean, std) -> dict:
    """The exact split of the mesh's error in the per-step failure rate (1 / MFPT):

        1/T_mesh - 1/T_true = sum_b (pi_mesh(b) - pi_true(b)) p_rep(b)     occupancy
                            + sum_b pi_true(b) (p_rep(b) - p_true(b))      representative

    pi: the share of steps spent in box b before failure (the mesh's from its chain, the true
    one from the recorded visits), p_rep: one-step failure probability of b's representative
    (all pushes), p_true: the recorded failure rate of visits to b. Sum pi p = 1 / T for both
    (every step in the sum, the failing one included). Visits to boxes the mesh lacks have
    p_rep = 0 there; that part of the representative term is reported as ``uncovered``.
    """
    ids = {k.tobytes(): i + 1 for i, k in enumerate(np.ascontiguousarray(box_keys(mesh.states, d, mean, std)))}
    visit = box_ids(runs["src"], d, mean, std, ids)
    failed = np.isnan(runs["dst"]).any(axis=1).astype(np.float64)
    n = mesh.size
    visits = np.bincount(visit, minlength=n + 1).astype(np.float64)        # index 0: boxes not in the mesh
    fails = np.bincount(visit, weights=failed, minlength=n + 1)
    pi_true = visits / visits.sum()
    p_true = np.divide(fails, visits, out=np.zeros(n + 1), where=visits > 0)
    p_rep = np.r_[0.0, mesh.failure_probability()]
    occupancy = mesh_occupancy(mesh)
    pi_mesh = np.r_[0.0, occupancy / occupancy.sum()]
    offset = (runs["src"][visit > 0] - mesh.states[visit[visit > 0] - 1]) / std
    in_mesh = visit > 0
    # one step from the representative vs from the visited state, same push: same next box?
    ok = ~np.isnan(runs["dst"]).any(axis=1)
    true_next = np.zeros(len(visit), dtype=np.int64)
    true_next[ok] = box_ids(runs["dst"][ok], d, mean, std, ids)
    true_next[ok & (true_next == 0)] = -1                      # a box the mesh lacks: never equal
    mesh_next = mesh.successors[visit[in_mesh] - 1, runs["push"][in_mesh]]
    same_next = mesh_next == true_next[in_mesh]
    failing = p_rep > 0
    return {"rate_mesh": float(pi_mesh @ p_rep), "rate_true": float(pi_true @ p_true),
            "occupancy_term": float((pi_mesh - pi_true) @ p_rep),
            "representative_term": float(pi_true[1:] @ (p_rep[1:] - p_true[1:])),
            "uncovered_term": float(-pi_true[0] * p_true[0]),
            "visits_in_mesh": float(in_mesh.mean()),
            "failure_rate_true_in_mesh_boxes": float(failed[in_mesh].mean()),
            "failure_probability_representative_on_true_visits": float(p_rep[visit[in_mesh]].mean()),
            "mesh_occupancy_in_boxes_never_visited": float(pi_mesh[1:][visits[1:] == 0].sum()),
            "total_variation_occupancy": float(0.5 * np.abs(pi_mesh - pi_true).sum()),
            "distance_to_representative_rms": float(np.sqrt((offset ** 2).sum(axis=1).mean())),
            "same_next_box": float(same_next.mean()),
            "same_next_box_note": "share of recorded transitions (boxes in the mesh) after which the representative, "
                                  "pushed alike, lands in the same box as the visited state (failure counts as a box)",
            "occupancy_in_boxes_that_can_fail_mesh": float(pi_mesh[failing].sum()),
            "occupancy_in_boxes_that_can_fail_true": float(pi_true[failing].sum()),
            "boxes_visited": int((visits[1:] > 0).sum()), "transitions": int(visits.sum())}


def finite(value):
    """``value`` with every infinite float written as the string "inf" (JSON has no inf)."""
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, float) and np.isinf(value):
        return "inf"
    return value


def spread(states: np.ndarray, weights: np.ndarray, centre: np.ndarray, std: np.ndarray) -> float:
    """RMS normalised distance from ``centre`` under weights."""
    r2 = (((states - centre) / std) ** 2).sum(axis=1)
    return float(np.sqrt(np.sum(weights * r2) / np.sum(weights)))


def kept_rows(path: Path, record: dict, box_sizes) -> list:
    """The rows of the record at ``path`` for box sizes not rebuilt now; refuses a record of another
    policy, push set or seed count, whose rows would not be comparable."""
    if not path.is_file():
        return []
    old = json.loads(path.read_text())
    for key in ("policy", "push_magnitude_N", "pushes", "seed_apexes"):
        if old.get(key) != record[key]:
            raise SystemExit(f"--keep-rows: {path} has {key} = {old.get(key)!r}, this run {record[key]!r}")
    record.setdefault("kept_rows_from", old["command"])
    return [r for r in old["rows"] if not any(np.isclose(r["box_size"], d) for d in box_sizes)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", default=str(shipped_policy("ars-hopper")))
    parser.add_argument("--magnitude", type=float, default=100.0)
    parser.add_argument("--pushes", type=int, default=25)
    parser.add_argument("--box-sizes", type=float, nargs="+", default=[1.0, 0.7, 0.5, 0.35])
    parser.add_argument("--max-states", type=int, default=40000)
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--jitter-episodes", type=int, default=100)
    parser.add_argument("--max-hops", type=int, default=1500)
    parser.add_argument("--work", default="runs/ch5/error")
    parser.add_argument("--out", default=str(RESULTS / "ch5" / "hopper_error.json"))
    parser.add_argument("--keep-rows", action="store_true",
                        help="keep the rows of --out whose box size is not in --box-sizes (same policy and pushes), "
                             "so a finer mesh is added without rebuilding the coarser ones")
    add_backend_flags(parser, "serial", "the meshes")
    args = parser.parse_args(argv)
    check_backend_flags(args, parser)
    torch.set_num_threads(1)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    agent = ARS.load(args.policy, backend="serial")
    section = HopperApexMap(agent.frozen_policy())
    seeds = section.apex_states(steps=2000, skip=3, seed=0)       # as hopper.py
    pushes = x_pushes(args.magnitude, args.pushes)
    mean, std = agent.stats.mean, agent.stats.std
    record = {"command": command_line("hybridctl.reproduce.hopper_error", argv), "machine": machine_info(),
              "policy": recorded_path(args.policy),
              "push_magnitude_N": args.magnitude, "pushes": args.pushes, "seed_apexes": int(len(seeds)),
              "monte_carlo_seed1": json.loads(Path(args.out).with_name("hopper.json").read_text())["monte_carlo"],
              "rows": []}
    kept = kept_rows(Path(args.out), record, args.box_sizes) if args.keep_rows else []
    runs, wall = cached_runs(work / "mc-seed2.npz", section=section, seeds=seeds, pushes=pushes,
                             episodes=args.episodes, max_hops=args.max_hops, seed=2)
    record["monte_carlo_seed2"] = {**interval(runs["steps"]), "censored": runs["censored"],
                                   "transitions": int(runs["src"].shape[0]), "wall_time_s": wall}
    print(json.dumps(record["monte_carlo_seed2"]), flush=True)
    visits = runs["src"]
    centre = visits.mean(axis=0)
    record["true_spread_rms"] = spread(visits, np.ones(len(visits)), centre, std)
    for d in args.box_sizes:
        t0 = time.perf_counter()
        mesh = build_mesh(section, seeds, pushes, d, mean=mean, std=std, max_states=args.max_states,
                          batch_size=256, checkpoint=work / f"mesh-d{d:g}.npz", resume=True, **backend_options(args),
                          checkpoint_minutes=2)
        row = {"box_size": d, "mesh_states": mesh.size, "complete": mesh.complete,
               "mesh_wall_time_s": mesh.wall_time, "this_call_s": time.perf_counter() - t0}
        if mesh.complete:
            result = mesh.mfpt()
            qsd = result.quasi_stationary[1:]
            row.update({"mesh_mfpt_seeds": result.mean(mesh.seed_distribution()),
                        "mesh_mfpt_quasi_stationary": result.mean(), "mesh_mfpt_eigen": result.eigen_estimate,
                        "mesh_spread_rms": spread(mesh.states, np.abs(qsd), centre, std)})
        if mesh.complete and np.isfinite(row["mesh_mfpt_seeds"]):
            row["decomposition"] = decompose(mesh, runs, d, mean, std)
        jitter = 0.5 * d * std.copy()
        jitter[VZ_INDEX] = 0.0
        jruns, jwall = cached_runs(work / f"jitter-d{d:g}.npz", section=section, seeds=seeds, pushes=pushes,
                                   episodes=args.jitter_episodes, max_hops=args.max_hops, seed=3, jitter=jitter)
        row["jitter"] = {**interval(jruns["steps"]), "censored": jruns["censored"], "wall_time_s": jwall}
        record["rows"].append(finite(row))
        print(json.dumps(record["rows"][-1]), flush=True)
        record["rows"] = sorted(kept + [r for r in record["rows"] if r not in kept], key=lambda r: -r["box_size"])
        record["wall_time_s"] = time.perf_counter() - start
        atomic_write_text(Path(args.out), json.dumps(record, indent=1, allow_nan=False) + "\n")
    plot(record, Path(args.out).with_suffix(".png"))
    return 0


def plot(record: dict, path: Path) -> None:
    """MFPT against box size for every estimate, with the Monte Carlo intervals."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = sorted(record["rows"], key=lambda r: r["box_size"])
    d = [r["box_size"] for r in rows]
    fig, (ax, bx, cx) = plt.subplots(1, 3, figsize=(16, 4.2))
    for key, colour in (("monte_carlo_seed1", "0.8"), ("monte_carlo_seed2", "0.6")):
        lo, hi = record[key]["interval95"]
        ax.axhspan(lo, hi, color=colour, alpha=0.6, label=f"Monte Carlo {key[-5:]} 95 %")
    ax.plot(d, [float(r.get("mesh_mfpt_seeds", np.nan)) for r in rows], "o-", label="mesh (first-arrival representative)")
    ax.errorbar(d, [r["jitter"]["mean"] for r in rows],
                yerr=[[r["jitter"]["mean"] - r["jitter"]["interval95"][0] for r in rows],
                      [r["jitter"]["interval95"][1] - r["jitter"]["mean"] for r in rows]],
                fmt="^-", capsize=3, label="true map + half-box jitter")
    ax.set(xlabel="box size (policy std units)", ylabel="mean apexes to failure", yscale="log",
           title="Hopper MFPT against box size")
    ax.legend(fontsize=7)
    parts = [r for r in rows if "decomposition" in r]
    x = np.arange(len(parts))
    for i, (key, label) in enumerate((("occupancy_term", "occupancy"), ("representative_term", "representative"),
                                      ("uncovered_term", "boxes not in mesh"))):
        bx.bar(x + (i - 1) * 0.27, [r["decomposition"][key] for r in parts], 0.27, label=label)
    bx.plot(x, [r["decomposition"]["rate_mesh"] - r["decomposition"]["rate_true"] for r in parts], "kD",
            label="1/MFPT mesh - 1/MFPT true")
    bx.axhline(0, color="k", lw=0.5)
    bx.set_xticks(x, [f"{r['box_size']:g}" for r in parts])
    bx.set(xlabel="box size", ylabel="per-step failure rate error", title="the mesh's error, split exactly")
    bx.legend(fontsize=7)
    cx.plot(d, [r["decomposition"]["occupancy_in_boxes_that_can_fail_mesh"] for r in parts], "o-",
            label="steps in boxes that can fail: mesh")
    cx.plot(d, [r["decomposition"]["occupancy_in_boxes_that_can_fail_true"] for r in parts], "s-",
            label="steps in boxes that can fail: true")
    cx.plot(d, [r["decomposition"]["same_next_box"] for r in parts], "^--",
            label="representative's next box = visit's (same push)")
    cx.set(xlabel="box size", ylabel="share", yscale="log", title="occupancy and one-step agreement")
    cx.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
