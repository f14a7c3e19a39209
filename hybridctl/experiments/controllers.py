"""Controllers by name (``energy``, ``lqr``, ``ssac:PATH``, ...): what the command line, notebooks
and worker processes pass around, since Drake systems and closures do not pickle."""

from __future__ import annotations

import os
from pathlib import Path

from ..drake import HybridDiagram, build_hybrid_diagram
from ..learn import APG, load_controller
from ..learn.apg import METHODS as APG_METHODS
from ..learn.finetune import FineTune
from ..systems import System
from ..systems.switched import (AlwaysGate, CostToGoGate, EnergySwingup, LearnedGate, NeverGate, SwitchedController,
                                TrajoptSwingup, ZeroSwingup)


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


ControllerParts = SwitchedController
"""The old name of what :func:`controller_parts` returns: a :class:`~hybridctl.systems.SwitchedController`."""


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


def controller_parts(system: System, controller: str = "energy") -> SwitchedController:
    """The :class:`~hybridctl.systems.SwitchedController` of a controller given by name (see ``CONTROLLERS``);
    loads checkpoints. What the name leaves open is the spec's (:meth:`SwitchedController.for_system`)."""
    def make(swingup=None, gate=None, gate_on=None, gate_off=None, decision_period=None):
        return SwitchedController.for_system(system, swingup=swingup, gate=gate, gate_on=gate_on, gate_off=gate_off,
                                             decision_period=decision_period)
    hand_designed = {"energy": (EnergySwingup, CostToGoGate), "lqr": (ZeroSwingup, AlwaysGate),
                     "swingup": (EnergySwingup, NeverGate), "zero": (ZeroSwingup, NeverGate),
                     "trajopt": (TrajoptSwingup, CostToGoGate)}   # trajopt: the diagram solves or reads the cache
    if controller in hand_designed:
        swingup, gate = hand_designed[controller]
        return make(swingup(), gate(system) if gate is CostToGoGate else gate())
    kind, sep, path = controller.partition(":")
    if sep and kind in ("ssac", "sac", "ssac-costgate"):
        if not path:
            raise ValueError(f"controller {controller!r} needs a checkpoint path after '{kind}:'")
        policy, gate, meta = load_controller(path, system, with_gate=kind != "ssac-costgate")
        if kind == "ssac-costgate":   # the spec's cost-to-go gate in place of the checkpoint's gate
            return make(policy, CostToGoGate(system))
        if kind == "ssac" and gate is None:
            raise ValueError(f"{path} is a {meta.get('algorithm')} checkpoint without a gate; use sac:{path}")
        gate_meta = meta.get("gate", {})
        return make(policy, NeverGate() if kind == "sac" else LearnedGate(gate), gate_meta.get("gate_on"),
                    gate_meta.get("gate_off"))
    if sep and kind == "finetune":   # thesis Ch. 6: a fine-tuned sac/ssac/APG-family swing-up (FineTune checkpoint)
        if not path:
            raise ValueError(f"controller {controller!r} needs a checkpoint path after 'finetune:'")
        tuner = FineTune.load(path, device="cpu")   # Drake runs on the CPU, whatever device it trained on
        if tuner.tunable.system != system.name:
            raise ValueError(f"{path} fine-tunes {tuner.tunable.source} on {tuner.env_name}; a Drake diagram of "
                             f"{system.name} needs a sac:/ssac:/APG-family source of that system")
        gate_meta = tuner.tunable.meta.get("gate", {})
        gate = tuner.tunable.gate   # None: no gate; a str: the spec's cost-to-go gate; else the learned gate
        gate = NeverGate() if gate is None else CostToGoGate(system) if isinstance(gate, str) else LearnedGate(gate)
        return make(tuner.tuned_module(), gate, gate_meta.get("gate_on"), gate_meta.get("gate_off"),
                    tuner.tunable.decision_period)
    if sep and kind in APG_METHODS:   # thesis Ch. 7: the trained GRU with its hidden state in the Context
        if not path:
            raise ValueError(f"controller {controller!r} needs a checkpoint path after '{kind}:'")
        agent = APG.load(path, device="cpu")   # Drake runs on the CPU, whatever device it trained on
        if agent.system.name != system.name:
            raise ValueError(f"{path} was trained on {agent.system.name}, not {system.name}")
        return make(agent.closed_loop_policy(), CostToGoGate(system), decision_period=agent.period)
    raise ValueError(f"unknown controller {controller!r}; known: "
                     + ", ".join(f"{k} ({v})" for k, v in CONTROLLERS.items()))


def build_named_diagram(system: System, controller: str = "energy", **kwargs) -> HybridDiagram:
    """``build_hybrid_diagram`` of the :class:`~hybridctl.systems.SwitchedController` of a controller given by
    name (see ``CONTROLLERS``).

    Names are what the command line and worker processes pass around, since
    Drake systems and closures do not pickle. ``kwargs`` go to ``build_hybrid_diagram``
    (and win over the checkpoint's gate thresholds and periods).
    """
    return build_hybrid_diagram(system, controller_parts(system, controller), **kwargs)
