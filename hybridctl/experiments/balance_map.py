"""Balance maps (thesis Fig. 3.6): does the controller balance from each rest state of a grid?

Each grid start is simulated in Drake by a named controller (:mod:`.controllers`) in local worker
processes, each building its own diagram.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .. import io
from ..parallel import require_main_guard
from ..drake import simulate
from ..systems import System, load
from ..viz import plot_balance_map
from .controllers import build_named_diagram


@dataclass
class BalanceMap:
    """Result of :func:`balance_map`: ``balanced[i, j]`` for the start (values1[i], values2[j])."""

    system: str
    controller: str
    axes: tuple[str, str]
    values1: np.ndarray
    values2: np.ndarray
    balanced: np.ndarray
    returns: np.ndarray
    diverged: np.ndarray
    duration: float
    wall_time: float
    meta: dict = field(default_factory=dict)

    @property
    def fraction(self) -> float:
        """Fraction of grid starts that satisfy the thesis success test (eq. 3.2)."""
        return float(self.balanced.mean())

    def summary(self) -> dict:
        """JSON-ready summary with the grid, the map and its balanced fraction."""
        return {
            "system": self.system, "controller": self.controller, "axes": list(self.axes),
            "grid": [len(self.values1), len(self.values2)],
            "balanced_fraction": self.fraction, "balanced_count": int(self.balanced.sum()),
            "mean_return": float(self.returns.mean()), "diverged_count": int(self.diverged.sum()),
            "duration_s": self.duration, "wall_time_s": self.wall_time,
            "values1": self.values1.tolist(), "values2": self.values2.tolist(),
            "balanced": self.balanced.astype(int).tolist(), **self.meta,
        }

    def save(self, out_dir: str | Path) -> dict:
        """Write ``balance_map.json`` and ``balance_map.png`` into ``out_dir``."""
        import matplotlib.pyplot as plt

        out = io.output_folder(out_dir)
        summary = self.summary()
        io.atomic_write_text(out / "balance_map.json", json.dumps(summary, indent=1))
        fig = plot_balance_map(self.values1, self.values2, self.balanced, diverged=self.diverged,
                               path=out / "balance_map.png",
                               title=f"{self.system}, {self.controller}, {self.duration:g} s")
        plt.close(fig)
        return summary


def grid_axes(system: System, axes: tuple[int, int] | None = None,
              ranges: tuple[tuple[float, float], tuple[float, float]] | None = None):
    """The two state coordinates a balance map varies and their ranges.

    Default: the first two coordinates that the spec's initial-state distribution
    varies (acrobot: th1 in [-3pi/2, pi/2], th2 in [-pi, pi], thesis Fig. 3.6);
    for a system varying fewer, its first angle over +-pi and that angle's velocity
    over +-2pi.
    """
    nominal, low, high = system.initial_state.nominal, system.initial_state.low, system.initial_state.high
    if axes is None:
        varying = [i for i in range(system.n_states) if high[i] > low[i]]
        if len(varying) >= 2:
            axes = (varying[0], varying[1])
        else:
            angle = system.angle_indices[0]
            axes = (angle, angle + system.n_states // 2)
            if ranges is None:
                ranges = ((nominal[angle] - np.pi, nominal[angle] + np.pi), (-2 * np.pi, 2 * np.pi))
    for a in axes:
        if not 0 <= a < system.n_states:
            raise ValueError(f"axes must index states 0..{system.n_states - 1}, got {axes}")
    if ranges is None:
        ranges = tuple((nominal[a] + low[a], nominal[a] + high[a]) for a in axes)
    return tuple(axes), tuple(tuple(map(float, r)) for r in ranges)


def _simulate_chunk(args) -> list[tuple[int, bool, float, bool]]:
    """Worker: build the system and diagram here (Drake objects do not pickle), run starts."""
    import torch

    torch.set_num_threads(1)
    spec_name, overrides, controller, duration, starts = args
    system = load(spec_name, **overrides)
    diagram = build_named_diagram(system, controller)
    results = []
    for index, x0 in starts:
        traj = simulate(diagram, x0, duration)
        results.append((index, traj.balanced, traj.episode_return, traj.diverged))
    return results


def balance_map(system: System | str, controller: str = "energy", grid: int = 41, duration: float | None = None,
                axes: tuple[int, int] | None = None, ranges=None, workers: int | None = None,
                progress: bool = True, overrides: dict | None = None) -> BalanceMap:
    """Simulate ``controller`` from every start of a ``grid`` x ``grid`` rest-state grid.

    Each start is the spec's nominal state with the two ``axes`` coordinates set
    from the grid (velocities at rest); success is the thesis test (eq. 3.2) on
    the decision-rate states of a ``duration``-second run (default: the spec's
    episode). Runs in ``workers`` local processes (default: all cores, at most the
    number of starts), each building its own Drake diagram.
    """
    if isinstance(system, str):
        system = load(system, **dict(overrides or {}))
    elif overrides:
        raise ValueError("pass overrides only with a system name; a loaded System already carries its own")
    overrides = dict(system.spec.overrides)
    if grid < 2:
        raise ValueError(f"grid must be >= 2, got {grid}")
    duration = system.episode_duration if duration is None else float(duration)
    if duration <= 0:
        raise ValueError(f"duration must be > 0, got {duration}")
    (a1, a2), (r1, r2) = grid_axes(system, axes, ranges)
    build_named_diagram(system, controller, log=False)  # bad names/checkpoints fail here, not in a worker
    values1, values2 = np.linspace(*r1, grid), np.linspace(*r2, grid)
    starts = []
    for i, v1 in enumerate(values1):
        for j, v2 in enumerate(values2):
            x0 = system.initial_state.nominal.copy()
            x0[a1], x0[a2] = v1, v2
            starts.append((i * grid + j, x0))
    workers = max(1, min(os.cpu_count() or 1, len(starts)) if workers is None else int(workers))
    chunk = max(1, min(25, len(starts) // (4 * workers) or 1))
    jobs = [(str(system.spec.path), overrides, controller, duration, starts[k:k + chunk])
            for k in range(0, len(starts), chunk)]
    balanced = np.zeros(grid * grid, dtype=bool)
    returns = np.zeros(grid * grid)
    diverged = np.zeros(grid * grid, dtype=bool)
    start_time = time.perf_counter()
    bar = tqdm(total=len(starts), desc=f"balance map {system.name}", disable=not progress, unit="run")
    if workers == 1:
        results_iter = map(_simulate_chunk, jobs)
        pool = None
    else:
        # spawn: a forked child would inherit torch/OpenMP thread state from the parent.
        require_main_guard()
        pool = mp.get_context("spawn").Pool(workers)
        results_iter = pool.imap_unordered(_simulate_chunk, jobs)
    try:
        for results in results_iter:
            for index, ok, ret, div in results:
                balanced[index], returns[index], diverged[index] = ok, ret, div
            bar.update(len(results))
    finally:
        bar.close()
        if pool is not None:
            pool.terminate()
    names = (system.state_names[a1], system.state_names[a2])
    return BalanceMap(system.name, controller, names, values1, values2, balanced.reshape(grid, grid),
                      returns.reshape(grid, grid), diverged.reshape(grid, grid), duration,
                      time.perf_counter() - start_time, meta={"workers": workers})
