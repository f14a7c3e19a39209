"""Viewing: meshcat (live and HTML replays), matplotlib plots, views of reachable meshes.

>>> from hybridctl import viz
>>> html = viz.replay_html(system, times, states, path="replay.html")
>>> fig = viz.plot_trajectory(times, states, inputs, gate, system, path="traj.png")
>>> viz.plot_training_curves("runs/sac/progress.csv", "curves.png")
"""

from .meshcat import add_meshcat, replay_html, start_meshcat
from .markov import plot_cumulative_mass, plot_mesh_sizes, plot_mesh_states, plot_transition_sparsity
from .plots import plot_balance_map, plot_trajectory
from .training import plot_training_curves

__all__ = ["start_meshcat", "add_meshcat", "replay_html", "plot_trajectory", "plot_balance_map",
           "plot_transition_sparsity", "plot_cumulative_mass", "plot_mesh_states", "plot_mesh_sizes",
           "plot_training_curves"]
