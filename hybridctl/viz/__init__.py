"""Viewing: meshcat (live and HTML replays), matplotlib plots, views of reachable meshes, training curves.

>>> from hybridctl import viz
>>> html = viz.replay_html(system, times, states, path="replay.html")
>>> fig = viz.plot_trajectory(times, states, inputs, gate, system, path="traj.png")
>>> viz.plot_training_curves("runs/sac/progress.csv", "curves.png")

Names load on first use (PEP 562): plotting training curves does not import pydrake
(only the meshcat views need it).
"""

from importlib import import_module

_HOMES = {
    "meshcat": ("add_meshcat", "replay_html", "start_meshcat"),
    "markov": ("plot_cumulative_mass", "plot_mesh_sizes", "plot_mesh_states", "plot_transition_sparsity"),
    "plots": ("plot_balance_map", "plot_trajectory"),
    "training": ("plot_training_curves",),
}
_HOME_OF = {name: module for module, names in _HOMES.items() for name in names}

__all__ = sorted(_HOME_OF)


def __getattr__(name: str):
    module = _HOME_OF.get(name)
    if module is None:
        raise AttributeError(f"module 'hybridctl.viz' has no attribute {name!r}")
    value = getattr(import_module(f".{module}", __name__), name)
    globals()[name] = value  # later look-ups skip this hook
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
