"""The switched controller of the thesis (Fig. 3.1) as one typed object, and its one batched rollout.

:class:`SwitchedController` holds what the controller is made of: a swing-up (a learned torch
module, a recurrent one with ``initial_state``, a batch callable, or a marker for a hand-designed
law: :class:`EnergySwingup`, :class:`ZeroSwingup`, :class:`TrajoptSwingup`), a :class:`Gate`
(:class:`LearnedGate`, :class:`CostToGoGate`, :class:`AlwaysGate`, :class:`NeverGate`: classes,
not strings), the LQR gain ``K`` and ``goal``, the swing-up's ``decision_period`` (its hold), the
hysteresis thresholds ``gate_on`` / ``gate_off`` and the gate's ``gate_period``.

:func:`closed_loop_rollout` runs it in batched torch, with the divergence policy an explicit
argument; :func:`switched_decision` is one decision of it (a pure function of tensors, so
``torch.compile`` can fuse it), the decision of :class:`hybridctl.envs.SwitchedVectorEnv` and of the APG
family's population rollout (``hybridctl.learn.apg.LQRTakeover``) too; :func:`gate_command`, one gate
evaluation (gate, hysteresis, LQR, saturation), is the one place that sequence is written.
``hybridctl.drake.build_hybrid_diagram(system, controller)`` builds the same controller as a
Drake diagram. Every law comes from :mod:`.control`.

>>> from hybridctl import systems, SwitchedController
>>> from hybridctl.systems.switched import CostToGoGate, EnergySwingup
>>> acrobot = systems.load("acrobot")
>>> controller = SwitchedController.for_system(acrobot, swingup=EnergySwingup(), gate=CostToGoGate(acrobot))
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np
import torch

from . import control

System = Any
"""A :class:`hybridctl.systems.System` (not imported: the package imports this module)."""

__all__ = ["Gate", "LearnedGate", "CostToGoGate", "ConstantGate", "AlwaysGate", "NeverGate", "as_gate",
           "EnergySwingup", "ZeroSwingup", "TrajoptSwingup", "SwitchedController", "gate_command", "switched_decision",
           "closed_loop_rollout", "Rollout", "DIVERGENCE_POLICIES"]


# ---------------------------------------------------------------------------------------------- gates
class Gate(torch.nn.Module):
    """A gate: states -> the probability that the LQR can take over.

    ``probability(x)`` on a torch batch (B, n) gives (B, 1) on ``x``'s device; ``numpy_probability``
    the same for numpy states (..., n) -> (..., 1) (what the Drake ``Gate`` block calls, through
    ``numpy_forward``). Calling a gate dispatches on the input's type (a torch input goes to ``forward``
    as it is, in the caller's dtype: :func:`switched_decision` casts to :attr:`compute_dtype`). A gate is a torch module, so
    ``.to(device)`` moves what it holds; ``compute_dtype`` is the dtype it computes in (its first
    parameter's; None: its input's).
    """

    def probability(self, x: torch.Tensor) -> torch.Tensor:
        """(B, n) -> (B, 1) in ``x``'s dtype (computed in :attr:`compute_dtype`), without autograd."""
        dtype = self.compute_dtype or x.dtype
        with torch.no_grad():
            return self(x.to(dtype)).reshape(*x.shape[:-1], 1).to(x.dtype)

    def numpy_probability(self, x) -> np.ndarray:  # pragma: no cover - every gate below overrides it
        raise NotImplementedError

    def numpy_forward(self, x) -> np.ndarray:
        return self.numpy_probability(x)

    @property
    def compute_dtype(self) -> torch.dtype | None:
        for tensor in self.parameters():
            return tensor.dtype
        return None

    def __call__(self, x):
        if isinstance(x, torch.Tensor):
            return super().__call__(x)
        return self.numpy_probability(x)


