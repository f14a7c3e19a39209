"""The thesis success test T(s) (eq. 3.2) and returns on decision-rate samples."""

from __future__ import annotations

import numpy as np
import torch

from ..systems import System


def decision_indices(n_samples: int, dt: float, decision_period: float) -> np.ndarray:
    """Indices of the samples at t = k * decision_period, k = 1, 2, ... (samples every dt from t=0)."""
    stride = int(round(decision_period / dt))
    if stride < 1:
        raise ValueError(f"decision_period ({decision_period}) must be >= dt ({dt})")
    return np.arange(stride, n_samples, stride)


def is_balanced(states, system: System, eps: float | None = None, lookback: int | None = None):
    """Thesis eq. 3.2: every one of the last ``lookback`` states within ``eps`` of the goal.

    ``states`` are decision-rate states (one per swing-up decision, thesis N_e = 50
    per episode), shape (T, n) -> bool, or (B, T, n) -> bool array (B,). Distances
    are L2 norms of ``system.state_error`` (angles wrapped). Defaults: the spec's
    ``success.eps`` (0.1) and ``success.lookback`` (10). Fewer than ``lookback``
    states -> False.
    """
    eps = system.success_eps if eps is None else float(eps)
    lookback = system.success_lookback if lookback is None else int(lookback)
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


def episode_return(states, system: System) -> float:
    """Sum of the per-decision reward over decision-rate states (thesis: max 100 for the acrobot)."""
    states = np.asarray(states, dtype=float)
    return float(np.sum(system.reward(states)))


def lqr_rollouts_balanced(system: System, x0, horizon: float, eps: float | None = None,
                          lookback: int | None = None, K: np.ndarray | None = None,
                          chunk: int = 65536) -> np.ndarray:
    """Run the saturated LQR (acting every ``dt``) from each row of ``x0`` in batched torch.

    Returns a bool array (N,): every one of the last ``lookback`` integration steps
    ends within ``eps`` (L2 of the wrapped state error) of the goal and the state
    stayed finite. Defaults: the spec's success eps and lookback. Thesis Algorithm 2
    labels its gate warm-start data this way (implementation notes: 2.5 s, eps 0.2).
    """
    eps = system.success_eps if eps is None else float(eps)
    lookback = system.success_lookback if lookback is None else int(lookback)
    steps = int(round(horizon / system.dt))
    if steps < lookback:
        raise ValueError(f"horizon must be >= lookback * dt = {lookback * system.dt}, got {horizon}")
    K = system.lqr()[0] if K is None else np.atleast_2d(K)
    Kt = torch.as_tensor(K, dtype=torch.float64)
    x_all = torch.as_tensor(np.asarray(x0, dtype=float))
    if x_all.ndim != 2 or x_all.shape[1] != system.n_states:
        raise ValueError(f"x0 must have shape (N, {system.n_states}), got {tuple(x_all.shape)}")
    limit = system.action_limit
    out = []
    with torch.no_grad():
        for x in torch.split(x_all, chunk):
            close = torch.ones(x.shape[0], dtype=torch.bool)
            for step in range(steps):
                u = (-(system.state_error(x) @ Kt.T)).clamp(-limit, limit)
                x = system.step_unchecked(x, u)
                x = torch.nan_to_num(x, nan=1e6, posinf=1e6, neginf=-1e6)
                if step >= steps - lookback:
                    close &= torch.linalg.norm(system.state_error(x), dim=-1) < eps
            out.append(close.numpy())
    return np.concatenate(out)
