"""Moved: the success test lives in :mod:`hybridctl.systems.success`, the LQR rollouts in
:mod:`hybridctl.systems.control`. This alias goes once every caller imports from there."""

from ..systems.control import lqr_rollouts_balanced  # noqa: F401
from ..systems.success import decision_indices, episode_return, is_balanced  # noqa: F401
