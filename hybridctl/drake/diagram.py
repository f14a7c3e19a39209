"""The hybrid (switched) controller as a Drake Diagram (thesis Fig. 3.1).

    plant --state--> [swing-up] --\\
          --state--> [LQR]     ----> [switch] -> [saturation] -> plant
          --state--> [gate] --selector--/

The swing-up and the gate are Python blocks updated periodically (zero-order holds,
:mod:`.blocks`); the LQR (``HeldLQR``), the switch (Drake's ``PortSwitch``, driven by the gate's
``selector`` state) and the saturation are C++ primitives, so between the periodic updates
the loop runs without calling Python.

Exported ports (by name): outputs ``state`` (spec convention), ``command``
(saturated input applied to the plant), ``mode`` (0 swing-up, 1 LQR),
``probability`` (gate output), ``swingup_command`` and ``balance_command``.
"""

from __future__ import annotations

import numpy as np
import torch
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import AffineSystem, LogVectorOutput, PortSwitch, Saturation

from ..systems import System
from ..systems import plants as _plants
from ..systems.control import CostToGoGate
from ..systems.switched import (AlwaysGate, EnergySwingup, LearnedGate, NeverGate, SwitchedController, TrajoptSwingup,
                                ZeroSwingup)
from ..viz.meshcat import add_meshcat
from .blocks import Gate, HeldController, HeldLQR, ModeSwitch, RecurrentTorchPolicy, TorchPolicy
from .controllers import LQRController, energy_swingup
from .trajopt import TrajectoryTracker, trajopt_swingup


class HybridDiagram(Diagram):
    """A Drake Diagram of plant + LQR + swing-up + gate that remembers its System.

    ``CreateDefaultContext`` writes the spec's parameters into the plant's
    context (AcrobotPlant/PendulumPlant keep them in the Context). Attributes:
    ``system``, ``plant``, ``swingup``, ``balance``, ``gate``, ``switch`` and
    ``loggers`` (dict of VectorLogSink by signal name, or empty).
    """

    def __init__(self, builder: DiagramBuilder, system: System, parts: dict):
        super().__init__()
        builder.BuildInto(self)
        self.system = system
        self.plant = parts["plant"].plant
        self._apply_parameters = parts["plant"].apply_parameters
        self.swingup = parts["swingup"]
        self.balance = parts["balance"]
        self.gate = parts["gate"]
        self.switch = parts["switch"]
        self.loggers = parts["loggers"]
        self.scene_graph = parts["scene_graph"]
        self.set_name(f"{system.name}_hybrid")

    def CreateDefaultContext(self):  # noqa: N802 - Drake's name
        """A default Context with the spec's plant parameters applied."""
        context = super().CreateDefaultContext()
        self._apply_parameters(self.plant.GetMyMutableContextFromRoot(context))
        return context

    def set_state(self, context, x: np.ndarray) -> None:
        """Set the plant's state from ``x`` in the spec's convention."""
        plant_context = self.plant.GetMyMutableContextFromRoot(context)
        plant_context.SetContinuousState(self.system.to_drake_state(x))


def _swingup_block(system: System, swingup, period: float | None):
    if swingup is None or isinstance(swingup, str):
        if swingup not in (None, "energy", "trajopt"):
            raise ValueError(f"swingup must be None/'energy'/'trajopt', a torch module or a callable, got {swingup!r}")
        if swingup == "trajopt":   # collocation trajectory + TVLQR; reads the time from its Context
            return trajopt_swingup(system, period or system.control_period)
        fn = energy_swingup(system)
        return HeldController(fn, system.n_states, system.n_actions, period or system.control_period,
                              limit=system.action_limit, name="swingup")
    if isinstance(swingup, (HeldController, RecurrentTorchPolicy, TrajectoryTracker)):
        return swingup
    if isinstance(swingup, torch.nn.Module) and hasattr(swingup, "initial_state"):   # recurrent (APG's GRU)
        return RecurrentTorchPolicy(swingup, system.n_states, system.n_actions, period or system.swingup_period,
                                    limit=system.action_limit, name="swingup")
    if isinstance(swingup, torch.nn.Module):
        return TorchPolicy(swingup, system.n_states, system.n_actions, period or system.swingup_period,
                           limit=system.action_limit, name="swingup")
    return HeldController(swingup, system.n_states, system.n_actions, period or system.control_period,
                          limit=system.action_limit, name="swingup")


SWITCHES = ("drake", "python")


def _gate_block(system: System, gate, on: float | None, off: float | None, period: float | None = None):
    on = system.gate.on if on is None else float(on)
    off = system.gate.off if off is None else float(off)
    if isinstance(gate, Gate):
        return gate
    if gate is None or gate == "cost":
        gate = CostToGoGate(system)
    elif isinstance(gate, str):
        raise ValueError(f"gate must be None/'cost', a classifier module or callable, got {gate!r}")
    return Gate(gate, system.n_states, period or system.control_period, on=on, off=off, name="gate")


