"""Viewing: meshcat (live and HTML replays), matplotlib plots, views of reachable meshes, training curves,
the Ch. 7 figures.

>>> from hybridctl import viz
>>> html = viz.replay_html(system, times, states, path="replay.html")
>>> fig = viz.plot_trajectory(times, states, inputs, gate, system, path="traj.png")
>>> viz.plot_training_curves("runs/sac/progress.csv", "curves.png")

Names load on first use (PEP 562): plotting training curves does not import pydrake
(only the meshcat views need it).
"""

from .. import lazy_exports

_HOMES = {
    "meshcat": ("add_meshcat", "replay_html", "start_meshcat", "shared_meshcat", "ReplayPage"),
    "markov": ("plot_cumulative_mass", "plot_mesh_sizes", "plot_mesh_states", "plot_transition_sparsity"),
    "plots": ("plot_balance_map", "plot_trajectory"),
    "angles": ("wrap_about_goal",),
    "training": ("plot_training_curves", "read_progress_rows"),
    "apg": ("plot_gradient_norms", "plot_method_comparison", "plot_return_landscape", "plot_return_curves"),
}
__getattr__, __dir__, __all__ = lazy_exports(__name__, _HOMES)
