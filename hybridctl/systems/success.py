"""The thesis success test T(s) (eq. 3.2) and returns on decision-rate samples."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:  # pragma: no cover
    from . import System

__all__ = ["decision_indices", "is_balanced", "stabilisation", "episode_return"]


def decision_indices(n_samples: int, dt: float, decision_period: float) -> np.ndarray:
    """Indices of the samples at t = k * decision_period, k = 1, 2, ... (samples every dt from t=0)."""
    stride = int(round(decision_period / dt))
    if stride < 1:
        raise ValueError(f"decision_period ({decision_period}) must be >= dt ({dt})")
    return np.arange(stride, n_samples, stride)


def is_balanced(states, system: "System", eps: float | None = None, lookback: int | None = None):
    """Thesis eq. 3.2: every one of the last ``lookback`` states within ``eps`` of the goal.

    ``states`` are decision-rate states (one per swing-up decision, thesis N_e = 50
    per episode), shape (T, n) -> bool, or (B, T, n) -> bool array (B,). Distances
    are L2 norms of ``system.state_error`` (angles wrapped). Defaults: the spec's
    ``success.eps`` (0.1) and ``success.lookback`` (10). Fewer than ``lookback``
    states -> False.
    """
    eps = system.success.eps if eps is None else float(eps)
    lookback = system.success.lookback if lookback is None else int(lookback)
    if isinstance(states, torch.Tensor):
        states = states.detach().cpu().numpy()
    states = np.asarray(states, dtype=float)
    if states.ndim not in (2, 3) or states.shape[-1] != system.n_states:
        raise ValueError(f"states must have shape (T, {system.n_states}) or (B, T, {system.n_states}), "
                         f"got {states.shape}")
    if states.shape[-2] < lookback:
        return np.zeros(states.shape[:-2], dtype=bool) if states.ndim == 3 else False
    tail = states[..., -lookback:, :]
    with np.errstate(invalid="ignore"):
        close = np.linalg.norm(system.state_error(tail.copy()), axis=-1) < eps
    result = close.all(axis=-1)
    return bool(result) if states.ndim == 2 else result


def stabilisation(states, system: "System", lookback: int) -> tuple[np.ndarray, np.ndarray]:
    """Per episode of ``states`` (B, T, n): (stabilised, upright), bool arrays (B,).

    ``stabilised``: :func:`is_balanced` over the last ``lookback`` states (every coordinate, a
    cart's position and the velocities included). ``upright``: every angle error alone below the
    spec's success eps over those states (the pole held up, the cart anywhere). An episode with a
    non-finite state is neither.
    """
    states = np.asarray(states, dtype=float)
    ok = np.isfinite(states).all(axis=(1, 2))
    stabilised, upright = np.zeros(len(states), dtype=bool), np.zeros(len(states), dtype=bool)
    if ok.any():
        stabilised[ok] = is_balanced(states[ok], system, lookback=lookback)
        err = system.state_error(states[ok][:, -lookback:, :].copy())[..., system.angle_indices]
        upright[ok] = (np.abs(err) < system.success.eps).all(axis=(1, 2))
    return stabilised, upright


def episode_return(states, system: "System") -> float:
    """Sum of the per-decision reward over decision-rate states (thesis: max 100 for the acrobot)."""
    states = np.asarray(states, dtype=float)
    return float(np.sum(system.reward(states)))
