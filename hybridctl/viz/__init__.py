"""Viewing: meshcat (live and HTML replays) and matplotlib plots.

>>> from hybridctl import viz
>>> html = viz.replay_html(system, times, states, path="replay.html")
>>> fig = viz.plot_trajectory(times, states, inputs, gate, system, path="traj.png")
"""

from .meshcat import add_meshcat, replay_html, start_meshcat
from .plots import plot_balance_map, plot_trajectory

__all__ = ["start_meshcat", "add_meshcat", "replay_html", "plot_trajectory", "plot_balance_map"]
