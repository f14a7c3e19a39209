"""Controllers by name (``energy``, ``lqr``, ``ssac:PATH``, ...): what the command line, notebooks
and worker processes pass around, since Drake systems and closures do not pickle."""

from __future__ import annotations

import os
from pathlib import Path

from ..drake import HybridDiagram, build_hybrid_diagram
from ..learn.registry import checkpoint_kinds, gate_of_kind, load_controller
from ..systems import System
from ..systems.switched import (AlwaysGate, CostToGoGate, EnergySwingup, NeverGate, SwitchedController,
                                TrajoptSwingup, ZeroSwingup)


HAND_DESIGNED = {"energy": (EnergySwingup, CostToGoGate), "lqr": (ZeroSwingup, AlwaysGate),
                 "swingup": (EnergySwingup, NeverGate), "zero": (ZeroSwingup, NeverGate),
                 "trajopt": (TrajoptSwingup, CostToGoGate)}   # trajopt: the diagram solves or reads the cache
"""The hand-designed controllers: (swing-up marker, gate class) by name."""

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
    "fitted:DIR": "the learned switched controller `hybridctl fit` kept in DIR (its report.json: SSAC's swing-up, "
                  "the learned or cost-to-go gate, Drake's LQR); use it with DIR/system.toml",
    "checkpoint:PATH": "the controller of any checkpoint that drives a system, by its config.json's algorithm "
                       "(hybridctl.learn.load_controller; also ALGORITHM:PATH for any registered learner)",
}
"""What the command line lists. Every ``KIND:PATH`` loads through :func:`hybridctl.learn.load_controller` (the
learner registered for the checkpoint's algorithm); the kind selects only the gate
(:data:`hybridctl.learn.registry.KIND_GATES`)."""


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


def controller_parts(system: System, controller: str = "energy", force: bool = False) -> SwitchedController:
    """The :class:`~hybridctl.systems.SwitchedController` of a controller given by name (see ``CONTROLLERS``);
    loads checkpoints. What the name leaves open is the spec's (:meth:`SwitchedController.for_system`).

    ``KIND:PATH``: the checkpoint's controller through the learner contract
    (:func:`hybridctl.learn.load_controller`), with the gate ``KIND`` selects
    (:func:`hybridctl.learn.registry.gate_of_kind`: ``sac`` none, ``ssac`` the learned one,
    ``ssac-costgate`` the spec's cost-to-go gate, every other kind the checkpoint's own); ``force``: load a
    checkpoint trained on other spec values (another plant) anyway, with ``load_controller``'s warning."""
    if controller in HAND_DESIGNED:
        swingup, gate = HAND_DESIGNED[controller]
        return SwitchedController.for_system(system, swingup=swingup(),
                                             gate=gate(system) if gate is CostToGoGate else gate())
    kind, sep, path = controller.partition(":")
    if kind == "fitted" and sep:
        from .fitted import fitted_controller
        checkpoint, kind = fitted_controller(path)
        path = str(checkpoint)
    gate = gate_of_kind(kind) if sep else None
    if gate is not None:
        if not path:
            raise ValueError(f"controller {controller!r} needs a checkpoint path after '{kind}:'")
        return load_controller(path, system, gate=gate, force=force)   # on the CPU, whatever device it trained on
    raise ValueError(f"unknown controller {controller!r}; known: "
                     + ", ".join(f"{k} ({v})" for k, v in CONTROLLERS.items())
                     + f"; checkpoint kinds: {', '.join(checkpoint_kinds())}")


def build_named_diagram(system: System, controller: str = "energy", force: bool = False, **kwargs) -> HybridDiagram:
    """``build_hybrid_diagram`` of the :class:`~hybridctl.systems.SwitchedController` of a controller given by
    name (see ``CONTROLLERS``).

    Names are what the command line and worker processes pass around, since
    Drake systems and closures do not pickle. ``kwargs`` go to ``build_hybrid_diagram``
    (and win over the checkpoint's gate thresholds and periods); ``force`` as in :func:`controller_parts`.
    """
    return build_hybrid_diagram(system, controller_parts(system, controller, force), **kwargs)
