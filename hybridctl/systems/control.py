"""The control laws of the switched controller, each written once for numpy and torch.

Every block that controls or judges a system calls these: the Drake blocks
(:mod:`hybridctl.drake`), the batched switched env (:mod:`hybridctl.envs`), SSAC and
the gate (:mod:`hybridctl.learn`), the success test (:mod:`.success`). The
torch-vs-Drake equality tests therefore test one formula.

- :func:`wrap_angles`: angle coordinates to [-pi, pi).
- :func:`lqr_command`: u = -K e for a wrapped state error e = x - goal.
- :func:`cost_to_go`: V = e' S e.
- :func:`hysteresis`: the gate's mode update (on above ``on``, off below ``off``).
- :func:`saturate`: clip to the actuator limit.
- :data:`DIVERGENCE_BOUND`: a state with a coordinate beyond it (or non-finite) has diverged.
- :class:`CostToGoGate`: the hand-designed gate p = exp(-V / scale).
- :func:`lqr_rollouts_balanced`, :func:`lqr_basin_level`: batched saturated-LQR rollouts
  (gate labels, thesis Alg. 2) and the LQR's basin level that sets the gate scale.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

System = Any
"""A :class:`hybridctl.systems.System` (not imported: the package imports this module, and an import back,
even under ``TYPE_CHECKING``, would make the two a cycle)."""

__all__ = ["DIVERGENCE_BOUND", "wrap_angle", "wrap_angles", "lqr_command", "tracking_command", "cost_to_go", "hysteresis", "saturate",
           "is_diverged", "CostToGoGate", "lqr_rollouts_balanced", "lqr_basin_level"]

DIVERGENCE_BOUND = 1e6
"""States with a coordinate beyond +-DIVERGENCE_BOUND (or non-finite) count as diverged."""


def wrap_angle(angle):
    """An angle (float, numpy or torch) wrapped to [-pi, pi)."""
    return (angle + np.pi) % (2 * np.pi) - np.pi


def wrap_angles(err, angle_indices):
    """Wrap the ``angle_indices`` columns of ``err`` (numpy or torch, (..., n)) to [-pi, pi), in place.

    Returns ``err``. Callers that must keep their input pass a copy (``System.state_error`` does).
    """
    err[..., angle_indices] = wrap_angle(err[..., angle_indices])
    return err


def lqr_command(err, K):
    """u = -K e for state errors ``err`` (..., n) and a gain ``K`` (m, n): (..., m), numpy or torch."""
    return -(err @ K.T)


def tracking_command(err, u0, K, k0):
    """The time-varying LQR's u = u0 - K e - k0 (Drake's ``FiniteHorizonLinearQuadraticRegulator``) for state
    errors ``err`` (..., n) from the nominal state, the rows' nominal inputs ``u0`` (..., m), gains ``K`` (..., m, n)
    and offsets ``k0`` (..., m): (..., m), numpy or torch. Unsaturated: the caller clips."""
    return u0 - (K @ err[..., None])[..., 0] - k0


def cost_to_go(err, S):
    """V = e' S e for state errors ``err`` (..., n): (...,), numpy or torch."""
    return ((err @ S) * err).sum(-1)


def hysteresis(probability, mode, on: float, off: float):
    """The gate's next mode: True above ``on``, False below ``off``, else ``mode`` (thesis Sec. 3.3).

    Works elementwise on torch tensors, numpy arrays and plain floats (a Drake block's
    mode is 0.0 / 1.0 and comes back as such).
    """
    if type(probability) is float and type(mode) is float:   # one Drake gate update: the common case first
        return 1.0 if probability > on else (0.0 if probability < off else mode)
    if isinstance(probability, torch.Tensor):
        mode = torch.as_tensor(mode, device=probability.device)
        return torch.where(probability > on, True, torch.where(probability < off, False, mode.bool()))
    if np.ndim(probability) == 0 and np.ndim(mode) == 0:
        if probability > on:
            return type(mode)(1)
        if probability < off:
            return type(mode)(0)
        return mode
    mode = np.asarray(mode, dtype=bool)
    return np.where(probability > on, True, np.where(probability < off, False, mode))


