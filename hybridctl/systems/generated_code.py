"""The chain formula recorded as straight-line code: one state on plain floats, or batched torch.

``_CodeWriter`` runs the formula of :class:`hybridctl.systems.dynamics.ChainDynamics` on symbols
and records it as straight-line Python over floats (``ChainDynamics.scalar``); ``_TorchCodeWriter``
records the torch namespace's calls the same way (``ChainDynamics.torch_step``). The integrator
loops (:func:`step_loop_source`, :func:`integrator_lines`), :func:`free_early` and the process-wide
cache of generated functions (:func:`shared_function`) are shared with the generated multibody code
(:mod:`hybridctl.systems.multibody`). The functions here take the chain's dynamics object
(``dynamics``: a ``ChainDynamics``) and call its ``_accelerations`` with a writer as namespace.
"""

from __future__ import annotations

import math
import re

from .array_namespace import NUMPY_NAMESPACE, ArrayNamespace

__all__ = ["scalar_source", "torch_source", "step_loop_source", "integrator_lines", "free_early", "shared_function",
           "SHARED_FUNCTIONS_LIMIT"]


# ------------------------------------------------------------ one state, plain floats
class _Sym:
    """A named float of generated code: arithmetic on it writes one line to its _CodeWriter."""

    __slots__ = ("writer", "name")

    def __init__(self, writer: "_CodeWriter", name: str):
        self.writer, self.name = writer, name

    def __add__(self, other):
        return self.writer.binary(self, "+", other)

    def __radd__(self, other):
        return self.writer.binary(other, "+", self)

    def __sub__(self, other):
        return self.writer.binary(self, "-", other)

    def __rsub__(self, other):
        return self.writer.binary(other, "-", self)

    def __mul__(self, other):
        return self.writer.binary(self, "*", other)

    def __rmul__(self, other):
        return self.writer.binary(other, "*", self)

    def __truediv__(self, other):
        return self.writer.binary(self, "/", other)

    def __rtruediv__(self, other):
        return self.writer.binary(other, "/", self)


class _CodeWriter:
    """A namespace for the chain formula that writes straight-line Python instead of computing.

    Running ``ChainDynamics._accelerations`` on :class:`_Sym` inputs records every
    operation of the numpy path on Python floats, in the same order, as one line of
    source each (``t7 = t3 + -0.5*t5``). Compiled once, that source evaluates one
    state with ``math.sin``/``math.cos`` and float arithmetic only: no array or
    tensor call, no table lookups. Floats that do not depend on the state (the
    folded constants) are written as literals (``repr`` round-trips exactly).
    """

    torch = False

    def __init__(self):
        self.lines: list[str] = []
        self._count = 0

    @staticmethod
    def _text(a) -> str:
        return a.name if isinstance(a, _Sym) else repr(float(a))

    def assign(self, expression: str) -> _Sym:
        name = f"t{self._count}"
        self._count += 1
        self.lines.append(f"{name} = {expression}")
        return _Sym(self, name)

    def binary(self, a, op: str, b):
        return self.assign(f"{self._text(a)} {op} {self._text(b)}")

    def sin(self, a):
        return self.assign(f"_sin({self._text(a)})") if isinstance(a, _Sym) else math.sin(a)

    def cos(self, a):
        return self.assign(f"_cos({self._text(a)})") if isinstance(a, _Sym) else math.cos(a)

    def lincomb(self, const: float, terms):
        """As ``ArrayNamespace.lincomb`` on floats: const + c1*f1[*g1] + ..., left to right.

        ``(c*f)*g`` is written as ``f*g`` for c = 1 and subtracted as ``|c|*f*g`` for
        c < 0, which IEEE arithmetic computes exactly as the general form.
        """
        if not terms:
            return const
        if all(not isinstance(f, _Sym) for t in terms for f in t[1:]):
            return NUMPY_NAMESPACE.lincomb(const, terms)
        expression = None if const == 0.0 else repr(float(const))
        for t in terms:
            coef, factors = t[0], [self._text(f) for f in t[1:]]
            product = "*".join(factors if abs(coef) == 1.0 else [repr(abs(coef))] + factors)
            if expression is None:
                expression = product if coef > 0 else f"-{product}" if coef == -1.0 else f"{coef!r}*{'*'.join(factors)}"
            else:
                expression += (" + " if coef > 0 else " - ") + product
        return self.assign(expression)

    products = ArrayNamespace.products

    def solve(self, A, b):
        raise NotImplementedError("no closed-form solve for more than 3 joint coordinates")

    stack = solve


