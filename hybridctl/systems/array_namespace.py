"""The few array operations the chain formula of :mod:`hybridctl.systems.dynamics` runs on, for numpy or torch.

:class:`ArrayNamespace` is the "namespace" ``xp`` of ``ChainDynamics._accelerations``: the same
formula evaluates numpy (one state, on Python floats), batched differentiable torch, or, through
:mod:`hybridctl.systems.generated_code`, symbols that record it as straight-line code.
:func:`solve_symmetric` is the closed-form solve of the mass matrix (n <= 3).
"""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = ["ArrayNamespace", "NUMPY_NAMESPACE", "solve_symmetric"]


class ArrayNamespace:
    """The few array operations the chain formula needs, for numpy or torch.

    The formula works on "columns": arrays of the batch shape (0-d for a single
    state), one per state coordinate or intermediate quantity, or plain floats
    for quantities that do not depend on the state (those cost no array call).
    Elementwise work on (batch,) columns beats (batch, n, n) tensor algebra here
    because the matrices are at most 3x3: each torch call costs microseconds of
    dispatch, so the number of calls matters more than the arithmetic.
    """

    def __init__(self, like):
        self.torch = isinstance(like, torch.Tensor)
        self.dtype, self.device = (like.dtype, like.device) if self.torch else (None, None)
        self._consts: dict[float, torch.Tensor] = {}
        self._generated: dict = {}

    def columns(self, a):
        """The last axis of ``a`` as a list of arrays of the batch shape (views)."""
        # unbind is one torch call however many columns there are. A single numpy
        # state becomes scalars (Python floats for float64, then math.sin/cos), whose
        # arithmetic is many times faster than that of 0-d arrays.
        if self.torch:
            return list(a.unbind(-1))
        if a.ndim == 1:
            return a.tolist() if a.dtype == np.float64 else list(a)
        return [a[..., i] for i in range(a.shape[-1])]

    def solve(self, A, b):
        if self.torch:
            return torch.linalg.solve(A, b.unsqueeze(-1)).squeeze(-1)
        return np.linalg.solve(A, b[..., None])[..., 0]

    def consts_for(self, fn) -> list:
        """The cached 0-d constants generated torch code ``fn`` refers to as ``K[i]``."""
        cached = self._generated.get(fn)
        if cached is None:
            cached = self._generated[fn] = [self.const(v) for v in fn.constants]
        return cached

    def cos(self, a):
        if self.torch:
            return torch.cos(a)
        return math.cos(a) if isinstance(a, float) else np.cos(a)

    def sin(self, a):
        if self.torch:
            return torch.sin(a)
        return math.sin(a) if isinstance(a, float) else np.sin(a)

    def cumsum(self, a):
        return torch.cumsum(a, dim=-1) if self.torch else np.cumsum(a, axis=-1)

    def const(self, value: float):
        """``value`` as a 0-d tensor of the namespace's dtype and device (cached), or a float.

        Passing Python floats to torch calls costs a scalar-to-tensor conversion
        per call (two in float32); cached 0-d tensors avoid it.
        """
        if not self.torch:
            return value
        if value not in self._consts:
            self._consts[value] = torch.tensor(value, dtype=self.dtype, device=self.device)
        return self._consts[value]

    def lincomb(self, const: float, terms):
        """const + sum of coef * f1 [* f2] over terms (coef, f1) or (coef, f1, f2) of columns.

        In torch every term is exactly one call, ``add(alpha=)`` or ``addcmul(value=)``,
        the first one starting from the cached constant. Returns ``const`` when
        there are no terms.
        """
        if not self.torch:
            out = const
            for t in terms:
                out = out + (t[0] * t[1] if len(t) == 2 else t[0] * t[1] * t[2])
            return out
        out = None
        for t in terms:
            if out is None and const == 0.0 and t[0] == 1.0 and len(t) == 2:
                out = t[1]              # a bare column: no call at all
                continue
            base = self.const(const) if out is None else out
            out = torch.add(base, t[1], alpha=t[0]) if len(t) == 2 else torch.addcmul(base, t[1], t[2], value=t[0])
        return const if out is None else out

    def products(self, terms):
        """sum of coef * x * y over terms (coef, x, y) whose factors are columns or floats."""
        const, arrays = 0.0, []
        for coef, x, y in terms:
            if isinstance(x, float) and isinstance(y, float):
                const += coef * x * y
            elif isinstance(x, float) or isinstance(y, float):
                arrays.append((coef * x, y) if isinstance(x, float) else (coef * y, x))
            else:
                arrays.append((coef, x, y))
        return self.lincomb(const, arrays)

    def stack(self, cols, like):
        """Columns (arrays or floats) -> one array (..., len(cols)); floats are broadcast
        to ``like``, a column that gives the batch shape, dtype and device."""
        if not self.torch:
            dtype = np.result_type(like, *cols)
            dtype = dtype if dtype.kind == "f" else np.dtype(float)
            shapes = {getattr(c, "shape", ()) for c in [like, *cols]}
            if shapes == {()}:
                return np.array(cols, dtype=dtype)      # one state: numpy scalars and floats
            out = np.empty(np.broadcast_shapes(*shapes) + (len(cols),), dtype=dtype)
            for i, col in enumerate(cols):
                out[..., i] = col
            return out
        cols = [torch.full_like(like, c) if isinstance(c, float) else c for c in cols]
        if len({c.shape for c in cols}) > 1:
            cols = torch.broadcast_tensors(*cols)
        if (cols[0].numel() >= 1024 and not any(c.requires_grad for c in cols)
                and all(c.dtype == cols[0].dtype for c in cols)):
            # torch.stack on the last axis is a slow strided cat for large batches
            # (~20 us at 4096 x 4); copying column by column into the interleaved
            # result is about twice as fast there (and slower for small batches).
            out = cols[0].new_empty(cols[0].shape + (len(cols),))
            for dst, src in zip(out.unbind(-1), cols):
                dst.copy_(src)
            return out
        return torch.stack(cols, dim=-1)


