"""Balance maps (thesis Fig. 3.6): does the controller balance from each rest state of a grid?

Two engines simulate the same named controller (:mod:`.controllers`) from every grid start:

- ``"drake"``: the Drake diagram, one run per start on a parallel backend (serial, local
  processes or Ray); each worker builds its diagram once and resets one Simulator for every start.
- ``"torch"``: the starts as batches of the switched controller in torch on one ``device``
  (:func:`torch_rollouts`: the policy, the gate with hysteresis, the LQR and the saturation of
  :class:`hybridctl.envs.SwitchedVectorEnv`, the dynamics of ``System.step_unchecked``): every start
  as one batch in this process (serial), or the grid split into one chunk per worker of a parallel
  backend, each chunk one batch; the map is the same cell for cell.

Both judge a start by the same test: :func:`hybridctl.systems.success.is_balanced` on the
states at the swing-up decision times (thesis eq. 3.2), False for a diverged run.
:func:`compare_engines` runs both on one grid and lists the cells where they disagree.
"""

from __future__ import annotations

import json
import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

import torch

from .. import io
from ..drake import resolve_swingup, simulate
from ..drake.simulate import check_duration
from ..envs import SwitchedVectorEnv
from ..learn.config_check import check_device as check_torch_device, check_device_available
from ..limits import MAX_GRID, MAX_TOTAL_STEPS, check_at_most, check_fits_memory, cpu_count
from ..parallel import BACKENDS, make_backend
from ..systems import System, load
from ..systems.switched import SwitchedController, TrajoptSwingup, closed_loop_rollout
from ..systems.success import decision_indices, episode_return, is_balanced
from .. import viz   # its names load on first use: pyplot when a map is drawn, not with this module
from .controllers import build_named_diagram, controller_parts, display_name

ENGINES = ("drake", "torch")


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
    units: tuple[str, str] = ("rad", "rad")     # of the two axes (System.state_unit)

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
        """Write ``balance_map.json`` and ``balance_map.png`` into ``out_dir``, held locked and checked as
        :func:`output_folder` does (a caller that holds it already, as ``hybridctl balance-map``, nests)."""
        import matplotlib.pyplot as plt

        with output_folder(out_dir) as out:
            summary = self.summary()
            io.atomic_write_text(out / "balance_map.json", json.dumps(summary, indent=1))
            fig = viz.plot_balance_map(self.values1, self.values2, self.balanced, diverged=self.diverged,
                                   path=out / "balance_map.png",
                                   title=f"{self.system}, {display_name(self.controller)}, {self.duration:g} s",
                                   axis_labels=tuple(f"initial {name} [{unit}]"
                                                     for name, unit in zip(self.axes, self.units)))
            plt.close(fig)
        return summary


OUTPUTS = ("balance_map.json", "balance_map.png")
"""What :meth:`BalanceMapResult.save` writes; ``balance_map.json`` makes a folder a balance map's own."""


def output_folder(out: str | Path):
    """The ``with`` context of a balance map's folder ``out`` (:func:`hybridctl.io.command_folder`): locked
    while held (a second run into it is refused), refused when it holds an input (a spec, a model, a
    checkpoint) or a ``balance_map.json`` / ``.png`` that a balance map did not write."""
    return io.command_folder(out, "balance-map", OUTPUTS, own=OUTPUTS[:1])


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


def near_hanging_down(system: System, half_width: float):
    """``(axes, ranges)`` of a map of starts near hanging down: the default map's two coordinates
    (:func:`grid_axes`), each within ``+-half_width`` of the spec's nominal (hanging-down) state.

    The learner x system matrix compares every learner on such a map (half-width 0.3, the cart-poles'
    own start spread), since a map over every angle asks the acrobot for more than a swing-up.
    """
    if not (isinstance(half_width, (int, float, np.floating)) and 0 < half_width <= np.pi):
        raise ValueError(f"--near must be in (0, pi] (a half-width in the axes' units), got {half_width!r}")
    axes, _ = grid_axes(system)
    nominal = system.initial_state.nominal
    return axes, tuple((float(nominal[a] - half_width), float(nominal[a] + half_width)) for a in axes)


