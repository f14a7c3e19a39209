"""The demo (``make demo``, ``hybridctl demo``): the pretrained SSAC acrobot in Drake, one run from
hanging down with a browser replay, and a balance map of rest states; then the cart-pole with its
pretrained analytic-policy-gradient swing-up (thesis Ch. 7), the cost-to-go gate and Drake's LQR,
one run with a replay and a balance map of its starts.

>>> from hybridctl.experiments import run_demo
>>> result = run_demo("runs/demo", grid=11)
>>> result["simulation"]["balanced"], result["balance_map"]["balanced_fraction"]
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

from ..io import read_json
from ..learn.checkpoint import resolve_checkpoint_dir
from ..systems import System, load
from ..systems.spec import MODELS_DIR
from .balance_map import balance_map, check_balance_map
from .simulation import simulate_and_write

PRETRAINED_ACROBOT = MODELS_DIR / "policies" / "ssac-acrobot"
"""The SSAC acrobot checkpoint shipped with hybridctl (how it was trained: README.md there)."""

PRETRAINED_CARTPOLE = MODELS_DIR / "policies" / "papg-gru-cartpole"
"""The cart-pole swing-up trained by PAPG with the thesis' GRU policy through the switched controller
(thesis Ch. 7 with the Ch. 3 switch), shipped with hybridctl (how it was trained: README.md there);
the APG family's best cart-pole map (113/121 against the MLP's 112/121, results/matrix)."""

DEMO_SYSTEM = "acrobot"
DEMO_GRID = 11
"""Balance-map grid points per axis in the demo (the thesis' figure uses 41)."""


def _silent(line: str) -> None:
    """A ``report`` that prints nothing."""


def run_demo(out: str | Path = "runs/demo", grid: int = DEMO_GRID, checkpoint: str | Path = PRETRAINED_ACROBOT,
             meshcat=None, progress: bool = True, command: str | None = None,
             report: Callable[[str], None] | None = print,
             cartpole_checkpoint: str | Path | None = PRETRAINED_CARTPOLE) -> dict:
    """The pretrained SSAC acrobot: simulate one episode from hanging down, then a balance map; then
    the same for the cart-pole with its pretrained APG swing-up.

    Writes ``out/acrobot`` (as :func:`simulate_and_write`: trajectory, summary, plot, replay) and
    ``out/balance_map`` (``balance_map.json``, ``balance_map.png``); then ``out/cartpole`` and
    ``out/cartpole_balance_map``. Each start is the spec's nominal state nudged by 1e-3 rad and
    each run lasts the spec's episode duration (10 s).

    Args:
        grid: balance-map grid points per axis.
        checkpoint: the SSAC checkpoint directory (default: the shipped one).
        cartpole_checkpoint: the APG-family cart-pole checkpoint (default: the shipped one);
            None skips the cart-pole part.
        meshcat: a running Meshcat to show the run live.
        progress: show the balance map's progress bar.
        command: the command line, recorded in the outputs.
        report: called with each line of the demo's account as it happens (default ``print``;
            None: silent).

    Returns:
        ``{"simulation": summary, "balance_map": summary, "cartpole": {"simulation": ...,
        "balance_map": ...} (or None), "out": Path, "wall_time_s": float}``;
        ``result["simulation"]["balanced"]`` (and the cart-pole's) say whether the demo succeeded.
    """
    report = report or _silent
    out = Path(out)
    acrobot_system, cartpole_system, method = check_demo_arguments(out, grid, checkpoint, cartpole_checkpoint)
    start = time.perf_counter()
    acrobot = _run_and_map(
        acrobot_system, f"ssac:{checkpoint}", checkpoint, out / "acrobot", out / "balance_map", grid,
        "hybridctl demo: acrobot (thesis Ch. 3) in Drake: learned SSAC swing-up (TorchPolicy) + learned gate "
        "(Gate, hysteresis) + Drake LQR",
        lambda summary: f"return={summary['return']:.1f} (thesis max 100), ",
        "of rest states", " (thesis: every start of a 41 x 41 grid)", meshcat, progress, command, report)
    cartpole = None
    if cartpole_system is not None:
        cartpole = _run_and_map(
            cartpole_system, f"{method}:{cartpole_checkpoint}", cartpole_checkpoint, out / "cartpole",
            out / "cartpole_balance_map", grid,
            f"cart-pole (thesis Ch. 7 + Ch. 3) in Drake: {method.upper()} swing-up (RecurrentTorchPolicy) + "
            "cost-to-go gate (Gate, hysteresis) + Drake LQR",
            lambda summary: "", "of starts (cart x, pole angle about hanging down)", "", meshcat, progress, command,
            report)
    wall = time.perf_counter() - start
    report(f"demo done in {wall:.0f} s; outputs under {out}/")
    return {**acrobot, "cartpole": cartpole, "out": out, "wall_time_s": wall}


def check_demo_arguments(out: Path, grid: int, checkpoint, cartpole_checkpoint) -> tuple[System, System | None,
                                                                                         str | None]:
    """Check every demo argument before anything is simulated: ``out`` is not a file, the balance-map
    ``grid`` (as :func:`check_balance_map`, for each system), the checkpoints exist. Returns the
    acrobot, the cart-pole (None without its checkpoint) and the cart-pole checkpoint's method."""
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"--out {out} is a file; outputs go into a folder")
    acrobot = load(DEMO_SYSTEM)
    check_balance_map(acrobot, grid, None)
    resolve_checkpoint_dir(checkpoint)
    if cartpole_checkpoint is None:
        return acrobot, None, None
    cartpole = load("cartpole")
    check_balance_map(cartpole, grid, None)
    config = read_json(resolve_checkpoint_dir(cartpole_checkpoint) / "config.json")
    method = config.get("method") if isinstance(config, dict) else None
    if not isinstance(method, str):
        raise ValueError(f"{cartpole_checkpoint}/config.json has no 'method' naming its learner")
    return acrobot, cartpole, method


def _run_and_map(system, controller: str, checkpoint, run_dir: Path, map_dir: Path, grid: int, headline: str,
                 return_text: Callable[[dict], str], starts: str, map_note: str, meshcat, progress: bool,
                 command: str | None, report: Callable[[str], None]) -> dict:
    """One part of the demo: simulate ``controller`` for the spec's episode from the nudged nominal state
    into ``run_dir`` (trajectory, summary, plot, replay), then a ``grid`` x ``grid`` balance map into
    ``map_dir``; reports each step. Returns ``{"simulation": summary, "balance_map": summary}``."""
    duration = system.episode_duration
    report(headline)
    report(f"  checkpoint: {checkpoint} (how it was trained: README.md there)")
    summary = simulate_and_write(system, controller, run_dir, x0=system.nudged_nominal_state(),
                                 duration=duration, meshcat=meshcat, command=command)
    report(f"  simulate {duration:g} s from hanging down: balanced={summary['balanced']} {return_text(summary)}"
           f"LQR from t={summary['first_balance_time']} s, {summary['realtime_factor']:.0f}x real time")
    report(f"  open {run_dir / 'replay.html'} in a browser to watch it")
    result = balance_map(system, controller, grid=grid, progress=progress)
    if command is not None:
        result.meta["command"] = command
    map_summary = result.save(map_dir)
    report(f"  balance map {grid}x{grid} {starts}, {result.duration:g} s each: "
           f"{map_summary['balanced_fraction']:.1%} balanced{map_note}")
    return {"simulation": summary, "balance_map": map_summary}
