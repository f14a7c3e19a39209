"""Hand-designed controllers: LQR, energy-shaping swing-ups and a cost-to-go gate.

Each is a plain callable ``numpy state (n,) -> numpy (k,)`` in the spec's state
convention, so it runs inside a Drake ``HeldController``/``Gate`` block or on its
own. The swing-ups pump the energy of the underactuated system towards the
upright energy through collocated partial feedback linearisation (PFL) of the
actuated coordinate (Spong 1995; Astrom & Furuta 2000).
"""

from __future__ import annotations

import numpy as np
import torch

from ..analysis.balance import lqr_rollouts_balanced
from ..systems import System


class LQRController:
    """u = -K (x - goal), angles wrapped; K and S from ``system.lqr()`` unless given."""

    def __init__(self, system: System, K: np.ndarray | None = None):
        self.system = system
        self.K = system.lqr()[0] if K is None else np.atleast_2d(np.asarray(K, dtype=float))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return -self.K @ self.system.state_error(np.asarray(x, dtype=float))


class CostToGoGate(torch.nn.Module):
    """Gate probability from the LQR cost-to-go: p = exp(-(x - goal)' S (x - goal) / scale).

    With the thesis hysteresis (on 0.9, off 0.5) the LQR takes over once the
    cost-to-go drops below 0.105 * scale and hands back above 0.69 * scale.
    Works on numpy single states (the Drake ``Gate``) and torch batches.
    """

    def __init__(self, system: System, scale: float | None = None, S: np.ndarray | None = None):
        super().__init__()
        self.system = system
        self.scale = float(system.spec.get("gate.cost_scale") if scale is None else scale)
        if not self.scale > 0:
            raise ValueError(f"scale must be > 0, got {self.scale}")
        S = system.lqr()[1] if S is None else np.asarray(S, dtype=float)
        self.register_buffer("S", torch.as_tensor(S, dtype=torch.float64))
        self._S_np = np.asarray(S, dtype=float)

    def cost_to_go(self, x):
        """(x - goal)' S (x - goal), numpy or torch, batched over leading dims."""
        err = self.system.state_error(x if isinstance(x, torch.Tensor) else np.asarray(x, dtype=float))
        S = self.S.to(err.dtype) if isinstance(err, torch.Tensor) else self._S_np
        return ((err @ S) * err).sum(-1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Probability that the LQR can take over, in (0, 1]; shape (..., 1)."""
        return torch.exp(-self.cost_to_go(x) / self.scale).unsqueeze(-1)

    def numpy_forward(self, x: np.ndarray) -> np.ndarray:
        """The same probability for numpy states, shape (..., 1) (used by the Drake ``Gate``)."""
        return np.exp(-np.asarray(self.cost_to_go(x)) / self.scale)[..., None]

    def __call__(self, x):
        if isinstance(x, torch.Tensor):
            return super().__call__(x)
        return self.numpy_forward(x)


def _collocated_pfl(M: np.ndarray, b: np.ndarray, actuated: int, accel: float) -> float:
    """Input that gives the actuated coordinate of a 2-DoF system acceleration ``accel``.

    From M qdd + b = e_a u: the unactuated row fixes its acceleration, the actuated
    row then gives u.
    """
    p = 1 - actuated
    qdd_p = -(M[p, actuated] * accel + b[p]) / M[p, p]
    return M[actuated, actuated] * accel + M[actuated, p] * qdd_p + b[actuated]


class _SpecGains:
    """Gains given as arguments, or else read from the spec's ``[swingup]`` table."""

    GAINS: tuple[str, ...] = ("k_energy",)

    def __init__(self, system: System, **gains: float | None):
        self.system = system
        for name in self.GAINS:
            given = gains.get(name)
            setattr(self, name, float(system.spec.get(f"swingup.{name}") if given is None else given))


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
        if system.chain.n_q != 2 or system.chain.has_cart:
            raise ValueError(f"AcrobotEnergySwingup needs a fixed-base 2-link system, got {system.name}")
        super().__init__(system, k_energy=k_energy, k_p=k_p, k_d=k_d)
        self._goal_energy = float(system.energy(system.goal))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        excess = float(self.system.energy(x)) - self._goal_energy
        q2 = (x[1] + np.pi) % (2 * np.pi) - np.pi
        u = -self.k_energy * excess * x[3] - self.k_p * q2 - self.k_d * x[3]
        return np.clip([u], -self.system.action_limit, self.system.action_limit)


class CartpoleEnergySwingup(_SpecGains):
    """Energy shaping of the pole through the cart (Astrom & Furuta 2000, underactuated ch. 3).

    Desired cart acceleration xdd = -k_e E~ dtheta cos(theta) - k_p x - k_d dx with
    E~ the pole's missing energy, realised by collocated PFL of the cart.
    """

    GAINS = ("k_energy", "k_p", "k_d")

    def __init__(self, system: System, k_energy: float | None = None, k_p: float | None = None,
                 k_d: float | None = None):
        if system.chain.n_q != 2 or not system.chain.has_cart:
            raise ValueError(f"CartpoleEnergySwingup needs a single-pole cart system, got {system.name}")
        super().__init__(system, k_energy=k_energy, k_p=k_p, k_d=k_d)
        p = system.chain
        self._pole_inertia = p.link_inertia[0] + p.link_mass[0] * p.link_com[0] ** 2
        self._pole_moment = p.link_mass[0] * p.link_com[0] * p.gravity

    def pole_energy(self, x: np.ndarray) -> float:
        """Energy of the pole about its pivot, zero potential at the pivot height."""
        return 0.5 * self._pole_inertia * x[3] ** 2 - self._pole_moment * np.cos(x[1])

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        missing = self._pole_moment - self.pole_energy(x)
        # dE_pole/dt = -m lc xdd dtheta cos(theta): push the cart against that product.
        accel = -self.k_energy * missing * x[3] * np.cos(x[1]) - self.k_p * x[0] - self.k_d * x[2]
        M, b = self.system.dynamics.manipulator(x[:2], x[2:])
        u = _collocated_pfl(M, b, 0, accel)
        return np.clip([u], -self.system.action_limit, self.system.action_limit)


class PendulumEnergySwingup(_SpecGains):
    """u = k_e (E_goal - E) dtheta, saturated: pumps energy in the direction of motion."""

    def __init__(self, system: System, k_energy: float | None = None):
        super().__init__(system, k_energy=k_energy)
        self._goal_energy = float(system.energy(system.goal))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        u = self.k_energy * (self._goal_energy - float(self.system.energy(x))) * x[1]
        return np.clip([u], -self.system.action_limit, self.system.action_limit)


SWINGUPS = {
    "energy_acrobot": AcrobotEnergySwingup,
    "energy_cartpole": CartpoleEnergySwingup,
    "energy_pendulum": PendulumEnergySwingup,
}


def energy_swingup(system: System):
    """The spec's hand-designed swing-up (``[swingup] controller``) for ``system``."""
    name = system.spec.get("swingup.controller", None)
    if name is None:
        raise ValueError(f"{system.name} has no hand-designed swing-up ([swingup] in {system.spec.path}); "
                         f"systems with one: those whose spec sets swingup.controller to one of {sorted(SWINGUPS)}")
    return SWINGUPS[name](system)


def lqr_basin_level(system: System, n_samples: int = 20000, horizon: float = 2.5,
                    spread: np.ndarray | None = None, seed: int = 0, K: np.ndarray | None = None,
                    S: np.ndarray | None = None) -> dict:
    """Estimate the cost-to-go level V* below which the saturated LQR balances.

    Samples states goal + U(-spread, spread), runs the LQR (acting every ``dt``,
    saturated at the action limit) for ``horizon`` seconds in batched torch, marks
    each rollout with the thesis success test on its last ``lookback`` steps, and
    returns V* = the smallest cost-to-go (x - goal)' S (x - goal) among failing
    samples, with the success rate below V*, 2 V* and 4 V*. A gate that switches
    on below V* (``CostToGoGate`` with scale V* / ln(1/0.9)) only hands over states
    from which every sampled LQR rollout balanced.
    """
    if n_samples < 10:
        raise ValueError(f"n_samples must be >= 10, got {n_samples}")
    K = system.lqr()[0] if K is None else np.atleast_2d(K)
    S = system.lqr()[1] if S is None else np.asarray(S)
    spread = np.ones(system.n_states) if spread is None else np.asarray(spread, dtype=float)
    rng = np.random.default_rng(seed)
    x0 = system.goal + rng.uniform(-1, 1, size=(n_samples, system.n_states)) * spread
    err = system.state_error(x0)
    V = np.einsum("ni,ij,nj->n", err, S, err)
    ok = lqr_rollouts_balanced(system, x0, horizon, K=K)
    failing = V[~ok]
    level = float(failing.min()) if failing.size else float(V.max())
    rates = {f"success_below_{k}x": float(ok[V < k * level].mean()) if np.any(V < k * level) else None
             for k in (1, 2, 4)}
    return {"level": level, "gate_scale": level / np.log(1 / 0.9), "n_samples": n_samples,
            "horizon": horizon, "seed": seed, "success_rate": float(ok.mean()), **rates}
