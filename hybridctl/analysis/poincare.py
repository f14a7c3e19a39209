"""Poincare (return) maps with disturbances: the interface that reachable-state meshes use (thesis Ch. 5).

A section map takes a state on the Poincare section and one disturbance and returns
the next state on the section, or failure::

    next_states = section_map.step_many(states, disturbances)   # (m, n) -> (m, n); NaN rows = failure
    section_map.step(state, disturbance)                           # one state: array, or None = failure

Adapters: :class:`FunctionMap` wraps a plain Python/numpy function;
:class:`RimlessWheel` is the analytic apex-to-apex map of a rimless wheel on rough
terrain (Byl & Tedrake 2009), cheap enough for Monte Carlo on the true map.
Section maps are plain, picklable objects: a map that needs a simulator builds it
lazily inside whichever process calls it.

Disturbance models give the mesh its finite disturbance set and Monte Carlo its draws:
:class:`FiniteDisturbances` (a set with weights), :class:`GaussianDisturbance` (a scalar
Gaussian) and :class:`ScipyDisturbance` (any continuous scipy.stats distribution). A continuous
model is discretised by a rule (:data:`DISTURBANCE_RULES`): ``"grid"`` (the default)
puts ``count`` equally spaced points from the ``tail`` to the ``1 - tail`` quantile (a Gaussian:
mean +- ``tails`` std, 6 by default) and gives each the probability of its cell, the outer
cells reaching to +-infinity, so the tails that make a system fail keep their weight;
``"quantiles"`` is the thesis' set of ``count`` equal-probability midpoint quantiles, which
for 25 points reaches only +-2.05 std. :func:`~hybridctl.analysis.refine.refined_mesh`
doubles a grid's points until the MFPT settles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
from scipy.special import ndtr, ndtri


def check_section_states(states, disturbances, width: int | None = None) -> np.ndarray:
    """``states`` as a finite float array (N, width) matching ``disturbances`` (length N).

    Raises ValueError naming the argument: a state that is NaN or infinite, a ragged or
    wrongly shaped batch, or a disturbance list of another length.
    """
    x = np.asarray(states, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] == 0 or (width is not None and x.shape[1] != width):
        want = f"(N, {width})" if width is not None else "(N, n_states)"
        raise ValueError(f"states must have shape {want} with N >= 1, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("states must be finite (a failed state is not a section state)")
    if len(disturbances) != x.shape[0]:
        raise ValueError(f"disturbances must hold one entry per state ({x.shape[0]}), got {len(disturbances)}")
    return x


class SectionMap:
    """Base class: ``step_many`` (vectorised) or ``step`` (one state) -- define either."""

    state_names: tuple[str, ...] = ()

    def step(self, state: np.ndarray, disturbance) -> np.ndarray | None:
        """Next state on the section after ``disturbance``, or None if the system failed."""
        state = np.asarray(state, dtype=np.float64)
        if state.ndim != 1:
            raise ValueError(f"state must be one state (n_states,), got shape {state.shape}")
        out = self.step_many(state[None, :], [disturbance])[0]
        return None if np.isnan(out).any() else out

    def step_many(self, states: np.ndarray, disturbances: Sequence) -> np.ndarray:
        """Next states (NaN rows for failures) of ``states[i]`` under ``disturbances[i]``."""
        states = check_section_states(states, disturbances)
        out = np.full(np.shape(states), np.nan)
        for i, (s, d) in enumerate(zip(states, disturbances)):
            nxt = self.step(s, d)
            if nxt is not None:
                out[i] = nxt
        return out


@dataclass
class FunctionMap(SectionMap):
    """A section map from ``fn(state, disturbance) -> next state or None`` (must pickle for workers)."""

    fn: Callable
    state_names: tuple[str, ...] = ()

    def step(self, state, disturbance):
        """``fn(state, disturbance)`` as a float array, or None for failure."""
        out = self.fn(np.asarray(state, dtype=np.float64), disturbance)
        return None if out is None else np.atleast_1d(np.asarray(out, dtype=np.float64))


@dataclass
class RimlessWheel(SectionMap):
    """Apex-to-apex map of a rimless wheel rolling down terrain whose slope changes every step.

    State: the angular velocity ``w`` (rad/s) when the stance leg is vertical. Disturbance:
    the slope ``gamma`` (rad, downhill positive) of the next step. From apex the stance leg
    rotates by ``alpha + gamma`` to the collision, which keeps ``cos(2 alpha)`` of the angular
    velocity, and the new stance leg rises by ``alpha - gamma`` to the next apex (Coleman's
    rimless wheel; Byl & Tedrake 2009, "Metastable walking machines"):

        w'^2 = cos^2(2 alpha) (w^2 + 2 g/l (1 - cos(alpha + gamma))) - 2 g/l (1 - cos(alpha - gamma))

    Failure when ``w'^2 <= 0``: the wheel rolls back before the next apex.
    """

    half_angle: float = math.pi / 8     # alpha: 8 spokes (hybridctl design choice, as in Byl & Tedrake)
    g_over_l: float = 9.81              # g / leg length (1 m)
    state_names: tuple[str, ...] = ("w",)

    def step_many(self, states, disturbances):
        """Vectorised map; NaN rows for failures."""
        states = np.asarray(states, dtype=np.float64)
        w = check_section_states(states.reshape(-1, 1) if states.ndim == 1 else states, disturbances, 1)[:, 0]
        gamma = np.asarray(disturbances, dtype=np.float64).reshape(-1)
        if gamma.shape != w.shape or not np.all(np.isfinite(gamma)):
            raise ValueError(f"disturbances must be {len(w)} finite slopes (rad), got {disturbances!r}")
        a, k = self.half_angle, 2.0 * self.g_over_l
        arg = math.cos(2 * a) ** 2 * (w ** 2 + k * (1 - np.cos(a + gamma))) - k * (1 - np.cos(a - gamma))
        out = np.sqrt(np.where(arg > 0, arg, np.nan))
        return out[:, None]

    def fixed_point(self, gamma: float) -> float:
        """Apex velocity of the period-1 gait on a constant slope ``gamma`` (NaN if none)."""
        a, k, c2 = self.half_angle, 2.0 * self.g_over_l, math.cos(2 * self.half_angle) ** 2
        value = (c2 * k * (1 - math.cos(a + gamma)) - k * (1 - math.cos(a - gamma))) / (1 - c2)
        return math.sqrt(value) if value > 0 else float("nan")


@dataclass
class FiniteDisturbances:
    """A finite disturbance set with probabilities (uniform by default)."""

    values: Sequence
    weights: np.ndarray | None = None

    def __post_init__(self):
        n = len(self.values)
        if n == 0:
            raise ValueError("the disturbance set is empty")
        w = np.full(n, 1.0 / n) if self.weights is None else np.asarray(self.weights, dtype=np.float64)
        if w.shape != (n,) or np.any(w < 0) or not math.isclose(w.sum(), 1.0, rel_tol=1e-9):
            raise ValueError(f"disturbance weights must be {n} non-negative numbers summing to 1")
        self.weights = w

    def finite_set(self) -> "FiniteDisturbances":
        """Itself."""
        return self

    def sample(self, rng: np.random.Generator, n: int) -> list:
        """``n`` draws from the set."""
        idx = rng.choice(len(self.values), size=n, p=self.weights)
        return [self.values[i] for i in idx]


DISTURBANCE_RULES = ("grid", "quantiles")
"""How a continuous disturbance model becomes a mesh's finite set (module docstring)."""
DEFAULT_TAILS = 6.0
"""Half-width of a Gaussian's weighted grid in standard deviations (and, as ``ndtr(-6)`` = 1e-9, the tail
probability of :class:`ScipyDisturbance`'s): the mass beyond lies on the end points, none is dropped."""