class LearnedGate(Gate):
    """A learned classifier as a gate, e.g. SSAC's ``hybridctl.learn.GateNet`` (held, not copied: a refit
    in place is seen at once). ``module``: a torch module (B, n) -> (B, 1), or a torch callable."""

    def __init__(self, module):
        super().__init__()
        if isinstance(module, Gate) or not callable(module):
            raise TypeError(f"LearnedGate needs a torch classifier module or callable, got {type(module).__name__}")
        self.module = module

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.module(x)

    def numpy_probability(self, x) -> np.ndarray:
        if hasattr(self.module, "numpy_forward"):
            return np.asarray(self.module.numpy_forward(x), dtype=float)
        x = np.asarray(x, dtype=float)
        dtype = self.compute_dtype or torch.float64
        with torch.no_grad():
            out = self.module(torch.as_tensor(x, dtype=dtype).reshape(-1, x.shape[-1]))
        return out.double().cpu().numpy().reshape(*x.shape[:-1], 1)


class CostToGoGate(control.CostToGoGate, Gate):
    """The hand-designed gate p = exp(-(x - goal)' S (x - goal) / scale): :class:`hybridctl.systems.control.
    CostToGoGate` (the one formula) as a :class:`Gate`. ``scale`` None: the spec's ``gate.cost_scale``;
    ``S`` None: the LQR's cost-to-go matrix."""

    def __init__(self, system: System, scale: float | None = None, S: np.ndarray | None = None):
        control.CostToGoGate.__init__(self, system, scale=scale, S=S)

    @classmethod
    def of(cls, law: control.CostToGoGate, system: System | None = None) -> "CostToGoGate":
        """The typed gate of a :class:`hybridctl.systems.control.CostToGoGate` (same scale and S), on ``system``
        (None: the law's; another object of the same plant, e.g. a worker's own, with which
        :func:`gate_command` shares the state error of the LQR)."""
        system = law.system if system is None else system
        return law if isinstance(law, cls) and system is law.system else cls(system, scale=law.scale, S=law._S_np)

    def numpy_probability(self, x) -> np.ndarray:
        return control.CostToGoGate.numpy_forward(self, x)

    def numpy_forward(self, x) -> np.ndarray:
        return control.CostToGoGate.numpy_forward(self, x)

    def __call__(self, x):
        return Gate.__call__(self, x)


class ConstantGate(Gate):
    """The same probability ``value`` for every state."""

    value = 0.0

    def __init__(self, value: float | None = None):
        super().__init__()
        if value is not None:
            self.value = float(value)
        if not 0.0 <= self.value <= 1.0:
            raise ValueError(f"a constant gate's value must be in [0, 1], got {self.value}")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.full((*x.shape[:-1], 1), self.value, dtype=x.dtype, device=x.device)

    def numpy_probability(self, x) -> np.ndarray:
        return np.full((*np.shape(x)[:-1], 1), self.value)

    def extra_repr(self) -> str:
        return f"value={self.value}"


class AlwaysGate(ConstantGate):
    """The LQR always (p = 1): the LQR alone, from the first gate evaluation on."""

    value = 1.0

    def __init__(self):
        super().__init__()


class NeverGate(ConstantGate):
    """The LQR never (p = 0): the swing-up alone."""

    value = 0.0

    def __init__(self):
        super().__init__()


def as_gate(gate, system: "System | None" = None) -> Gate:
    """``gate`` as a :class:`Gate`: a Gate as it is; a :class:`hybridctl.systems.control.CostToGoGate` as a
    :class:`CostToGoGate`; None as the spec's cost-to-go gate (needs ``system``); another torch module or
    callable as a :class:`LearnedGate`."""
    if isinstance(gate, Gate):
        return gate
    if isinstance(gate, control.CostToGoGate):
        return CostToGoGate.of(gate)
    if gate is None:
        if system is None:
            raise ValueError("gate None means the spec's cost-to-go gate: give the system")
        return CostToGoGate(system)
    if isinstance(gate, str) or not callable(gate):
        raise TypeError(f"gate must be a Gate (LearnedGate, CostToGoGate, AlwaysGate, NeverGate), a torch module "
                        f"or callable, got {gate!r}")
    return LearnedGate(gate)


