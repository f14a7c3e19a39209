"""A classical swing-up from Drake's own tools: direct collocation + time-varying LQR.

For any :class:`~hybridctl.systems.System`:

1. :func:`swingup_trajectory` solves Drake's ``DirectCollocation`` (``pydrake.planning``) on the
   system's Drake plant from hanging down at rest (``initial_state.nominal``) to the goal, minimising
   the input effort over a fixed duration, inputs within a margin of ``action_limit`` (the shortest of
   a ladder of durations that solves; Hargraves & Paris 1987; Tedrake, Underactuated Robotics, ch.
   "Trajectory Optimization"). Every setting is in :class:`TrajoptSettings`.
2. :func:`tracking_gains` runs Drake's ``FiniteHorizonLinearQuadraticRegulator`` along it, with the
   spec's Q, R and the infinite-horizon LQR's S (``system.lqr()``) as final cost, so at the end of the
   trajectory the gain is the balancing LQR's (Tedrake, ch. "Linear Quadratic Regulators", TVLQR).
3. :class:`TrajectoryTracker` is the Drake block: every ``period`` it reads the time from its Context and
   holds ``u = u0(t) - K(t) (x - x0(t)) - k0(t)``, clipped to the action limit (angles of the error
   wrapped). In :func:`hybridctl.drake.build_hybrid_diagram` (``swingup="trajopt"``) it is the swing-up
   block: the spec's cost-to-go gate hands over to Drake's LQR at the top.

Solving takes from 0.1 s (the acrobot) to about 10 s (the double cart-pole), so both results are cached
per system as
``.npz`` files (read with ``allow_pickle=False``, written atomically), named by a hash of everything that
determines them: the spec's values, the Drake model, the settings, the period and Drake's version. The
cache folder is ``$HYBRIDCTL_CACHE/trajopt`` when ``HYBRIDCTL_CACHE`` is set, else ``runs/trajopt`` in
the working folder. A cache file that cannot be read, or does not hold what its name promises, is
reported (a warning) and recomputed; it is never unpickled, and the sizes in its array headers are checked
(``limits.MAX_TRAJOPT_ROWS``) before anything is allocated. A swing-up that Drake cannot compute (SNOPT's
iteration limit, the Riccati integration's step below Drake's minimum) is a :class:`TrajoptError`: one line
naming the system, the stage and what to try.
"""

from __future__ import annotations

import math
import os
import time
import warnings
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np
from pydrake.systems.framework import Context, DiagramBuilder, DiscreteValues, LeafSystem

from ..limits import MAX_TRAJOPT_KNOTS, MAX_TRAJOPT_ROWS, check_at_most
from ..systems import System, control
from ..systems import plants as _plants
from .trajopt_cache import CACHE_ENV, DEFAULT_CACHE, cache_folder, cache_key  # noqa: F401 - the module's names of old
from .trajopt_cache import load_npz as _load_npz
from .trajopt_cache import save_npz as _save_npz

class TrajoptError(ValueError):
    """A swing-up Drake could not compute: one line naming the system, the stage, what to try (CLI: exit 2)."""


SOLVE_FIELDS = ("knots", "durations", "input_margin", "cart_bound", "major_iterations", "minor_iterations")
"""The :class:`TrajoptSettings` fields that change the collocation solve (the trajectory's cache key)."""


