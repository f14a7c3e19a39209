"""Measure the ``trajopt`` controller on every benchmark chain; writes results/trajopt/.

Run from the repository root: ``.venv/bin/python results/trajopt/measure.py [SYSTEM ...]``
(default: pendulum acrobot cartpole double_cartpole). For each system:

- the collocation swing-up and its TVLQR solved without the cache (cold: solve time, trajectory
  duration, attempts), then from the cache (``runs/trajopt/``, filled first if empty): the read's time;
- a Drake simulation (the spec's episode) from exactly hanging down and from the command line's
  default start (hanging down with the first angle nudged by 1e-3 rad): balanced? when did the gate
  hand over?
- the 11 x 11 Drake balance map of ``trajopt`` over the spec's default ranges (those of the learned
  controllers' maps), and of ``energy`` where the spec has an energy swing-up, on the same grid;
- for the pendulum and the acrobot, whose default map spans every angle, an 11 x 11 map of starts
  near hanging down too (the two map axes within +-0.3 of hanging down).

Maps run on the serial backend (the machine has 2 cores shared with other work). The record:
``results/trajopt/trajopt.json`` (merged per system, so systems can be measured in separate runs) and
``results/trajopt/maps/SYSTEM-CONTROLLER[-near]/balance_map.{json,png}``.
"""

from __future__ import annotations

import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch

from hybridctl import io, systems
from hybridctl.drake import build_hybrid_diagram, simulate, swingup_trajectory, tracking_gains
from hybridctl.experiments.balance_map import balance_map
from hybridctl.reproduce.common import machine_info

OUT = Path("results") / "trajopt"
SYSTEMS = ("pendulum", "acrobot", "cartpole", "double_cartpole")
GRID = 11
NEAR = 0.3   # half-width of the near-hanging-down map's ranges (rad, rad/s), the spec spreads of the cart-poles


def measure(name: str) -> dict:
    """The record of one system (see the module docstring)."""
    system = systems.load(name)
    record: dict = {"system": name}

    start = time.perf_counter()
    cold = swingup_trajectory(system, cache=False)
    gains = tracking_gains(system, cold, cache=False)
    record["cold"] = {"wall_s": time.perf_counter() - start, "trajectory_solve_s": cold.solve_time,
                      "tvlqr_s": gains.solve_time, "duration_s": cold.duration, "knots": len(cold.times),
                      "max_abs_input": float(np.abs(cold.inputs).max()), "action_limit": system.action_limit,
                      "attempts": cold.attempts, "solver": cold.solver}
    tracking_gains(system, swingup_trajectory(system))    # fills runs/trajopt/ if it is empty
    start = time.perf_counter()
    cached = swingup_trajectory(system)
    cached_gains = tracking_gains(system, cached)
    record["cached"] = {"wall_s": time.perf_counter() - start, "read_from_cache": cached.cached and cached_gains.cached,
                        "same_as_cold": bool(np.allclose(cached.states, cold.states, atol=1e-6)
                                             and np.allclose(cached_gains.K, gains.K, rtol=1e-6, atol=1e-6))}

    diagram = build_hybrid_diagram(system, swingup="trajopt")
    runs = {}
    for label, x0 in (("hanging_down", system.initial_state.nominal), ("nudged", system.nudged_nominal_state())):
        summary = simulate(diagram, x0).summary()
        runs[label] = {k: summary[k] for k in ("balanced", "return", "diverged", "first_balance_time",
                                               "fraction_in_balance_mode", "max_abs_input", "x0", "final_state",
                                               "wall_time_s")}
    record["simulate"] = runs

    maps = {}
    controllers = ["trajopt"] + (["energy"] if system.swingup.controller is not None else [])
    for controller in controllers:
        maps[controller] = _map(system, controller, None, f"{name}-{controller}")
    if name in ("pendulum", "acrobot"):
        nominal = system.initial_state.nominal
        axes = (0, 1)
        ranges = tuple((nominal[a] - NEAR, nominal[a] + NEAR) for a in axes)
        for controller in controllers:
            maps[f"{controller} (near hanging down)"] = _map(system, controller, (axes, ranges),
                                                             f"{name}-{controller}-near")
    record["maps"] = maps
    return record


def _map(system, controller: str, axes_ranges, folder: str) -> dict:
    axes, ranges = axes_ranges if axes_ranges is not None else (None, None)
    start = time.perf_counter()
    result = balance_map(system, controller, grid=GRID, axes=axes, ranges=ranges, backend="serial", progress=False)
    wall = time.perf_counter() - start
    summary = result.save(OUT / "maps" / folder)
    print(f"{system.name} {controller} {folder}: {summary['balanced_count']}/{GRID * GRID} in {wall:.0f} s", flush=True)
    return {"balanced_fraction": summary["balanced_fraction"], "balanced_count": summary["balanced_count"],
            "grid": GRID, "axes": summary["axes"], "ranges": [list(map(float, (v[0], v[-1])))
                                                               for v in (summary["values1"], summary["values2"])],
            "wall_s": wall, "record": f"results/trajopt/maps/{folder}/balance_map.json"}


def main(argv: list[str] | None = None) -> None:
    """Measure the systems named in ``argv`` (default all four) and merge them into trajopt.json."""
    torch.set_num_threads(1)
    names = list(argv if argv is not None else sys.argv[1:]) or list(SYSTEMS)
    path = OUT / "trajopt.json"
    record = json.loads(path.read_text()) if path.exists() else {"systems": {}}
    for name in names:
        start = time.perf_counter()
        entry = measure(name)
        entry["wall_s"] = time.perf_counter() - start
        entry["command"] = shlex.join([".venv/bin/python", "results/trajopt/measure.py", *names])
        entry["machine"] = machine_info()
        record["systems"][name] = entry
        record["note"] = ("trajopt = direct-collocation swing-up (hybridctl.drake.trajopt, default TrajoptSettings) "
                          "tracked by Drake's FiniteHorizonLinearQuadraticRegulator + the spec's cost-to-go gate "
                          "(hysteresis) + Drake's LQR; maps: Drake engine, thesis success test, the spec's episode")
        io.write_json(path, record)
    print(json.dumps({n: {"balanced_from_hanging_down": e["simulate"]["hanging_down"]["balanced"],
                          "solve_s": round(e["cold"]["trajectory_solve_s"], 2), "duration_s": e["cold"]["duration_s"],
                          "maps": {k: v["balanced_count"] for k, v in e["maps"].items()}}
                      for n, e in record["systems"].items()}, indent=1))


if __name__ == "__main__":
    main()