# ------------------------------------------------------------------------------------------ swing-ups
@dataclass(frozen=True)
class EnergySwingup:
    """The spec's energy-shaping swing-up (``[swingup]``; :func:`hybridctl.drake.energy_swingup`). It lives
    in the drake room: ``law`` is its batch callable once resolved (``hybridctl.drake.resolve_swingup``),
    which the torch rollout needs; Drake builds its own block."""

    law: Callable | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class ZeroSwingup:
    """No swing-up input (u = 0): with :class:`AlwaysGate` the LQR alone, with :class:`NeverGate` the passive
    dynamics."""


@dataclass(frozen=True)
class TrajoptSwingup:
    """The direct-collocation swing-up tracked by TVLQR (:mod:`hybridctl.drake.trajopt`): it reads the time,
    so it runs in Drake only."""


HAND_DESIGNED = (EnergySwingup, ZeroSwingup, TrajoptSwingup)


def is_recurrent(swingup) -> bool:
    """A recurrent swing-up (APG's GRU): a torch module with ``initial_state``."""
    return isinstance(swingup, torch.nn.Module) and hasattr(swingup, "initial_state")


def _finite_array(name: str, value, ndim: int) -> np.ndarray:
    array = np.array(value, dtype=float, ndmin=ndim)
    if array.ndim != ndim or array.size == 0:
        raise ValueError(f"{name} must be a {ndim}-D array, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} contains NaN or Inf")
    return array


def _positive(name: str, value) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {value}")
    return value


# ------------------------------------------------------------------------------------- the controller
@dataclass
class SwitchedController:
    """The switched controller (thesis Fig. 3.1): swing-up, gate with hysteresis, LQR.

    Fields:
        swingup: a torch module (states (B, n) -> actions (B, m); a recurrent one has ``initial_state``
            and maps (x, h) -> (u, h)), a batch callable, a marker (:class:`EnergySwingup`,
            :class:`ZeroSwingup`, :class:`TrajoptSwingup`), or None: actions given from outside (the
            switched env's agent).
        gate: a :class:`Gate`.
        K: the LQR gain (m, n). goal: the state the LQR drives to (n,).
        decision_period: the swing-up's hold (s). gate_period: how often the gate classifies the state
            and the LQR acts (s).
        gate_on, gate_off: the hysteresis (0 < gate_off < gate_on < 1): the LQR takes over above
            ``gate_on`` and hands back below ``gate_off``.

    :meth:`for_system` fills every default from a system's spec.
    """

    swingup: Any
    gate: Gate
    K: np.ndarray
    goal: np.ndarray
    decision_period: float
    gate_on: float
    gate_off: float
    gate_period: float

    def __post_init__(self):
        if not isinstance(self.gate, Gate):
            raise TypeError(f"gate must be a Gate (LearnedGate, CostToGoGate, AlwaysGate, NeverGate), got "
                            f"{type(self.gate).__name__}; hybridctl.systems.switched.as_gate converts a module")
        if not (self.swingup is None or isinstance(self.swingup, HAND_DESIGNED) or callable(self.swingup)):
            raise TypeError(f"swingup must be a torch module, a callable, EnergySwingup, ZeroSwingup, TrajoptSwingup "
                            f"or None, got {type(self.swingup).__name__}")
        self.K = _finite_array("K", self.K, 2)
        self.goal = _finite_array("goal", self.goal, 1)
        if self.K.shape[1] != self.goal.shape[0]:
            raise ValueError(f"K has shape {self.K.shape}: it needs {self.goal.shape[0]} columns, one per state")
        self.decision_period = _positive("decision_period", self.decision_period)
        self.gate_period = _positive("gate_period", self.gate_period)
        self.gate_on, self.gate_off = float(self.gate_on), float(self.gate_off)
        if not 0.0 < self.gate_off < self.gate_on < 1.0:
            raise ValueError(f"gate_on / gate_off need 0 < gate_off < gate_on < 1, got gate_off={self.gate_off}, "
                             f"gate_on={self.gate_on}")

    @classmethod
    def for_system(cls, system: System, swingup: Any = None, gate: Any = None, **overrides) -> "SwitchedController":
        """The controller on ``system`` with the spec's defaults: ``swingup`` None is the spec's
        :class:`EnergySwingup`; ``gate`` None the spec's :class:`CostToGoGate` (a module becomes a
        :class:`LearnedGate`); ``K`` the LQR gain of ``system.lqr()``; ``goal`` the spec's;
        ``decision_period`` the spec's ``swingup_period`` for a learned swing-up (a torch module), else
        ``control.period`` (as the Drake blocks hold them); ``gate_on`` / ``gate_off`` the spec's
        hysteresis; ``gate_period`` the spec's ``control.period``. ``overrides`` set fields (None: the
        default)."""
        unknown = set(overrides) - {"K", "goal", "decision_period", "gate_on", "gate_off", "gate_period"}
        if unknown:
            raise TypeError(f"unknown SwitchedController fields: {sorted(unknown)}")
        swingup = EnergySwingup() if swingup is None else swingup
        defaults = {
            "K": lambda: system.lqr()[0], "goal": lambda: system.goal,
            "decision_period": lambda: (system.swingup_period if isinstance(swingup, torch.nn.Module)
                                        else system.control_period),
            "gate_on": lambda: system.gate.on, "gate_off": lambda: system.gate.off,
            "gate_period": lambda: system.control_period}
        values = {key: default() if overrides.get(key) is None else overrides[key] for key, default in defaults.items()}
        return cls(swingup=swingup, gate=as_gate(gate, system), **values)

    def replace(self, **changes) -> "SwitchedController":
        """A copy with ``changes`` (checked again)."""
        return replace(self, **changes)

    def gate_stride(self, system: System) -> int:
        """Integration steps of ``system`` between gate evaluations (``gate_period / dt``, at least 1)."""
        return max(1, int(round(self.gate_period / system.dt)))

    def substeps(self, system: System) -> int:
        """Integration steps of ``system`` in one swing-up decision; ValueError unless a whole number."""
        substeps = int(round(self.decision_period / system.dt))
        if substeps < 1 or not math.isclose(substeps * system.dt, self.decision_period, rel_tol=1e-9):
            raise ValueError(f"decision_period must be a positive multiple of dt={system.dt} s, "
                             f"got {self.decision_period}")
        return substeps


