"""The demo (``make demo``, ``hybridctl demo``): the pretrained SSAC acrobot in Drake, one run from
hanging down with a browser replay, and a balance map of rest states.

>>> from hybridctl.experiments import run_demo
>>> result = run_demo("runs/demo", grid=11)
>>> result["simulation"]["balanced"], result["balance_map"]["balanced_fraction"]
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

from ..systems import load
from ..systems.spec import MODELS_DIR
from .balance_map import balance_map
from .simulation import simulate_and_write

PRETRAINED_ACROBOT = MODELS_DIR / "policies" / "ssac-acrobot"
"""The SSAC acrobot checkpoint shipped with hybridctl (how it was trained: README.md there)."""

DEMO_SYSTEM = "acrobot"
DEMO_GRID = 11
"""Balance-map grid points per axis in the demo (the thesis' figure uses 41)."""


def _silent(line: str) -> None:
    """A ``report`` that prints nothing."""


def run_demo(out: str | Path = "runs/demo", grid: int = DEMO_GRID, checkpoint: str | Path = PRETRAINED_ACROBOT,
             meshcat=None, progress: bool = True, command: str | None = None,
             report: Callable[[str], None] | None = print) -> dict:
    """The pretrained SSAC acrobot: simulate one episode from hanging down, then a balance map.

    Writes ``out/acrobot`` (as :func:`simulate_and_write`: trajectory, summary, plot, replay) and
    ``out/balance_map`` (``balance_map.json``, ``balance_map.png``). The start is the spec's nominal
    state nudged by 1e-3 rad and the run lasts the spec's episode duration (acrobot: 10 s).

    Args:
        grid: balance-map grid points per axis.
        checkpoint: the SSAC checkpoint directory (default: the shipped one).
        meshcat: a running Meshcat to show the run live.
        progress: show the balance map's progress bar.
        command: the command line, recorded in the outputs.
        report: called with each line of the demo's account as it happens (default ``print``;
            None: silent).

    Returns:
        ``{"simulation": summary, "balance_map": summary, "out": Path, "wall_time_s": float}``;
        ``result["simulation"]["balanced"]`` says whether the demo succeeded.
    """
    report = report or _silent
    out = Path(out)
    start = time.perf_counter()
    system = load(DEMO_SYSTEM)
    controller = f"ssac:{checkpoint}"
    duration = system.episode_duration
    report("hybridctl demo: acrobot (thesis Ch. 3) in Drake: learned SSAC swing-up (TorchPolicy) + learned gate "
           "(Gate, hysteresis) + Drake LQR")
    report(f"  checkpoint: {checkpoint} (how it was trained: README.md there)")
    summary = simulate_and_write(system, controller, out / "acrobot", x0=system.nudged_nominal_state(),
                                 duration=duration, meshcat=meshcat, command=command)
    report(f"  simulate {duration:g} s from hanging down: balanced={summary['balanced']} "
           f"return={summary['return']:.1f} (thesis max 100), LQR from t={summary['first_balance_time']} s, "
           f"{summary['realtime_factor']:.0f}x real time")
    report(f"  open {out / 'acrobot' / 'replay.html'} in a browser to watch it")
    result = balance_map(system, controller, grid=grid, progress=progress)
    if command is not None:
        result.meta["command"] = command
    map_summary = result.save(out / "balance_map")
    report(f"  balance map {grid}x{grid} of rest states, {result.duration:g} s each: "
           f"{map_summary['balanced_fraction']:.1%} balanced (thesis: every start of a 41 x 41 grid)")
    wall = time.perf_counter() - start
    report(f"demo done in {wall:.0f} s; outputs under {out}/")
    return {"simulation": summary, "balance_map": map_summary, "out": out, "wall_time_s": wall}