_WORKER_DIAGRAMS: dict = {}


def _worker_diagram(spec_name: str, overrides: dict, controller: str, force: bool = False):
    """The diagram of (system, controller), built once per process and reused for every start (``force``: a
    checkpoint trained on other spec values loads anyway, as in the parent, which warned)."""
    key = (spec_name, tuple(sorted(overrides.items())), controller, force)
    if key not in _WORKER_DIAGRAMS:
        _WORKER_DIAGRAMS.clear()     # one diagram per worker: a new map replaces the last one
        with warnings.catch_warnings():
            if force:
                warnings.simplefilter("ignore")
            _WORKER_DIAGRAMS[key] = build_named_diagram(load(spec_name, **overrides), controller, force)
    return _WORKER_DIAGRAMS[key]


def _simulate_chunk(args) -> tuple[list[tuple[int, bool, float, bool]], float]:
    """Worker: simulate starts with this process' diagram (Drake objects do not pickle); returns the
    results and the CPU seconds this process spent on them."""
    cpu = time.process_time()
    torch.set_num_threads(1)
    spec_name, overrides, controller, duration, force, starts = args
    diagram = _worker_diagram(spec_name, overrides, controller, force)
    results = []
    for index, x0 in starts:
        traj = simulate(diagram, x0, duration, force=force)
        results.append((index, traj.balanced, traj.episode_return, traj.diverged))
    return results, time.process_time() - cpu


TORCH_BYTES_PER_VALUE = 3 * 8
"""Bytes per float64 of a state the torch engine records: the list of decision states, their stacked
copy and the decision-rate states cut from it."""


def check_device(engine: str, device: str | torch.device | None) -> torch.device | None:
    """The torch engine's device as a ``torch.device`` (None: no device was asked for).

    Refuses (ValueError, one line naming ``--device``): a device with the drake engine (Drake
    simulates on the CPU), a name torch does not know, and a CUDA device this machine lacks
    (:func:`hybridctl.learn.config_check.check_device_available`).
    """
    if device is None:
        return None
    if engine != "torch":
        raise ValueError(f"--device {device} applies to --engine torch only (the {engine} engine simulates on the CPU)")
    return check_torch_device("--device", device)


def check_balance_map(system: System, grid: int, duration: float | None, engine: str = "drake",
                      workers: int | None = None, force: bool = False,
                      device: str | torch.device | None = None) -> tuple[float, int | None]:
    """Check a balance map's size before any work; returns (duration, workers) as they will be used.

    Refuses (one line naming the flag and its limit): a grid outside [2, MAX_GRID], a duration as
    :func:`hybridctl.drake.simulate.check_duration` does, more than MAX_TOTAL_STEPS time steps of
    all runs together, local ``workers`` above the cores this process may use (``force`` lifts
    these; both engines), batched arrays of the torch engine beyond the memory budget (nothing
    lifts that; checked for the whole grid, as local workers hold their chunks at once), and a
    ``device`` as :func:`check_device` does.
    """
    check_device(engine, device)
    if not (isinstance(grid, (int, np.integer)) and grid >= 2):
        raise ValueError(f"--grid must be >= 2 (an integer), got {grid!r}")
    check_at_most("--grid", int(grid), MAX_GRID, force, why="points per axis")
    duration = check_duration(system, duration, force)
    runs, steps = int(grid) ** 2, duration / system.dt
    check_at_most(f"--grid {grid} x {grid} runs of --duration {duration:g} s", round(runs * steps),
                  MAX_TOTAL_STEPS, force, why=f"time steps of all runs together, dt = {system.dt:g} s")
    check_fits_memory("--grid", runs * system.n_states * 8.0, "the grid of starts")
    if engine == "torch":
        # states at every decision of the fastest swing-up period (control.period); see torch_rollouts
        decisions = duration / min(system.control_period, system.swingup_period) + 1
        check_fits_memory("--grid and --duration", runs * decisions * system.n_states * TORCH_BYTES_PER_VALUE,
                          "the torch engine's batched states")
    if workers is not None:
        check_at_most("--workers", int(workers), cpu_count(), force, why="cores this process may use")
    return duration, workers


