"""Poincare sections of Drake hybrid systems, found by witness functions (thesis Ch. 5).

The section is detected by a witness function on an observer block that ends the
simulation (``EventStatus.ReachedTermination``), not by a simulator monitor: a
monitor sees the state one integration step after a witness-triggered reset, which
gives a wrong return map (implementation notes, pydrake pitfalls).

:class:`DrakeRimlessWheelMap` is Drake's ``RimlessWheel`` (a hybrid system with
collision guards and resets) as a :class:`~hybridctl.analysis.poincare.SectionMap`:
state = angular velocity at the apex (stance leg vertical), disturbance = the slope
of the next step. It must agree with the analytic map
:class:`~hybridctl.analysis.poincare.RimlessWheel` (tests check 2e-6 at the default accuracy, 1e-9 at 1e-10). The map
pickles as plain parameters; each process builds its own Drake diagram on first use.
"""

from __future__ import annotations

import math
import time

import numpy as np
from pydrake.systems.framework import (BasicVector, DiagramBuilder, EventStatus, LeafSystem, PublishEvent,
                                       WitnessFunctionDirection)

from ..analysis.poincare import SectionMap
from ..limits import MAX_SECTION_INTEGRATOR_STEPS, MAX_SECTION_STEP_SECONDS

APEX = "apex"
ROLLED_BACK = "rolled back"
TIMED_OUT = "no section within the simulated-time limit"
WALL_GUARD = "wall-time guard"
STEPS_GUARD = "integrator-step guard"
STRIKES_GUARD = "heel-strike guard"
GUARDS = (WALL_GUARD, STEPS_GUARD, STRIKES_GUARD)
"""Why a step stopped early (``last_failure``); each counts as a fall and is tallied in ``guard_trips``."""


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
    diagram is built on first use in each process, since Drake objects do not pickle).

    Every step is guarded, so that none hangs: no section within ``timeout`` s of simulated time,
    more than ``max_integrator_steps`` integrator steps (default
    :data:`~hybridctl.limits.MAX_SECTION_INTEGRATOR_STEPS`), more than ``max_strikes`` collisions
    (subclasses; None: no limit) or more than ``wall_limit`` s of wall time (default
    :data:`~hybridctl.limits.MAX_SECTION_STEP_SECONDS`) each end the step as a fall (None). The
    reason is in ``last_failure`` and the guards' trips are counted in ``guard_trips`` (per process:
    worker processes keep their own). Only the wall-time guard depends on the machine; the others
    keep the map a pure function of (state, disturbance).
    """

    section_index = 0        # the state coordinate whose upward zero crossing is the section
    speed_index = 1          # the rate whose downward zero crossing is failure (turned back)
    max_strikes: int | None = None    # collisions (stance-toe moves) one step may have

    def __init__(self, timeout: float, accuracy: float, max_step: float, wall_limit: float = MAX_SECTION_STEP_SECONDS,
                 max_integrator_steps: int = MAX_SECTION_INTEGRATOR_STEPS):
        for name, value in (("timeout", timeout), ("accuracy", accuracy), ("max_step", max_step),
                            ("wall_limit", wall_limit), ("max_integrator_steps", max_integrator_steps)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be finite and > 0, got {value}")
        self.timeout, self.accuracy, self.max_step = timeout, accuracy, max_step
        self.wall_limit, self.max_integrator_steps = float(wall_limit), int(max_integrator_steps)
        self.last_failure: str | None = None
        self.guard_trips = {name: 0 for name in GUARDS}
        self._parts = None

    def __getstate__(self):
        return {k: v for k, v in self.__dict__.items() if k not in ("_parts", "_guard")}   # Drake objects do not pickle

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
        # The integrator's own target: the Simulator gives its integrator a target of 1e-4, which wins over
        # the context's accuracy, so a context-only setting was silently ignored (a 1e-10 "accuracy" ran at 1e-4).
        simulator.get_mutable_integrator().set_target_accuracy(self.accuracy)
        simulator.get_mutable_integrator().set_maximum_step_size(self.max_step)
        context = simulator.get_mutable_context()
        context.SetAccuracy(self.accuracy)
        plant_context = plant.GetMyMutableContextFromRoot(context)
        self._configure(plant_context)
        simulator.set_monitor(lambda root: self._monitor(plant_context))
        self._parts = (simulator, context, plant_context, observer)

    def _monitor(self, plant_context):
        """After each simulator step: stop the step (as a fall) when a guard trips."""
        guard = self._guard
        guard["steps"] += 1
        toe = plant_context.get_discrete_state_vector().GetAtIndex(0)
        if toe != guard["toe"]:
            guard["toe"], guard["strikes"] = toe, guard["strikes"] + 1
        if self.max_strikes is not None and guard["strikes"] > self.max_strikes:
            guard["tripped"] = STRIKES_GUARD
        elif guard["steps"] > self.max_integrator_steps:
            guard["tripped"] = STEPS_GUARD
        elif guard["steps"] % 64 == 0 and time.monotonic() > guard["deadline"]:
            guard["tripped"] = WALL_GUARD
        else:
            return EventStatus.DidNothing()
        return EventStatus.ReachedTermination(None, guard["tripped"])

    def _full_state(self, state: np.ndarray) -> list[float]:
        """The plant's continuous state on the section for a section state."""
        raise NotImplementedError

    def step(self, state, disturbance):
        """Simulate from the section state on slope ``disturbance`` to the next section, or None
        (a fall; why in ``last_failure``)."""
        if self._parts is None:
            self._build()
        simulator, context, plant_context, observer = self._parts
        state = np.asarray(state, dtype=np.float64).reshape(-1)
        self.last_failure = "not finite"
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
        integrator.set_target_accuracy(self.accuracy)
        integrator.set_maximum_step_size(self.max_step)
        self._guard = {"steps": 0, "strikes": 0, "toe": 0.0, "tripped": None,
                       "deadline": time.monotonic() + self.wall_limit}
        simulator.Initialize()
        simulator.AdvanceTo(self.timeout)
        tripped = self._guard["tripped"]
        if tripped is not None:
            self.guard_trips[tripped] += 1
            self.last_failure = tripped
            return None
        if observer.last_event != APEX:
            self.last_failure = observer.last_event or TIMED_OUT
            return None
        self.last_failure = None
        x = plant_context.get_continuous_state_vector().CopyToVector()
        return np.delete(x, self.section_index)

    def _reset_abstract(self, plant_context) -> None:
        raise NotImplementedError