def weighted_grid(cdf: Callable, ppf: Callable, count: int, tail: float) -> FiniteDisturbances:
    """``count`` equally spaced points from ``ppf(tail)`` to ``ppf(1 - tail)``, each weighted by the
    probability of its cell (edges halfway between points, the outer ones at -+inf); points of zero
    probability are left out."""
    if count == 1:
        return FiniteDisturbances([float(ppf(0.5))])
    points = np.linspace(float(ppf(tail)), float(ppf(1.0 - tail)), count)
    edges = np.r_[-np.inf, (points[:-1] + points[1:]) / 2, np.inf]
    weights = np.diff(np.clip(np.asarray(cdf(edges), dtype=np.float64), 0.0, 1.0))
    keep = weights > 0
    if not np.all(np.isfinite(points)) or not keep.any():
        raise ValueError(f"the distribution's quantiles {tail:g} and {1 - tail:g} must be finite and hold mass")
    return FiniteDisturbances(list(points[keep]), weights[keep] / weights[keep].sum())


def _check_rule(name: str, count, rule: str) -> None:
    if not (isinstance(count, (int, np.integer)) and count >= 1):
        raise ValueError(f"{name} needs an integer count >= 1, got {count!r}")
    if rule not in DISTURBANCE_RULES:
        raise ValueError(f"{name} rule must be one of {DISTURBANCE_RULES}, got {rule!r}")


