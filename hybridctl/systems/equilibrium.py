"""The equilibrium a goal balances at: :func:`nearest_equilibrium`.

The LQR linearises about the goal, so the goal must be an equilibrium with u = 0 (Drake's
``xdot`` below :data:`EQUILIBRIUM_XDOT`). A goal written to a few digits (an MJCF file's
``-3.1416``, a ``3.14159``) misses the exact one by 1e-5: such a goal, within
:data:`GOAL_TOLERANCE` of an equilibrium, is moved there when the system is built, with one
warning naming the old and the new goal and the distance. A goal farther from every
equilibrium is kept as written and the LQR refuses it in one line.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["nearest_equilibrium", "equilibrium_residual", "EquilibriumError", "GOAL_TOLERANCE", "EQUILIBRIUM_XDOT"]

EQUILIBRIUM_XDOT = 1e-8
"""The largest |xdot| (Drake's plant, u = 0) at a state that counts as an equilibrium (``System.lqr``'s test)."""
GOAL_TOLERANCE = 1e-2
"""How far (max-norm over the state, rad / m / rad/s / m/s) a goal may be moved to the nearest
equilibrium: more than a rounded pi (3.1416 is 7e-6 off, 3.14 is 1.6e-3 off), less than any
physical offset a goal might mean."""


class EquilibriumError(ValueError):
    """No equilibrium within the tolerance of the given state (one line)."""


def equilibrium_residual(system, x) -> np.ndarray:
    """xdot at state ``x`` with u = 0 from ``system``'s generated (or chain) dynamics, float64."""
    # on the CPU whatever torch's default device (systems are built inside a training's device scope)
    x = torch.as_tensor(np.asarray(x, dtype=float), dtype=torch.float64, device="cpu").reshape(1, -1)
    u = torch.zeros(1, system.n_actions, dtype=torch.float64, device="cpu")
    return system.dynamics.derivatives(x, u)[0].numpy()


def _drake_residual(system, x: np.ndarray) -> np.ndarray:
    plant = system.drake_plant()
    context = system.drake_context(plant)
    return system.drake_derivatives(plant, context, x, np.zeros(system.n_actions))


def nearest_equilibrium(system, x, *, tolerance: float = GOAL_TOLERANCE, check_drake: bool = True):
    """The equilibrium (u = 0) of ``system`` (a :class:`~hybridctl.systems.System`) nearest to state ``x``:
    ``(x_eq, distance)``; :func:`hybridctl.systems.nearest_equilibrium` also takes a name or model file.
    Solves qdd(q, v = 0, u = 0) = 0 from the given q by Levenberg-Marquardt
    (``scipy.optimize.root``, which also copes with coordinates the dynamics do not depend on, as a
    reaction wheel's angle) on the system's generated dynamics, with the velocities set to 0; then
    checks the result on Drake's plant (``check_drake``). ``distance`` is the max-norm of the move.
    Raises :class:`EquilibriumError` (one line) where no equilibrium lies within ``tolerance``.
    """
    x = np.asarray(x, dtype=float).reshape(-1)
    if x.shape != (system.n_states,) or not np.all(np.isfinite(x)):
        raise EquilibriumError(f"{system.name}: x must be {system.n_states} finite numbers, got {x.tolist()}")
    if not tolerance > 0:
        raise EquilibriumError(f"tolerance must be > 0, got {tolerance}")
    n_q = system.n_states // 2
    if np.abs(equilibrium_residual(system, x)).max() <= EQUILIBRIUM_XDOT:
        return x.copy(), 0.0
    from scipy.optimize import root

    def qdd(q):
        return equilibrium_residual(system, np.concatenate([q, np.zeros(n_q)]))[n_q:]

    solution = root(qdd, x[:n_q], method="lm", options={"xtol": 1e-15, "ftol": 1e-15, "maxiter": 200})
    found = np.concatenate([solution.x, np.zeros(n_q)])
    distance = float(np.abs(found - x).max())
    worst = float(np.abs(equilibrium_residual(system, found)).max())
    if not np.all(np.isfinite(found)) or worst > EQUILIBRIUM_XDOT or distance > tolerance:
        raise EquilibriumError(f"{system.name}: {_show(x)} is not an equilibrium with u = 0 (max |xdot| "
                               f"{np.abs(equilibrium_residual(system, x)).max():.3g}) and none lies within "
                               f"{tolerance:g} of it" + (f" (the nearest found: {_show(found)}, {distance:.3g} away)"
                                                         if worst <= EQUILIBRIUM_XDOT else ""))
    if check_drake:
        drake = float(np.abs(_drake_residual(system, found)).max())
        if drake > EQUILIBRIUM_XDOT:
            raise EquilibriumError(f"{system.name}: the equilibrium {_show(found)} of the generated dynamics is not "
                                   f"one of Drake's plant (max |xdot| {drake:.3g})")
    return found, distance


def _show(x: np.ndarray) -> str:
    return "[" + ", ".join(f"{v:.10g}" for v in x) + "]"


def settle_goal(system) -> np.ndarray:
    """The goal ``System`` uses: the spec's, or the nearest equilibrium within :data:`GOAL_TOLERANCE`
    (with one warning, once per process) where the spec's is one only to a few digits. A goal that is
    no equilibrium and near none is kept: ``System.lqr`` refuses it in one line."""
    import multiprocessing
    import warnings

    goal = system.goal
    try:
        if np.abs(equilibrium_residual(system, goal)).max() <= EQUILIBRIUM_XDOT:
            return goal
        found, distance = nearest_equilibrium(system, goal)
    except (EquilibriumError, ValueError, RuntimeError):
        return goal
    if multiprocessing.parent_process() is None:
        warnings.warn(f"{system.name}: the goal {_show(goal)} is an equilibrium only to "
                      f"{np.abs(equilibrium_residual(system, goal)).max():.2g}; moved {distance:.2g} to the nearest "
                      f"equilibrium {_show(found)}", UserWarning, stacklevel=4)
    return found