def scalar_source(dynamics, name: str, dt: float, integrator: str | None,
                   bound: float | None) -> str:
    """Python source of one-state functions over plain floats (see ``ChainDynamics.scalar``).

    ``integrator`` None: ``name(x, u)`` returns dx/dt as a list. Otherwise
    ``name(x, u, steps)`` takes ``steps`` steps of ``dt`` (``euler``: x + dt f(x, u);
    ``runge_kutta2``: x + (0.5 dt)(k1 + k2), k2 = f(x + dt k1, u), the operation order of
    ``System.step_unchecked``) and returns the state as a list, or None as soon as a
    coordinate leaves [-bound, bound] or turns NaN (when ``bound`` is given).
    """
    n_q, n_u = dynamics.p.n_q, dynamics.p.actuation.shape[1]
    writer = _CodeWriter()
    state = [f"x{i}" for i in range(2 * n_q)]
    inputs = [f"u{i}" for i in range(n_u)]

    def stage(names):
        """Emit the accelerations at the state named ``names``; return their texts."""
        syms = [_Sym(writer, s) for s in names]
        acc = dynamics._accelerations(writer, syms[:n_q], syms[n_q:], [_Sym(writer, s) for s in inputs])
        return [writer._text(a) for a in acc]

    head = [f"{', '.join(state)}, = x", f"{', '.join(inputs)}, = u"]
    if integrator is None:
        acc = stage(state)
        body = writer.lines + [f"return [{', '.join(state[n_q:] + acc)}]"]
        return "\n".join([f"def {name}(x, u):"] + ["    " + line for line in head + body]) + "\n"
    return step_loop_source(name, head, state, n_q, writer.lines, stage, dt, integrator, bound)


def step_loop_source(name: str, head: list[str], state: list[str], n_q: int, lines: list[str], stage,
                     dt: float, integrator: str, bound: float | None) -> str:
    """Source of ``name(x, u, steps)``: ``head`` unpacks x and u into the names ``state`` and the
    inputs, ``stage(names)`` appends to ``lines`` the code of the accelerations at the state named
    ``names`` and returns their texts; the loop takes ``steps`` integrator steps (``euler``:
    x + dt f; ``runge_kutta2``: x + (dt/2)(k1 + k2), k2 = f(x + dt k1)) and returns the state as a
    list, or None as soon as a coordinate leaves [-bound, bound] or turns NaN (``bound`` given).
    Shared by the chain family and the generated multibody code."""
    k1 = state[n_q:] + stage(state)
    if integrator == "euler":
        new = [f"{s} + {dt!r}*{k}" for s, k in zip(state, k1)]
    elif integrator == "runge_kutta2":
        mid = [f"m{i}" for i in range(2 * n_q)]
        lines += [f"{m} = {s} + {dt!r}*{k}" for m, s, k in zip(mid, state, k1)]
        k2 = mid[n_q:] + stage(mid)
        new = [f"{s} + {0.5 * dt!r}*({a} + {b})" for s, a, b in zip(state, k1, k2)]
    else:
        raise ValueError(f"integrator must be 'euler' or 'runge_kutta2', got {integrator!r}")
    loop = lines + [f"n{i} = {e}" for i, e in enumerate(new)]
    if bound is not None:
        inside = " and ".join(f"{-bound!r} <= n{i} <= {bound!r}" for i in range(2 * n_q))
        loop += [f"if not ({inside}):", "    return None"]
    loop += [f"{', '.join(state)} = {', '.join(f'n{i}' for i in range(2 * n_q))}"]
    return "\n".join([f"def {name}(x, u, steps):"] + ["    " + line for line in head]
                     + ["    for _ in range(steps):"] + ["        " + line for line in loop]
                     + [f"    return [{', '.join(state)}]"]) + "\n"


class _TorchCodeWriter(_CodeWriter):
    """As :class:`_CodeWriter`, but records the torch namespace's calls (``ArrayNamespace`` with
    ``torch=True``): the same ``add(alpha=)`` / ``addcmul(value=)`` chains from cached 0-d
    constants, the same operators, the same stack. The generated function therefore computes
    bit for bit what the table-driven torch path computes (batched, differentiable), without
    its Python bookkeeping (dict lookups, term loops) at every call.
    """

    torch = True

    def __init__(self):
        super().__init__()
        self.constants: list[float] = []

    def const(self, value: float) -> str:
        if value not in self.constants:
            self.constants.append(value)
        return f"K[{self.constants.index(value)}]"

    def sin(self, a):
        return self.assign(f"_torch.sin({self._text(a)})")

    def cos(self, a):
        return self.assign(f"_torch.cos({self._text(a)})")

    def lincomb(self, const: float, terms):
        out = None
        for t in terms:
            if out is None and const == 0.0 and t[0] == 1.0 and len(t) == 2:
                out = t[1]
                continue
            base = self.const(const) if out is None else self._text(out)
            factors = ", ".join(self._text(f) for f in t[1:])
            out = self.assign(f"_torch.add({base}, {factors}, alpha={t[0]!r})" if len(t) == 2
                              else f"_torch.addcmul({base}, {factors}, value={t[0]!r})")
        return const if out is None else out