# ---------------------------------------------------------------------------------------- the rollout
def gate_command(system: System, gate, x: torch.Tensor, u: torch.Tensor, mode: torch.Tensor, K: torch.Tensor,
                 gate_dtype: torch.dtype, gate_on: float, gate_off: float, goal: torch.Tensor | None = None):
    """One gate evaluation of the switched controller at states ``x`` (B, n): the gate classifies ``x``
    (in ``gate_dtype``), the hysteresis (``gate_on`` / ``gate_off``) moves ``mode`` (B,) bool (True: LQR),
    and where the mode is on the LQR command -K (x - goal) replaces the held swing-up action ``u`` (B, m);
    the command is saturated to the action limit. Returns ``(command, mode)``.

    The one place this sequence is written: :func:`switched_decision` runs it every gate stride, the APG
    family's LQR takeover (``hybridctl.learn.apg.LQRTakeover``) through it. Autograd flows through the
    LQR command and ``u`` (the switch itself is a hard choice). ``goal`` (n,): the LQR's goal where it is
    not the system's (None: ``system.state_error``).
    """
    err = system.state_error(x) if goal is None else control.wrap_angles(x - goal, system.angle_indices)
    if goal is None and isinstance(gate, control.CostToGoGate) and gate.system is system and gate_dtype == x.dtype:
        p = gate.of_error(err)                  # the same formula on the error computed once
    else:
        p = gate(x.to(gate_dtype))
    mode = control.hysteresis(p.reshape(-1).to(x.dtype), mode, gate_on, gate_off)
    lqr = control.lqr_command(err, K)
    return control.saturate(torch.where(mode[:, None], lqr, u), system.action_limit), mode