@dataclass
class GaussianDisturbance:
    """A scalar Gaussian disturbance; the mesh uses ``count`` points of it by ``rule`` (module docstring):
    ``"grid"`` (default) over mean +- ``tails`` std with cell probabilities, or ``"quantiles"``."""

    mean: float
    std: float
    count: int = 25
    label: str = field(default="gaussian", repr=False)
    rule: str = "grid"
    tails: float = DEFAULT_TAILS

    def __post_init__(self):
        if not (self.std > 0 and math.isfinite(self.std) and math.isfinite(self.mean)):
            raise ValueError(f"GaussianDisturbance needs a finite mean and std > 0, got mean={self.mean}, "
                             f"std={self.std}, count={self.count}")
        _check_rule("GaussianDisturbance", self.count, self.rule)
        if not (math.isfinite(self.tails) and self.tails > 0):
            raise ValueError(f"GaussianDisturbance tails must be a finite number of std > 0, got {self.tails!r}")

    @property
    def central_std(self) -> float:
        """Half the width of the central 68.3 %: the std."""
        return float(self.std)

    def finite_set(self) -> FiniteDisturbances:
        """``"grid"``: points mean + std z, z equally spaced on [-tails, tails], weights Phi(cell);
        ``"quantiles"``: mean + std * Phi^-1((k + 1/2) / count), equal weights."""
        if self.rule == "quantiles":
            q = (np.arange(self.count) + 0.5) / self.count
            return FiniteDisturbances(list(self.mean + self.std * ndtri(q)))
        return weighted_grid(lambda x: ndtr((np.asarray(x) - self.mean) / self.std),
                             lambda q: self.mean + self.std * ndtri(q), self.count, float(ndtr(-self.tails)))

    def describe(self) -> dict:
        """JSON-ready: the model and its discretisation."""
        return {"distribution": "gaussian", "mean": self.mean, "std": self.std, "rule": self.rule,
                "count": self.count, **({"tails_std": self.tails} if self.rule == "grid" else {})}

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` draws from the continuous Gaussian."""
        return rng.normal(self.mean, self.std, size=n)


@dataclass
class ScipyDisturbance:
    """Any continuous scipy.stats distribution (frozen, e.g. ``scipy.stats.t(3, loc=0.15, scale=0.05)``)
    as a scalar disturbance: the mesh uses ``count`` points by ``rule``; Monte Carlo draws from it."""

    distribution: object
    count: int = 25
    rule: str = "grid"
    tail: float = float(ndtr(-DEFAULT_TAILS))

    def __post_init__(self):
        if not all(hasattr(self.distribution, name) for name in ("cdf", "ppf", "rvs")):
            raise ValueError(f"ScipyDisturbance needs a frozen scipy.stats distribution (cdf, ppf, rvs), "
                             f"got {type(self.distribution).__name__}")
        _check_rule("ScipyDisturbance", self.count, self.rule)
        if not 0 < self.tail < 0.5:
            raise ValueError(f"ScipyDisturbance tail must be a probability in (0, 0.5), got {self.tail!r}")

    @property
    def central_std(self) -> float:
        """Half the width of the central 68.3 % (a Gaussian's std; finite for heavy tails, whose std is not)."""
        return float(self.distribution.ppf(ndtr(1.0)) - self.distribution.ppf(ndtr(-1.0))) / 2.0

    def finite_set(self) -> FiniteDisturbances:
        """The ``rule``'s points of the distribution (module docstring)."""
        if self.rule == "quantiles":
            return FiniteDisturbances(list(self.distribution.ppf((np.arange(self.count) + 0.5) / self.count)))
        return weighted_grid(self.distribution.cdf, self.distribution.ppf, self.count, self.tail)

    def describe(self) -> dict:
        """JSON-ready: the model and its discretisation."""
        dist = getattr(self.distribution, "dist", None)
        return {"distribution": getattr(dist, "name", type(self.distribution).__name__),
                "args": [float(a) for a in getattr(self.distribution, "args", ())],
                "kwds": {k: float(v) for k, v in getattr(self.distribution, "kwds", {}).items()},
                "rule": self.rule, "count": self.count, **({"tail": self.tail} if self.rule == "grid" else {})}

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` draws from the distribution."""
        return np.asarray(self.distribution.rvs(size=n, random_state=rng), dtype=np.float64)
