"""Simulating hybrid diagrams into a ``Trajectory`` (times, states, inputs, gate mode)."""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.systems.analysis import ResetIntegratorFromFlags, Simulator

from .. import io
from ..limits import MAX_SIMULATION_STEPS, check_at_most, check_fits_memory
from ..systems import System
from ..systems.control import DIVERGENCE_BOUND
from ..systems.success import decision_indices, episode_return, is_balanced
from ..viz.angles import wrap_about_goal

_DRAKE_INTEGRATOR = {"euler": "explicit_euler", "runge_kutta2": "runge_kutta2"}
# A state this large means the simulation has left any physical regime.


@dataclass
class Trajectory:
    """A simulated run: samples every ``system.dt`` from t = 0.

    ``t`` (T,), ``x`` (T, n) states in the spec convention, ``u`` (T, m) the
    (saturated) input applied over [t_k, t_k+1), ``gate`` (T,) the mode over that
    interval (0 swing-up, 1 balance), ``probability`` (T,) the gate output computed
    at t_k;
    so (x[k], u[k]) -> x[k+1] is one step of ``System.step``. ``diverged`` marks a
    run stopped because the state left the finite range (then the inputs of the
    last sample repeat the previous ones).
    """

    system: System
    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    gate: np.ndarray
    probability: np.ndarray
    diverged: bool = False
    wall_time: float = 0.0
    meta: dict = field(default_factory=dict)

    def decision_states(self, period: float | None = None) -> np.ndarray:
        """States at the swing-up decision times k * period, k >= 1 (thesis: 50 per 10 s)."""
        period = self.system.swingup_period if period is None else period
        return self.x[decision_indices(len(self.t), self.system.dt, period)]

    @property
    def balanced(self) -> bool:
        """Thesis eq. 3.2 on the decision-rate states (False if the run diverged)."""
        return (not self.diverged) and bool(is_balanced(self.decision_states(), self.system))

    @property
    def episode_return(self) -> float:
        """Sum of the per-decision reward (thesis eq. 3.1; acrobot max 100 over 10 s)."""
        states = self.decision_states()
        return episode_return(states, self.system) if len(states) else 0.0

    def summary(self) -> dict:
        """JSON-ready summary: balanced, return, diverged, durations, first LQR time, the final state
        (``final_state`` with angles wrapped into [goal - pi, goal + pi), ``final_state_unwrapped``)."""
        on = np.flatnonzero(self.gate > 0.5)
        return {
            "system": self.system.name,
            "balanced": self.balanced,
            "return": self.episode_return,
            "diverged": self.diverged,
            "duration": float(self.t[-1]) if len(self.t) else 0.0,
            "samples": int(len(self.t)),
            "first_balance_time": float(self.t[on[0]]) if len(on) else None,
            "fraction_in_balance_mode": float(np.mean(self.gate > 0.5)) if len(self.gate) else 0.0,
            "max_abs_input": float(np.abs(self.u).max()) if self.u.size else 0.0,
            "x0": self.x[0].tolist() if len(self.x) else None,
            # angles wrapped about the goal, as the plots draw them (an elbow that made full turns on the
            # way up ends at the goal, not at 4 pi); the unwrapped state is kept beside it
            "final_state": wrap_about_goal(self.x[-1:], self.system)[0].tolist() if len(self.x) else None,
            "final_state_unwrapped": self.x[-1].tolist() if len(self.x) else None,
            "wall_time_s": self.wall_time,
            "realtime_factor": (float(self.t[-1]) / self.wall_time) if self.wall_time > 0 and len(self.t) else None,
            **self.meta,
        }

    def save(self, out_dir: str | Path) -> dict:
        """Write ``trajectory.npz`` (t, x, u, gate, probability) and ``summary.json`` atomically."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        io.atomic_write(out / "trajectory.npz", lambda f: np.savez(f, t=self.t, x=self.x, u=self.u,
                                                                  gate=self.gate, probability=self.probability))
        summary = self.summary()
        io.atomic_write(out / "summary.json", lambda f: f.write(json.dumps(summary, indent=2).encode()))
        return summary


def _validate_x0(x0, n: int) -> np.ndarray:
    x0 = np.asarray(x0, dtype=float)
    if x0.shape != (n,):
        raise ValueError(f"x0 must have shape ({n},), got {x0.shape}")
    if not np.all(np.isfinite(x0)):
        raise ValueError(f"x0 contains NaN or Inf: {x0}")
    if np.any(np.abs(x0) > DIVERGENCE_BOUND):
        raise ValueError(f"x0 entries must lie in [-{DIVERGENCE_BOUND:g}, {DIVERGENCE_BOUND:g}] "
                         f"(beyond it a state counts as diverged), got {x0}")
    return x0


CHECK_STEPS = 25
"""simulate() checks for divergence every this many integration steps (not at every step: a
Python monitor called by Drake after each step cost more than the rest of the loop)."""


class _Runner:
    """One Context and Simulator of a diagram, reset for every run (cached on the diagram).

    Building them costs more than a short run; a reset restores the time, the state (the
    plant's, the held commands, the gate's mode, recurrent policies' hidden states) and the
    parameters from a pristine default Context and clears the loggers.
    """

    def __init__(self, diagram):
        system = diagram.system
        self.pristine = diagram.CreateDefaultContext()
        self.context = self.pristine.Clone()
        self.simulator = Simulator(diagram, self.context)
        integrator = ResetIntegratorFromFlags(self.simulator, _DRAKE_INTEGRATOR[system.integrator], system.dt)
        integrator.set_fixed_step_mode(True)
        self.plant_context = diagram.plant.GetMyContextFromRoot(self.context)
        self.logger_contexts = {name: logger.GetMyContextFromRoot(self.context)
                                for name, logger in diagram.loggers.items()}

    def reset(self, diagram, x0: np.ndarray, realtime_rate: float) -> None:
        self.context.SetTimeStateAndParametersFrom(self.pristine)
        for name, logger in diagram.loggers.items():
            logger.GetMutableLog(self.logger_contexts[name]).Clear()
        diagram.set_state(self.context, x0)
        self.simulator.set_target_realtime_rate(realtime_rate)
        self.simulator.Initialize()


def _runner(diagram) -> _Runner:
    runner = getattr(diagram, "_hybridctl_runner", None)
    if runner is None:
        runner = _Runner(diagram)
        diagram._hybridctl_runner = runner
    return runner


def _first_diverged(x: np.ndarray) -> int | None:
    """Index of the first row of ``x`` (T, n) that is non-finite or beyond DIVERGENCE_BOUND, or None."""
    with np.errstate(invalid="ignore"):
        bad = np.flatnonzero(~(np.abs(x) < DIVERGENCE_BOUND).all(axis=1))
    return int(bad[0]) if len(bad) else None


RECORDED_BYTES_PER_VALUE = 3 * 8
"""Bytes one recorded float64 takes while a run is simulated: Drake's logs grow by doubling (up to
twice the samples), and the Trajectory copies them out once."""


def check_duration(system: System, duration: float | None, force: bool = False, name: str = "--duration") -> float:
    """The duration of one run (default: the spec's episode), checked before any work.

    Raises ValueError (``name`` in one line) for a duration that is not a finite number > 0 or
    is shorter than one time step ``dt`` (nothing would be recorded); LimitError for one of
    more than :data:`~hybridctl.limits.MAX_SIMULATION_STEPS` steps (``force`` lifts that cap)
    or whose recorded trajectory would not fit in memory (nothing lifts that).
    """
    duration = system.episode_duration if duration is None else float(duration)
    if not (math.isfinite(duration) and duration > 0):
        raise ValueError(f"{name} must be a finite number > 0 (seconds), got {duration:g}")
    if duration < system.dt * (1 - 1e-9):
        raise ValueError(f"{name} {duration:g} s is shorter than one time step of {system.name} "
                         f"(dt = {system.dt:g} s): nothing would be simulated")
    check_at_most(name, duration, MAX_SIMULATION_STEPS * system.dt, force,
                  why=f"seconds of one run: {MAX_SIMULATION_STEPS:,} steps of dt = {system.dt:g} s")
    steps = duration / system.dt
    # the four logs: state (n), command (m), mode and probability, each with its sample times
    values = (system.n_states + 1) + (system.n_actions + 1) + 2 + 2
    check_fits_memory(name, steps * values * RECORDED_BYTES_PER_VALUE, f"the recorded run of {steps:,.0f} steps")
    return duration


def simulate(diagram, x0, duration: float | None = None, realtime_rate: float = 0.0,
             force: bool = False) -> Trajectory:
    """Simulate a hybrid diagram from ``x0`` (spec convention) for ``duration`` seconds.

    Uses the spec's integrator as a Drake fixed-step integrator of step ``dt``
    (explicit Euler for the acrobot, as the thesis), so a run equals the torch
    ``System.step`` loop. A run whose state becomes non-finite or exceeds
    ``DIVERGENCE_BOUND`` stops early with ``diverged=True`` instead of raising: the
    trajectory ends at the first such state (checked every ``CHECK_STEPS`` steps, so the
    simulation itself may run a few steps past it). ``realtime_rate`` > 0 paces the
    simulation (e.g. 1.0 to watch in meshcat). One Context and Simulator per diagram are
    kept and reset for every call, so repeated runs (balance maps) do not rebuild them.
    A duration is refused before any work as :func:`check_duration` says (``force`` lifts the
    step cap, not the memory limit).
    """
    system: System = getattr(diagram, "system", None)
    if system is None:
        raise TypeError("diagram must come from hybridctl.drake.build_hybrid_diagram")
    if not diagram.loggers:
        raise ValueError("diagram was built with log=False; rebuild with log=True to simulate into a Trajectory")
    x0 = _validate_x0(x0, system.n_states)
    duration = check_duration(system, duration, force, name="duration")

    runner = _runner(diagram)
    runner.reset(diagram, x0, realtime_rate)
    simulator, context, plant_context = runner.simulator, runner.context, runner.plant_context
    # Past the end: Drake logs the command held over [t_k-1, t_k) at t_k, so the input
    # applied from the last sample on is logged at t_end + dt. A second extra step keeps
    # that sample off the final time, where events are ordered differently. The checks
    # fall on the dt grid (k * dt, as Drake's periodic event times), so they cut no step.
    end = duration + 2 * system.dt
    last = int(np.floor(end / system.dt + 1e-9))
    checks = [k * system.dt for k in range(CHECK_STEPS, last, CHECK_STEPS)] + [end]
    error = None
    start = time.perf_counter()
    try:
        for boundary in checks:
            simulator.AdvanceTo(boundary)
            x = plant_context.get_continuous_state_vector().CopyToVector()
            if not np.all(np.abs(x) < DIVERGENCE_BOUND):  # also catches NaN
                break
    except RuntimeError as exc:  # Drake raises on NaN derivatives in some integrators
        error = str(exc)
    wall = time.perf_counter() - start

    logs = {name: logger.GetLog(runner.logger_contexts[name]) for name, logger in diagram.loggers.items()}
    t = logs["state"].sample_times()
    states = logs["state"].data().T
    n_samples = len(t)
    bad = _first_diverged(states + system.drake_state_offset())   # the plant's own coordinates
    diverged = bad is not None or error is not None
    if bad is not None:
        n_samples = bad + 1          # the run ends at the first diverged state
        error = None                 # an error after the divergence is its consequence
    elif error is None:
        diverged = context.get_time() < duration + 1.5 * system.dt
    t = t[:n_samples]
    keep = int(np.searchsorted(t, duration + 0.5 * system.dt))  # samples with t <= duration

    def applied(data: np.ndarray) -> np.ndarray:
        """Shift held values one sample back; repeat the last where the run stopped early."""
        shifted = data[1:min(keep + 1, n_samples)]
        return np.concatenate([shifted, shifted[-1:]]) if len(shifted) < keep and len(shifted) else shifted

    traj = Trajectory(
        system=system,
        t=t[:keep].copy(),
        x=states[:keep].copy(),
        u=applied(logs["command"].data().T).copy(),
        gate=applied(logs["mode"].data()[0]).copy(),
        probability=applied(logs["probability"].data()[0]).copy(),
        diverged=diverged,
        wall_time=wall,
        meta={} if error is None else {"error": error},
    )
    return traj