class DrakeRimlessWheelMap(_DrakeSectionMap):
    """Apex-to-apex map of Drake's ``RimlessWheel`` with the slope as the disturbance.

    ``timeout``: simulated seconds without reaching the next apex that count as failure
    (the wheel came to rest in double support). ``accuracy``: the error-controlled integrator's
    target accuracy and the witnesses' isolation. ``max_step``: the integrator's largest step.
    Against the analytic map (20 random apex states and slopes, max_step 1e-2) the largest
    difference was 7.6e-7 at accuracy 1e-6 (the default, 4 ms an apex here), 8.1e-9 at 1e-8
    (11 ms) and 8.2e-11 at 1e-10 (39 ms).
    """

    state_names = ("w",)

    def __init__(self, half_angle: float = math.pi / 8, g_over_l: float = 9.81, timeout: float = 10.0,
                 accuracy: float = 1e-6, max_step: float = 1e-2):
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
            self.last_failure = ROLLED_BACK
            return None
        return super().step(state, disturbance)


COMPASS_GAIT_RANGES = {"mass_hip": (1e-3, 1e4), "mass_leg": (1e-3, 1e4), "length_leg": (1e-2, 1e2),
                       "gravity": (1e-2, 1e3), "slope": (-0.5, 0.5)}
"""Ranges (inclusive) of :class:`DrakeCompassGaitMap`'s parameters; ``center_of_mass_leg`` is in
(0, ``length_leg``]."""


def hip_pd_block(kp: float, kd: float, target: float):
    """Hip torque ``u = kp (target - (swing - stance)) - kd (swingdot - stancedot)`` from the compass
    gait's state (stance, swing, stancedot, swingdot): a PD on the inter-leg angle toward ``target`` (rad),
    as Drake's stateless ``AffineSystem`` ``u = D x + y0``.

    A C++ block, not a Python ``LeafSystem``: the integrator evaluates the torque several times a step,
    and the Python callback made each compass-gait step 2x slower (40 against 21 ms here)."""
    from pydrake.systems.primitives import AffineSystem

    gains = np.array([[kp, -kp, kd, -kd]], dtype=np.float64)
    return AffineSystem(np.zeros((0, 0)), np.zeros((0, 4)), np.zeros(0), np.zeros((1, 0)), gains,
                        np.array([kp * target], dtype=np.float64))


