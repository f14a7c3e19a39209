"""Controllers by name (``energy``, ``lqr``, ``ssac:PATH``, ...): what the command line, notebooks
and worker processes pass around, since Drake systems and closures do not pickle."""

from __future__ import annotations

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
    "ssac:PATH": "learned swing-up + learned gate (hysteresis) + LQR from an SSAC checkpoint directory",
    "finetune:PATH": "a fine-tuned sac/ssac swing-up (hybridctl finetune's final/ checkpoint), with its gate and LQR",
    "sac:PATH": "learned swing-up only from a SAC checkpoint directory (gate always off)",
    "ce-apg:PATH": "learned recurrent swing-up from an APG/PAPG/CEM/CE-APG checkpoint (thesis Ch. 7; also "
                   "apg:, papg:, cem:, shapg:) + cost-to-go gate (hysteresis) + LQR",
}


def build_named_diagram(system: System, controller: str = "energy", **kwargs) -> HybridDiagram:
    """``build_hybrid_diagram`` for a controller given by name (see ``CONTROLLERS``).

    Names are what the command line and worker processes pass around, since
    Drake systems and closures do not pickle.
    """
    if controller == "energy":
        return build_hybrid_diagram(system, **kwargs)
    if controller == "lqr":
        return build_hybrid_diagram(system, swingup=_zero_command, gate=_always_balance, **kwargs)
    if controller == "swingup":
        return build_hybrid_diagram(system, gate=_never_balance, **kwargs)
    if controller == "zero":
        return build_hybrid_diagram(system, swingup=_zero_command, gate=_never_balance, **kwargs)
    kind, sep, path = controller.partition(":")
    if sep and kind in ("ssac", "sac"):
        if not path:
            raise ValueError(f"controller {controller!r} needs a checkpoint path after '{kind}:'")
        policy, gate, meta = load_controller(path, system)
        if kind == "ssac" and gate is None:
            raise ValueError(f"{path} is a {meta.get('algorithm')} checkpoint without a gate; use sac:{path}")
        if kind == "sac":
            gate = _never_balance
        gate_meta = meta.get("gate", {})
        kwargs.setdefault("gate_on", gate_meta.get("gate_on"))
        kwargs.setdefault("gate_off", gate_meta.get("gate_off"))
        return build_hybrid_diagram(system, swingup=policy, gate=gate, **kwargs)
    if sep and kind == "finetune":   # thesis Ch. 6: a fine-tuned sac/ssac swing-up (FineTune checkpoint)
        if not path:
            raise ValueError(f"controller {controller!r} needs a checkpoint path after 'finetune:'")
        tuner = FineTune.load(path)
        if tuner.tunable.system != system.name:
            raise ValueError(f"{path} fine-tunes {tuner.tunable.source} on {tuner.env_name}; a Drake diagram of "
                             f"{system.name} needs a sac:/ssac: source of that system")
        for key, value in tuner.tunable.meta.get("gate", {}).items():
            kwargs.setdefault(key, value)
        gate = tuner.tunable.gate if tuner.tunable.gate is not None else _never_balance
        return build_hybrid_diagram(system, swingup=tuner.tuned_module(), gate=gate, **kwargs)
    if sep and kind in APG_METHODS:   # thesis Ch. 7: the trained GRU with its hidden state in the Context
        if not path:
            raise ValueError(f"controller {controller!r} needs a checkpoint path after '{kind}:'")
        agent = APG.load(path)
        if agent.system.name != system.name:
            raise ValueError(f"{path} was trained on {agent.system.name}, not {system.name}")
        kwargs.setdefault("swingup_period", agent.period)
        return build_hybrid_diagram(system, swingup=agent.closed_loop_policy(), **kwargs)
    raise ValueError(f"unknown controller {controller!r}; known: "
                     + ", ".join(f"{k} ({v})" for k, v in CONTROLLERS.items()))