@dataclass(frozen=True)
class TrajoptSettings:
    """Every setting of the collocation swing-up and its tracking, each with its value's source.

    The problem (Tedrake, Underactuated Robotics, ch. "Trajectory Optimization"): minimise the effort
    integral of |u / action_limit|^2 over a swing-up of fixed duration T from hanging down at rest to
    the goal, |u| <= input_margin * action_limit at the knots, a cart within +-cart_bound; T is the
    first of ``durations`` for which SNOPT finds a solution.

    ``knots`` = 41: hybridctl, measured: every benchmark system solves at 41 knots (0.05 s apart over
    2 s, fine enough for the double cart-pole's light upper pole).
    ``durations`` = (2.0, 3.0, 4.0, 6.0, 8.0) s: the ladder of fixed durations tried, shortest first;
    hybridctl, measured (docs/trajopt.md): a fixed duration with the effort cost solves where a free
    duration with a time cost did not (the double cart-pole: SNOPT's iteration limit after 120-160 s
    with a time weight of 0.3, solved in 9 s at T = 2 s); the torque-limited pendulum needs more than
    2 s of pumping.
    ``input_margin`` = 0.8: the nominal input stays within 80 % of the action limit, leaving 20 % for
    the tracking feedback; hybridctl, measured on the 11 x 11 Drake balance maps: the acrobot balances
    from 42 starts (24 with the nominal input up to the full limit), the pendulum from 103 (68).
    ``cart_bound`` = 2.0 m: bound on a cart's position at the knots (the chain family's cart, and each
    prismatic joint of a multibody model whose file states no position limits: its limits where it does;
    :func:`rail_bounds`); hybridctl, measured: without it SNOPT hit its iteration limit on the double
    cart-pole after 230 s (a free-duration problem); the double cart-pole's swing-up uses 0.5 m.
    ``major_iterations``, ``minor_iterations`` = None: SNOPT's "Major iterations limit" and "Iterations
    limit"; None keeps SNOPT's defaults (max(1000, 3 m) and max(10000, 20 m) for m constraints), with
    which every benchmark system solves (measured: the double cart-pole in 9 s with them as with 3000
    and 200000).
    ``Q``, ``R``: the weights of the time-varying LQR that tracks the trajectory; None: the spec's
    ``[lqr]`` Q and R (the balancing LQR's, so the tracking gain joins the LQR's at the end, where the
    final cost is the LQR's S; Tedrake, Underactuated Robotics, ch. "LQR", TVLQR).

    The trajectory's cache key holds :data:`SOLVE_FIELDS`; the tracking's adds Q and R.
    """

    knots: int = 41
    durations: tuple = (2.0, 3.0, 4.0, 6.0, 8.0)
    input_margin: float = 0.8
    cart_bound: float = 2.0
    major_iterations: int | None = None
    minor_iterations: int | None = None
    Q: tuple | None = None
    R: tuple | None = None

    def __post_init__(self):
        def bad(name, value, what):
            raise ValueError(f"TrajoptSettings.{name} must be {what}, got {value!r}")

        def number(value) -> bool:
            return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)

        for name in ("knots", "major_iterations", "minor_iterations"):
            value = getattr(self, name)
            if value is None and name != "knots":
                continue
            if not (number(value) and float(value).is_integer() and value >= (3 if name == "knots" else 1)):
                bad(name, value, "an integer >= 3" if name == "knots" else "an integer >= 1 or None")
            object.__setattr__(self, name, int(value))
        check_at_most("TrajoptSettings.knots", self.knots, MAX_TRAJOPT_KNOTS, force_flag=None)
        durations = self.durations if isinstance(self.durations, (tuple, list)) else (self.durations,)
        if not durations or not all(number(d) and math.isfinite(d) and d > 0 for d in durations):
            bad("durations", self.durations, "a non-empty sequence of finite numbers > 0 (seconds)")
        object.__setattr__(self, "durations", tuple(float(d) for d in durations))
        if not (number(self.input_margin) and 0 < self.input_margin <= 1):
            bad("input_margin", self.input_margin, "a number in (0, 1]")
        if not (number(self.cart_bound) and math.isfinite(self.cart_bound) and self.cart_bound > 0):
            bad("cart_bound", self.cart_bound, "a finite number > 0 (m)")
        for name in ("Q", "R"):
            value = getattr(self, name)
            if value is not None:   # stored as nested tuples: hashable, and the same JSON in the cache key
                try:
                    matrix = np.atleast_2d(np.asarray(value, dtype=float))
                except (TypeError, ValueError):
                    bad(name, value, "a finite square matrix or None")
                if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1] or not np.isfinite(matrix).all():
                    bad(name, value, "a finite square matrix or None")
                object.__setattr__(self, name, tuple(tuple(float(v) for v in row) for row in matrix))


