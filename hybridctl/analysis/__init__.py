"""Analysis: the thesis success test, balance maps (and later meshes, dimensions, MFPT)."""

from .balance import decision_indices, episode_return, is_balanced, lqr_rollouts_balanced
from .balance_map import BalanceMap, balance_map, grid_axes

__all__ = ["decision_indices", "episode_return", "is_balanced", "lqr_rollouts_balanced", "BalanceMap", "balance_map", "grid_axes"]