def _grid_starts(system: System, grid: int, axes, ranges):
    """(axis indices, values1, values2, starts (grid * grid, n)) of a rest-state grid, row-major."""
    if grid < 2:
        raise ValueError(f"grid must be >= 2, got {grid}")
    (a1, a2), (r1, r2) = grid_axes(system, axes, ranges)
    values1, values2 = np.linspace(*r1, grid), np.linspace(*r2, grid)
    starts = np.repeat(system.initial_state.nominal[None], grid * grid, axis=0)
    starts[:, a1] = np.repeat(values1, grid)
    starts[:, a2] = np.tile(values2, grid)
    return (a1, a2), values1, values2, starts


def _torch_controller(system: System, controller: str, force: bool = False) -> SwitchedController:
    """The :class:`~hybridctl.systems.SwitchedController` of a named controller, built on the CPU, with its
    energy swing-up's law resolved for torch.

    Checkpoints load and the spec's gate builds inside ``torch.device("cpu")`` whatever the
    default device, as :func:`hybridctl.learn.run.seeded` builds networks: the rollout moves them
    to its device. ``force``: a checkpoint trained on other spec values loads anyway (warned)."""
    with torch.device("cpu"):
        parts = resolve_swingup(system, controller_parts(system, controller, force))
    if isinstance(parts.swingup, TrajoptSwingup):
        raise ValueError(f"the torch engine cannot run controller {controller!r}: the trajopt swing-up reads the "
                         f"time, so it runs in Drake only (use --engine drake)")
    return parts


def torch_rollouts(system: System, controller: str, starts, duration: float | None = None,
                   device: str | torch.device = "cpu", force: bool = False) -> dict:
    """Simulate a named controller from every row of ``starts`` (N, n) at once, in batched torch on ``device``.

    The controller's :class:`~hybridctl.systems.SwitchedController` (the one the Drake diagram is built
    from) runs through :func:`hybridctl.systems.closed_loop_rollout`: the swing-up acts every its
    ``decision_period`` (a learned policy ``swingup_period``, a hand-designed law ``control.period``, as
    the Drake blocks), held in between; inside, the gate with hysteresis, the LQR and the saturation
    every ``control.period`` and ``System.step_unchecked`` every ``dt``, in float64, as the Drake diagram
    does (the decision of :class:`hybridctl.envs.SwitchedVectorEnv`). ``duration`` (default: the spec's
    episode) must be a whole number of swing-up periods. ``force``: a ``KIND:PATH`` checkpoint trained on
    other spec values loads anyway (with ``load_controller``'s warning).

    Everything stepped lives on ``device``: the states, the policy (a loaded one is moved there),
    the gate, the LQR gain and the per-run records. The loop copies nothing to the host: the
    states come back once, after the last decision. A run that diverges keeps its last finite
    state from then on (the env would restart it from a random state; either is meaningless).

    Returns a dict: ``states`` (N, D + 1, n) at the swing-up's decision times ``times`` (D + 1,)
    from t = 0, ``diverged`` (N,) bool (a diverged row's states after its divergence are
    meaningless), ``decision_states`` (N, K, n) at the spec's ``swingup_period`` (thesis'
    decision rate, what the success test reads), ``balanced`` (N,) and ``returns`` (N,) (over
    the decision states before a divergence), ``wall_time`` (s).
    """
    start_time = time.perf_counter()
    device = torch.device(device)
    duration = system.episode_duration if duration is None else float(duration)
    starts = np.atleast_2d(np.asarray(starts, dtype=float))
    n_runs = len(starts)
    parts = _torch_controller(system, controller, force)
    period = parts.decision_period
    overrides = {**system.spec.overrides, "episode__duration": duration}
    run_system = load(str(system.spec.path), **overrides)
    # the env checks the schedule, the batch's memory and the starts; the rollout runs here directly, since
    # env.step copies flags to the host every decision (autoreset)
    env = SwitchedVectorEnv(run_system, n_runs, controller=parts, decision_period=period, device=device,
                            dtype=torch.float64)
    x, _ = env.reset(options={"state": starts})
    limit = run_system.action_limit
    run = closed_loop_rollout(run_system, parts, x, env.max_decisions, on_divergence="freeze", device=device)
    finite_actions, ended_at = run.actions_finite, run.diverged_at
    if not bool(finite_actions):
        raise ValueError(f"the swing-up of {controller!r} gave a NaN or Inf action (clipped to [-{limit}, {limit}])")
    states = run.states.cpu().numpy()
    ended_at = ended_at.cpu().numpy()
    diverged = ended_at <= env.max_decisions
    stride = system.swingup_period / period
    if abs(stride - round(stride)) > 1e-9:
        raise ValueError(f"the swing-up period {period} s does not divide the spec's swingup_period "
                         f"{system.swingup_period} s, at which the success test reads the states")
    decisions = decision_indices(states.shape[1], period, system.swingup_period)
    decision_states = states[:, decisions]
    balanced = is_balanced(decision_states, system) & ~diverged
    # a diverged run's return counts the decision states before the decision it diverged in
    kept = np.searchsorted(decisions, ended_at, side="left")
    returns = np.array([episode_return(decision_states[i, :kept[i]], system) for i in range(n_runs)])
    return {"states": states, "times": np.arange(states.shape[1]) * period, "diverged": diverged,
            "decision_states": decision_states, "balanced": balanced, "returns": returns,
            "wall_time": time.perf_counter() - start_time}