# ----------------------------------------------------------------------------------- the plant
def _plant_diagram(system: System):
    """(diagram, context) of the system's Drake plant with one input (the system's action) and one
    output (the plant's state, Drake's convention), parameters written into the context.

    Built with the diagrams' own ``add_plant``, so a multibody model whose spec actuates a subset of its
    actuators gets the same input matrix as the switched controller.
    """
    builder = DiagramBuilder()
    handle, _ = _plants.add_plant(system, builder)
    builder.ExportInput(handle.actuation_input, "action")
    builder.ExportOutput(handle.state_output, "state")
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    handle.apply_parameters(handle.plant.GetMyMutableContextFromRoot(context))
    return diagram, context


def _has_cart(system: System) -> bool:
    return system.chain is not None and system.chain.has_cart


def rail_bounds(system: System, diagram, cart_bound: float) -> list[tuple[int, float, float]]:
    """(index into the Drake state, lower, upper) of each cart's travel in the collocation: the chain family's
    cart (the first coordinate) within +-``cart_bound``; each prismatic joint of a multibody model within its
    position limits where the model states them, else within +-``cart_bound`` too (an unbounded rail let SNOPT
    wander: docs/trajopt.md)."""
    if _has_cart(system):
        return [(0, -cart_bound, cart_bound)]
    plants = [s for s in diagram.GetSystems() if hasattr(s, "GetJointIndices")]
    if len(plants) != 1 or plants[0].num_continuous_states() != diagram.num_continuous_states():
        return []          # the plant's state is not the diagram's: no index to bound (not a multibody model)
    plant, bounds = plants[0], []
    for i in plant.GetJointIndices():
        joint = plant.get_joint(i)
        if joint.type_name() != "prismatic" or joint.num_positions() != 1:
            continue
        lower, upper = float(joint.position_lower_limits()[0]), float(joint.position_upper_limits()[0])
        bounds.append((joint.position_start(), lower if math.isfinite(lower) else -cart_bound,
                       upper if math.isfinite(upper) else cart_bound))
    return bounds


# ----------------------------------------------------------------------------------- trajectory
@dataclass
class SwingupTrajectory:
    """A solved collocation swing-up of ``system``: ``times`` (N,), ``states`` (N, n) in the Drake
    plant's convention, their time ``derivatives`` (N, n) from the plant's dynamics, ``inputs`` (N, m)
    (the system's action). ``solve_time`` (s, all attempts) and ``solver`` of the solve that made it,
    ``attempts`` (a dict per solve tried: ``duration_s``, ``input_bound``, ``solved``, ``seconds``); ``cached``: whether
    it was read from ``path``."""

    system: System
    settings: TrajoptSettings
    times: np.ndarray
    states: np.ndarray
    derivatives: np.ndarray
    inputs: np.ndarray
    solve_time: float
    solver: str
    key: str
    attempts: list = field(default_factory=list)
    path: Path | None = None
    cached: bool = False

    @property
    def duration(self) -> float:
        """Length of the trajectory in seconds."""
        return float(self.times[-1] - self.times[0])

    def state_trajectory(self):
        """The state trajectory (Drake's convention) as the collocation defines it: a cubic Hermite
        ``PiecewisePolynomial`` through the knots with the dynamics' derivatives there."""
        from pydrake.trajectories import PiecewisePolynomial
        return PiecewisePolynomial.CubicHermite(self.times, self.states.T, self.derivatives.T)

    def input_trajectory(self):
        """The input trajectory as the collocation defines it: first-order hold between the knots."""
        from pydrake.trajectories import PiecewisePolynomial
        return PiecewisePolynomial.FirstOrderHold(self.times, self.inputs.T)

    def summary(self) -> dict:
        """JSON-ready: knots, duration, solve time, solver, max |u|, the attempts, the cache file and whether
        it was read, the settings."""
        return {"system": self.system.name, "knots": int(len(self.times)), "duration_s": self.duration,
                "solve_time_s": self.solve_time, "solver": self.solver,
                "max_abs_input": float(np.abs(self.inputs).max()), "attempts": self.attempts,
                "cache": str(self.path) if self.path is not None else None, "cached": self.cached,
                "settings": asdict(self.settings)}