def switched_decision(system: System, gate, x0: torch.Tensor, u: torch.Tensor, mode: torch.Tensor, K: torch.Tensor,
                      substeps: int, gate_stride: int, gate_dtype: torch.dtype, gate_on: float, gate_off: float,
                      goal: torch.Tensor | None = None, restore_diverged: bool = True):
    """One decision of the switched controller from states ``x0`` (B, n) with the held swing-up
    action ``u`` (B, m) and gate modes ``mode`` (B,) bool (True: LQR).

    Every ``gate_stride`` integration steps the gate classifies the state and the hysteresis
    updates the mode (:func:`gate_command`); the command (LQR or ``u``, saturated) is held until the
    next gate evaluation (a :class:`NeverGate` is not evaluated: its mode is off throughout, the same
    numbers without the gate's work). A row that diverges (:func:`~hybridctl.systems.control.is_diverged`)
    is put back to its start state. Returns ``(x, diverged, mode, lqr_steps)``: the states after the decision,
    the diverged rows, the final modes and the number of integration steps the LQR acted.
    A pure function (no env state), so ``torch.compile`` can fuse it whole. ``goal`` (n,): the LQR's
    goal where it is not the system's (None: ``system.state_error``). ``restore_diverged`` False: no
    divergence check, a diverging row goes on (to Inf / NaN: the APG family's rollouts, where a
    non-finite return marks the member), and ``diverged`` is None.
    """
    x = x0
    diverged = torch.zeros(x0.shape[0], dtype=torch.bool, device=x0.device) if restore_diverged else None
    lqr_steps = torch.zeros(x0.shape[0], dtype=x0.dtype, device=x0.device)
    command = u
    never = isinstance(gate, NeverGate)     # p = 0 < gate_off: the mode is off and the held action acts
    if never:
        command, mode = control.saturate(u, system.action_limit), torch.zeros_like(mode)
    for k in range(substeps):
        if k % gate_stride == 0 and not never:
            command, mode = gate_command(system, gate, x, u, mode, K, gate_dtype, gate_on, gate_off, goal)
        lqr_steps = lqr_steps + mode.to(x0.dtype)
        x = system.step_unchecked(x, command)
        if restore_diverged:
            diverged = diverged | control.is_diverged(x)
            x = torch.where(diverged[:, None], x0, x)
    return x, diverged, mode, lqr_steps


DIVERGENCE_POLICIES = ("freeze", "restart", "continue", "propagate")
"""What :func:`closed_loop_rollout` does with a row once it diverges (a coordinate beyond
:data:`~hybridctl.systems.control.DIVERGENCE_BOUND` or non-finite; the decision it diverged in ends at its
start state, except under ``"propagate"``): ``"freeze"`` holds that last finite state to the end (the balance
map's torch engine); ``"continue"`` goes on deciding from it (the chunk tasks of random search, which count the
row's reward as 0 from then on); ``"restart"`` starts the row again from its row of ``x0``, in swing-up mode
with a fresh swing-up state (the switched env's autoreset, from given starts); ``"propagate"`` checks nothing
inside a decision and lets the row run on to Inf / NaN (the APG family's rollouts and the Ch. 7 study's
metrics, where a non-finite return marks the row; ``Rollout.diverged`` is then read at the decision times)."""


@dataclass
class Rollout:
    """What :func:`closed_loop_rollout` returns (tensors on the rollout's device).

    ``states`` (B, steps + 1, n): the states at the decision times from t = 0 (None unless ``record``);
    ``final`` (B, n): the last states; ``mode`` (B,) bool: the gate's last modes (True: LQR);
    ``lqr_steps`` (B, steps): integration steps of each decision in which the LQR acted; ``diverged``
    (B, steps) bool: the rows that diverged in each decision; ``diverged_at`` (B,) long: the first
    decision (1-based) a row diverged in, ``steps + 1`` where it never did; ``actions_finite`` (): every
    swing-up action was finite (they are clipped to the limit); ``swingup_state``: a recurrent swing-up's
    last state (else None).
    """

    states: torch.Tensor | None
    final: torch.Tensor
    mode: torch.Tensor
    lqr_steps: torch.Tensor
    diverged: torch.Tensor
    diverged_at: torch.Tensor
    actions_finite: torch.Tensor
    swingup_state: Any = None

    @property
    def ever_diverged(self) -> torch.Tensor:
        """(B,) bool: the rows that diverged at some decision."""
        return self.diverged.any(dim=1)


