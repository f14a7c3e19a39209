"""Hand-designed controllers: LQR and energy-shaping swing-ups, as numpy callables for Drake blocks.

Each is a plain callable ``numpy state (n,) -> numpy (k,)`` in the spec's state
convention, so it runs inside a Drake ``HeldController`` block or on its own; the swing-ups
also take batches (..., n) of numpy or torch states (the balance map's torch engine runs
them on every grid start at once). The
laws they share with the torch paths (LQR command, angle wrapping, saturation) and
the cost-to-go gate live in :mod:`hybridctl.systems.control`. The swing-ups pump the energy of the underactuated system towards the
upright energy through collocated partial feedback linearisation (PFL) of the
actuated coordinate (Spong 1995; Astrom & Furuta 2000).
"""

from __future__ import annotations

import numpy as np
import torch

from ..systems import System, control
from ..systems.switched import EnergySwingup, SwitchedController


class LQRController:
    """u = -K (x - goal), angles wrapped; K and S from ``system.lqr()`` unless given."""

    def __init__(self, system: System, K: np.ndarray | None = None):
        self.system = system
        self.K = system.lqr()[0] if K is None else np.atleast_2d(np.asarray(K, dtype=float))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return control.lqr_command(self.system.state_error(np.asarray(x, dtype=float)), self.K)


def _as_states(x):
    """Numpy float array or torch tensor, unchanged."""
    return x if isinstance(x, torch.Tensor) else np.asarray(x, dtype=float)


def _command(u):
    """Per-state scalar commands (...) -> (..., 1), numpy or torch."""
    return u.unsqueeze(-1) if isinstance(u, torch.Tensor) else np.asarray(u)[..., None]


def _cos(x):
    return torch.cos(x) if isinstance(x, torch.Tensor) else np.cos(x)


def _collocated_pfl(M: np.ndarray, b: np.ndarray, actuated: int, accel: float) -> float:
    """Input that gives the actuated coordinate of a 2-DoF system acceleration ``accel``.

    From M qdd + b = e_a u: the unactuated row fixes its acceleration, the actuated
    row then gives u.
    """
    p = 1 - actuated
    qdd_p = -(M[..., p, actuated] * accel + b[..., p]) / M[..., p, p]
    return M[..., actuated, actuated] * accel + M[..., actuated, p] * qdd_p + b[..., actuated]


class _SpecGains:
    """Gains given as arguments, or else read from the spec's ``[swingup]`` table (``system.swingup.gains``)."""

    GAINS: tuple[str, ...] = ("k_energy",)

    def __init__(self, system: System, **gains: float | None):
        self.system = system
        for name in self.GAINS:
            given = gains.get(name)
            if given is None and name not in system.swingup.gains:
                raise ValueError(f"{system.name}: the swing-up needs gain '{name}' ([swingup] in the spec)")
            setattr(self, name, float(system.swingup.gains[name] if given is None else given))


class AcrobotEnergySwingup(_SpecGains):
    """Passivity-based energy swing-up for the acrobot (Fantoni, Lozano & Spong 2000).

    tau = -k_e E~ dq2 - k_p q2 - k_d dq2 with E~ = E - E_goal. Since dE/dt = tau dq2,
    V = k_e E~^2 / 2 + k_p q2^2 / 2 decreases along solutions while the torque is
    not saturated, which drives the acrobot to the homoclinic orbit (E = E_goal,
    q2 = 0) that approaches the upright. Unlike Spong's (1995) collocated PFL law,
    its torque stays moderate, which matters with the thesis' heavy second link
    (I2 = 1.0) and 25 N m limit: there PFL saturates and never holds q2 near 0.
    """

    GAINS = ("k_energy", "k_p", "k_d")

    def __init__(self, system: System, k_energy: float | None = None, k_p: float | None = None,
                 k_d: float | None = None):
        if not _two_revolute_joints(system):
            raise ValueError(f"AcrobotEnergySwingup needs a fixed-base 2-link system, got {system.name}")
        super().__init__(system, k_energy=k_energy, k_p=k_p, k_d=k_d)
        self._goal_energy = float(system.energy(system.goal))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = _as_states(x)
        excess = self.system.energy(x) - self._goal_energy
        q2 = control.wrap_angle(x[..., 1])
        u = -self.k_energy * excess * x[..., 3] - self.k_p * q2 - self.k_d * x[..., 3]
        return control.saturate(_command(u), self.system.action_limit)


