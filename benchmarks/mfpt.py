"""Exact mean first passage time on four families of absorbing chains of 1e4, 1e5 and 1e6 states:
hybridctl's ``absorbing_mfpt`` (method "auto") against scipy's ``spsolve`` and deeptime's
``mfpt`` (if installed) in the same run, with ratios. Prints one JSON document.

    .venv/bin/python benchmarks/mfpt.py [--quick] [--sizes N ...] [--families F ...] [--out FILE]
        [--peer-timeout S] [--repeats N]

(``--quick``: 1e3 states. deeptime is a peer where importable, e.g. ``PYTHONPATH=/tmp/dtlib``.)

Families: "birth-death": a 1-D line, down 0.5, up 0.5 - 1e-4, failure 1e-4 per step (state 1 steps down
into it; MFPT about 1e4). "grid-2d": a walk on a square grid, 4 neighbours, stepping off the grid fails,
plus 1e-6 per step. "mesh-like" imitates a reachable-state mesh of a gait: states on a 2-D lattice, each
with 8 successors scattered by one cell around a slowly turning, slightly contracting image
(most states cycle for a long time), failure off the lattice or, rarely, near its edge and
with a small floor (mean first passage times of 1e2-1e4 steps). "uniform": random sparse rows,
5 successors drawn uniformly from all states (the failure state included) with random weights.
Each solver runs ``--repeats`` times and the median is reported. The peers run in a forked
child killed after ``--peer-timeout`` seconds (their LU fills in without bound on uniform
chains); a peer that timed out is reported so, and the ratio is then a lower bound.
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402
import scipy.sparse.linalg as spla  # noqa: E402

from common import emit, machine_info  # noqa: E402
from hybridctl.analysis.markov import absorbing_mfpt  # noqa: E402


def mesh_like_chain(states: int, successors: int = 8, seed: int = 0) -> sp.csr_matrix:
    """Mesh-like absorbing chain of about ``states`` states on a 2-D lattice (+ failure state 0)."""
    rng = np.random.default_rng(seed)
    side = max(int(round(np.sqrt(states))), 2)
    n = side * side
    grid = np.stack(np.unravel_index(np.arange(n), (side, side)), axis=1).astype(np.float64)
    centre = (side - 1) / 2
    rel = grid - centre
    turn = 0.05
    rotation = np.array([[np.cos(turn), np.sin(turn)], [-np.sin(turn), np.cos(turn)]])
    image = centre + 0.995 * rel @ rotation                     # slow spiral towards the centre
    target = np.rint(image[:, None, :] + rng.normal(scale=1.0, size=(n, successors, 2)))
    radius = np.linalg.norm(rel / max(centre, 1), axis=1)
    outside = np.any((target < 0) | (target > side - 1), axis=2)
    fails = outside | (rng.uniform(size=(n, successors)) < 1e-4 + 0.02 * radius[:, None] ** 8)
    index = np.ravel_multi_index(np.clip(target, 0, side - 1).astype(np.int64).transpose(2, 0, 1), (side, side)) + 1
    rows = np.repeat(np.arange(1, n + 1), successors)
    return _chain(rows, np.where(fails, 0, index).ravel(), np.full(rows.size, 1.0 / successors), n + 1)


def uniform_chain(states: int, successors: int = 5, seed: int = 0) -> sp.csr_matrix:
    """Absorbing chain with random sparse rows: ``successors`` columns uniform over all states."""
    rng = np.random.default_rng(seed)
    rows = np.repeat(np.arange(1, states), successors)
    return _chain(rows, rng.integers(0, states, size=rows.size), rng.uniform(size=rows.size), states)


def birth_death_chain(states: int, fail: float = 1e-4, seed: int = 0) -> sp.csr_matrix:
    """1-D birth-death line of ``states`` states (failure state 0, reflecting top)."""
    i = np.arange(1, states)
    up = np.where(i == states - 1, 0.0, 0.5 - fail)
    rows, cols = np.r_[i, i, i, i], np.r_[i - 1, np.minimum(i + 1, states - 1), np.zeros(i.size, int), i]
    vals = np.r_[np.full(i.size, 0.5), up, np.full(i.size, fail), np.maximum(0.5 - up - fail, 0.0)]
    return _chain(rows, cols, vals, states)


def grid_chain(states: int, fail: float = 1e-6, seed: int = 0) -> sp.csr_matrix:
    """Walk on a square grid of about ``states`` cells: 4 neighbours, off the grid fails, ``fail`` per step."""
    side = max(int(round(np.sqrt(states))), 2)
    r, c = np.unravel_index(np.arange(side * side), (side, side))
    rows, cols, vals = [], [], []
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        rr, cc = r + dr, c + dc
        off = (rr < 0) | (rr >= side) | (cc < 0) | (cc >= side)
        j = np.ravel_multi_index((np.clip(rr, 0, side - 1), np.clip(cc, 0, side - 1)), (side, side)) + 1
        rows.append(r * side + c + 1), cols.append(np.where(off, 0, j)), vals.append(np.full(r.size, (1 - fail) / 4))
    rows.append(r * side + c + 1), cols.append(np.zeros(r.size, int)), vals.append(np.full(r.size, fail))
    return _chain(np.concatenate(rows), np.concatenate(cols), np.concatenate(vals), side * side + 1)


FAMILIES = {"birth-death": birth_death_chain, "grid-2d": grid_chain, "mesh-like": mesh_like_chain,
            "uniform": uniform_chain}


def _chain(rows, cols, vals, n) -> sp.csr_matrix:
    """Row-normalised CSR chain from triplets, with state 0 absorbing."""
    T = sp.csr_matrix((np.r_[1.0, vals], (np.r_[0, rows], np.r_[0, cols])), shape=(n, n))
    T.sum_duplicates()
    return (sp.diags(1.0 / np.asarray(T.sum(axis=1)).ravel()) @ T).tocsr()


def timed(fn, repeats: int):
    """(last result, wall times) of ``repeats`` calls."""
    result, times = None, []
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return result, times


def _spsolve(T):
    A = (sp.identity(T.shape[0] - 1, format="csc") - T[1:, 1:]).tocsc()
    return np.r_[0.0, spla.spsolve(A, np.ones(T.shape[0] - 1))]


def _deeptime(T):
    from deeptime.markov.tools.analysis import mfpt
    return np.asarray(mfpt(T, 0))


def _child(fn, T, repeats, conn):
    conn.send(timed(lambda: fn(T), repeats))


def peer(fn, T, repeats: int, timeout: float) -> tuple[np.ndarray | None, list | str]:
    """Run a peer solver in a forked child: (solution, times) or (None, why it has none)."""
    parent, child = multiprocessing.get_context("fork").Pipe(duplex=False)
    process = multiprocessing.get_context("fork").Process(target=_child, args=(fn, T, repeats, child))
    process.start()
    child.close()
    if not parent.poll(timeout):
        process.kill()
        process.join()
        return None, f"timed out after {timeout:g} s"
    try:
        x, times = parent.recv()
    except EOFError:
        x, times = None, "the child died (memory?)"
    process.join()
    return x, times


def bench_chain(family: str, states: int, repeats: int, peer_timeout: float, has_deeptime: bool) -> dict:
    """One chain: auto (hybridctl), spsolve, deeptime; ratios are peer time / auto time (> 1: auto faster)."""
    T = FAMILIES[family](states)
    ours, times = timed(lambda: absorbing_mfpt(T, eigen=False), repeats)
    finite = np.isfinite(ours.mfpt)
    entry = {"family": family, "states": int(T.shape[0]), "nonzeros": int(T.nnz),
             "auto_s": statistics.median(times), "auto_path": ours.solver["path"], "auto_solver": ours.solver,
             "mfpt_mean_over_states": float(ours.mfpt[finite][1:].mean()), "mfpt_max": float(ours.mfpt[finite].max()),
             "infinite_states": int(ours.infinite_states.size)}
    peers = {"spsolve": _spsolve, **({"deeptime": _deeptime} if has_deeptime else {})}
    best = None
    for name, fn in peers.items():
        x, peer_times = peer(fn, T, repeats, peer_timeout)
        if x is None:
            entry[name] = {"skipped": peer_times, "ratio_at_least": peer_timeout / entry["auto_s"]}
            continue
        seconds = statistics.median(peer_times)
        entry[name] = {"seconds": seconds, "ratio": seconds / entry["auto_s"],
                       "max_rel_diff": float(np.max(np.abs(x[finite][1:] - ours.mfpt[finite][1:]) / x[finite][1:]))}
        best = seconds if best is None else min(best, seconds)
    if not has_deeptime:
        entry["deeptime"] = {"skipped": "deeptime not installed"}
    entry["ratio_vs_best_peer"] = best / entry["auto_s"] if best is not None else None
    return entry


def run(quick: bool, peer_timeout: float, repeats: int, sizes=None, families=None) -> dict:
    """All chains and the machine record."""
    try:
        import deeptime
        has_deeptime, deeptime_version = True, deeptime.__version__
    except ImportError:
        has_deeptime, deeptime_version = False, "deeptime not installed"
    sizes = sizes or ((1_000,) if quick else (10_000, 100_000, 1_000_000))
    return {"benchmark": "mfpt", "quick": quick, "command": sys.argv,
            "timestamp": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "machine": machine_info(),
            "deeptime": deeptime_version, "repeats": repeats, "peer_timeout_s": peer_timeout,
            "ratio": "peer median seconds / auto median seconds (> 1: auto faster; >= 0.5: within 2x)",
            "entries": [bench_chain(family, n, repeats, peer_timeout, has_deeptime)
                        for n in sizes for family in (families or FAMILIES)]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="1e3-state chains only (for tests)")
    parser.add_argument("--sizes", type=int, nargs="+", help="states per chain (default 1e4 1e5 1e6)")
    parser.add_argument("--families", nargs="+", choices=sorted(FAMILIES), help="default: all four")
    parser.add_argument("--out", type=Path, help="also write the JSON to this file")
    parser.add_argument("--peer-timeout", type=float, default=60.0, help="seconds a peer may run on one chain")
    parser.add_argument("--repeats", type=int, default=3, help="runs of each solver (median reported)")
    args = parser.parse_args(argv)
    emit(run(args.quick, args.peer_timeout, args.repeats, args.sizes, args.families), args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