def _parameter_dtype(module, default: torch.dtype) -> torch.dtype:
    for tensor in getattr(module, "parameters", lambda: [])():
        return tensor.dtype
    return default


def swingup_policy(system: System, swingup, device: torch.device):
    """(policy(x [B, n], h) -> (u [B, m], h), initial_state(B) -> h) of a controller's swing-up on ``device``
    (a torch module is moved there, in place, and put in eval mode)."""
    if swingup is None:
        raise ValueError("this controller's swing-up is its agent's (swingup=None): give the actions")
    if isinstance(swingup, ZeroSwingup):
        return ((lambda x, h: (torch.zeros(len(x), system.n_actions, dtype=x.dtype, device=x.device), h)),
                (lambda n: None))
    if isinstance(swingup, EnergySwingup):
        if swingup.law is None:
            raise ValueError("EnergySwingup() holds no law here (it lives in the drake room): resolve it with "
                             "hybridctl.drake.resolve_swingup(system, controller) for a torch rollout")
        law = swingup.law
        return (lambda x, h: (law(x), h)), (lambda n: None)
    if isinstance(swingup, TrajoptSwingup):
        raise ValueError("TrajoptSwingup reads the time and runs in Drake only (hybridctl.drake.build_hybrid_diagram)")
    if isinstance(swingup, torch.nn.Module):
        module = swingup.to(device).eval()
        dtype = _parameter_dtype(module, torch.float64)
        if is_recurrent(module):       # as the Drake RecurrentTorchPolicy
            def recurrent(x, h):
                u, h = module(x.to(dtype), h)
                return u.to(x.dtype), h
            return recurrent, (lambda n: module.initial_state(n))
        return (lambda x, h: (module(x.to(dtype)).to(x.dtype), h)), (lambda n: None)
    return (lambda x, h: (swingup(x), h)), (lambda n: None)


