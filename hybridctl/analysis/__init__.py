"""Analysis, numpy and scipy only: box meshes, mesh dimension and variation estimators (Ch. 4);
Poincare section maps, reachable-state meshes, absorbing Markov chains and mean first passage
time (Ch. 5).

Names load on first use (PEP 562), so ``from hybridctl.analysis.poincare import SectionMap``
does not pull in scipy.sparse and the reachable-mesh code.
"""

from importlib import import_module

_HOMES = {
    "markov": ("MFPTResult", "absorbing_mfpt", "check_transition_matrix", "cumulative_transition_mass"),
    "mesh": ("MeshDimension", "box_keys", "box_mesh_size", "count_distinct_rows", "mesh_dimension"),
    "poincare": ("FiniteDisturbances", "FunctionMap", "GaussianDisturbance", "RimlessWheel", "SectionMap"),
    "postprocess": ("PostProcessor",),
    "reachable": ("MonteCarloResult", "ReachableMesh", "build_mesh", "failure_states", "mesh_sizes",
                  "monte_carlo_mfpt", "reachable_dimension"),
    "variation": ("madogram", "power_variation", "variation_dimension", "variogram"),
}
_HOME_OF = {name: module for module, names in _HOMES.items() for name in names}

__all__ = sorted(_HOME_OF)


def __getattr__(name: str):
    module = _HOME_OF.get(name)
    if module is None:
        raise AttributeError(f"module 'hybridctl.analysis' has no attribute {name!r}")
    value = getattr(import_module(f".{module}", __name__), name)
    globals()[name] = value  # later look-ups skip this hook
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
