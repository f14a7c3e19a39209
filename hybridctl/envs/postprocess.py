"""A gymnasium wrapper that post-processes the episode return by trajectory dimension (thesis Ch. 4).

The dimension of an episode is known only at its end, so :class:`DimensionReward`
returns reward 0 at every step but the last, where it returns the whole post-processed
return ``R*`` (see :mod:`hybridctl.analysis.postprocess`). Return-based learners
(ARS, random-search fine-tuning) see exactly ``R*``; the per-step reward is kept in
``info["raw_reward"]``. The ``identity`` kind passes rewards through step by step.

>>> env = DimensionReward(gym.make("Hopper-v5"), "mesh-lower")
>>> obs, info = env.reset(seed=0)
>>> ... at the last step: reward == R*, info["raw_return"], info["dimension"], info["postprocess"]
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from ..analysis.postprocess import PostProcessor


class DimensionReward(gym.Wrapper):
    """Replace the episode's reward by its dimension-post-processed return (paid at the last step).

    ``postprocessor``: a :class:`~hybridctl.analysis.postprocess.PostProcessor` or a kind name
    ("identity", "mesh-lower", "mesh-upper", "mesh-mean", "madogram", "variogram").
    The dimension is computed from the observations, the reset observation included.
    """

    def __init__(self, env: gym.Env, postprocessor: PostProcessor | str = "identity"):
        super().__init__(env)
        self.postprocessor = (postprocessor if isinstance(postprocessor, PostProcessor)
                              else PostProcessor(postprocessor))
        self._observations: list[np.ndarray] = []
        self._raw_return = 0.0

    def reset(self, **kwargs):
        """Reset the env and the episode's record."""
        obs, info = self.env.reset(**kwargs)
        self._observations = [np.asarray(obs, dtype=np.float64).ravel()]
        self._raw_return = 0.0
        return obs, info

    def step(self, action):
        """Step; reward 0 until the episode ends, then the post-processed return."""
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._observations.append(np.asarray(obs, dtype=np.float64).ravel())
        self._raw_return += float(reward)
        info = dict(info, raw_reward=float(reward))
        if self.postprocessor.kind == "identity":
            if terminated or truncated:
                info.update(raw_return=self._raw_return, dimension=1.0)
            return obs, reward, terminated, truncated, info
        if not (terminated or truncated):
            return obs, 0.0, terminated, truncated, info
        processed, details = self.postprocessor(np.stack(self._observations), self._raw_return)
        info.update(raw_return=self._raw_return, dimension=details["dimension"], postprocess=details)
        return obs, processed, terminated, truncated, info