def closed_loop_rollout(system: System, controller: SwitchedController, x0, steps: int, *,
                        differentiable: bool = False, on_divergence: str = "freeze", actions=None,
                        mode: torch.Tensor | None = None, swingup_state: Any = None, record: bool = True,
                        device: str | torch.device | None = None, dtype: torch.dtype = torch.float64,
                        decision: Callable | None = None) -> Rollout:
    """Run ``controller`` on ``system`` from every row of ``x0`` (B, n) for ``steps`` swing-up decisions, batched.

    Each decision: the swing-up's action (from the state at the decision, clipped to the action limit;
    ``actions`` (B, steps, m) in its place for a controller whose swing-up is an agent's) is held for
    ``decision_period``; inside, every ``gate_period`` the gate classifies the state, the hysteresis
    (``gate_on`` / ``gate_off``) updates the mode, and the saturated LQR command or the held action acts,
    over ``System.step_unchecked`` every ``dt`` (:func:`switched_decision`).

    Args:
        differentiable: keep autograd's graph (False: the rollout runs under ``torch.no_grad``). The switch
            is a hard choice: no gradient flows through the switching time.
        on_divergence: one of :data:`DIVERGENCE_POLICIES` (``"freeze"``, ``"continue"``, ``"restart"``,
            ``"propagate"``).
        mode: the gate's modes at the start (B,) bool (None: swing-up, as at every episode start);
            swingup_state: a recurrent swing-up's state (None: its ``initial_state``).
        record: keep the states at every decision (``Rollout.states``).
        device, dtype: where and in which precision the states run (None: ``x0``'s device, else the CPU).
        decision: the decision function (default :func:`switched_decision`; the switched env passes its
            ``torch.compile``-d one).
    """
    if on_divergence not in DIVERGENCE_POLICIES:
        raise ValueError(f"on_divergence must be one of {DIVERGENCE_POLICIES}, got {on_divergence!r}")
    if not isinstance(controller, SwitchedController):
        raise TypeError(f"controller must be a SwitchedController, got {type(controller).__name__}")
    steps = int(steps)
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    if device is None:
        device = x0.device if isinstance(x0, torch.Tensor) else torch.device("cpu")
    device = torch.device(device)
    x = torch.as_tensor(x0, dtype=dtype, device=device)
    if x.ndim != 2 or x.shape[1] != system.n_states or x.shape[1] != controller.goal.shape[0]:
        raise ValueError(f"x0 must have shape (B, {system.n_states}), got {tuple(x.shape)}")
    n_rows, limit = x.shape[0], system.action_limit
    substeps, stride = controller.substeps(system), controller.gate_stride(system)
    gate = controller.gate.to(device)
    gate_dtype = gate.compute_dtype or dtype
    K = torch.as_tensor(controller.K, dtype=dtype, device=device)
    goal = None if np.array_equal(controller.goal, system.goal) else torch.as_tensor(controller.goal, dtype=dtype,
                                                                                      device=device)
    if actions is None:
        policy, initial_state = swingup_policy(system, controller.swingup, device)
    else:
        actions = torch.as_tensor(actions, device=device).to(dtype)
        if tuple(actions.shape) != (n_rows, steps, system.n_actions):
            raise ValueError(f"actions must have shape ({n_rows}, {steps}, {system.n_actions}), "
                             f"got {tuple(actions.shape)}")
        policy, initial_state = None, (lambda n: None)
    decide = switched_decision if decision is None else decision
    options = ({} if goal is None else {"goal": goal}) | ({"restore_diverged": False} if on_divergence == "propagate"
                                                           else {})
    start = x
    h = initial_state(n_rows) if swingup_state is None else swingup_state
    mode = torch.zeros(n_rows, dtype=torch.bool, device=device) if mode is None else mode
    diverged_at = torch.full((n_rows,), steps + 1, device=device)
    finite = torch.ones((), dtype=torch.bool, device=device)
    states, lqr_steps, diverged_rows = ([x] if record else None), [], []
    with torch.set_grad_enabled(differentiable and torch.is_grad_enabled()):
        for j in range(1, steps + 1):
            if policy is None:
                u = actions[:, j - 1]
            else:
                u, h = policy(x, h)
            finite = finite & torch.isfinite(u).all()
            u = u.clamp(-limit, limit)
            x_next, diverged, mode, lqr = decide(system, gate, x, u, mode, K, substeps, stride, gate_dtype,
                                                 controller.gate_on, controller.gate_off, **options)
            if on_divergence == "propagate":
                diverged = control.is_diverged(x_next)
                x = x_next
            elif on_divergence == "freeze":
                ended = diverged_at <= j                          # diverged before this decision: frozen
                x = torch.where(ended[:, None], x, x_next)       # a diverging row is back at its last finite state
            elif on_divergence == "restart":
                x = torch.where(diverged[:, None], start, x_next)
                mode = mode & ~diverged
                if h is not None and bool(diverged.any()):
                    fresh = initial_state(n_rows)
                    h = torch.where(diverged.reshape(1, -1, *([1] * (h.ndim - 2))) if h.ndim > 2
                                    else diverged[:, None], fresh.to(h.device, h.dtype), h)
            else:
                x = x_next
            diverged_at = torch.where(diverged & (diverged_at > steps), j, diverged_at)
            lqr_steps.append(lqr)
            diverged_rows.append(diverged)
            if record:
                states.append(x)
    empty = torch.zeros((n_rows, 0), dtype=dtype, device=device)
    return Rollout(states=torch.stack(states, dim=1) if record else None, final=x, mode=mode,
                   lqr_steps=torch.stack(lqr_steps, dim=1) if lqr_steps else empty,
                   diverged=torch.stack(diverged_rows, dim=1) if diverged_rows else empty.bool(),
                   diverged_at=diverged_at, actions_finite=finite, swingup_state=h)
