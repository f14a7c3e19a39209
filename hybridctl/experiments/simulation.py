"""Simulate a named controller in Drake and write the run: ``trajectory.npz``, ``summary.json``,
``plot.png`` and ``replay.html`` (what ``hybridctl simulate`` does).

>>> from hybridctl.experiments import simulate_and_write
>>> summary = simulate_and_write("acrobot", "energy", out="runs/sim")
>>> summary["balanced"], summary["return"]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import io
from ..drake import build_hybrid_diagram, simulate
from ..drake.simulate import check_duration
from ..learn.registry import gate_of_kind, load_controller
from ..systems import System, SwitchedController, load
from .. import viz   # its names load on first use: pyplot when a plot is drawn, not with this module
from .controllers import controller_parts, display_name

OUTPUTS = ("trajectory.npz", "summary.json", "plot.png", "replay.html")
"""What :func:`simulate_and_write` writes into its folder."""
OWN = ("trajectory.npz", "summary.json")
"""The files that make a folder a simulation's own (one written before folders were marked)."""

def simulate_and_write(system: System | str, controller: str = "energy", out: str | Path = "runs/simulate",
                       x0=None, duration: float | None = None, html: bool = True, meshcat=None,
                       command: str | None = None, force: bool = False) -> dict:
    """Simulate ``controller`` (a name from ``CONTROLLERS``, e.g. ``"energy"`` or ``"ssac:PATH"``)
    on ``system`` and write ``trajectory.npz``, ``summary.json``, ``plot.png`` and (with
    ``html``) ``replay.html`` into ``out``.

    Args:
        system: a System or a system name.
        x0: the initial state (default: ``system.nudged_nominal_state()``).
        duration: seconds (default: the spec's episode duration).
        meshcat: a running Meshcat (``viz.start_meshcat()``) to show the run live at real time.
        command: the command line that asked for the run, recorded in ``summary.json``.
        out: the folder, held locked while the run writes it (:func:`hybridctl.io.command_folder`):
            refused when another run holds it, or when it holds an input (a spec, a model, a
            checkpoint) or files of these names that a simulation did not write.
        force: lift the stated cap on the steps of one run (not the memory limit); the duration
            is checked before anything is built or written (``drake.simulate.check_duration``); and load a
            ``KIND:PATH`` checkpoint trained on other spec values (another plant) anyway, with a warning
            (:func:`hybridctl.learn.load_controller`'s ``force``), as ``train --resume --force`` does.

    Returns:
        The run's summary (``Trajectory.summary``: balanced, return, diverged, ...), plus
        ``written``: the names of the files written into ``out`` (a run that diverged within
        its first step has no plot or replay).
    """
    import matplotlib.pyplot as plt

    system = load(system) if isinstance(system, str) else system
    duration = check_duration(system, duration, force)
    start = system.nudged_nominal_state() if x0 is None else np.asarray(x0, dtype=float)
    with io.command_folder(out, "simulate", OUTPUTS, OWN) as out:
        diagram = build_hybrid_diagram(system, _controller(system, controller, force), meshcat=meshcat)
        traj = simulate(diagram, start, duration, realtime_rate=1.0 if meshcat is not None else 0.0, force=force)
        traj.meta["controller"] = controller
        if command is not None:
            traj.meta["command"] = command
        summary = traj.save(out)
        written = ["trajectory.npz", "summary.json"]
        if len(traj.t) >= 2:  # else it diverged within the first step: nothing to draw, the summary says why
            fig = viz.plot_trajectory(traj.t, traj.x, traj.u, traj.gate, system, path=out / "plot.png",
                                  title=f"{system.name}, {display_name(controller)}: balanced={summary['balanced']}")
            plt.close(fig)
            written.append("plot.png")
            if html:
                viz.replay_html(system, traj.t, traj.x, path=out / "replay.html")
                written.append("replay.html")
        return {**summary, "written": written}


def _controller(system: System, controller: str, force: bool) -> SwitchedController:
    """The controller named ``controller`` (``controller_parts``); with ``force`` a ``KIND:PATH`` checkpoint
    trained on other spec values is loaded anyway (``load_controller(..., force=True)`` warns what differs)."""
    kind, sep, path = controller.partition(":")
    gate = gate_of_kind(kind) if sep and path else None
    if force and gate is not None:
        return load_controller(path, system, gate=gate, force=True)   # on the CPU, as controller_parts
    return controller_parts(system, controller)
