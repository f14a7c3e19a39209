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
from ..drake import simulate
from ..systems import System, load
from ..viz import plot_trajectory, replay_html
from .controllers import build_named_diagram

def simulate_and_write(system: System | str, controller: str = "energy", out: str | Path = "runs/simulate",
                       x0=None, duration: float | None = None, html: bool = True, meshcat=None,
                       command: str | None = None) -> dict:
    """Simulate ``controller`` (a name from ``CONTROLLERS``, e.g. ``"energy"`` or ``"ssac:PATH"``)
    on ``system`` and write ``trajectory.npz``, ``summary.json``, ``plot.png`` and (with
    ``html``) ``replay.html`` into ``out``.

    Args:
        system: a System or a system name.
        x0: the initial state (default: ``system.nudged_nominal_state()``).
        duration: seconds (default: the spec's episode duration).
        meshcat: a running Meshcat (``viz.start_meshcat()``) to show the run live at real time.
        command: the command line that asked for the run, recorded in ``summary.json``.

    Returns:
        The run's summary (``Trajectory.summary``: balanced, return, diverged, ...).
    """
    import matplotlib.pyplot as plt

    system = load(system) if isinstance(system, str) else system
    start = system.nudged_nominal_state() if x0 is None else np.asarray(x0, dtype=float)
    out = io.output_folder(out)
    diagram = build_named_diagram(system, controller, meshcat=meshcat)
    traj = simulate(diagram, start, duration, realtime_rate=1.0 if meshcat is not None else 0.0)
    traj.meta["controller"] = controller
    if command is not None:
        traj.meta["command"] = command
    summary = traj.save(out)
    if len(traj.t) < 2:  # diverged within the first step: nothing to draw, the summary says why
        return summary
    fig = plot_trajectory(traj.t, traj.x, traj.u, traj.gate, system, path=out / "plot.png",
                          title=f"{system.name}, {controller}: balanced={summary['balanced']}")
    plt.close(fig)
    if html and len(traj.t) > 1:
        replay_html(system, traj.t, traj.x, path=out / "replay.html")
    return summary
