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
from .vector import TorchVectorEnv


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
        compile: ``"off"`` (default), ``"on"`` or ``"auto"``: run each decision (the gate, the
            LQR and the dynamics of every substep) as one ``torch.compile``-d function
            (:mod:`hybridctl.systems.compiled`; ~13x faster at batch 32, equal to ~1e-15).

    Extra ``infos`` per step: ``"lqr_fraction"`` (N,) share of this decision's
    control periods in which the LQR acted, ``"lqr_at_start"`` (N,) bool, the
    gate mode when the decision began (SSAC's gate data are the states of
    LQR-active decisions), and ``"decision_start"`` (N, n) the state the agent saw.
    """

    def __init__(self, system: str | System, num_envs: int, gate: torch.nn.Module, K=None,
                 gate_on: float | None = None, gate_off: float | None = None, **kwargs):
        super().__init__(system, num_envs, **kwargs)
        sys_ = self.system
        self.gate_on = sys_.gate.on if gate_on is None else float(gate_on)
        self.gate_off = sys_.gate.off if gate_off is None else float(gate_off)
        if not 0.0 < self.gate_off < self.gate_on < 1.0:
            raise ValueError(f"need 0 < gate_off < gate_on < 1, got off={self.gate_off}, on={self.gate_on}")
        K = sys_.lqr()[0] if K is None else np.atleast_2d(np.asarray(K, dtype=float))
        self._K = torch.as_tensor(K, dtype=self.dtype, device=self.device)
        ratio = sys_.control_period / sys_.dt
        self.gate_stride = max(1, int(round(ratio)))
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
            x, diverged, self._mode, lqr_steps = self._decision_fn(
                self.system, self.gate, self._state, u, self._mode, self._K, self.substeps, self.gate_stride,
                self._gate_dtype(), self.gate_on, self.gate_off)
        self._infos = {"lqr_fraction": lqr_steps / self.substeps, "lqr_at_start": start_mode,
                       "decision_start": self._state.clone()}
        return x, diverged

    def _gate_dtype(self) -> torch.dtype:
        for tensor in getattr(self.gate, "parameters", lambda: [])():
            return tensor.dtype
        return self.dtype

    def _step_infos(self) -> dict[str, torch.Tensor]:
        return self._infos

    @property
    def mode(self) -> torch.Tensor:
        """Current gate modes (N,) bool: True where the LQR is in control (a copy)."""
        return self._mode.clone()


def switched_decision(system: System, gate, x0: torch.Tensor, u: torch.Tensor, mode: torch.Tensor, K: torch.Tensor,
                      substeps: int, gate_stride: int, gate_dtype: torch.dtype, gate_on: float, gate_off: float):
    """One decision of the switched controller from states ``x0`` (B, n) with the held swing-up
    action ``u`` (B, m) and gate modes ``mode`` (B,) bool (True: LQR).

    Every ``gate_stride`` integration steps the gate classifies the state and the hysteresis
    updates the mode; the command (LQR or ``u``, saturated) is held until the next gate
    evaluation. A row that diverges (:func:`~hybridctl.systems.control.is_diverged`) is put back
    to its start state. Returns ``(x, diverged, mode, lqr_steps)``: the states after the decision,
    the diverged rows, the final modes and the number of integration steps the LQR acted.
    A pure function (no env state), so ``torch.compile`` can fuse it whole.
    """
    limit = system.action_limit
    x = x0
    diverged = torch.zeros(x0.shape[0], dtype=torch.bool, device=x0.device)
    lqr_steps = torch.zeros(x0.shape[0], dtype=x0.dtype, device=x0.device)
    command = u
    for k in range(substeps):
        if k % gate_stride == 0:
            p = gate(x.to(gate_dtype)).reshape(-1).to(x0.dtype)
            mode = control.hysteresis(p, mode, gate_on, gate_off)
            lqr = control.lqr_command(system.state_error(x), K)
            command = control.saturate(torch.where(mode[:, None], lqr, u), limit)
        lqr_steps = lqr_steps + mode.to(x0.dtype)
        x = system.step_unchecked(x, command)
        diverged = diverged | control.is_diverged(x)
        x = torch.where(diverged[:, None], x0, x)
    return x, diverged, mode, lqr_steps