def _torch_chunk(args) -> tuple[int, dict, float]:
    """Worker: the batched torch rollouts of one chunk of grid starts; returns (index of its first
    start, its ``balanced``/``returns``/``diverged``, the CPU seconds this process spent on it)."""
    cpu = time.process_time()
    spec_path, overrides, controller, duration, device, threads, first, starts, force = args
    if threads is not None:      # a worker process: one thread each, so that the workers share the cores
        torch.set_num_threads(threads)
    check_device_available("--device", torch.device(device))    # a Ray worker's own GPUs
    with warnings.catch_warnings():
        if force and threads is not None:     # a worker process: the parent said it
            warnings.simplefilter("ignore")
        result = torch_rollouts(load(spec_path, **overrides), controller, starts, duration, device, force)
    return first, {key: result[key] for key in ("balanced", "returns", "diverged")}, time.process_time() - cpu


def _torch_map(system: System, controller: str, grid_states: np.ndarray, duration: float, device: torch.device,
               backend: str, workers: int | None, address: str | None, progress: bool, force: bool = False):
    """(balanced, returns, diverged (grid * grid,), meta) of the torch engine: one batched chunk of
    the starts per worker of ``backend`` (serial: one batch, in this process)."""
    n = len(grid_states)
    pool = make_backend("ray", workers, address) if backend == "ray" else None   # its size: the cluster's
    if pool is not None:
        workers = pool.workers
    else:
        workers = 1 if backend == "serial" else max(1, min(cpu_count() if workers is None else int(workers), n))
        # one process needs no pool (spawned workers each import torch and Drake: seconds)
        pool = make_backend("serial" if workers == 1 else "processes", workers if workers > 1 else None, address)
    if pool.name != "serial":
        _torch_controller(system, controller, force)   # a bad name or checkpoint fails here, not in a worker
    # one chunk per worker: every chunk costs the same (all runs take every decision), so more
    # chunks would only add per-task costs
    threads = None if pool.name == "serial" else 1
    jobs = [(str(system.spec.path), dict(system.spec.overrides), controller, duration, str(device), threads,
             int(rows[0]), grid_states[rows], force) for rows in np.array_split(np.arange(n), min(workers, n))]
    balanced, returns, diverged = np.zeros(n, dtype=bool), np.zeros(n), np.zeros(n, dtype=bool)
    bar = tqdm(total=n, desc=f"balance map {system.name} (torch)", disable=not progress, unit="run")
    cpu = 0.0
    with pool:
        try:
            for first, result, seconds in pool.imap_unordered(_torch_chunk, jobs):
                cpu += seconds
                rows = slice(first, first + len(result["balanced"]))
                balanced[rows], returns[rows], diverged[rows] = result["balanced"], result["returns"], result["diverged"]
                bar.update(len(result["balanced"]))
        finally:
            bar.close()
        workers = pool.workers
    meta = {"engine": "torch", "backend": backend, "workers": workers, "chunks": len(jobs), "device": str(device),
            "cpu_s": cpu, "load_average": list(os.getloadavg())}
    return balanced, returns, diverged, meta


