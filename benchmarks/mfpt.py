"""Exact mean first passage time on mesh-like absorbing chains of 1e4, 1e5 and 1e6 states:
hybridctl's Krylov solve against scipy's sparse LU (``spsolve``), and deeptime if installed,
in the same run. Prints one JSON document.

    .venv/bin/python benchmarks/mfpt.py [--quick] [--out FILE] [--spsolve-max N]

The chains imitate a reachable-state mesh: states on a 3-D lattice (m^3 of them), each
with 25 "disturbance" successors scattered near a contracted image of the state (a
stable map), and a failure probability that grows towards the lattice's edge (mean
first passage times of tens to hundreds of steps, like the thesis' hopper). Sparse LU
fills in badly on such chains, so ``spsolve`` runs only up to ``--spsolve-max`` states
(default 2e4) and is reported as skipped above that. Every solve is checked against
the others where both ran (max relative difference).
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
import scipy.sparse as sp  # noqa: E402
import scipy.sparse.linalg as spla  # noqa: E402

from common import emit, machine_info  # noqa: E402
from hybridctl.analysis.markov import absorbing_mfpt  # noqa: E402

DISTURBANCES = 25


def mesh_like_chain(side: int, seed: int = 0) -> sp.csr_matrix:
    """Absorbing chain on a side^3 lattice (+ failure state 0); see the module docstring."""
    rng = np.random.default_rng(seed)
    n = side ** 3
    grid = np.stack(np.unravel_index(np.arange(n), (side,) * 3), axis=1).astype(np.float64)
    centre = (side - 1) / 2
    image = centre + 0.7 * (grid - centre)                       # contraction towards the centre
    jumps = rng.normal(scale=0.12 * side, size=(n, DISTURBANCES, 3))
    target = np.rint(image[:, None, :] + jumps)
    radius = np.linalg.norm((grid - centre) / max(centre, 1), axis=1)
    outside = np.any((target < 0) | (target > side - 1), axis=2)
    fails = outside | (rng.uniform(size=(n, DISTURBANCES)) < 0.02 * radius[:, None] ** 2)
    index = np.ravel_multi_index(np.clip(target, 0, side - 1).astype(np.int64).transpose(2, 0, 1), (side,) * 3) + 1
    cols = np.where(fails, 0, index).ravel()
    rows = np.repeat(np.arange(1, n + 1), DISTURBANCES)
    T = sp.csr_matrix((np.full(rows.size, 1.0 / DISTURBANCES), (rows, cols)), shape=(n + 1, n + 1))
    T = T + sp.csr_matrix(([1.0], ([0], [0])), shape=(n + 1, n + 1))
    T.sum_duplicates()
    return T.tocsr()


def timed(fn, repeats: int):
    result, times = None, []
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return result, times


def bench_chain(side: int, repeats: int, spsolve_max: int) -> dict:
    """One chain: Krylov (hybridctl), spsolve (if small enough), deeptime (if installed)."""
    T = mesh_like_chain(side)
    n = T.shape[0]
    krylov, k_times = timed(lambda: absorbing_mfpt(T, eigen=False), repeats)
    finite = np.isfinite(krylov.mfpt)
    entry = {"states": n, "nonzeros": int(T.nnz), "krylov_s": statistics.median(k_times),
             "krylov_min_s": min(k_times), "krylov_solver": krylov.solver,
             "mfpt_mean_over_states": float(krylov.mfpt[finite][1:].mean()),
             "mfpt_max": float(krylov.mfpt[finite].max()), "infinite_states": int(krylov.infinite_states.size)}
    if n <= spsolve_max:
        idx = np.flatnonzero(finite)[1:]
        A = (sp.identity(idx.size, format="csc") - T[idx][:, idx]).tocsc()
        direct, d_times = timed(lambda: spla.spsolve(A, np.ones(idx.size)), 1)
        entry["spsolve_s"] = statistics.median(d_times)
        entry["speedup_vs_spsolve"] = entry["spsolve_s"] / entry["krylov_s"]
        entry["max_rel_diff_vs_spsolve"] = float(np.max(np.abs(direct - krylov.mfpt[idx]) / direct))
    else:
        entry["spsolve"] = {"skipped": f"{n} states > --spsolve-max {spsolve_max} (LU fill-in)"}
    try:
        import deeptime  # noqa: F401
        entry["deeptime"] = {"skipped": "installed, but no absorbing-MFPT entry point is wired up yet"}
    except ImportError:
        entry["deeptime"] = {"skipped": "not installed"}
    return entry


def run(quick: bool, spsolve_max: int) -> dict:
    """All chains and the machine record."""
    sides = (12,) if quick else (22, 47, 100)       # quick: 1,728; else 10,648 / 103,823 / 1,000,000 states
    return {"benchmark": "mfpt", "quick": quick, "command": sys.argv,
            "timestamp": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "machine": machine_info(),
            "chain": f"mesh-like lattice chain, {DISTURBANCES} successors per state (see docstring)",
            "peer": "scipy.sparse.linalg.spsolve on (I - Q) t = 1",
            "entries": [bench_chain(s, repeats=3 if s < 100 else 1, spsolve_max=spsolve_max) for s in sides]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="one 1,728-state chain only (for tests)")
    parser.add_argument("--out", type=Path, help="also write the JSON to this file")
    parser.add_argument("--spsolve-max", type=int, default=20_000, help="largest chain given to spsolve")
    args = parser.parse_args(argv)
    emit(run(args.quick, args.spsolve_max), args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