def _settings(settings: TrajoptSettings | None, overrides: dict) -> TrajoptSettings:
    """``settings`` (default ``TrajoptSettings()``) with keyword ``overrides``; an unknown name is a ValueError."""
    base = TrajoptSettings() if settings is None else settings
    if not isinstance(base, TrajoptSettings):
        raise ValueError(f"settings must be a TrajoptSettings, got {type(base).__name__}")
    known = {f.name for f in fields(TrajoptSettings)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise ValueError(f"unknown trajopt setting(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    return TrajoptSettings(**{**asdict(base), **overrides}) if overrides else base


def _check_system(system) -> None:
    if not isinstance(system, System):
        raise ValueError(f"system must be a hybridctl.systems.System, got {type(system).__name__}")


def _solve_fixed_duration(system: System, settings: TrajoptSettings, duration: float, diagram, context,
                          bound: float, guess: dict | None = None):
    """One collocation solve of fixed ``duration`` with |u| <= ``bound``, from ``guess`` (arrays of an earlier
    solve) or else a straight line: (arrays or None, the solver's name, its result text)."""
    from pydrake.planning import DirectCollocation
    from pydrake.solvers import SnoptSolver, Solve, SolverOptions
    from pydrake.trajectories import PiecewisePolynomial

    step = duration / (settings.knots - 1)
    dircol = DirectCollocation(diagram, context, settings.knots, step, step,
                               input_port_index=diagram.get_input_port(0).get_index())
    prog = dircol.prog()
    x_start = system.to_drake_state(system.initial_state.nominal)
    x_goal = system.to_drake_state(system.goal)
    prog.AddBoundingBoxConstraint(x_start, x_start, dircol.initial_state())
    prog.AddBoundingBoxConstraint(x_goal, x_goal, dircol.final_state())
    for u_i in dircol.input():
        dircol.AddConstraintToAllKnotPoints(u_i <= bound)
        dircol.AddConstraintToAllKnotPoints(u_i >= -bound)
    for index, lower, upper in rail_bounds(system, diagram, settings.cart_bound):
        dircol.AddConstraintToAllKnotPoints(dircol.state()[index] <= upper)
        dircol.AddConstraintToAllKnotPoints(dircol.state()[index] >= lower)
    dircol.AddEqualTimeIntervalsConstraints()
    # element by element: numpy's vectorised ops on symbolic arrays warn about "invalid values"
    dircol.AddRunningCost(sum((u_i / system.action_limit) ** 2 for u_i in dircol.input()))
    if guess is None:     # a straight line in state space, zero input
        dircol.SetInitialTrajectory(PiecewisePolynomial(), PiecewisePolynomial.FirstOrderHold(
            [0.0, duration], np.column_stack([x_start, x_goal])))
    else:
        dircol.SetInitialTrajectory(PiecewisePolynomial.FirstOrderHold(guess["times"], guess["inputs"].T),
                                    PiecewisePolynomial.CubicHermite(guess["times"], guess["states"].T,
                                                                     guess["derivatives"].T))
    options = SolverOptions()
    for name, value in (("Major iterations limit", settings.major_iterations),
                        ("Iterations limit", settings.minor_iterations)):
        if value is not None:
            options.SetOption(SnoptSolver.id(), name, value)
    result = Solve(prog, None, options)
    solver, status = result.get_solver_id().name(), result.get_solution_result().name
    if not result.is_success():
        return None, solver, status
    times = np.asarray(dircol.GetSampleTimes(result), dtype=float)
    states = np.asarray(dircol.GetStateSamples(result), dtype=float).T
    inputs = np.asarray(dircol.GetInputSamples(result), dtype=float).T
    # the derivatives the collocation's cubic Hermite uses: the dynamics at each knot
    derivatives = np.empty_like(states)
    for i, (x, u_i) in enumerate(zip(states, inputs)):
        context.SetContinuousState(x)
        diagram.get_input_port(0).FixValue(context, u_i)
        derivatives[i] = diagram.EvalTimeDerivatives(context).CopyToVector()
    return dict(times=times, states=states, derivatives=derivatives, inputs=inputs), solver, status


def solve_swingup(system: System, settings: TrajoptSettings) -> dict:
    """Solve the collocation swing-up (no cache), trying ``settings.durations`` in turn.

    At each duration: a solve within the full action limit from a straight-line guess; if its input
    exceeds ``input_margin`` of the limit, a second solve within the margin, started from the first
    (SNOPT found the double cart-pole's 45 N swing-up within 100 N in 9 s, but hit its iteration
    limit when the bound of 80 N was there from the start: a continuation, not a cold start). The
    first duration with a solution within the margin is taken.

    Returns arrays ``times``, ``states``, ``derivatives``, ``inputs``, the whole ``solve_time`` (s), the
    ``solver`` and the attempts (``attempt_durations``, ``attempt_bounds``, ``attempt_solved``,
    ``attempt_seconds``). :class:`TrajoptError` naming every attempt and what to try when none succeeds.
    """
    diagram, context = _plant_diagram(system)
    limit, margin = system.action_limit, settings.input_margin * system.action_limit
    attempts, start, found = [], time.perf_counter(), None

    def attempt(duration, bound, guess=None):
        began = time.perf_counter()
        try:
            arrays, solver, status = _solve_fixed_duration(system, settings, duration, diagram, context, bound, guess)
        except RuntimeError as exc:      # Drake or the solver threw: this attempt failed, the next may solve
            arrays, solver, status = None, "SNOPT", f"error: {(str(exc) or type(exc).__name__).splitlines()[0]}"
        attempts.append((duration, bound, arrays is not None, time.perf_counter() - began, status, solver))
        return arrays

    for duration in settings.durations:
        arrays = attempt(duration, limit)
        if arrays is not None and np.abs(arrays["inputs"]).max() > margin * (1 + 1e-6):
            arrays = attempt(duration, margin, arrays)
        if arrays is not None:
            found = arrays
            break
    if found is None:
        tried = ", ".join(f"T = {d:g} s, |u| <= {b:g}: {status} ({sec:.1f} s)" for d, b, _, sec, status, _ in attempts)
        cart = (f", another cart_bound (now {settings.cart_bound:g} m: a cart's travel where the model states "
                f"no limits)" if rail_bounds(system, diagram, settings.cart_bound) else "")
        raise TrajoptError(f"{system.name}: the collocation swing-up did not solve with {attempts[-1][5]} ({tried}); "
                           f"try longer durations (TrajoptSettings.durations, e.g. {2 * max(settings.durations):g} s), "
                           f"more knots, more SNOPT iterations (major_iterations, minor_iterations){cart}")
    durations, bounds, solved, seconds, _, solvers = zip(*attempts)
    return dict(found, solve_time=time.perf_counter() - start, solver=solvers[-1],
                attempt_durations=np.array(durations), attempt_bounds=np.array(bounds),
                attempt_solved=np.array(solved), attempt_seconds=np.array(seconds))


def swingup_trajectory(system: System, settings: TrajoptSettings | None = None, *, cache: bool = True,
                       cache_dir: str | os.PathLike | None = None, **overrides) -> SwingupTrajectory:
    """The direct-collocation swing-up of ``system`` from hanging down to the goal, cached per system.

    Args:
        system: a :class:`~hybridctl.systems.System`.
        settings: a :class:`TrajoptSettings` (default: its defaults); keyword ``overrides`` replace its
            fields (``swingup_trajectory(system, knots=31, durations=(3.0,))``); an unknown name or a bad
            value is a ValueError naming it.
        cache: read and write the cache (False: always solve, write nothing).
        cache_dir: the cache folder (default :func:`cache_folder`).

    Raises :class:`TrajoptError` (one line, what to try) when the solver finds no trajectory.
    """
    _check_system(system)
    settings = _settings(settings, overrides)
    key = cache_key(system, {name: getattr(settings, name) for name in SOLVE_FIELDS}, what="trajectory")
    folder = Path(cache_dir) if cache_dir is not None else cache_folder()
    path = folder / f"{system.name}-trajectory-{key}.npz"
    n, m = system.n_states, system.n_actions
    shapes = {"times": (settings.knots,), "states": (settings.knots, n), "derivatives": (settings.knots, n),
              "inputs": (settings.knots, m), "solve_time": (), "solver": (), "attempt_durations": (-1,),
              "attempt_bounds": (-1,), "attempt_solved": (-1,), "attempt_seconds": (-1,)}
    arrays = _load_npz(path, key, shapes) if cache else None
    cached = arrays is not None
    if arrays is None:
        arrays = solve_swingup(system, settings)
        if cache:
            _save_npz(path, key, arrays)
    return SwingupTrajectory(system, settings, times=arrays["times"], states=arrays["states"],
                             derivatives=arrays["derivatives"], inputs=arrays["inputs"],
                             solve_time=float(arrays["solve_time"]), solver=str(arrays["solver"]), key=key,
                             attempts=[{"duration_s": float(d), "input_bound": float(b), "solved": bool(ok),
                                        "seconds": float(sec)}
                                       for d, b, ok, sec in zip(arrays["attempt_durations"], arrays["attempt_bounds"],
                                                                arrays["attempt_solved"], arrays["attempt_seconds"])],
                             path=path if cache else None, cached=cached)


# ----------------------------------------------------------------------------------- TVLQR
@dataclass
class TrackingGains:
    """The time-varying LQR along a swing-up, sampled at the tracking block's update times
    ``t_k = k * period``, k = 0..K: nominal states ``x0`` (K+1, n) in the spec's convention, inputs
    ``u0`` (K+1, m), gains ``K`` (K+1, m, n) and offsets ``k0`` (K+1, m); u = u0 - K (x - x0) - k0.
    The block runs only at these times, so the table is exactly what it needs. ``solve_time`` (s) of the
    Riccati integration that made it; ``cached``: read from ``path``."""

    period: float
    x0: np.ndarray
    u0: np.ndarray
    K: np.ndarray
    k0: np.ndarray
    solve_time: float
    key: str
    path: Path | None = None
    cached: bool = False


def _check_period(period) -> float:
    number = isinstance(period, (int, float, np.integer, np.floating)) and not isinstance(period, bool)
    if not (number and math.isfinite(period) and period > 0):
        raise ValueError(f"period must be a finite number > 0 (seconds), got {period!r}")
    return float(period)


MAX_TVLQR_SOLUTIONS = 4
"""Drake's TVLQR solutions kept in this process (the fit screens several periods of one trajectory)."""
_TVLQR_SOLUTIONS: dict[str, tuple] = {}


def solve_tracking(system: System, trajectory: SwingupTrajectory, period: float) -> dict:
    """Drake's finite-horizon LQR along ``trajectory`` (no file cache), sampled every ``period``: arrays
    ``x0`` (spec convention), ``u0``, ``K``, ``k0`` and ``solve_time`` (seconds of the Riccati solve). The solution
    is solved once per trajectory, Q and R in this process (the last :data:`MAX_TVLQR_SOLUTIONS`) and sampled at
    each period asked for: the same numbers as a solve per period, without its cost."""
    from pydrake.systems.controllers import (FiniteHorizonLinearQuadraticRegulator,
                                             FiniteHorizonLinearQuadraticRegulatorOptions)

    settings = trajectory.settings
    Q = system.Q if settings.Q is None else np.asarray(settings.Q, dtype=float)
    R = system.R if settings.R is None else np.asarray(settings.R, dtype=float)
    if Q.shape != (system.n_states,) * 2 or R.shape != (system.n_actions,) * 2:
        raise ValueError(f"TrajoptSettings Q {Q.shape} and R {R.shape} must be {system.n_states}x{system.n_states} "
                         f"and {system.n_actions}x{system.n_actions} for {system.name}")
    # the Riccati solution does not depend on the sampling period: one solve serves every period screened
    memo_key = cache_key(system, {"Q": Q.tolist(), "R": R.tolist()}, what="tracking-solution",
                         trajectory=trajectory.key)
    if memo_key in _TVLQR_SOLUTIONS:
        result, solve_seconds = _TVLQR_SOLUTIONS[memo_key]
    else:
        diagram, context = _plant_diagram(system)
        options = FiniteHorizonLinearQuadraticRegulatorOptions()
        options.x0 = trajectory.state_trajectory()
        options.u0 = trajectory.input_trajectory()
        options.Qf = system.lqr(Q, R)[1]
        options.input_port_index = diagram.get_input_port(0).get_index()
        start = time.perf_counter()
        try:
            result = FiniteHorizonLinearQuadraticRegulator(diagram, context, float(trajectory.times[0]),
                                                           float(trajectory.times[-1]), Q, R, options)
        except RuntimeError as exc:   # e.g. the Riccati integrator's "step smaller than minimum allowed"
            first = (str(exc) or type(exc).__name__).splitlines()[0]
            raise TrajoptError(f"{system.name}: the TVLQR along the {trajectory.duration:g} s swing-up failed "
                               f"({first}); try longer TrajoptSettings.durations or more knots, or a larger R") from None
        solve_seconds = time.perf_counter() - start
        while len(_TVLQR_SOLUTIONS) >= MAX_TVLQR_SOLUTIONS:     # the oldest first
            _TVLQR_SOLUTIONS.pop(next(iter(_TVLQR_SOLUTIONS)))
        _TVLQR_SOLUTIONS[memo_key] = (result, solve_seconds)
    # the block's update times over the trajectory; k * period, as Drake's periodic events fall
    steps = int(math.floor(trajectory.duration / period + 1e-9))
    times = np.minimum(trajectory.times[0] + period * np.arange(steps + 1), trajectory.times[-1])
    x0 = np.array([system.from_drake_state(result.x0.value(t).ravel()) for t in times])
    u0 = np.array([result.u0.value(t).ravel() for t in times])
    K = np.array([result.K.value(t) for t in times])
    k0 = np.array([result.k0.value(t).ravel() for t in times])
    return dict(x0=x0, u0=u0, K=K, k0=k0, solve_time=solve_seconds)


def tracking_gains(system: System, trajectory: SwingupTrajectory, period: float | None = None, *,
                   cache: bool = True, cache_dir: str | os.PathLike | None = None) -> TrackingGains:
    """The time-varying LQR that tracks ``trajectory``, sampled every ``period`` (default the spec's
    ``control.period``), cached beside the trajectory (key: the trajectory's, the period)."""
    _check_system(system)
    if not isinstance(trajectory, SwingupTrajectory) or trajectory.system.name != system.name:
        raise ValueError("trajectory must be the SwingupTrajectory of this system (from swingup_trajectory)")
    period = _check_period(system.control_period if period is None else period)
    check_at_most(f"{system.name}: the tracking rows (duration {trajectory.duration:g} s / period {period:g} s)",
                  trajectory.duration / period + 1, MAX_TRAJOPT_ROWS, force_flag=None, why="limits.MAX_TRAJOPT_ROWS")
    key = cache_key(system, {"Q": trajectory.settings.Q, "R": trajectory.settings.R}, what="tracking",
                    trajectory=trajectory.key, period=period)
    folder = Path(cache_dir) if cache_dir is not None else cache_folder()
    path = folder / f"{system.name}-tracking-{key}.npz"
    n, m = system.n_states, system.n_actions
    shapes = {"x0": (-1, n), "u0": (-1, m), "K": (-1, m, n), "k0": (-1, m), "solve_time": ()}
    arrays = _load_npz(path, key, shapes) if cache else None
    lengths = {len(arrays[name]) for name in ("x0", "u0", "K", "k0")} if arrays is not None else set()
    if arrays is not None and (len(lengths) != 1 or 0 in lengths):
        warnings.warn(f"trajopt cache {path} cannot be used (tables of unequal lengths); recomputing it", stacklevel=2)
        arrays = None
    cached = arrays is not None
    if arrays is None:
        arrays = solve_tracking(system, trajectory, period)
        if cache:
            _save_npz(path, key, arrays)
    return TrackingGains(period, arrays["x0"], arrays["u0"], arrays["K"], arrays["k0"],
                         float(arrays["solve_time"]), key, path if cache else None, cached)


# ----------------------------------------------------------------------------------- the block
class TrajectoryTracker(LeafSystem):
    """The TVLQR tracking of a swing-up trajectory as a Drake block, held for ``gains.period``.

    Ports: input ``state`` (spec convention), output ``command``. Every ``period`` (offset 0) it
    reads the time t from its Context, takes the table row k = round(t / period) (the last row, the
    goal with the LQR's gain, once the trajectory has ended) and holds
    ``clip(u0[k] - K[k] (x - x0[k]) - k0[k], -limit, limit)``, the angles of x - x0[k] wrapped to
    [-pi, pi). Every run tracks the trajectory from its start: the time-indexed join of LQR-trees
    (start where the TVLQR's cost-to-go is least) was tried and balanced fewer map starts on every
    system (docs/trajopt.md). ``trajectory`` and ``gains`` stay as attributes.
    """

    def __init__(self, system: System, trajectory: SwingupTrajectory, gains: TrackingGains, name: str = "swingup"):
        super().__init__()
        self.system, self.trajectory, self.gains = system, trajectory, gains
        self.period = gains.period
        self._limit = float(system.action_limit)
        self._angles = system.angle_indices
        self.DeclareVectorInputPort("state", system.n_states)
        self._held = self.DeclareDiscreteState(np.zeros(system.n_actions))
        self.DeclarePeriodicDiscreteUpdateEvent(self.period, 0.0, self._update)
        self.DeclareStateOutputPort("command", self._held)
        self.set_name(name)

    def command(self, t: float, x: np.ndarray) -> np.ndarray:
        """The clipped TVLQR command at time ``t`` (s since the start) and state ``x`` (spec convention)."""
        g = self.gains
        k = min(max(int(round(t / self.period)), 0), len(g.x0) - 1)
        err = np.asarray(x, dtype=float) - g.x0[k]
        control.wrap_angles(err, self._angles)
        return control.saturate(control.tracking_command(err, g.u0[k], g.K[k], g.k0[k]), self._limit)

    def _update(self, context: Context, discrete_state: DiscreteValues) -> None:
        x = self.get_input_port(0).Eval(context)
        discrete_state.set_value(0, self.command(context.get_time(), x))


def trajopt_swingup(system: System, period: float | None = None, settings: TrajoptSettings | None = None, *,
                    cache: bool = True, cache_dir: str | os.PathLike | None = None, **overrides) -> TrajectoryTracker:
    """The collocation swing-up of ``system`` tracked by TVLQR, as a ready :class:`TrajectoryTracker`
    updated every ``period`` (default the spec's ``control.period``); both solves cached
    (:func:`swingup_trajectory`, :func:`tracking_gains`)."""
    trajectory = swingup_trajectory(system, settings, cache=cache, cache_dir=cache_dir, **overrides)
    gains = tracking_gains(system, trajectory, period, cache=cache, cache_dir=cache_dir)
    return TrajectoryTracker(system, trajectory, gains)