def balance_map(system: System | str, controller: str = "energy", grid: int = 41, duration: float | None = None,
                axes: tuple[int, int] | None = None, ranges=None, workers: int | None = None,
                progress: bool = True, overrides: dict | None = None, engine: str = "drake",
                force: bool = False, backend: str | None = None, address: str | None = None,
                device: str | torch.device | None = None) -> BalanceMap:
    """Simulate ``controller`` from every start of a ``grid`` x ``grid`` rest-state grid.

    Each start is the spec's nominal state with the two ``axes`` coordinates set
    from the grid (velocities at rest); success is the thesis test (eq. 3.2) on
    the decision-rate states of a ``duration``-second run (default: the spec's
    episode). Both engines run on a parallel ``backend``
    (:func:`hybridctl.parallel.make_backend`: ``"processes"``, ``workers`` local processes,
    default all cores and at most the number of starts; ``"serial"``, this process; ``"ray"``, a
    new local instance or the cluster at ``address`` / ``RAY_ADDRESS``, where every worker needs the
    system's spec and the controller's checkpoint at the same paths). ``engine``: ``"drake"`` runs
    the Drake diagram (default backend ``"processes"``), each worker building its diagram once and
    taking chunks of starts; ``"torch"`` runs batched torch rollouts (:func:`torch_rollouts`) on
    ``device`` (default ``"cpu"``; the drake engine refuses one), by default every start as one batch
    in this process (``"serial"``), else one chunk of the grid per worker, each chunk one batch: the
    same map cell for cell. The map's ``meta`` records the engine, the backend, the workers, the
    workers' CPU seconds (``cpu_s``) and the load average at the end: on a shared machine the wall
    time alone says little.

    The size is checked before any work (:func:`check_balance_map`: grid, duration, all steps
    together, workers, memory, device); ``force`` lifts the stated caps, not the memory limit, and loads a
    ``KIND:PATH`` checkpoint trained on other spec values anyway (warned, as ``simulate --force``). Never
    more worker processes start than there are tasks.
    """
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    if backend is None:
        backend = "serial" if engine == "torch" else "processes"
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if isinstance(system, str):
        system = load(system, **dict(overrides or {}))
    elif overrides:
        raise ValueError("pass overrides only with a system name; a loaded System already carries its own")
    overrides = dict(system.spec.overrides)
    duration, workers = check_balance_map(system, grid, duration, engine, workers if backend != "ray" else None,
                                          force, device)
    (a1, a2), values1, values2, grid_states = _grid_starts(system, grid, axes, ranges)
    names = (system.state_names[a1], system.state_names[a2])
    units = (system.state_unit(a1), system.state_unit(a2))
    start_time = time.perf_counter()
    if engine == "torch":
        balanced, returns, diverged, meta = _torch_map(system, controller, grid_states, duration,
                                                       torch.device("cpu" if device is None else device), backend,
                                                       workers, address, progress, force)
        return BalanceMap(system.name, controller, names, values1, values2, balanced.reshape(grid, grid),
                          returns.reshape(grid, grid), diverged.reshape(grid, grid), duration,
                          time.perf_counter() - start_time, meta=meta, units=units)
    build_named_diagram(system, controller, force, log=False)  # bad names/checkpoints fail here, not in a worker
    starts = list(enumerate(grid_states))
    pool = make_backend("ray", workers, address) if backend == "ray" else None   # its size: the cluster's
    if pool is not None:
        workers = pool.workers
    else:
        workers = 1 if backend == "serial" else max(1, min(cpu_count() if workers is None else int(workers),
                                                           len(starts)))
    # chunks: about 4 per worker (at most 25 starts each), so that every worker stays busy to the end
    chunk = max(1, min(25, len(starts) // (4 * workers) or 1))
    jobs = [(str(system.spec.path), overrides, controller, duration, force, starts[k:k + chunk])
            for k in range(0, len(starts), chunk)]
    if pool is None:
        workers = min(workers, len(jobs))  # a worker without a task would only cost its start-up
        # one process needs no pool (spawned workers each import torch and Drake: seconds)
        pool = make_backend("serial" if workers == 1 else "processes", workers if workers > 1 else None, address)
    balanced = np.zeros(grid * grid, dtype=bool)
    returns = np.zeros(grid * grid)
    diverged = np.zeros(grid * grid, dtype=bool)
    bar = tqdm(total=len(starts), desc=f"balance map {system.name}", disable=not progress, unit="run")
    cpu = 0.0
    with pool:
        try:
            for results, seconds in pool.imap_unordered(_simulate_chunk, jobs):
                cpu += seconds
                for index, ok, ret, div in results:
                    balanced[index], returns[index], diverged[index] = ok, ret, div
                bar.update(len(results))
        finally:
            bar.close()
        workers = pool.workers
    return BalanceMap(system.name, controller, names, values1, values2, balanced.reshape(grid, grid),
                      returns.reshape(grid, grid), diverged.reshape(grid, grid), duration,
                      time.perf_counter() - start_time,
                      meta={"engine": "drake", "backend": backend, "workers": workers, "cpu_s": cpu, "load_average": list(os.getloadavg())}, units=units)


def divergence_time(times, a, b, tol: float = 1e-3) -> float | None:
    """First of the sample ``times`` (T,) at which two trajectories (T, n) differ by more than ``tol``
    in some coordinate (or one is not finite), or None if they never do."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    n = min(len(a), len(b), len(times))
    with np.errstate(invalid="ignore"):
        apart = ~(np.abs(a[:n] - b[:n]) <= tol).all(axis=-1)
    hits = np.flatnonzero(apart)
    return float(times[hits[0]]) if len(hits) else None


def compare_engines(system: System | str, controller: str = "energy", grid: int = 11, duration: float | None = None,
                    axes=None, ranges=None, tol: float = 1e-3, drake_map: BalanceMap | None = None,
                    progress: bool = False) -> dict:
    """Balance maps of one controller by both engines on one grid, and where they disagree.

    Returns a dict: ``drake`` and ``torch`` (the two :class:`BalanceMap`), ``agreement`` (share of
    cells with the same verdict), ``disagreements``: for each cell whose verdicts differ, its grid
    index, start, both verdicts and ``divergence_time``: the first swing-up decision time at which
    the Drake and torch trajectories differ by more than ``tol`` in any coordinate (None if they
    never do). ``drake_map``: a Drake map of this grid computed before (it is not recomputed).
    """
    if isinstance(system, str):
        system = load(system)
    duration = system.episode_duration if duration is None else float(duration)
    (a1, a2), values1, values2, starts = _grid_starts(system, grid, axes, ranges)
    torch_map = balance_map(system, controller, grid, duration, axes, ranges, engine="torch")
    if drake_map is None:
        drake_map = balance_map(system, controller, grid, duration, axes, ranges, workers=1, progress=progress)
    same = drake_map.balanced == torch_map.balanced
    rows = []
    if not same.all():
        cells = np.argwhere(~same)
        flat = [i * grid + j for i, j in cells]
        runs = torch_rollouts(system, controller, starts[flat], duration)
        diagram = build_named_diagram(system, controller)
        for k, ((i, j), index) in enumerate(zip(cells, flat)):
            traj = simulate(diagram, starts[index], duration)
            times = runs["times"]
            stride = int(round((times[1] - times[0]) / system.dt)) if len(times) > 1 else 1
            drake_states = traj.x[::stride]
            rows.append({"cell": [int(i), int(j)], "x0": starts[index].tolist(),
                         "drake_balanced": bool(drake_map.balanced[i, j]),
                         "torch_balanced": bool(torch_map.balanced[i, j]),
                         "divergence_time": divergence_time(times, drake_states, runs["states"][k], tol)})
    return {"drake": drake_map, "torch": torch_map, "agreement": float(same.mean()), "cells": int(same.size),
            "tolerance": tol, "disagreements": rows}