def saturate(u, limit: float):
    """Clip commands to [-limit, limit] (numpy or torch)."""
    if isinstance(u, torch.Tensor):
        return u.clamp(-limit, limit)
    return np.clip(u, -limit, limit)


def is_diverged(x):
    """Rows (..., n) -> (...) bool: some coordinate is non-finite or beyond ``DIVERGENCE_BOUND``."""
    if isinstance(x, torch.Tensor):
        return ~(x.abs() <= DIVERGENCE_BOUND).all(-1)
    with np.errstate(invalid="ignore"):
        return ~(np.abs(x) <= DIVERGENCE_BOUND).all(-1)


class CostToGoGate(torch.nn.Module):
    """Gate probability from the LQR cost-to-go: p = exp(-(x - goal)' S (x - goal) / scale).

    With the spec's hysteresis (on 0.9, off 0.5 for the thesis systems) the LQR takes
    over once the cost-to-go drops below ln(1/on) * scale and hands back above
    ln(1/off) * scale. Works on numpy single states (the Drake ``Gate``) and torch batches.
    """

    def __init__(self, system: System, scale: float | None = None, S: np.ndarray | None = None):
        super().__init__()
        self.system = system
        self.scale = float(system.gate.cost_scale if scale is None else scale)
        if not self.scale > 0:
            raise ValueError(f"scale must be > 0, got {self.scale}")
        S = system.lqr()[1] if S is None else np.asarray(S, dtype=float)
        self.register_buffer("S", torch.as_tensor(S, dtype=torch.float64, device="cpu"))  # moved with .to(device)
        self._S_np = np.asarray(S, dtype=float)

    def cost_to_go(self, x):
        """(x - goal)' S (x - goal), numpy or torch, batched over leading dims."""
        err = self.system.state_error(x if isinstance(x, torch.Tensor) else np.asarray(x, dtype=float))
        S = self.S.to(err.dtype) if isinstance(err, torch.Tensor) else self._S_np
        return cost_to_go(err, S)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Probability that the LQR can take over, in (0, 1]; shape (..., 1)."""
        return self.of_error(self.system.state_error(x))

    def of_error(self, err: torch.Tensor) -> torch.Tensor:
        """:meth:`forward` from the state errors ``err = system.state_error(x)`` (torch, (..., n)) where the
        caller has them already (the switched controller's gate step, which needs them for the LQR too)."""
        return torch.exp(-cost_to_go(err, self.S.to(err.dtype)) / self.scale).unsqueeze(-1)

    def numpy_forward(self, x: np.ndarray) -> np.ndarray:
        """The same probability for numpy states, shape (..., 1) (used by the Drake ``Gate``)."""
        return np.exp(-np.asarray(self.cost_to_go(x)) / self.scale)[..., None]

    def __call__(self, x):
        if isinstance(x, torch.Tensor):
            return super().__call__(x)
        return self.numpy_forward(x)


def lqr_rollouts_balanced(system: System, x0, horizon: float, eps: float | None = None,
                          lookback: int | None = None, K: np.ndarray | None = None,
                          chunk: int = 65536, device: str | torch.device | None = None,
                          hold: int = 1) -> np.ndarray:
    """Run the saturated LQR (acting every ``hold`` integration steps ``dt``, the command held in between)
    from each row of ``x0`` in batched torch.

    Returns a bool array (N,): every one of the last ``lookback`` integration steps
    ends within ``eps`` (L2 of the wrapped state error) of the goal and the state
    stayed finite. Defaults: the spec's success eps and lookback. Thesis Algorithm 2
    labels its gate warm-start data this way (implementation notes: 2.5 s, eps 0.2).

    ``x0``: numpy or torch (N, n). The rollouts run in float64 on ``device``; None: a torch
    ``x0``'s device, else the CPU. The labels come back to the host once per ``chunk`` rows.
    """
    eps = system.success.eps if eps is None else float(eps)
    lookback = system.success.lookback if lookback is None else int(lookback)
    steps = int(round(horizon / system.dt))
    if steps < lookback:
        raise ValueError(f"horizon must be >= lookback * dt = {lookback * system.dt}, got {horizon}")
    if int(hold) != hold or hold < 1:
        raise ValueError(f"hold must be a whole number of integration steps >= 1, got {hold}")
    hold = int(hold)
    if device is None:
        device = x0.device if isinstance(x0, torch.Tensor) else "cpu"
    K = system.lqr()[0] if K is None else np.atleast_2d(K)
    Kt = torch.as_tensor(K, dtype=torch.float64, device=device)
    if isinstance(x0, torch.Tensor):
        x_all = x0.detach().to(device=device, dtype=torch.float64)
    else:
        x_all = torch.as_tensor(np.asarray(x0, dtype=float), device=device)
    if x_all.ndim != 2 or x_all.shape[1] != system.n_states:
        raise ValueError(f"x0 must have shape (N, {system.n_states}), got {tuple(x_all.shape)}")
    limit = system.action_limit
    bound = DIVERGENCE_BOUND
    out = []
    with torch.no_grad():
        for x in torch.split(x_all, chunk):
            close = torch.ones(x.shape[0], dtype=torch.bool, device=x.device)
            for step in range(steps):
                if step % hold == 0:
                    u = saturate(lqr_command(system.state_error(x), Kt), limit)
                x = system.step_unchecked(x, u)
                x = torch.nan_to_num(x, nan=bound, posinf=bound, neginf=-bound)
                if step >= steps - lookback:
                    close &= torch.linalg.norm(system.state_error(x), dim=-1) < eps
            out.append(close.cpu().numpy())  # one host copy per chunk, after its rollouts
    return np.concatenate(out)


def lqr_basin_level(system: System, n_samples: int = 20000, horizon: float | None = None,
                    spread: np.ndarray | None = None, seed: int = 0, K: np.ndarray | None = None,
                    S: np.ndarray | None = None, device: str | torch.device | None = None, hold: int = 1) -> dict:
    """Estimate the cost-to-go level V* below which the saturated LQR balances.

    Samples states goal + U(-spread, spread), runs the LQR (acting every ``dt``,
    saturated at the action limit) for ``horizon`` seconds (default: the spec's
    ``gate.label_horizon``) in batched torch, marks each rollout with the thesis success
    test on its last ``lookback`` steps, and returns V* = the smallest cost-to-go
    (x - goal)' S (x - goal) among failing samples, with the success rate below V*, 2 V*
    and 4 V*. A gate that switches on below V* (``CostToGoGate`` with scale
    V* / ln(1/gate.on)) only hands over states from which every sampled LQR rollout balanced.
    The rollouts run on ``device`` (None: the CPU), as :func:`lqr_rollouts_balanced`; ``hold``: the LQR
    acts every ``hold`` integration steps (a control period of ``hold * dt``), its command held in between.
    """
    if n_samples < 10:
        raise ValueError(f"n_samples must be >= 10, got {n_samples}")
    horizon = system.gate.label_horizon if horizon is None else float(horizon)
    K = system.lqr()[0] if K is None else np.atleast_2d(K)
    S = system.lqr()[1] if S is None else np.asarray(S)
    spread = np.ones(system.n_states) if spread is None else np.asarray(spread, dtype=float)
    rng = np.random.default_rng(seed)
    x0 = system.goal + rng.uniform(-1, 1, size=(n_samples, system.n_states)) * spread
    V = cost_to_go(system.state_error(x0), S)
    ok = lqr_rollouts_balanced(system, x0, horizon, K=K, device=device, hold=hold)
    failing = V[~ok]
    level = float(failing.min()) if failing.size else float(V.max())
    rates = {f"success_below_{k}x": float(ok[V < k * level].mean()) if np.any(V < k * level) else None
             for k in (1, 2, 4)}
    return {"level": level, "gate_scale": level / np.log(1 / system.gate.on), "n_samples": n_samples,
            "horizon": horizon, "seed": seed, "hold": hold, "success_rate": float(ok.mean()), **rates}
