"""The one result format of every rollout (:func:`episode_result`), the seeds of held-out episodes and the
dimension measures of an episode's states."""

from __future__ import annotations

import math

import numpy as np

from ..analysis.mesh import mesh_dimension
from ..analysis.postprocess import MIN_POINTS, TRANSIENT_STEPS, PostProcessor
from ..analysis.variation import madogram, variogram


def episode_result(states: np.ndarray, raw_return: float, shifted_return: float, steps: int, terminated: bool,
                   postprocessor: PostProcessor, *, finite: bool = True, success: bool | None = None,
                   keep_states: bool = False, measure: bool = False) -> dict:
    """The result of one episode of ``states`` (steps + 1 rows), in the one format of this module.

    ``shifted_return`` is what the post-processor gets (ARS: the raw return less ``reward_shift``
    per step; fine-tuning: the raw return); ``finite`` False (or a NaN/inf state or return)
    gives ``{"finite": False, "steps": steps}``.
    """
    if not finite or not math.isfinite(raw_return) or not np.all(np.isfinite(states)):
        return {"finite": False, "steps": steps}
    processed, info = postprocessor(states, float(shifted_return))
    out = {"finite": True, "return": float(processed), "raw_return": float(raw_return), "steps": int(steps),
           "terminated": bool(terminated), "success": success, "dimension": info["dimension"],
           "reason": info["reason"], "sum": states[:-1].sum(axis=0), "sumsq": (states[:-1] ** 2).sum(axis=0),
           "count": states.shape[0] - 1}
    if keep_states:
        out["states"] = states
    if measure:
        out["dimensions"] = measure_dimensions(states, postprocessor.transient_steps)
    return out


def evaluation_seeds(seed: int, episodes: int) -> list[int]:
    """The env seeds of ``episodes`` held-out episodes (evaluations, failure rates) from ``seed``."""
    return [int(s) for s in np.random.default_rng(seed).integers(0, 2 ** 31 - 1, size=episodes)]


def measure_dimensions(states: np.ndarray, transient_steps: int = TRANSIENT_STEPS) -> dict:
    """Raw (unclipped) lower/upper mesh dimension, madogram and variogram of the states after the
    transient (thesis Table 4.1 metrics); None where the episode is too short to measure."""
    tail = states[transient_steps:]
    if tail.shape[0] < MIN_POINTS:
        return {"mesh_lower": None, "mesh_upper": None, "madogram": None, "variogram": None}
    md = mesh_dimension(tail)
    return {"mesh_lower": md.lower, "mesh_upper": md.upper, "madogram": madogram(tail), "variogram": variogram(tail)}
