"""The toy envs now live in the package (``hybridctl.envs.toy``); re-exported for the tests."""

from hybridctl.envs.toy import PointReach, goal_seeking_policy, point_reach, point_reach_nan

__all__ = ["PointReach", "point_reach", "point_reach_nan", "goal_seeking_policy"]
