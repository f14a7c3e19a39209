"""Small gymnasium envs for trying learners in seconds (ARS examples, robustness tests).

Module-level classes and factories, so spawned rollout workers (``hybridctl.parallel``) can
import them by name:

>>> from hybridctl.envs.toy import goal_seeking_policy, point_reach
>>> from hybridctl.learn import ARS, ARSConfig
>>> agent = ARS(point_reach, ARSConfig(n_directions=8, top_directions=4, backend="serial"))
"""

import gymnasium as gym
import numpy as np

__all__ = ["PointReach", "point_reach", "point_reach_nan", "goal_seeking_policy"]


class PointReach(gym.Env):
    """A damped point in the plane, pushed by the action; reward 2 - distance to the origin (the goal).

    It starts at rest up to 1.5 away; linear feedback (a PD law) is optimal, so a linear policy
    on normalised observations (no bias term) can learn it in a few epochs. The episode
    terminates ("falls") when the point leaves the disc of radius ``fall_radius``.
    ``nan_after`` makes the state NaN from that step on (to test NaN guards).
    """

    observation_space = gym.spaces.Box(-np.inf, np.inf, (4,))
    action_space = gym.spaces.Box(-1.0, 1.0, (2,))
    goal = np.zeros(2)

    def __init__(self, steps: int = 60, fall_radius: float = 4.0, nan_after: int | None = None):
        self.steps, self.fall_radius, self.nan_after = steps, fall_radius, nan_after

    def reset(self, *, seed=None, options=None):
        """Start at rest at a uniform position in [-1.5, 1.5]^2; returns (observation, info)."""
        super().reset(seed=seed)
        self.t = 0
        self.state = np.r_[self.np_random.uniform(-1.5, 1.5, 2), 0.0, 0.0]
        return self.state.copy(), {}

    def step(self, action):
        """One damped step pushed by ``action``; returns gymnasium's 5-tuple."""
        self.t += 1
        pos, vel = self.state[:2], self.state[2:]
        vel = 0.8 * vel + 0.1 * np.asarray(action, dtype=float)
        self.state = np.r_[pos + vel, vel]
        if self.nan_after is not None and self.t >= self.nan_after:
            self.state[:] = np.nan
        reward = 2.0 - float(np.linalg.norm(self.state[:2] - self.goal))
        fell = bool(np.linalg.norm(self.state[:2]) > self.fall_radius)
        return self.state.copy(), reward, fell, self.t >= self.steps, {}


def point_reach():
    """A default :class:`PointReach` (60 steps, fall radius 4): an env factory for learners."""
    return PointReach()


def point_reach_nan():
    """A :class:`PointReach` whose state turns NaN after 5 steps (for NaN-guard tests)."""
    return PointReach(nan_after=5)


def goal_seeking_policy(obs):
    """A fixed policy for robustness examples: PD towards the goal (raw observations)."""
    return 2.0 * (PointReach.goal - obs[:2]) - 4.0 * obs[2:]
