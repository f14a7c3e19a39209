"""The switched environment of SSAC (thesis Algorithm 3) as a batched torch VectorEnv.

The agent chooses the swing-up action once per decision (0.2 s for the acrobot).
Inside the decision, every ``control.period`` (0.01 s) the gate classifies the
state; with hysteresis (on above 0.9, off below 0.5) it hands control to the LQR,
which then acts at every control period (a slower hold destabilises the acrobot),
or back to the held swing-up action. The gate's mode starts in swing-up at every
episode start. Seen from the agent, the LQR and gate are part of the dynamics,
so SAC on this env is the swing-up learner of SSAC.
"""

from __future__ import annotations

import numpy as np
import torch

from ..systems import System, control
from ..systems.compiled import LazyCompiled
from ..systems.switched import SwitchedController, as_gate, closed_loop_rollout, switched_decision
from .vector import TorchVectorEnv

__all__ = ["SwitchedVectorEnv", "switched_decision"]


class SwitchedVectorEnv(TorchVectorEnv):
    """``TorchVectorEnv`` whose decisions run gate + LQR + held swing-up action.

    Args:
        system, num_envs, decision_period, device, dtype, seed, autoreset_mode: as
            :class:`TorchVectorEnv`.
        gate: a torch module mapping states (B, n) to probabilities (B, 1), e.g.
            ``hybridctl.learn.GateNet`` or ``hybridctl.drake.CostToGoGate``; it is moved to
            the env's ``device`` (in place, ``Module.to``), where the decisions run.
            Replace it at any time with :meth:`set_gate` (SSAC refits it).
        K: LQR gain (m, n); default ``system.lqr()``.
        gate_on, gate_off: hysteresis thresholds (default: the spec's 0.9 / 0.5).
        controller: a :class:`~hybridctl.systems.SwitchedController` whose gate, K and thresholds the env
            uses in place of ``gate``, ``K``, ``gate_on`` and ``gate_off`` (its swing-up is the agent's).
        compile: ``"off"`` (default), ``"on"`` or ``"auto"``: run each decision (the gate, the
            LQR and the dynamics of every substep) as one ``torch.compile``-d function
            (:mod:`hybridctl.systems.compiled`; ~13x faster at batch 32, equal to ~1e-15).

    Each decision is one step of :func:`hybridctl.systems.closed_loop_rollout` of :attr:`controller`
    (swing-up: the agent's actions; a diverged row ends at its last finite state and the autoreset restarts
    it). Extra ``infos`` per step: ``"lqr_fraction"`` (N,) share of this decision's
    control periods in which the LQR acted, ``"lqr_at_start"`` (N,) bool, the
    gate mode when the decision began (SSAC's gate data are the states of
    LQR-active decisions), and ``"decision_start"`` (N, n) the state the agent saw.
    """

    def __init__(self, system: str | System, num_envs: int, gate: torch.nn.Module | None = None, K=None,
                 gate_on: float | None = None, gate_off: float | None = None,
                 controller: SwitchedController | None = None, **kwargs):
        super().__init__(system, num_envs, **kwargs)
        sys_ = self.system
        if controller is not None:
            if gate is not None or K is not None or gate_on is not None or gate_off is not None:
                raise ValueError("give either controller or gate / K / gate_on / gate_off, not both")
            gate, K, gate_on, gate_off = controller.gate, controller.K, controller.gate_on, controller.gate_off
            goal, gate_period = controller.goal, controller.gate_period
        elif gate is None:
            raise TypeError("gate must be a torch module or callable (or give a controller), got None")
        else:
            goal, gate_period = sys_.goal, sys_.control_period
        K = sys_.lqr()[0] if K is None else np.atleast_2d(np.asarray(K, dtype=float))
        self.controller = SwitchedController(
            swingup=None, gate=as_gate(gate), K=K, goal=goal, decision_period=self.decision_period,
            gate_on=sys_.gate.on if gate_on is None else gate_on, gate_off=sys_.gate.off if gate_off is None else gate_off,
            gate_period=gate_period)
        self.gate_on, self.gate_off = self.controller.gate_on, self.controller.gate_off
        self._K = torch.as_tensor(K, dtype=self.dtype, device=self.device)
        self.gate_stride = self.controller.gate_stride(sys_)
        self.gate = gate      # what was given (SSAC refits its GateNet in place); the controller holds it typed
        self.set_gate(gate)
        N = self.num_envs
        self._mode = torch.zeros(N, dtype=torch.bool, device=self.device)
        self._infos: dict[str, torch.Tensor] = {}

    def set_gate(self, gate: torch.nn.Module) -> None:
        """Use ``gate`` (states (B, n) -> probabilities (B, 1)) from the next decision on.

        A torch module is moved to the env's device first (in place, as ``Module.to`` does; a
        no-op where it is there already): the gate runs inside every decision, on the env's
        states. A plain callable is used as it is."""
        if not callable(gate):
            raise TypeError(f"gate must be a torch module or callable, got {type(gate).__name__}")
        if isinstance(gate, torch.nn.Module):
            gate.to(self.device)
        if gate is not self.gate:
            # a new gate gets a new typed wrapper (the same one keeps its own: a compiled decision keeps its graph)
            self.controller.gate = as_gate(gate)
        self.controller.gate.to(self.device)
        self.gate = gate

    def lqr(self, x: torch.Tensor) -> torch.Tensor:
        """u = -K (x - goal), angles wrapped (batched): :func:`hybridctl.systems.control.lqr_command`."""
        return control.lqr_command(self.system.state_error(x), self._K)

    def _make_decision_fn(self, enabled: bool, strict: bool) -> LazyCompiled:
        return LazyCompiled(switched_decision, enabled, strict=strict, name="the switched env's decision")

    def _restart(self, rows: torch.Tensor, x0=None) -> None:
        super()._restart(rows, x0)
        if hasattr(self, "_mode"):
            self._mode[rows] = False  # thesis: every episode starts in swing-up

    def _advance(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        start_mode = self._mode.clone()
        with torch.no_grad():
            run = closed_loop_rollout(self.system, self.controller, self._state, 1, actions=u[:, None],
                                      mode=self._mode, on_divergence="continue", record=False, dtype=self.dtype,
                                      decision=self._decision_fn)
        self._mode = run.mode
        self._infos = {"lqr_fraction": run.lqr_steps[:, 0] / self.substeps, "lqr_at_start": start_mode,
                       "decision_start": self._state.clone()}
        return run.final, run.diverged[:, 0]

    def _step_infos(self) -> dict[str, torch.Tensor]:
        return self._infos

    @property
    def mode(self) -> torch.Tensor:
        """Current gate modes (N,) bool: True where the LQR is in control (a copy)."""
        return self._mode.clone()
