"""Analysis: the thesis success test and balance maps (Ch. 3); box meshes, mesh dimension and
variation estimators (Ch. 4); absorbing Markov chains and mean first passage time (Ch. 5)."""

from .balance import decision_indices, episode_return, is_balanced, lqr_rollouts_balanced
from .markov import MFPTResult, absorbing_mfpt, check_transition_matrix, cumulative_transition_mass
from .mesh import MeshDimension, box_keys, box_mesh_size, count_distinct_rows, mesh_dimension
from .poincare import FiniteDisturbances, FunctionMap, GaussianDisturbance, RimlessWheel, SectionMap
from .postprocess import PostProcessor
from .reachable import (MonteCarloResult, ReachableMesh, build_mesh, failure_states, mesh_sizes, monte_carlo_mfpt,
                        reachable_dimension)
from .variation import madogram, power_variation, variation_dimension, variogram

__all__ = ["decision_indices", "episode_return", "is_balanced", "lqr_rollouts_balanced", 
           "MeshDimension", "box_keys", "box_mesh_size", "count_distinct_rows",
           "mesh_dimension", "PostProcessor", "MFPTResult", "absorbing_mfpt", "check_transition_matrix",
           "FiniteDisturbances", "FunctionMap", "GaussianDisturbance", "RimlessWheel", "SectionMap", "MonteCarloResult",
           "ReachableMesh", "build_mesh", "mesh_sizes", "monte_carlo_mfpt", "cumulative_transition_mass",
           "failure_states", "reachable_dimension", "madogram", "power_variation", "variation_dimension", "variogram"]
