"""Drake models as systems: batched torch dynamics generated from Drake's symbolic plant.

A spec of ``[model] family = "multibody"`` names a URDF or SDF file. Drake parses it into a
continuous-time ``MultibodyPlant``; its symbolic twin (``MultibodyPlant.ToSymbolic``) writes
the manipulator terms as expressions of the joint coordinates q and velocities v
(``systems/symbolic.py``, which needs pydrake and sympy). For joints that are revolute or
prismatic, every entry is a polynomial in

    s_i = sin q_i, c_i = cos q_i (revolute joints), q_i (prismatic joints), v_i,

reduced exactly (in rational arithmetic) modulo s_i^2 + c_i^2 = 1. This module holds that
result as plain data (:class:`MultibodyModel`: numbers only, JSON in and out, cached on disk)
and turns it into code:

    qdd = M(q)^-1 (B u + tau_g(q) - C(q, v) v - D v)

as straight-line batched torch (``(B, n)`` rows or ``(n, B)`` columns, float32 or float64,
differentiable, on the input's device), and as straight-line Python over floats for one
state (:meth:`GeneratedDynamics.scalar`). Every distinct monomial is computed once and shared
by all entries (common subexpressions), and M is solved by an unrolled LDL^T factorisation
(M is symmetric positive definite), so there is no batched LU and no Python loop per call.

The generated source is built here from the numbers of a :class:`MultibodyModel` alone; a
cache file is data (checked on reading), never code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import torch

from ..limits import MAX_CACHE_INTEGER, MAX_MODEL_BODIES, MAX_NAME_CHARS
from .generated_code import free_early, integrator_lines, shared_function, step_loop_source

MAX_TERMS = 20_000
"""Most polynomial terms (all entries of M, C v, tau_g and the energies together) a model may
have: the generated code has about one operation per term, so a model above this would make
a step slower than a batched LU on Drake's numbers and its source too large to compile quickly.
A planar chain of 3 links has about 60, a spatial 6-joint arm several thousand."""

MAX_JOINTS = 12
"""Most joint coordinates of a generated model: the unrolled LDL^T solve grows as n^3."""

Term = tuple[float, tuple[int, ...]]
"""One monomial: (coefficient, exponents of the variables s_0.., c_0.., q_0.., v_0..)."""


class ModelError(ValueError):
    """A Drake model that cannot become a system, or a damaged cache of one; the message names the
    file and what to change."""


# ============================================================================ the model as data
@dataclass(frozen=True)
class MultibodyModel:
    """The manipulator equations of a Drake model as polynomials (plain numbers).

    ``positions`` / ``velocities``: names of q and v (Drake's order). ``revolute[i]``: whether
    q_i is an angle (then it enters through sin and cos only). ``mass``: the upper triangle of
    M(q), row by row; ``bias``: C(q, v) v; ``gravity``: tau_g(q); ``kinetic`` / ``potential``:
    the energies; ``tip``: the world position (x, y, z) of the spec's tip point, or empty.
    ``actuation``: B (n_v x n_u); ``damping``: the joints' viscous damping per velocity.
    Each polynomial is a list of :data:`Term`.
    """

    positions: tuple[str, ...]
    velocities: tuple[str, ...]
    actuators: tuple[str, ...]
    revolute: tuple[bool, ...]
    mass: tuple[tuple[Term, ...], ...]
    bias: tuple[tuple[Term, ...], ...]
    gravity: tuple[tuple[Term, ...], ...]
    kinetic: tuple[Term, ...]
    potential: tuple[Term, ...]
    actuation: tuple[tuple[float, ...], ...]
    damping: tuple[float, ...]
    tip: tuple[tuple[Term, ...], ...] = ()
    bodies: tuple[str, ...] = ()                      # the moving bodies, in Drake's order
    body_parents: tuple[int, ...] = ()                # index of each body's parent body; -1: the world
    body_origins: tuple[tuple[Term, ...], ...] = ()   # world (x, y, z) of each body frame's origin
    info: dict = field(default_factory=dict, compare=False)

    @property
    def n_q(self) -> int:
        return len(self.positions)

    @property
    def n_u(self) -> int:
        return len(self.actuators)

    @property
    def effort(self) -> tuple[float, ...]:
        """Each action's effort limit (``info['effort_limits']``, inf: none); Drake and the generated code clamp to it."""
        limits = self.info.get("effort_limits") or [None] * self.n_u
        return tuple(math.inf if e is None else float(e) for e in limits)

    def n_terms(self) -> int:
        """All terms of all polynomials (the size :data:`MAX_TERMS` bounds)."""
        polys = [*self.mass, *self.bias, *self.gravity, self.kinetic, self.potential, *self.tip, *self.body_origins]
        return sum(len(p) for p in polys)

    def to_json(self) -> dict:
        """A JSON-able dict (lists and numbers) that :meth:`from_json` reads back exactly."""
        def poly(p):
            return [[float(c), list(e)] for c, e in p]
        return {"format": 1, "positions": list(self.positions), "velocities": list(self.velocities),
                "actuators": list(self.actuators), "revolute": list(self.revolute),
                "mass": [poly(p) for p in self.mass], "bias": [poly(p) for p in self.bias],
                "gravity": [poly(p) for p in self.gravity], "kinetic": poly(self.kinetic),
                "potential": poly(self.potential), "tip": [poly(p) for p in self.tip],
                "bodies": list(self.bodies), "body_parents": list(self.body_parents),
                "body_origins": [poly(p) for p in self.body_origins],
                "actuation": [list(map(float, row)) for row in self.actuation],
                "damping": list(map(float, self.damping)), "info": dict(self.info)}

    @classmethod
    def from_json(cls, doc: Any, where: str = "the model cache") -> "MultibodyModel":
        """Read :meth:`to_json`'s dict back, checking every type and size; ModelError names ``where``."""
        def fail(what):
            raise ModelError(f"{where} is damaged: {what}")

        if not isinstance(doc, dict) or doc.get("format") != 1:
            fail("not a format-1 model record")

        def named(value, most):
            return (isinstance(value, list) and len(value) <= most
                    and all(isinstance(s, str) and len(s) <= MAX_NAME_CHARS for s in value))

        names = {}
        for key in ("positions", "velocities", "actuators"):
            value = doc.get(key)
            if not named(value, MAX_JOINTS):
                fail(f"'{key}' must be a list of at most {MAX_JOINTS} names of at most {MAX_NAME_CHARS} characters")
            names[key] = tuple(value)
        n = len(names["positions"])
        if not 1 <= n <= MAX_JOINTS or len(names["velocities"]) != n:
            fail(f"needs 1 to {MAX_JOINTS} positions and as many velocities")
        n_u = len(names["actuators"])
        revolute = doc.get("revolute")
        if not isinstance(revolute, list) or len(revolute) != n or not all(isinstance(b, bool) for b in revolute):
            fail("'revolute' must be one true/false per position")
        width = 4 * n

        def number(v):   # an integer beyond MAX_CACHE_INTEGER would overflow float() or round
            return ((isinstance(v, float) and math.isfinite(v))
                    or (isinstance(v, int) and not isinstance(v, bool) and abs(v) <= MAX_CACHE_INTEGER))

        count = [0]

        def poly(p, key):
            if not isinstance(p, list):
                fail(f"'{key}' must be a list of terms")
            count[0] += len(p)
            if count[0] > MAX_TERMS:
                fail(f"more than {MAX_TERMS:,} terms")
            out = []
            for term in p:
                if not (isinstance(term, list) and len(term) == 2 and number(term[0]) and isinstance(term[1], list)
                        and len(term[1]) == width
                        and all(isinstance(k, int) and not isinstance(k, bool) and 0 <= k <= 16 for k in term[1])):
                    fail(f"a term of '{key}' must be [coefficient, {width} exponents in 0..16]")
                out.append((float(term[0]), tuple(term[1])))
            return tuple(out)

        def polys(key, length):
            value = doc.get(key)
            if not isinstance(value, list) or len(value) != length:
                fail(f"'{key}' must hold {length} polynomials")
            return tuple(poly(p, key) for p in value)

        actuation = doc.get("actuation")
        if not (isinstance(actuation, list) and len(actuation) == n
                and all(isinstance(r, list) and len(r) == n_u and all(map(number, r)) for r in actuation)):
            fail(f"'actuation' must be a {n} x {n_u} matrix of numbers")
        damping = doc.get("damping")
        if not (isinstance(damping, list) and len(damping) == n and all(map(number, damping))):
            fail(f"'damping' must be {n} numbers")
        tip = doc.get("tip", [])
        bodies = doc.get("bodies", [])
        parents = doc.get("body_parents", [])
        if not (named(bodies, MAX_MODEL_BODIES) and isinstance(parents, list) and len(parents) == len(bodies)
                and all(isinstance(p, int) and not isinstance(p, bool) and -1 <= p < len(bodies) for p in parents)):
            fail(f"'bodies' must be at most {MAX_MODEL_BODIES} names and 'body_parents' one index in "
                 f"-1..len(bodies)-1 per body")
        info = _checked_info(doc.get("info", {}), n_u, len(bodies), number, fail)
        return cls(positions=names["positions"], velocities=names["velocities"], actuators=names["actuators"],
                   revolute=tuple(revolute), mass=polys("mass", n * (n + 1) // 2), bias=polys("bias", n),
                   gravity=polys("gravity", n), kinetic=poly(doc.get("kinetic"), "kinetic"),
                   potential=poly(doc.get("potential"), "potential"),
                   tip=polys("tip", 3) if tip else (), bodies=tuple(bodies), body_parents=tuple(parents),
                   body_origins=polys("body_origins", 3 * len(bodies)),
                   actuation=tuple(tuple(map(float, r)) for r in actuation),
                   damping=tuple(map(float, damping)), info=info)


def _checked_info(info, n_u: int, n_bodies: int, number, fail) -> dict:
    """The cache record's ``info``: only the keys :func:`~hybridctl.systems.symbolic.derive` writes, each checked."""
    if not isinstance(info, dict):
        fail("'info' must be an object")
    unknown = sorted(set(info) - {"generation_seconds", "terms", "expression_chars", "effort_limits",
                                  "tip_body_index"})
    if unknown:
        fail(f"'info' holds keys it never has: {', '.join(map(repr, unknown))[:200]}")
    if not all(number(info[k]) and info[k] >= 0 for k in ("generation_seconds", "terms", "expression_chars")
               if k in info):
        fail("'info' counts must be numbers >= 0")
    efforts = info.get("effort_limits", [None] * n_u)
    if not (isinstance(efforts, list) and len(efforts) == n_u
            and all(e is None or (number(e) and e > 0) for e in efforts)):
        fail(f"'info.effort_limits' must be {n_u} limits, each a number > 0 or null (none)")
    index = info.get("tip_body_index", 0)
    if not (isinstance(index, int) and not isinstance(index, bool) and 0 <= index < max(n_bodies, 1)):
        fail("'info.tip_body_index' must index 'bodies'")
    return dict(info)


# ============================================================================ code generation
class _Code:
    """Straight-line code with constant folding: a value is a float (known now) or a name (a column).

    ``torch=True`` writes fused torch calls (``torch.add(a, b, alpha=c)``: one kernel for a
    multiply-add); otherwise plain operators, which serve Python floats and numpy arrays alike.
    """

    def __init__(self, torch_calls: bool, prefix: str = "t"):
        self.lines: list[str] = []
        self.torch = torch_calls
        self.prefix = prefix
        self._count = 0

    def assign(self, expression: str) -> str:
        name = f"{self.prefix}{self._count}"
        self._count += 1
        self.lines.append(f"{name} = {expression}")
        return name

    @staticmethod
    def text(a) -> str:
        return repr(float(a)) if isinstance(a, float) else a

    def mul(self, a, b):
        if isinstance(a, float) and isinstance(b, float):
            return a * b
        if isinstance(a, float):
            a, b = b, a
        if isinstance(b, float):
            if b == 0.0:
                return 0.0
            if b == 1.0:
                return a
            if b == -1.0:
                return self.assign(f"-{a}")
        return self.assign(f"{self.text(a)} * {self.text(b)}")

    def add(self, a, b, scale: float = 1.0):
        """a + scale * b."""
        if isinstance(b, float) or scale == 0.0:
            b = scale * b if isinstance(b, float) else b
            if scale == 0.0:
                return a
            if isinstance(b, float):
                if isinstance(a, float):
                    return a + b
                return a if b == 0.0 else self.assign(f"{a} + {b!r}")
        if isinstance(a, float):
            if a == 0.0:
                return self.mul(b, scale)
            scaled = self.mul(b, scale)
            return self.assign(f"{scaled} + {a!r}")
        if scale == 1.0:
            return self.assign(f"{a} + {b}")
        if scale == -1.0:
            return self.assign(f"{a} - {b}")
        if self.torch:
            return self.assign(f"_torch.add({a}, {b}, alpha={scale!r})")
        return self.assign(f"{a} + {scale!r} * {b}" if scale > 0 else f"{a} - {-scale!r} * {b}")

    def div(self, a, b):
        if isinstance(b, float):
            return self.mul(a, 1.0 / b)
        if isinstance(a, float) and a == 0.0:
            return 0.0
        return self.assign(f"{self.text(a)} / {b}")


class _PolynomialWriter:
    """Evaluates polynomials of :class:`MultibodyModel` in a :class:`_Code`, sharing monomials."""

    def __init__(self, code: _Code, sin: str, cos: str, coordinates: Sequence[str]):
        self.code = code
        self.sin, self.cos = sin, cos
        self.coordinates = list(coordinates)    # names of q_0.., v_0.. columns
        self.n = len(coordinates) // 2
        self._var: dict[int, str] = {}
        self._mono: dict[tuple[int, ...], str] = {}

    def variable(self, k: int) -> str:
        """The column of variable slot k: s_i, c_i, q_i or v_i."""
        if k not in self._var:
            n = self.n
            kind, i = divmod(k, n)
            if kind == 0:
                self._var[k] = self.code.assign(f"{self.sin}({self.coordinates[i]})")
            elif kind == 1:
                self._var[k] = self.code.assign(f"{self.cos}({self.coordinates[i]})")
            else:
                self._var[k] = self.coordinates[(kind - 2) * n + i]
        return self._var[k]

    def monomial(self, exponents: tuple[int, ...]):
        """The column of one monomial, built from a shared shorter one times one variable."""
        factors = tuple(k for k, e in enumerate(exponents) for _ in range(e))
        return self._product(factors)

    def _product(self, factors: tuple[int, ...]):
        if not factors:
            return 1.0
        if len(factors) == 1:
            return self.variable(factors[0])
        if factors not in self._mono:
            self._mono[factors] = self.code.mul(self._product(factors[:-1]), self.variable(factors[-1]))
        return self._mono[factors]

    def polynomial(self, terms: Sequence[Term]):
        """sum_k c_k m_k: a float where every term is constant."""
        const = 0.0
        out = None
        for coef, exponents in terms:
            if not any(exponents):
                const += coef
                continue
            m = self.monomial(exponents)
            out = self.code.mul(m, coef) if out is None else self.code.add(out, m, coef)
        if out is None:
            return const
        return self.code.add(out, const) if const != 0.0 else out


def _ldlt_solve(code: _Code, m: dict, r: list):
    """Solve M x = r for symmetric positive definite M by an unrolled LDL^T (no pivoting).

    ``m[(i, k)]`` (i <= k) and ``r[i]`` are floats or column names; constants fold away."""
    n = len(r)
    L: dict = {}
    inv_d: list = [None] * n
    # W_ij = L_ij D_j (i > j) is kept unscaled: D_j = M_jj - sum_k L_jk W_jk, W_ij = M_ij - sum_k L_ik W_jk
    D: list = []
    W: dict = {}
    for j in range(n):
        d = m[(j, j)]
        for k in range(j):
            d = code.add(d, code.mul(L[(j, k)], W[(j, k)]), -1.0)
        if isinstance(d, float) and not d > 0.0:
            raise ModelError(f"the mass matrix is not positive definite (pivot {j} is the constant {d!r})")
        D.append(d)
        inv_d[j] = code.div(1.0, d)
        for i in range(j + 1, n):
            w = m[(j, i)]
            for k in range(j):
                w = code.add(w, code.mul(L[(i, k)], W[(j, k)]), -1.0)
            W[(i, j)] = w
            L[(i, j)] = code.mul(w, inv_d[j])
    y: list = []
    for i in range(n):
        value = r[i]
        for k in range(i):
            value = code.add(value, code.mul(L[(i, k)], y[k]), -1.0)
        y.append(value)
    x: list = [0.0] * n
    for i in reversed(range(n)):
        value = code.mul(y[i], inv_d[i])
        for k in range(i + 1, n):
            value = code.add(value, code.mul(L[(k, i)], x[k]), -1.0)
        x[i] = value
    return x


def _accelerations(model: MultibodyModel, code: _Code, q: Sequence[str], v: Sequence[str], u: Sequence[str],
                   sin: str, cos: str):
    """Emit qdd = M^-1 (B u + tau_g - C v - D v) into ``code``; return the n accelerations."""
    n = model.n_q
    poly = _PolynomialWriter(code, sin, cos, [*q, *v])
    m, index = {}, 0
    for i in range(n):
        for k in range(i, n):
            m[(i, k)] = poly.polynomial(model.mass[index])
            index += 1
    rhs = []
    for i in range(n):
        # tau_g - C v as one polynomial: shared monomials, no separate negation
        terms: dict = {}
        for coef, exponents in model.gravity[i]:
            terms[exponents] = terms.get(exponents, 0.0) + coef
        for coef, exponents in model.bias[i]:
            terms[exponents] = terms.get(exponents, 0.0) - coef
        value = poly.polynomial([(c, e) for e, c in terms.items() if c != 0.0])
        if model.damping[i] != 0.0:
            value = code.add(value, v[i], -model.damping[i])
        for j, b in enumerate(model.actuation[i]):
            if b != 0.0:
                value = code.add(value, u[j], b)
        rhs.append(value)
    return _ldlt_solve(code, m, rhs)


def _column_value(value, like: str) -> str:
    """A column name, or a constant float spread to the shape of column ``like``."""
    return value if isinstance(value, str) else f"_torch.full_like({like}, {float(value)!r})"


def _clamped(model: MultibodyModel, inputs: Sequence[str]) -> list[tuple[str, float]]:
    """(input, effort limit) of the inputs with a finite limit, which Drake's MultibodyPlant clamps to
    [-effort, effort] (pydrake 1.51: u = 10 under effort 2.5 moves it as u = 2.5; no limit: inf, no clamp)."""
    return [(name, e) for name, e in zip(inputs, model.effort) if math.isfinite(e)]


def torch_source(model: MultibodyModel, dt: float | None, integrator: str | None, columns: bool = False) -> str:
    """Source of ``torch_step(x, u)``: dx/dt (``integrator`` None) or one step of ``dt``.

    ``euler``: x + dt f(x, u); ``runge_kutta2``: x + (dt/2)(k1 + k2), k2 = f(x + dt k1, u), as
    the chain family and Drake's RungeKutta2Integrator. ``columns``: x (n, B), u (m, B)."""
    n, axis = model.n_q, 0 if columns else -1
    code = _Code(torch_calls=True)
    u = [f"u{j}" for j in range(model.n_u)]
    if u:
        code.lines.append(f"{', '.join(u)}, = u.unbind({axis})")
    code.lines += [f"{name} = _torch.clamp({name}, {-e!r}, {e!r})" for name, e in _clamped(model, u)]

    def derivative(state: str, tag: str) -> str:
        names = [f"{tag}{i}" for i in range(2 * n)]
        code.lines.append(f"{', '.join(names)}, = {state}.unbind({axis})")
        acc = _accelerations(model, code, names[:n], names[n:], u, "_torch.sin", "_torch.cos")
        cols = names[n:] + [_column_value(a, names[0]) for a in acc]
        code.lines.append(f"d{tag} = _torch.stack([{', '.join(cols)}], {axis})")
        return f"d{tag}"

    integrator_lines(code.lines, derivative, dt, integrator)
    return "def torch_step(x, u):\n" + "".join(f"    {line}\n" for line in free_early(code.lines))


def scalar_source(model: MultibodyModel, dt: float | None, integrator: str | None, bound: float | None) -> str:
    """Source of one-state functions over plain floats: ``derivatives(x, u)`` (``integrator``
    None) or ``step(x, u, steps)``, which returns the state as a list, or None as soon as a
    coordinate leaves [-bound, bound] or turns NaN (when ``bound`` is given)."""
    n = model.n_q
    code = _Code(torch_calls=False)
    state = [f"x{i}" for i in range(2 * n)]
    inputs = [f"u{j}" for j in range(model.n_u)]

    def stage(names):
        acc = _accelerations(model, code, names[:n], names[n:], inputs, "_sin", "_cos")
        return [_Code.text(a) for a in acc]

    head = [f"{', '.join(state)}, = x"] + ([f"{', '.join(inputs)}, = u"] if inputs else [])
    head += [f"{name} = min(max({name}, {-e!r}), {e!r})" for name, e in _clamped(model, inputs)]  # NaN stays NaN
    if integrator is None:
        acc = stage(state)
        body = code.lines + [f"return [{', '.join(state[n:] + acc)}]"]
        return "def derivatives(x, u):\n" + "".join(f"    {line}\n" for line in head + body)
    return step_loop_source("step", head, state, n, code.lines, stage, dt, integrator, bound)


def polynomials_source(model: MultibodyModel, polys: Sequence[Sequence[Term]]) -> str:
    """Source of ``values(q, v, sin, cos)``: the given polynomials at columns q, v (numpy or torch)."""
    n = model.n_q
    code = _Code(torch_calls=False)
    q, v = [f"q{i}" for i in range(n)], [f"v{i}" for i in range(n)]
    writer = _PolynomialWriter(code, "sin", "cos", [*q, *v])
    values = [_Code.text(writer.polynomial(p)) for p in polys]
    head = [f"{', '.join(q)}, = q", f"{', '.join(v)}, = v"]
    return ("def values(q, v, sin, cos):\n" + "".join(f"    {line}\n" for line in head + code.lines)
            + f"    return [{', '.join(values)}]\n")


def _compile(source: str, name: str, namespace: dict):
    """Compile generated source (built from numbers only) and return the function ``name``."""
    # one function object per source in the process (see shared_function: torch.compile guards on it);
    # .source as ChainDynamics' generated functions: benchmarks count its operations
    return shared_function(source, name, namespace, f"<hybridctl generated {name}>")


class GeneratedDynamics:
    """Time derivatives and integrator steps of a :class:`MultibodyModel` (the multibody family's
    counterpart of ``ChainDynamics``): batched torch, column-major torch, plain floats."""

    def __init__(self, model: MultibodyModel):
        self.model = model
        self.n_q = model.n_q
        self._torch: dict = {}
        self._scalar: dict = {}
        self._compiled: dict = {}
        self._evaluators: dict = {}   # energy, tip, body points: generated on first use

    # ----------------------------------------------------------------- torch
    def generate_torch_step(self, dt: float | None, integrator: str | None, columns: bool = False):
        """The generated ``torch_step(x, u)`` for (dt, integrator, columns), built once."""
        key = (dt, integrator, columns)
        if key not in self._torch:
            self._torch[key] = _compile(torch_source(self.model, dt, integrator, columns), "torch_step",
                                        {"_torch": torch})
        return self._torch[key]

    def derivatives(self, x, u):
        """dx/dt of states (B, 2n) or (2n,) under inputs (B, m) or (m,), torch."""
        if x.dim() == 1:
            return self.derivatives(x[None], u[None])[0]
        return self.generate_torch_step(None, None)(x, u)

    def torch_step(self, x, u, dt: float | None = None, integrator: str | None = None):
        """One step (or dx/dt where ``integrator`` is None) of batched rows, differentiable."""
        if x.dim() == 1:
            return self.torch_step(x[None], u[None], dt, integrator)[0]
        return self.generate_torch_step(dt, integrator)(x, u)

    def torch_step_columns(self, x, u, dt: float, integrator: str, compiled: bool = False):
        """:meth:`torch_step` of column-major states (n, B); ``compiled`` runs it through torch.compile."""
        step = self.generate_torch_step(dt, integrator, columns=True)
        if compiled:   # one fused loop (as the chain family's; ~15 s to build per process, dtype and batch)
            key = (dt, integrator)
            if key not in self._compiled:
                self._compiled[key] = torch.compile(step, dynamic=False)
            step = self._compiled[key]
        return step(x, u)

    # ----------------------------------------------------------------- floats
    def scalar(self, dt: float | None = None, integrator: str | None = None, bound: float | None = None):
        """The plain-float function of one state: ``derivatives(x, u)`` or ``step(x, u, steps)``."""
        key = (dt, integrator, bound)
        if key not in self._scalar:
            name = "derivatives" if integrator is None else "step"
            self._scalar[key] = _compile(scalar_source(self.model, dt, integrator, bound), name,
                                         {"_sin": math.sin, "_cos": math.cos})
        return self._scalar[key]

    # ----------------------------------------------------------------- energies and the tip
    def _split(self, x):
        n = self.n_q
        if isinstance(x, torch.Tensor):
            cols = x.unbind(-1)
            return list(cols[:n]), list(cols[n:]), torch.sin, torch.cos
        x = np.asarray(x, dtype=float)
        cols = [x[..., i] for i in range(2 * n)]
        return cols[:n], cols[n:], np.sin, np.cos

    def _values(self, name: str, polys, x) -> list:
        """The polynomials ``polys`` (evaluator generated once under ``name``) at states x, each as an array
        or tensor like x's columns (constant polynomials spread to that shape)."""
        if name not in self._evaluators:
            self._evaluators[name] = _compile(polynomials_source(self.model, list(polys)), "values", {})
        q, v, sin, cos = self._split(x)
        like = q[0]
        full = torch.full_like if isinstance(like, torch.Tensor) else np.full_like
        return [full(like, value) if isinstance(value, float) else value
                for value in self._evaluators[name](q, v, sin, cos)]

    def energy(self, x):
        """Kinetic plus potential energy of states x (numpy or torch, batched), as Drake computes them."""
        kinetic, potential = self._values("energy", [self.model.kinetic, self.model.potential], x)
        return kinetic + potential

    def tip_world(self, x):
        """World (x, y, z) of the spec's tip point at states x (numpy or torch, batched)."""
        if not self.model.tip:
            raise ValueError("this model has no tip point: name one in the spec ([model] tip_body and tip_point)")
        return self._values("tip", self.model.tip, x)

    def points(self, x) -> np.ndarray:
        """(len(x), bodies + tip, 3) world positions of the body origins (and the tip point, if any) at
        states x (numpy, batched): what a stick-figure drawing and a view box need."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        values = self._values("points", [*self.model.body_origins, *self.model.tip], x)
        return np.stack(values, axis=-1).reshape(x.shape[0], -1, 3)

    def segments(self) -> list[tuple[int, int]]:
        """Pairs (parent, child) of :meth:`points` indices to draw: each body from its parent's origin
        (the world origin for -1: index ``len(points)``, which callers add), then the last body to the tip."""
        n = len(self.model.bodies)
        pairs = [(parent if parent >= 0 else -1, child) for child, parent in enumerate(self.model.body_parents)]
        if self.model.tip:
            owner = self.model.info.get("tip_body_index", n - 1)
            pairs.append((owner, n))
        return pairs

    def tip_height(self, x):
        """World height z of the tip point."""
        return self.tip_world(x)[2]

    def tip_position(self, x):
        """(horizontal x, height z) of the tip point in the world."""
        world = self.tip_world(x)
        return world[0], world[2]

    def tip_height_single(self, x) -> float:
        """:meth:`tip_height` of one state given as a sequence of floats."""
        return float(self.tip_height(np.asarray(x, dtype=float)))