def _two_revolute_joints(system: System) -> bool:
    """A fixed-base chain of 2 links, or a multibody model of 2 revolute joints (the acrobot's shape)."""
    if system.chain is not None:
        return system.chain.n_q == 2 and not system.chain.has_cart
    return system.model.n_q == 2 and all(system.model.revolute)


class CartpoleEnergySwingup(_SpecGains):
    """Energy shaping of the pole through the cart (Astrom & Furuta 2000, underactuated ch. 3).

    Desired cart acceleration xdd = -k_e E~ dtheta cos(theta) - k_p x - k_d dx with
    E~ the pole's missing energy, realised by collocated PFL of the cart.
    """

    GAINS = ("k_energy", "k_p", "k_d")

    def __init__(self, system: System, k_energy: float | None = None, k_p: float | None = None,
                 k_d: float | None = None):
        if system.chain is None or system.chain.n_q != 2 or not system.chain.has_cart:
            raise ValueError(f"CartpoleEnergySwingup needs a single-pole cart system, got {system.name}")
        super().__init__(system, k_energy=k_energy, k_p=k_p, k_d=k_d)
        p = system.chain
        self._pole_inertia = p.link_inertia[0] + p.link_mass[0] * p.link_com[0] ** 2
        self._pole_moment = p.link_mass[0] * p.link_com[0] * p.gravity

    def pole_energy(self, x: np.ndarray) -> float:
        """Energy of the pole about its pivot, zero potential at the pivot height."""
        return 0.5 * self._pole_inertia * x[..., 3] ** 2 - self._pole_moment * _cos(x[..., 1])

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = _as_states(x)
        missing = self._pole_moment - self.pole_energy(x)
        # dE_pole/dt = -m lc xdd dtheta cos(theta): push the cart against that product.
        accel = -self.k_energy * missing * x[..., 3] * _cos(x[..., 1]) - self.k_p * x[..., 0] - self.k_d * x[..., 2]
        M, b = self.system.dynamics.manipulator(x[..., :2], x[..., 2:])
        u = _collocated_pfl(M, b, 0, accel)
        return control.saturate(_command(u), self.system.action_limit)


class PendulumEnergySwingup(_SpecGains):
    """u = k_e (E_goal - E) dtheta, saturated: pumps energy in the direction of motion."""

    def __init__(self, system: System, k_energy: float | None = None):
        super().__init__(system, k_energy=k_energy)
        self._goal_energy = float(system.energy(system.goal))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = _as_states(x)
        u = self.k_energy * (self._goal_energy - self.system.energy(x)) * x[..., 1]
        return control.saturate(_command(u), self.system.action_limit)


SWINGUPS = {
    "energy_acrobot": AcrobotEnergySwingup,
    "energy_cartpole": CartpoleEnergySwingup,
    "energy_pendulum": PendulumEnergySwingup,
}


def energy_swingup(system: System):
    """The spec's hand-designed swing-up (``[swingup] controller``) for ``system``."""
    name = system.swingup.controller
    if name is None:
        raise ValueError(f"{system.name} has no hand-designed swing-up ([swingup] in {system.spec.path}); "
                         f"systems with one: those whose spec sets swingup.controller to one of {sorted(SWINGUPS)}")
    return SWINGUPS[name](system)


def resolve_swingup(system: System, controller: SwitchedController) -> SwitchedController:
    """``controller`` with an :class:`~hybridctl.systems.switched.EnergySwingup` that holds its law (the spec's
    :func:`energy_swingup`, which takes numpy and torch batches), as the torch rollout
    (:func:`hybridctl.systems.closed_loop_rollout`) needs it; any other controller as it is."""
    if isinstance(controller.swingup, EnergySwingup) and controller.swingup.law is None:
        return controller.replace(swingup=EnergySwingup(law=energy_swingup(system)))
    return controller
