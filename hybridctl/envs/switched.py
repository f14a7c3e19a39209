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
from .vector import TorchVectorEnv


class SwitchedVectorEnv(TorchVectorEnv):
    """``TorchVectorEnv`` whose decisions run gate + LQR + held swing-up action.

    Args:
        system, num_envs, decision_period, device, dtype, seed, autoreset_mode: as
            :class:`TorchVectorEnv`.
        gate: a torch module mapping states (B, n) to probabilities (B, 1), e.g.
            ``hybridctl.learn.GateNet`` or ``hybridctl.drake.CostToGoGate``.
            Replace it at any time with :meth:`set_gate` (SSAC refits it).
        K: LQR gain (m, n); default ``system.lqr()``.
        gate_on, gate_off: hysteresis thresholds (default: the spec's 0.9 / 0.5).

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
        """Use ``gate`` (states (B, n) -> probabilities (B, 1)) from the next decision on."""
        if not callable(gate):
            raise TypeError(f"gate must be a torch module or callable, got {type(gate).__name__}")
        self.gate = gate

    def lqr(self, x: torch.Tensor) -> torch.Tensor:
        """u = -K (x - goal), angles wrapped (batched): :func:`hybridctl.systems.control.lqr_command`."""
        return control.lqr_command(self.system.state_error(x), self._K)

    def _restart(self, rows: torch.Tensor, x0=None) -> None:
        super()._restart(rows, x0)
        if hasattr(self, "_mode"):
            self._mode[rows] = False  # thesis: every episode starts in swing-up

    def _advance(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        system, limit = self.system, self.system.action_limit
        x = x0 = self._state
        start_mode = self._mode.clone()
        diverged = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        lqr_steps = torch.zeros(self.num_envs, dtype=self.dtype, device=self.device)
        mode = self._mode
        with torch.no_grad():
            for k in range(self.substeps):
                if k % self.gate_stride == 0:
                    p = self.gate(x.to(self._gate_dtype())).reshape(-1).to(self.dtype)
                    mode = control.hysteresis(p, mode, self.gate_on, self.gate_off)
                    command = control.saturate(torch.where(mode[:, None], self.lqr(x), u), limit)
                lqr_steps += mode.to(self.dtype)
                x = system.step_unchecked(x, command)
                diverged = diverged | control.is_diverged(x)
                x = torch.where(diverged[:, None], x0, x)
        self._mode = mode
        self._infos = {"lqr_fraction": lqr_steps / self.substeps, "lqr_at_start": start_mode,
                       "decision_start": x0.clone()}
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