def _zero_command(x: np.ndarray) -> np.ndarray:
    return np.zeros(1)  # single-input systems only, as all benchmark systems are


def controller_of(system: System, swingup=None, gate=None, *, swingup_period: float | None = None,
                  gate_on: float | None = None, gate_off: float | None = None) -> SwitchedController:
    """The :class:`~hybridctl.systems.SwitchedController` that ``build_hybrid_diagram``'s keyword form names:
    ``swingup`` None / "energy" / "trajopt" / "zero" / a torch module / a numpy callable, ``gate`` None /
    "cost" / "always" / "never" / a classifier, with the spec's defaults."""
    markers = {None: EnergySwingup(), "energy": EnergySwingup(), "trajopt": TrajoptSwingup(), "zero": ZeroSwingup()}
    if swingup is None or isinstance(swingup, str):
        if swingup not in markers:
            raise ValueError(f"swingup must be None/'energy'/'trajopt', a torch module or a callable, got {swingup!r}")
        swingup = markers[swingup]
    gates = {"cost": None, "always": AlwaysGate(), "never": NeverGate()}
    if isinstance(gate, str):
        if gate not in gates:
            raise ValueError(f"gate must be None/'cost', a classifier module or callable, got {gate!r}")
        gate = gates[gate]
    return SwitchedController.for_system(system, swingup=swingup, gate=gate, decision_period=swingup_period,
                                         gate_on=gate_on, gate_off=gate_off)


def _drake_parts(system: System, controller: SwitchedController):
    """(swing-up, gate classifier) of ``controller`` as ``_swingup_block`` / ``_gate_block`` take them: the
    hand-designed laws as their numpy callables, a learned gate as its own module."""
    swingup = controller.swingup
    if isinstance(swingup, EnergySwingup):
        swingup = HeldController(swingup.law or energy_swingup(system), system.n_states, system.n_actions,
                                 controller.decision_period, limit=system.action_limit, name="swingup")
    elif isinstance(swingup, TrajoptSwingup):
        swingup = "trajopt"
    elif isinstance(swingup, ZeroSwingup):
        swingup = _zero_command
    elif swingup is None:
        raise ValueError("a Drake diagram needs the controller's swing-up (its swingup is None: an agent's)")
    gate = controller.gate
    return swingup, (gate.module if isinstance(gate, LearnedGate) else gate)


