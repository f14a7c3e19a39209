"""Rewards as objects: one class per spec ``reward.kind``, chosen once when a System is built.

:func:`reward_for` gives a system its :class:`Reward` (``System.reward_function``);
``System.reward(x)`` calls it on states (numpy or torch, batched) and ``System.reward_single(x)``
on one state of plain floats. A reward reads its settings (the spec's optional ``reward.*`` keys)
when it is made and the system's state error, dynamics and LQR when it is called.

* :class:`TipHeight` -- thesis eq. 3.1;
* :class:`Quadratic` -- the author's SSAC script: -0.1 * |x - goal|^2 over positions;
* :class:`TipHeightCentered`, :class:`UprightCentered` -- hybridctl's for systems on a cart;
* :class:`Chapter7Reward` -- the thesis' Ch. 7 kinds ``angle_squared``, ``angle_cosine``, ``tip_distance``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from . import control
from .spec import CH7_REWARD_KINDS

System = Any
"""A :class:`hybridctl.systems.System` (not imported: it imports this module, and an import back, even
under ``TYPE_CHECKING``, would make the two a cycle)."""

__all__ = ["Reward", "TipHeight", "Quadratic", "TipHeightCentered", "UprightCentered", "Chapter7Reward",
           "REWARDS", "reward_for"]


class Reward:
    """The per-decision reward of one system's states, for numpy or torch arrays (batched)."""

    kind = ""
    """The spec's ``reward.kind`` this class computes."""

    def __init__(self, system: System):
        self.system = system

    def __call__(self, x):
        """The reward of states ``x`` (..., n)."""
        raise NotImplementedError

    def single(self, x) -> float:
        """The reward of one state given as a sequence of floats, as a float (through the numpy path)."""
        return float(self(np.asarray(x, dtype=float)))

    def _position_errors(self, x):
        """``state_error`` of the positions (the first half of the state)."""
        return self.system.state_error(x)[..., : self.system.n_states // 2]

    def _linear_positions(self) -> list[int]:
        """The positions that are not angles (a cart's x)."""
        system = self.system
        return [i for i in range(system.n_states // 2) if i not in system.angle_indices]


class TipHeight(Reward):
    """Thesis eq. 3.1: the height of the chain's tip."""

    kind = "tip_height"

    def __call__(self, x):
        return self.system.dynamics.tip_height(x)

    def single(self, x) -> float:
        """Evaluated on Python floats (``ChainDynamics.tip_height_single``)."""
        return self.system.dynamics.tip_height_single(x)


class Quadratic(Reward):
    """The author's SSAC script: -0.1 * |x - goal|^2 over positions."""

    kind = "quadratic"

    def __call__(self, x):
        err = self._position_errors(x)
        return -0.1 * (err * err).sum(-1)


class TipHeightCentered(Reward):
    """``tip_height_centered`` (hybridctl): tip height - 0.1 * |error|^2 over the positions that are not
    angles (a cart's position). On a cart-pole, tip height alone pays as much for a pole held up over a cart
    driving away as over one at the goal. It equals tip height on systems whose positions are all angles
    (acrobot, pendulum)."""

    kind = "tip_height_centered"

    def __call__(self, x):
        err = self._position_errors(x)
        linear = self._linear_positions()
        if not linear:
            return self.system.dynamics.tip_height(x)
        return self.system.dynamics.tip_height(x) - 0.1 * (err[..., linear] ** 2).sum(-1)


class UprightCentered(Reward):
    """``upright_centered`` (hybridctl): upright * exp(-|p|^2 / (2 s_p^2) - |v|^2 / (2 s_v^2)).

    upright = (1 + h / L) / 2 in [0, 1] (h the tip height above the base pivot, L the
    chain's length: 1 only with every link up); p the non-angle positions (a cart's x,
    measured from the goal) and v their velocities; s_p = ``reward.position_scale``,
    s_v = ``reward.speed_scale``. A product, as the DeepMind Control Suite's cart-pole
    swing-up reward (Tassa et al. 2018): a pole held up over a cart that drives away
    earns little, and every reward is >= 0. On systems without a cart it is the
    upright term alone (an affine map of the tip height).
    """

    kind = "upright_centered"

    def __init__(self, system: System):
        super().__init__(system)
        self.position_scale = system.reward_position_scale
        self.speed_scale = system.reward_speed_scale

    def __call__(self, x):
        system = self.system
        total_length = float(np.sum(system.chain.link_length))
        upright = 0.5 * (1.0 + system.dynamics.tip_height(x) / total_length)
        half = system.n_states // 2
        linear = self._linear_positions()
        if not linear:
            return upright
        position = system.state_error(x)[..., linear]
        speed = x[..., [half + i for i in linear]]
        exponent = (position * position).sum(-1) / (2.0 * self.position_scale ** 2) \
            + (speed * speed).sum(-1) / (2.0 * self.speed_scale ** 2)
        return upright * (torch.exp(-exponent) if isinstance(exponent, torch.Tensor) else np.exp(-exponent))


class Chapter7Reward(Reward):
    """The thesis' Ch. 7 rewards (analytic policy gradients), from the spec's ``reward.kind``.

    Angles phi are ``state_error``'s (wrapped, measured from upright; relative joint
    angles as the state holds them); dphi their velocities; p the non-angle positions
    (a cart's x) and dp their velocities. With b = ``reward.alive_bonus``,
    c = ``reward.velocity_penalty``, w = ``reward.position_weight``,
    v = ``reward.linear_velocity_weight``, k = ``reward.cost_to_go_weight`` (all 0 unless set):

    * ``angle_squared``: b - sum phi^2 - w sum p^2 - v sum dp^2 - c sum dphi^2 - k log(1 + e' S e / s).
      With b = c = w = v = k = 0 it is the thesis' acrobot -phi1^2 - phi2^2 (Sec. 7.2.3) and cart-pole -phi^2
      (Sec. 7.2.4); the author's acrobot is b = 10, c = 0.01, his double cart-pole
      b = 10, w = 1, c = 0.01 (implementation notes Ch. 7). -phi^2 jumps at phi = +-pi.
    * ``angle_cosine``: the smooth option, 2 (1 - cos phi) in place of phi^2 (equal to
      second order at upright, no jump at +-pi).
    * ``tip_distance``: thesis eqs. 7.5-7.7: b - (0.05 x_tip^2 + (y_tip - y_des)^2) -
      c sum dphi^2 (- k log(1 + e' S e / s)), the distal tip's position (x_tip: horizontal, with the cart;
      y_tip: height above the pivot; y_des: its upright height). Eq. 7.6's alive bonus
      is b = 10; eq. 7.8 prints the velocity term as the signed sum dphi1 + dphi2, which
      pays for spinning one way, so the squared form (weight c) is used instead.

    v and k are hybridctl's (the thesis and the author penalise only angle rates); v applies
    to the angle kinds, k to all three. A swing-up handed to the LQR by the cost-to-go gate
    must bring the cart to rest: a cart drifting at 1 m/s is, for the double cart-pole's
    gate, a cost-to-go above its switch-on level by itself. k subtracts
    k log(1 + e' S e / s), S the spec's LQR cost-to-go matrix and s = ``gate.cost_scale``:
    the gate's own measure, flat (log) far from the goal, so it pulls a state that is
    nearly up into the gate's region, cart position and speed weighed as the LQR weighs them.

    Our systems keep their own parameters (the thesis' Brax models differ), so returns
    are not comparable number for number with the thesis' tables.
    """

    def __init__(self, system: System, kind: str):
        super().__init__(system)
        if kind not in CH7_REWARD_KINDS:
            raise ValueError(f"a Ch. 7 reward kind is one of {CH7_REWARD_KINDS}, got {kind!r}")
        self.kind = kind
        self.alive_bonus = system.reward_alive_bonus
        self.velocity_penalty = system.reward_velocity_penalty
        self.position_weight = system.reward_position_weight
        self.linear_velocity_weight = system.reward_linear_velocity_weight
        self.cost_to_go_weight = system.reward_cost_to_go_weight
        self._S: dict = {}   # (dtype, device) -> the LQR's S as a tensor, for reward.cost_to_go_weight

    def __call__(self, x):
        system = self.system
        n_q = system.n_states // 2
        err = system.state_error(x)
        angles = list(system.angle_indices)
        linear = [i for i in range(n_q) if i not in angles]
        phi, dphi = err[..., angles], err[..., [n_q + i for i in angles]]
        penalty = self.velocity_penalty * (dphi * dphi).sum(-1)
        if self.cost_to_go_weight:
            penalty = penalty + self.cost_to_go_weight * self.log_cost_to_go(err)
        if self.kind == "tip_distance":
            x_tip, y_tip = system.dynamics.tip_position(x)
            distance = 0.05 * x_tip * x_tip + (y_tip - float(system.chain.link_length.sum())) ** 2
            return self.alive_bonus - distance - penalty
        if self.kind == "angle_cosine":
            cost = (2.0 * (1.0 - (phi.cos() if isinstance(phi, torch.Tensor) else np.cos(phi)))).sum(-1)
        else:
            cost = (phi * phi).sum(-1)
        if linear:
            p = err[..., linear]
            cost = cost + self.position_weight * (p * p).sum(-1)
            if self.linear_velocity_weight:   # off by default: no gather on the rollouts' hot path
                dp = err[..., [n_q + i for i in linear]]
                cost = cost + self.linear_velocity_weight * (dp * dp).sum(-1)
        return self.alive_bonus - cost - penalty

    def log_cost_to_go(self, err):
        """log(1 + e' S e / gate.cost_scale) of state errors ``err`` (numpy or torch), S the spec's LQR's."""
        system = self.system
        scale = system.gate.cost_scale
        if not isinstance(err, torch.Tensor):
            return np.log1p(control.cost_to_go(err, system.lqr()[1]) / scale)
        key = (err.dtype, err.device)
        if key not in self._S:
            self._S[key] = torch.as_tensor(system.lqr()[1], dtype=err.dtype, device=err.device)
        return torch.log1p(control.cost_to_go(err, self._S[key]) / scale)


REWARDS = {cls.kind: cls for cls in (TipHeight, Quadratic, TipHeightCentered, UprightCentered)}
"""The reward class of each non-Ch. 7 ``reward.kind`` (the Ch. 7 kinds: :class:`Chapter7Reward`)."""


def reward_for(system: System) -> Reward:
    """The :class:`Reward` of ``system``'s ``reward.kind`` (a spec's kind is checked when it is read)."""
    kind = system.reward_kind
    if kind in CH7_REWARD_KINDS:
        return Chapter7Reward(system, kind)
    return REWARDS[kind](system)
