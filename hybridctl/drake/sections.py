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


class _DrakeSectionMap(SectionMap):
    """A Drake hybrid system with a slope parameter as a section map (plain parameters; the
    diagram is built on first use in each process, since Drake objects do not pickle)."""

    section_index = 0        # the state coordinate whose upward zero crossing is the section
    speed_index = 1          # the rate whose downward zero crossing is failure (turned back)

    def __init__(self, timeout: float, accuracy: float, max_step: float):
        self.timeout, self.accuracy, self.max_step = timeout, accuracy, max_step
        self._parts = None

    def __getstate__(self):
        return {k: v for k, v in self.__dict__.items() if k != "_parts"}   # Drake objects do not pickle

    def __setstate__(self, state):
        self.__dict__.update(state, _parts=None)

    def _plant(self, builder):
        """Add the plant (and any fixed inputs); return it."""
        raise NotImplementedError

    def _configure(self, plant_context) -> None:
        """Set the plant's fixed parameters."""

    def _build(self):
        from pydrake.systems.analysis import Simulator

        builder = DiagramBuilder()
        plant = self._plant(builder)
        size = plant.get_output_port(0).size()
        observer = builder.AddSystem(SectionObserver(size, self.section_index, self.speed_index))
        builder.Connect(plant.get_output_port(0), observer.get_input_port(0))
        diagram = builder.Build()
        simulator = Simulator(diagram)
        simulator.get_mutable_integrator().set_maximum_step_size(self.max_step)
        context = simulator.get_mutable_context()
        context.SetAccuracy(self.accuracy)
        plant_context = plant.GetMyMutableContextFromRoot(context)
        self._configure(plant_context)
        self._parts = (simulator, context, plant_context, observer)

    def _full_state(self, state: np.ndarray) -> list[float]:
        """The plant's continuous state on the section for a section state."""
        raise NotImplementedError

    def step(self, state, disturbance):
        """Simulate from the section state on slope ``disturbance`` to the next section, or None."""
        if self._parts is None:
            self._build()
        simulator, context, plant_context, observer = self._parts
        state = np.asarray(state, dtype=np.float64).reshape(-1)
        if not np.all(np.isfinite(state)):
            return None
        context.SetTime(0.0)
        plant_context.get_mutable_numeric_parameter(0).set_slope(float(disturbance))
        plant_context.SetContinuousState(self._full_state(state))
        plant_context.get_mutable_discrete_state_vector().SetAtIndex(0, 0.0)   # stance toe position
        self._reset_abstract(plant_context)
        observer.last_event = None
        # An error-controlled integrator carries its step-size history from the last call; reset it so
        # that the map is a pure function of (state, disturbance), bit for bit, in any process.
        integrator = simulator.get_mutable_integrator()
        integrator.Reset()
        integrator.set_maximum_step_size(self.max_step)
        simulator.Initialize()
        simulator.AdvanceTo(self.timeout)
        if observer.last_event != APEX:
            return None
        x = plant_context.get_continuous_state_vector().CopyToVector()
        return np.delete(x, self.section_index)

    def _reset_abstract(self, plant_context) -> None:
        raise NotImplementedError


class DrakeRimlessWheelMap(_DrakeSectionMap):
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
        super().__init__(timeout, accuracy, max_step)
        self.half_angle, self.g_over_l = half_angle, g_over_l

    def _plant(self, builder):
        from pydrake.examples import RimlessWheel
        return builder.AddSystem(RimlessWheel())

    def _configure(self, plant_context):
        params = plant_context.get_mutable_numeric_parameter(0)
        params.set_number_of_spokes(round(math.pi / self.half_angle))
        params.set_length(1.0)
        params.set_gravity(self.g_over_l)

    def _full_state(self, state):
        return [0.0, float(state[0])]

    def _reset_abstract(self, plant_context):
        plant_context.get_mutable_abstract_state(0).set_value(False)   # not in double support

    def step(self, state, disturbance):
        """Simulate from the apex with angular velocity ``state[0]`` on slope ``disturbance``."""
        if not float(np.asarray(state).reshape(-1)[0]) > 0:
            return None
        return super().step(state, disturbance)


class DrakeCompassGaitMap(_DrakeSectionMap):
    """Mid-stance-to-mid-stance map of Drake's passive ``CompassGait`` (hip torque 0), slope per step.

    Section: the stance leg passes vertical (stance angle 0, walking forward). Section state:
    (swing angle, stance rate, swing rate). Failure: the stance leg turns back, or no next
    section within ``timeout`` s. On Drake's default slope 0.0525 the map has a period-1
    passive gait near (-0.0927, 0.4239, -1.9771) (see :meth:`gait`).
    """

    state_names = ("swing", "stancedot", "swingdot")
    section_index, speed_index = 0, 2

    def __init__(self, timeout: float = 5.0, accuracy: float = 1e-10, max_step: float = 1e-3):
        super().__init__(timeout, accuracy, max_step)

    def _plant(self, builder):
        from pydrake.examples import CompassGait
        from pydrake.systems.primitives import ConstantVectorSource

        plant = builder.AddSystem(CompassGait())
        torque = builder.AddSystem(ConstantVectorSource([0.0]))
        builder.Connect(torque.get_output_port(0), plant.get_input_port(0))
        return plant

    def _full_state(self, state):
        return [0.0, *map(float, state)]

    def _reset_abstract(self, plant_context):
        plant_context.get_mutable_abstract_state(0).set_value(True)    # left leg is the stance leg

    def gait(self, slope: float = 0.0525, start=(0.0, 0.4, -2.0), steps: int = 60) -> np.ndarray:
        """The passive gait's section state on a constant ``slope``, by iterating the map."""
        s = np.asarray(start, dtype=np.float64)
        for _ in range(steps):
            nxt = self.step(s, slope)
            if nxt is None:
                raise ValueError(f"the compass gait fell on slope {slope} while settling into its gait")
            s = nxt
        return s
