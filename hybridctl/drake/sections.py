"""Poincare sections of Drake hybrid systems, found by witness functions (thesis Ch. 5).

The section is detected by a witness function on an observer block that ends the
simulation (``EventStatus.ReachedTermination``), not by a simulator monitor: a
monitor sees the state one integration step after a witness-triggered reset, which
gives a wrong return map (implementation notes, pydrake pitfalls).

:class:`DrakeRimlessWheelMap` is Drake's ``RimlessWheel`` (a hybrid system with
collision guards and resets) as a :class:`~hybridctl.analysis.poincare.SectionMap`:
state = angular velocity at the apex (stance leg vertical), disturbance = the slope
of the next step. It must agree with the analytic map
:class:`~hybridctl.analysis.poincare.RimlessWheel` (tests check 1e-6). The map
pickles as plain parameters; each process builds its own Drake diagram on first use.
"""

from __future__ import annotations

import math

import numpy as np
from pydrake.systems.framework import (BasicVector, DiagramBuilder, EventStatus, LeafSystem, PublishEvent,
                                       WitnessFunctionDirection)

from ..analysis.poincare import SectionMap

APEX = "apex"
ROLLED_BACK = "rolled back"


class SectionObserver(LeafSystem):
    """Ends a simulation when ``state[index]`` crosses 0 upwards (the section) or ``state[speed]``
    crosses 0 downwards (failure: the system turned back). The reason is kept in ``last_event``."""

    def __init__(self, size: int, index: int = 0, speed: int = 1):
        super().__init__()
        self.DeclareVectorInputPort("state", BasicVector(size))
        self.index, self.speed = index, speed
        self.last_event: str | None = None
        self._section = self.MakeWitnessFunction(
            "section", WitnessFunctionDirection.kNegativeThenNonNegative,
            lambda ctx: float(self.get_input_port(0).Eval(ctx)[self.index]),
            PublishEvent(lambda ctx, event: self._stop(APEX)))
        self._turned = self.MakeWitnessFunction(
            "turned back", WitnessFunctionDirection.kPositiveThenNonPositive,
            lambda ctx: float(self.get_input_port(0).Eval(ctx)[self.speed]),
            PublishEvent(lambda ctx, event: self._stop(ROLLED_BACK)))

    def _stop(self, reason: str):
        self.last_event = reason
        return EventStatus.ReachedTermination(self, reason)

    def DoGetWitnessFunctions(self, context):
        """Both witnesses, always active."""
        return [self._section, self._turned]


class DrakeRimlessWheelMap(SectionMap):
    """Apex-to-apex map of Drake's ``RimlessWheel`` with the slope as the disturbance.

    ``timeout``: simulated seconds without reaching the next apex that count as failure
    (the wheel came to rest in double support). ``accuracy``: the error-controlled
    integrator's target accuracy. ``max_step``: the integrator's largest step, which also
    bounds how precisely Drake isolates the collision witness: against the analytic map
    (20 random apex states and slopes) the largest difference was 5e-5 with Drake's default,
    2.3e-6 at 1e-2 (8 ms per apex here), 2.4e-9 at 1e-3 (28 ms) and 3e-12 at 1e-4 (150 ms).
    """

    state_names = ("w",)

    def __init__(self, half_angle: float = math.pi / 8, g_over_l: float = 9.81, timeout: float = 10.0,
                 accuracy: float = 1e-10, max_step: float = 1e-2):
        spokes = math.pi / half_angle
        if abs(spokes - round(spokes)) > 1e-9 or round(spokes) < 3:
            raise ValueError(f"half_angle must be pi / N for an integer number of spokes N >= 3, got {half_angle}")
        self.half_angle, self.g_over_l, self.timeout, self.accuracy = half_angle, g_over_l, timeout, accuracy
        self.max_step = max_step
        self._parts = None

    def __getstate__(self):
        return {k: v for k, v in self.__dict__.items() if k != "_parts"}   # Drake objects do not pickle

    def __setstate__(self, state):
        self.__dict__.update(state, _parts=None)

    def _build(self):
        from pydrake.examples import RimlessWheel
        from pydrake.systems.analysis import Simulator

        builder = DiagramBuilder()
        wheel = builder.AddSystem(RimlessWheel())
        observer = builder.AddSystem(SectionObserver(2))
        builder.Connect(wheel.get_output_port(0), observer.get_input_port(0))
        diagram = builder.Build()
        simulator = Simulator(diagram)
        simulator.get_mutable_integrator().set_maximum_step_size(self.max_step)
        context = simulator.get_mutable_context()
        context.SetAccuracy(self.accuracy)
        wheel_context = wheel.GetMyMutableContextFromRoot(context)
        params = wheel_context.get_mutable_numeric_parameter(0)
        params.set_number_of_spokes(round(math.pi / self.half_angle))
        params.set_length(1.0)
        params.set_gravity(self.g_over_l)
        self._parts = (simulator, context, wheel_context, observer)

    def step(self, state, disturbance):
        """Simulate from the apex with angular velocity ``state[0]`` on slope ``disturbance``."""
        if self._parts is None:
            self._build()
        simulator, context, wheel_context, observer = self._parts
        w = float(np.asarray(state).reshape(-1)[0])
        if not (w > 0):
            return None
        context.SetTime(0.0)
        wheel_context.get_mutable_numeric_parameter(0).set_slope(float(disturbance))
        wheel_context.SetContinuousState([0.0, w])
        wheel_context.get_mutable_discrete_state_vector().SetAtIndex(0, 0.0)   # stance toe position
        wheel_context.get_mutable_abstract_state(0).set_value(False)           # not in double support
        observer.last_event = None
        simulator.Initialize()
        simulator.AdvanceTo(self.timeout)
        if observer.last_event != APEX:
            return None
        return np.array([float(wheel_context.get_continuous_state_vector().CopyToVector()[1])])