NUMPY_NAMESPACE = ArrayNamespace(np.zeros(0))


def solve_symmetric(xp, m, r):
    """Solve M qdd = r for symmetric M (n <= 3) in closed form (Cramer's rule / adjugate).

    ``m[i][k]`` (i <= k) and ``r[i]`` are columns or floats, so this is batched
    and differentiable wherever the namespace is. Mass matrices are symmetric
    positive definite and well conditioned, where the explicit inverse is as
    accurate as LU (the Drake comparison holds to 1e-9).
    """
    n = len(r)
    if n == 1:
        return [r[0] / m[0][0]]
    if n == 2:
        (a, b), d = m[0], m[1][1]
        det = xp.products([(1.0, a, d), (-1.0, b, b)])
        return [xp.products([(1.0, d, r[0]), (-1.0, b, r[1])]) / det,
                xp.products([(1.0, a, r[1]), (-1.0, b, r[0])]) / det]
    (a, b, c), (d, e), f = m[0], m[1][1:], m[2][2]
    # Cofactors of [[a, b, c], [b, d, e], [c, e, f]] (the adjugate is symmetric too).
    A = [[xp.products([(1.0, d, f), (-1.0, e, e)]), xp.products([(1.0, c, e), (-1.0, b, f)]),
          xp.products([(1.0, b, e), (-1.0, c, d)])],
         [None, xp.products([(1.0, a, f), (-1.0, c, c)]), xp.products([(1.0, b, c), (-1.0, a, e)])],
         [None, None, xp.products([(1.0, a, d), (-1.0, b, b)])]]
    det = xp.products([(1.0, a, A[0][0]), (1.0, b, A[0][1]), (1.0, c, A[0][2])])
    return [xp.products([(1.0, A[min(i, k)][max(i, k)], r[k]) for k in range(3)]) / det
            for i in range(3)]