class DrakeCompassGaitMap(_DrakeSectionMap):
    """Mid-stance-to-mid-stance map of Drake's ``CompassGait``, slope per step (the disturbance).

    Section: the stance leg passes vertical (stance angle 0, walking forward). Section state:
    (swing angle, stance rate, swing rate). Failure (None): a stance rate <= 0 on the section, the
    stance leg turns back, no next section within ``timeout`` s of simulated time (default 5 s: the
    walker stopped or lies on the ground), more than ``max_strikes`` (2) heel strikes in one step (the
    legs chatter on the ground, a Zeno fall that once ran for minutes), or the integrator-step and
    wall-time guards of :class:`_DrakeSectionMap`; ``last_failure`` says which.

    Parameters (Drake's ``CompassGaitParams``, ranges in :data:`COMPASS_GAIT_RANGES`): ``mass_hip``,
    ``mass_leg`` (kg), ``length_leg`` (m), ``center_of_mass_leg`` (m from the hip), ``gravity``;
    ``slope`` is the nominal slope (rad) that :meth:`gait` walks on (each step's slope is the
    disturbance). ``hip_pd=(kp, kd, target)``: a hip-torque controller (:func:`hip_pd_block`); None (default):
    the passive walker (torque 0). On the defaults the map has a period-1 passive gait near
    (-0.0927, 0.4239, -1.9771) (see :meth:`gait`).

    ``accuracy`` (the integrator's target and the witnesses' isolation) and ``max_step``: against a
    reference at 1e-11 and 1e-4 (12 section states within 0.02 of the gait, slopes 0.0525 +- 0.005), the
    defaults 1e-7 and 1e-3 differ by at most 6.4e-8, passive or with ``hip_pd=(10, 1, -0.4)``
    (14-18 ms a step here); 1e-6 by 4.2e-7 (17-18 ms), 1e-8 by 1.2e-8 (29 ms).
    """

    state_names = ("swing", "stancedot", "swingdot")
    section_index, speed_index = 0, 2
    max_strikes = 2

    def __init__(self, mass_hip: float = 10.0, mass_leg: float = 5.0, length_leg: float = 1.0,
                 center_of_mass_leg: float = 0.5, gravity: float = 9.81, slope: float = 0.0525,
                 hip_pd: tuple[float, float, float] | None = None, timeout: float = 5.0, accuracy: float = 1e-7,
                 max_step: float = 1e-3, **guards):
        values = {"mass_hip": mass_hip, "mass_leg": mass_leg, "length_leg": length_leg, "gravity": gravity,
                  "slope": slope}
        for name, value in values.items():
            lo, hi = COMPASS_GAIT_RANGES[name]
            if not (math.isfinite(value) and lo <= value <= hi):
                raise ValueError(f"{name} must be in [{lo:g}, {hi:g}], got {value}")
        if not (math.isfinite(center_of_mass_leg) and 0 < center_of_mass_leg <= length_leg):
            raise ValueError(f"center_of_mass_leg must be in (0, length_leg={length_leg:g}], got {center_of_mass_leg}")
        if hip_pd is not None:
            hip_pd = tuple(float(v) for v in hip_pd)
            if len(hip_pd) != 3 or not all(math.isfinite(v) for v in hip_pd):
                raise ValueError(f"hip_pd must be three finite numbers (kp, kd, target), got {hip_pd}")
        super().__init__(timeout, accuracy, max_step, **guards)
        self.params = {**values, "center_of_mass_leg": center_of_mass_leg}
        self.slope, self.hip_pd = slope, hip_pd

    def _plant(self, builder):
        from pydrake.examples import CompassGait
        from pydrake.systems.primitives import ConstantVectorSource

        plant = builder.AddSystem(CompassGait())
        if self.hip_pd is None:
            torque = builder.AddSystem(ConstantVectorSource([0.0]))
        else:
            torque = builder.AddSystem(hip_pd_block(*self.hip_pd))
            builder.Connect(plant.get_output_port(0), torque.get_input_port(0))
        builder.Connect(torque.get_output_port(0), plant.get_input_port(0))
        return plant

    def _configure(self, plant_context):
        params = plant_context.get_mutable_numeric_parameter(0)
        for name, value in self.params.items():
            getattr(params, f"set_{name}")(float(value))

    def _full_state(self, state):
        return [0.0, *map(float, state)]

    def _reset_abstract(self, plant_context):
        plant_context.get_mutable_abstract_state(0).set_value(True)    # left leg is the stance leg

    def step(self, state, disturbance):
        """Simulate from mid-stance (swing, stancedot, swingdot) on slope ``disturbance``; None: a fall."""
        if not float(np.asarray(state, dtype=np.float64).reshape(-1)[1]) > 0:
            self.last_failure = ROLLED_BACK
            return None
        return super().step(state, disturbance)

    def gait(self, slope: float | None = None, start=(0.0, 0.4, -2.0), steps: int = 60) -> np.ndarray:
        """The gait's section state on a constant ``slope`` (default: the map's ``slope``), by iterating the map."""
        slope = self.slope if slope is None else slope
        s = np.asarray(start, dtype=np.float64)
        for _ in range(steps):
            nxt = self.step(s, slope)
            if nxt is None:
                raise ValueError(f"the compass gait fell on slope {slope} while settling into its gait "
                                 f"({self.last_failure})")
            s = nxt
        return s
