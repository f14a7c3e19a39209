"""Analysis: the thesis success test, balance maps (and later meshes, dimensions, MFPT)."""

from .balance import decision_indices, episode_return, is_balanced

__all__ = ["decision_indices", "episode_return", "is_balanced"]
