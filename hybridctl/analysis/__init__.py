"""Analysis, numpy and scipy only: box meshes, mesh dimension and variation estimators (Ch. 4);
Poincare section maps, reachable-state meshes, absorbing Markov chains and mean first passage
time (Ch. 5).

Names load on first use (PEP 562), so ``from hybridctl.analysis.poincare import SectionMap``
does not pull in scipy.sparse and the reachable-mesh code.
"""

from .. import lazy_exports

_HOMES = {
    "markov": ("MFPTResult", "MFPTSolveError", "NearlyNeverFailsError", "absorbing_mfpt", "check_transition_matrix",
               "cumulative_transition_mass"),
    "mesh": ("MeshDimension", "box_keys", "box_mesh_size", "count_distinct_rows", "mesh_dimension"),
    "poincare": ("DISTURBANCE_RULES", "FiniteDisturbances", "FunctionMap", "GaussianDisturbance", "RimlessWheel",
                 "ScipyDisturbance", "SectionMap", "weighted_grid"),
    "postprocess": ("PostProcessor",),
    "refine": ("DEFAULT_REFINE_RTOL", "refined_mesh"),
    "reachable": ("MonteCarloResult", "ReachableMesh", "build_mesh", "failure_states", "mesh_sizes",
                  "monte_carlo_mfpt", "reachable_dimension", "shared_backend"),
    "variation": ("madogram", "power_variation", "variation_dimension", "variogram"),
}
__getattr__, __dir__, __all__ = lazy_exports(__name__, _HOMES)