def build_hybrid_diagram(system: System, swingup=None, gate=None, *, balance=None,
                         swingup_period: float | None = None, gate_on: float | None = None,
                         gate_off: float | None = None, meshcat=None, log: bool = True,
                         switch: str = "drake") -> HybridDiagram:
    """Build plant + swing-up + LQR + gate + switch + saturation as a Drake Diagram.

    Args:
        system: a ``hybridctl.systems.System``.
        swingup: a :class:`~hybridctl.systems.SwitchedController` (the typed form: its swing-up, gate, K,
            decision period, hysteresis and gate period; ``gate`` must then be None, and
            ``swingup_period`` / ``gate_on`` / ``gate_off`` given here win over its own), or, in the
            keyword form mapped onto one (:func:`controller_of`): None or "energy" (the spec's energy-shaping swing-up, updated every
            ``control.period``), "trajopt" (a direct-collocation swing-up tracked by TVLQR,
            :mod:`.trajopt`, updated every ``control.period``; cached per system), a torch
            module (a learned policy as ``TorchPolicy`` held for ``control.swingup_period``), a
            numpy callable, or a ready block.
        gate: None or "cost" (cost-to-go gate ``CostToGoGate``), a torch classifier
            returning a probability, a callable, or a ready ``Gate``.
        balance: the balancing controller, updated every ``control.period``: None (the
            LQR from the spec's Q, R) or a gain K (m, n) run as ``HeldLQR`` (C++ primitives), a
            callable (run in a Python ``HeldController``) or a ready block.
        swingup_period: override the swing-up hold period.
        gate_on, gate_off: hysteresis thresholds (default: the spec's, 0.9 / 0.5).
        meshcat: a ``pydrake.geometry.Meshcat`` to draw the robot live, or None.
        log: add VectorLogSinks (one sample per integration step) for simulate().
        switch: "drake" (default): Drake's C++ ``PortSwitch`` driven by the gate's
            ``selector`` output and the LQR as ``HeldLQR``; "python": the loop before issue
            15, kept to measure against: the Python feedthrough ``ModeSwitch`` (evaluated at
            every derivative evaluation) driven by the gate's ``mode``, and the LQR in a
            Python ``HeldController``. Both give the same run (to rounding in the LQR).
    """
    if not isinstance(system, System):
        raise TypeError(f"system must be a hybridctl.systems.System, got {type(system).__name__}")
    if switch not in SWITCHES:
        raise ValueError(f"switch must be one of {SWITCHES}, got {switch!r}")
    if isinstance(swingup, SwitchedController):
        if gate is not None:
            raise ValueError("give the gate in the SwitchedController, not beside it")
        controller = swingup.replace(**{key: value for key, value in (
            ("decision_period", swingup_period), ("gate_on", gate_on), ("gate_off", gate_off)) if value is not None})
    elif isinstance(swingup, (HeldController, RecurrentTorchPolicy, TrajectoryTracker)) or isinstance(gate, Gate):
        controller = None     # ready blocks: built as they are
    else:
        controller = controller_of(system, swingup, gate, swingup_period=swingup_period, gate_on=gate_on,
                                   gate_off=gate_off)
    if controller is not None:
        if not np.array_equal(controller.goal, system.goal):
            raise ValueError(f"the Drake diagram's LQR drives to the system's goal {system.goal.tolist()}; load the "
                             f"system with the controller's goal {controller.goal.tolist()}")
        swingup, gate = _drake_parts(system, controller)
        swingup_period, gate_on, gate_off = controller.decision_period, controller.gate_on, controller.gate_off
        balance = controller.K if balance is None else balance
    period = system.control_period if controller is None else controller.gate_period
    builder = DiagramBuilder()
    handle, scene_graph = _plants.add_plant(system, builder, with_geometry=meshcat is not None)
    if meshcat is not None:
        # Publish events end integration steps: keep them on the dt grid (about 30 fps)
        # so a fixed-step run with the viewer equals one without it.
        frames = max(1, int(np.ceil((1 / 30) / system.dt - 1e-9)))
        add_meshcat(builder, scene_graph, meshcat, publish_period=frames * system.dt)

    # The Drake plant measures the acrobot's th1 from hanging down: convert once.
    offset = system.drake_state_offset()
    state_port = handle.state_output
    if np.any(offset):
        n = system.n_states
        convert = builder.AddSystem(AffineSystem(np.zeros((0, 0)), np.zeros((0, n)), np.zeros(0),
                                                 np.zeros((n, 0)), np.eye(n), -offset))
        convert.set_name("to_spec_state")
        builder.Connect(state_port, convert.get_input_port())
        state_port = convert.get_output_port()

    swing = builder.AddSystem(_swingup_block(system, swingup, swingup_period))
    if (balance is None or isinstance(balance, np.ndarray)) and switch == "drake":
        bal = HeldLQR(system, system.lqr()[0] if balance is None else balance, period,
                      limit=system.action_limit, name="balance")
    else:
        if balance is None or isinstance(balance, np.ndarray):
            balance = LQRController(system, K=balance)
        bal = balance if isinstance(balance, (HeldController, HeldLQR)) else HeldController(
            balance, system.n_states, system.n_actions, period, limit=system.action_limit,
            name="balance")
    bal = builder.AddSystem(bal)
    gate_block = builder.AddSystem(_gate_block(system, gate, gate_on, gate_off, period))
    if switch == "python":
        switch_block = builder.AddSystem(ModeSwitch(system.n_actions))
        swing_in, balance_in = switch_block.GetInputPort("swingup"), switch_block.GetInputPort("balance")
        builder.Connect(gate_block.GetOutputPort("mode"), switch_block.GetInputPort("mode"))
    else:
        switch_block = builder.AddSystem(PortSwitch(system.n_actions))
        switch_block.set_name("switch")
        swing_in, balance_in = switch_block.DeclareInputPort("swingup"), switch_block.DeclareInputPort("balance")
        if (swing_in.get_index(), balance_in.get_index()) != gate_block.selector_ports:
            raise ValueError(f"the gate selects input ports {gate_block.selector_ports}; the switch has swingup "
                             f"{swing_in.get_index()} and balance {balance_in.get_index()}")
        builder.Connect(gate_block.GetOutputPort("selector"), switch_block.get_port_selector_input_port())
    limit = np.full(system.n_actions, system.action_limit)
    saturation = builder.AddSystem(Saturation(-limit, limit))
    saturation.set_name("saturation")

    for block in (swing, bal, gate_block):
        builder.Connect(state_port, block.get_input_port(0))
    builder.Connect(swing.get_output_port(0), swing_in)
    builder.Connect(bal.get_output_port(0), balance_in)
    builder.Connect(switch_block.get_output_port(0), saturation.get_input_port())
    builder.Connect(saturation.get_output_port(), handle.actuation_input)

    outputs = {
        "state": state_port,
        "command": saturation.get_output_port(),
        "mode": gate_block.GetOutputPort("mode"),
        "probability": gate_block.GetOutputPort("probability"),
        "swingup_command": swing.get_output_port(0),
        "balance_command": bal.get_output_port(0),
    }
    for name, port in outputs.items():
        builder.ExportOutput(port, name)
    loggers = {}
    if log:
        for name in ("state", "command", "mode", "probability"):
            loggers[name] = LogVectorOutput(outputs[name], builder, system.dt)
            loggers[name].set_name(f"log_{name}")
    parts = dict(plant=handle, swingup=swing, balance=bal, gate=gate_block, switch=switch_block,
                 loggers=loggers, scene_graph=scene_graph)
    return HybridDiagram(builder, system, parts)