def torch_source(dynamics, dt: float | None, integrator: str | None, columns: bool = False):
    """(source, constants) of ``f(x, u, xp, K)``: the batched torch derivatives (``integrator``
    None) or one integrator step, as ``System.step`` computes it (see ``ChainDynamics.torch_step``).
    ``columns``: states (n, batch) and inputs (m, batch), one contiguous row per coordinate."""
    axis = 0 if columns else -1
    n_q, n_u = dynamics.p.n_q, dynamics.p.actuation.shape[1]
    writer = _TorchCodeWriter()

    def derivative(state: str, tag: str) -> str:
        """Lines computing dx/dt at tensor ``state`` into ``d{tag}``; returns its name."""
        names = [f"{tag}{i}" for i in range(2 * n_q)]
        writer.lines.append(f"{', '.join(names)}, = {state}.unbind({axis})")
        syms = [_Sym(writer, s) for s in names]
        acc = dynamics._accelerations(writer, syms[:n_q], syms[n_q:], [_Sym(writer, f"u{i}") for i in range(n_u)])
        cols = names[n_q:] + [writer._text(a) for a in acc]
        writer.lines.append(f"d{tag} = _torch.stack([{', '.join(cols)}], 0)" if columns
                            else f"d{tag} = xp.stack([{', '.join(cols)}], {names[0]})")
        return f"d{tag}"

    writer.lines.append(f"{', '.join(f'u{i}' for i in range(n_u))}, = u.unbind({axis})")
    integrator_lines(writer.lines, derivative, dt, integrator)
    source = "def torch_step(x, u, xp, K):\n" + "".join(f"    {line}\n" for line in free_early(writer.lines))
    return source, writer.constants


def integrator_lines(lines: list[str], derivative, dt: float | None, integrator: str | None) -> None:
    """Append to ``lines`` the batched step's integrator: ``derivative(state, tag)`` appends the code of
    dx/dt at the tensor named ``state`` and returns its name; the code returns dx/dt (``integrator``
    None), x + dt k1 (``euler``) or x + (dt/2)(k1 + k2), k2 at m = x + dt k1 (``runge_kutta2``).
    Shared by the chain family and the generated multibody code."""
    k1 = derivative("x", "a")
    if integrator is None:
        lines.append(f"return {k1}")
    elif integrator == "euler":
        lines.append(f"return x + {dt!r} * {k1}")
    elif integrator == "runge_kutta2":
        lines.append(f"m = x + {dt!r} * {k1}")
        k2 = derivative("m", "b")
        lines.append(f"return x + {0.5 * dt!r} * ({k1} + {k2})")
    else:
        raise ValueError(f"integrator must be 'euler' or 'runge_kutta2', got {integrator!r}")


def free_early(lines: list[str]) -> list[str]:
    """``lines`` with ``del`` of each temporary ``tN`` right after its last use: straight-line code
    would otherwise keep every intermediate (batch,) tensor alive to the end (hundreds for the
    double cart-pole), which at large batches leaves the cache and slows every operation."""
    names = [re.findall(r"\bt\d+\b", line) for line in lines]
    last = {}
    for i, used in enumerate(names):
        for name in used:
            last[name] = i
    out = []
    for i, line in enumerate(lines):
        out.append(line)
        dead = sorted({n for n in names[i] if last[n] == i and not line.lstrip().startswith("return")},
                      key=lambda n: int(n[1:]))
        if dead:
            out.append(f"del {', '.join(dead)}")
    return out


# Generated functions, shared by every dynamics object whose generated source (and constants) match.
# Why: torch.compile guards on the code object of each function it traces, so a function generated
# afresh for every System (as every training run loads its own) made a compiled rollout recompile per
# run; after torch._dynamo's recompile limit (8 graphs) it silently ran eager, 5-10x slower (measured:
# the 3rd and 4th APG runs of one double cart-pole study process took 1614-1811 s, the first two 182-333 s).
SHARED_FUNCTIONS_LIMIT = 256     # distinct generated functions kept (oldest dropped first)
_SHARED_FUNCTIONS: dict = {}


def shared_function(source: str, name: str, scope: dict, filename: str, constants: list | tuple = ()):
    """The function ``name`` defined by generated ``source`` (built from numbers only, never from a
    file's text) executed in a copy of ``scope``, one object per (source, name, constants) in this
    process; it carries ``.source`` and ``.constants``."""
    key = (source, name, tuple(constants))
    function = _SHARED_FUNCTIONS.get(key)
    if function is None:
        namespace = dict(scope)
        exec(compile(source, filename, "exec"), namespace)  # noqa: S102 - our own generated code
        function = namespace[name]
        function.source, function.constants = source, list(constants)
        while len(_SHARED_FUNCTIONS) >= SHARED_FUNCTIONS_LIMIT:
            _SHARED_FUNCTIONS.pop(next(iter(_SHARED_FUNCTIONS)))
        _SHARED_FUNCTIONS[key] = function
    return function
