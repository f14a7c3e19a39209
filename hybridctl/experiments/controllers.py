"""Controllers by name (``energy``, ``lqr``, ``ssac:PATH``, ...): what the command line, notebooks
and worker processes pass around, since Drake systems and closures do not pickle."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..drake import HybridDiagram, build_hybrid_diagram
from ..learn import APG, load_controller
from ..learn.apg import METHODS as APG_METHODS
from ..learn.finetune import FineTune
from ..systems import System


def _zero_command(x: np.ndarray) -> np.ndarray:
    return np.zeros(1)  # single-input systems only, as all benchmark systems are


def _always_balance(x: np.ndarray) -> list[float]:
    return [1.0]


def _never_balance(x: np.ndarray) -> list[float]:
    return [0.0]


CONTROLLERS = {
    "energy": "energy-shaping swing-up + cost-to-go gate (hysteresis) + LQR",
    "lqr": "LQR only (gate always on)",
    "swingup": "energy-shaping swing-up only (gate always off)",
    "zero": "no input (passive dynamics)",
    "trajopt": "direct-collocation swing-up from hanging down tracked by Drake's time-varying LQR + cost-to-go "
               "gate (hysteresis) + LQR; any system, solved once and cached (Drake engine only)",
    "ssac:PATH": "learned swing-up + learned gate (hysteresis) + LQR from an SSAC checkpoint directory",
    "finetune:PATH": "a fine-tuned sac/ssac/APG-family swing-up (hybridctl finetune's final/ checkpoint), with its "
                     "gate and LQR",
    "sac:PATH": "learned swing-up only from a SAC checkpoint directory (gate always off)",
    "ssac-costgate:PATH": "learned swing-up of an SSAC (or SAC) checkpoint + the spec's cost-to-go gate (hysteresis) "
                          "+ LQR, as the APG controllers; for a system whose learned gate does not fire",
    "ce-apg:PATH": "learned recurrent swing-up from an APG/PAPG/CEM/CE-APG checkpoint (thesis Ch. 7; also "
                   "apg:, papg:, cem:, shapg:) + cost-to-go gate (hysteresis) + LQR",
}


@dataclass
class ControllerParts:
    """What a named controller is made of, before it becomes Drake blocks (:func:`build_named_diagram`) or
    a batched torch rollout (:func:`hybridctl.experiments.balance_map.torch_rollouts`).

    ``swingup``: None (the spec's energy swing-up), ``"zero"``, ``"trajopt"`` (the collocation swing-up
    tracked by TVLQR, :mod:`hybridctl.drake.trajopt`: a Drake block that reads the time, so Drake only) or
    a torch module (a recurrent one has ``initial_state``); ``gate``: None (the spec's cost-to-go gate),
    ``"always"``, ``"never"`` or a torch classifier; ``gate_on`` / ``gate_off`` (None: the spec's) and
    ``swingup_period`` (None: the block's default) as for :func:`hybridctl.drake.build_hybrid_diagram`.
    """

    swingup: Any = None
    gate: Any = None
    gate_on: float | None = None
    gate_off: float | None = None
    swingup_period: float | None = None


def display_name(controller: str) -> str:
    """``controller`` for a plot title: a checkpoint path relative to the working folder when it lies
    inside it, else its last two parts after ``.../`` (so titles show no machine's absolute paths)."""
    kind, sep, path = controller.partition(":")
    if not sep or not os.path.isabs(path):
        return controller
    absolute = Path(path)
    try:
        return f"{kind}:{absolute.relative_to(Path.cwd())}"
    except ValueError:
        return f"{kind}:.../{Path(*absolute.parts[-2:])}"


def controller_parts(system: System, controller: str = "energy") -> ControllerParts:
    """The parts of a controller given by name (see ``CONTROLLERS``); loads checkpoints."""
    if controller == "energy":
        return ControllerParts()
    if controller == "lqr":
        return ControllerParts(swingup="zero", gate="always")
    if controller == "swingup":
        return ControllerParts(gate="never")
    if controller == "zero":
        return ControllerParts(swingup="zero", gate="never")
    if controller == "trajopt":   # build_hybrid_diagram solves (or reads from the cache) the trajectory
        return ControllerParts(swingup="trajopt")
    kind, sep, path = controller.partition(":")
    if sep and kind in ("ssac", "sac", "ssac-costgate"):
        if not path:
            raise ValueError(f"controller {controller!r} needs a checkpoint path after '{kind}:'")
        policy, gate, meta = load_controller(path, system, with_gate=kind != "ssac-costgate")
        if kind == "ssac-costgate":   # the spec's cost-to-go gate (None) in place of the checkpoint's gate
            return ControllerParts(policy)
        if kind == "ssac" and gate is None:
            raise ValueError(f"{path} is a {meta.get('algorithm')} checkpoint without a gate; use sac:{path}")
        gate_meta = meta.get("gate", {})
        return ControllerParts(policy, "never" if kind == "sac" else gate, gate_meta.get("gate_on"),
                               gate_meta.get("gate_off"))
    if sep and kind == "finetune":   # thesis Ch. 6: a fine-tuned sac/ssac/APG-family swing-up (FineTune checkpoint)
        if not path:
            raise ValueError(f"controller {controller!r} needs a checkpoint path after 'finetune:'")
        tuner = FineTune.load(path, device="cpu")   # Drake runs on the CPU, whatever device it trained on
        if tuner.tunable.system != system.name:
            raise ValueError(f"{path} fine-tunes {tuner.tunable.source} on {tuner.env_name}; a Drake diagram of "
                             f"{system.name} needs a sac:/ssac:/APG-family source of that system")
        gate_meta = tuner.tunable.meta.get("gate", {})
        gate = tuner.tunable.gate
        gate = "never" if gate is None else None if isinstance(gate, str) else gate   # str: the spec's cost-to-go gate
        return ControllerParts(tuner.tuned_module(), gate, gate_meta.get("gate_on"), gate_meta.get("gate_off"),
                               swingup_period=tuner.tunable.decision_period)
    if sep and kind in APG_METHODS:   # thesis Ch. 7: the trained GRU with its hidden state in the Context
        if not path:
            raise ValueError(f"controller {controller!r} needs a checkpoint path after '{kind}:'")
        agent = APG.load(path, device="cpu")   # Drake runs on the CPU, whatever device it trained on
        if agent.system.name != system.name:
            raise ValueError(f"{path} was trained on {agent.system.name}, not {system.name}")
        return ControllerParts(agent.closed_loop_policy(), swingup_period=agent.period)
    raise ValueError(f"unknown controller {controller!r}; known: "
                     + ", ".join(f"{k} ({v})" for k, v in CONTROLLERS.items()))


_DRAKE_STAND_INS = {"zero": _zero_command, "always": _always_balance, "never": _never_balance}


def build_named_diagram(system: System, controller: str = "energy", **kwargs) -> HybridDiagram:
    """``build_hybrid_diagram`` for a controller given by name (see ``CONTROLLERS``).

    Names are what the command line and worker processes pass around, since
    Drake systems and closures do not pickle. ``kwargs`` go to ``build_hybrid_diagram``
    (and win over the checkpoint's gate thresholds and periods).
    """
    parts = controller_parts(system, controller)
    for key in ("gate_on", "gate_off", "swingup_period"):
        if getattr(parts, key) is not None:
            kwargs.setdefault(key, getattr(parts, key))
    swingup = _DRAKE_STAND_INS.get(parts.swingup, parts.swingup) if isinstance(parts.swingup, str) else parts.swingup
    gate = _DRAKE_STAND_INS.get(parts.gate, parts.gate) if isinstance(parts.gate, str) else parts.gate
    return build_hybrid_diagram(system, swingup=swingup, gate=gate, **kwargs)
