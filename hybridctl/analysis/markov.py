"""Absorbing Markov chains: mean first passage time to failure (thesis Ch. 5, Sec. 5.2).

A reachable-state mesh gives a row-stochastic transition matrix ``T`` (scipy sparse)
whose state ``failure`` (index 0 by convention) is absorbing. With ``Q`` the block of
the other (transient) states, the expected number of steps to failure from each state
is the solution of

    (I - Q) t = 1                                                   (exact MFPT)

solved by the solver the chain calls for (``method="auto"``, the default). A chain whose
graph is low-dimensional (a birth-death line, a grid walk, a gait's mesh: the breadth-first
depth of ``I - Q``'s symmetrised pattern is at least ``n ** (1 / DIRECT_MAX_DIMENSION)``) is
factored at once by SuperLU's complete LU (``splu``, path "direct-first") where a factor of
:data:`DIRECT_FILL_GUESS` x nnz fits the memory budget. Any other chain gets a short
unpreconditioned BiCGSTAB probe (enough for chains that mix fast, such as random sparse
rows), then a sparse LU capped at :data:`FILL_CAP` times the nonzeros of ``I - Q``
(SuperLU's ILU with no drop tolerance: exact while the fill stays under the cap), and
where the cap is hit, GMRES preconditioned by the capped (now incomplete) factor. The
path taken is recorded in ``result.solver["path"]``. Never dense.
The thesis' estimate (eq. 5.2, Byl 2009) is ``1 / (1 - lambda_2)`` with lambda_2 the
largest eigenvalue of ``Q``: exact for a start drawn from the quasi-stationary
distribution, and close to the exact value only when the chain mixes much faster
than it fails (``|lambda_3| << lambda_2``, reported as a diagnostic).

States that cannot reach failure, or that can reach such a state, never fail with
positive probability: their MFPT is infinite. They are found by graph search and
reported, not fed to the solver.

Every method's answer is checked before it is returned: finite, at least one step
from every transient state (``t >= 1``: each needs one step to fail) and, for the exact
methods, a relative residual ``||(I - Q) t - 1|| / ||1||`` of at most :data:`RESIDUAL_TOLERANCE`.
A chain that almost never fails (per-step failure probabilities near float64's resolution, MFPT
beyond about 1e9 steps) makes ``I - Q`` numerically singular: every method then raises
:class:`NearlyNeverFailsError` (a ValueError, one line) instead of returning a negative, NaN or
meaningless number; ``method="eigen"`` raises it where ``1 - lambda_2`` is below
:data:`EIGEN_GAP_FLOOR`.

>>> result = absorbing_mfpt(T)                 # exact, per state
>>> result.mfpt[1:], result.eigen_estimate, result.infinite_states, result.lambda3_ratio
>>> result.mean(start_distribution)            # MFPT from a start distribution
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla

from ..limits import LimitError, memory_budget

METHODS = ("auto", "krylov", "eigen", "direct")
ROW_SUM_TOLERANCE = 1e-9
PROBE_ITERATIONS = 40
"""BiCGSTAB iterations ``method="auto"`` tries before factorizing: a fast-mixing chain converges in
about 25 (random sparse rows, 1e3-1e5 states); a slowly mixing mesh needs hundreds."""
FILL_CAP = 60.0
"""Nonzeros of the LU factors ``method="auto"`` accepts, as a multiple of the nonzeros of ``I - Q``
(12 bytes each; lowered further where the memory budget of :mod:`hybridctl.limits` is smaller).
Mesh-like chains need 8-36 at 1e3-1e5 states; random sparse rows need 60-560 and more."""
FACTOR_BYTES_PER_NONZERO = 12
DIRECT_MAX_DIMENSION = 3.0
"""Largest graph dimension (``log n / log depth``, depth the breadth-first eccentricity of a pseudo-peripheral
state) ``method="auto"`` factors at once, without the Krylov probe: 1-D birth-death chains measure 1.0, 2-D grid
walks 1.7-1.8, mesh-like chains 2.5, random sparse rows 4-7 (whose LU fills in without bound)."""
DIRECT_FILL_GUESS = 100.0
"""Nonzeros of the LU factors, per nonzero of ``I - Q``, assumed when checking that a direct-first factor fits
the memory budget (SuperLU/COLAMD measured 1.3 on birth-death lines, 13-29 on grids, 13-37 on mesh-like chains
at 1e4-1e6 states); over the budget, the capped factor of the probe path is used instead."""
EIGEN_MAX_SECONDS = 60.0
"""Wall-time cap of the ARPACK eigen estimate (``method="eigen"`` and the ``eigen=True`` diagnostics):
without it a slowly mixing 1e5-state mesh ran past 150 s. Hitting it raises :class:`EigenLimitError`
for ``method="eigen"``; for the diagnostics of an exact solve it leaves them None with a note."""
EIGEN_MAX_RESTARTS = 2_000
"""ARPACK restarts of the eigen estimate (the iteration cap beside :data:`EIGEN_MAX_SECONDS`)."""


RESIDUAL_TOLERANCE = 1e-6
"""Largest relative residual ``||(I - Q) t - 1||_2 / ||1||_2`` an exact MFPT may have. Rounding alone
leaves about 4e-16 x max(t), so this accepts MFPTs up to about 1e9 steps; past that the chain
almost never fails and float64 cannot resolve it (:class:`NearlyNeverFailsError`)."""
EIGEN_GAP_FLOOR = 1e-12
"""Smallest ``1 - lambda_2`` the eigen estimate ``1 / (1 - lambda_2)`` is returned for (``method="eigen"``);
below it ARPACK's own rounding decides the answer (:class:`NearlyNeverFailsError`)."""


NEVER_FAILS_GAP = 1e-9
"""A solve that fails on a chain with ``1 - lambda_2`` below this (MFPT from the quasi-stationary
distribution above 1e9 steps) is reported as :class:`NearlyNeverFailsError`."""


class MFPTSolveError(ValueError, RuntimeError):
    """No trustworthy MFPT: a solver did not converge or its answer failed the checks (one line).
    A ValueError for the CLI's one-line errors, a RuntimeError for callers that caught the old errors."""


class NearlyNeverFailsError(MFPTSolveError):
    """The chain fails so rarely that ``(I - Q) t = 1`` is numerically singular: its MFPT is effectively
    infinite (beyond what float64 resolves), whatever the method."""


class EigenLimitError(LimitError):
    """The eigen estimate did not converge within :data:`EIGEN_MAX_SECONDS` / :data:`EIGEN_MAX_RESTARTS`."""


def check_transition_matrix(T, failure: int = 0) -> sp.csr_matrix:
    """``T`` as CSR float64 after checks: square, finite, non-negative, rows summing to 1,
    ``failure`` a valid absorbing index. Errors name the offending row or entry."""
    if not sp.issparse(T):
        T = sp.csr_matrix(np.asarray(T, dtype=np.float64))
    T = sp.csr_matrix(T, dtype=np.float64)
    n = T.shape[0]
    if T.ndim != 2 or T.shape[0] != T.shape[1]:
        raise ValueError(f"transition matrix must be square, got shape {T.shape}")
    if n < 1:
        raise ValueError("transition matrix is empty")
    if not (isinstance(failure, (int, np.integer)) and 0 <= failure < n):
        raise ValueError(f"failure index must be an integer in [0, {n - 1}], got {failure!r}")
    if not np.all(np.isfinite(T.data)):
        row = int(np.searchsorted(T.indptr, np.flatnonzero(~np.isfinite(T.data))[0], side="right") - 1)
        raise ValueError(f"transition matrix row {row} contains NaN or inf")
    if T.data.size and T.data.min() < 0:
        k = int(np.argmin(T.data))
        row = int(np.searchsorted(T.indptr, k, side="right") - 1)
        raise ValueError(f"transition matrix has a negative entry {T.data[k]:g} at row {row}, column {T.indices[k]}")
    sums = np.asarray(T.sum(axis=1)).ravel()
    bad = np.flatnonzero(np.abs(sums - 1.0) > ROW_SUM_TOLERANCE)
    if bad.size:
        raise ValueError(f"transition matrix rows must sum to 1: row {bad[0]} sums to {sums[bad[0]]:.12g} "
                         f"({bad.size} rows off by more than {ROW_SUM_TOLERANCE:g})")
    if abs(T[failure, failure] - 1.0) > ROW_SUM_TOLERANCE:
        raise ValueError(f"failure state {failure} is not absorbing: T[{failure}, {failure}] = {T[failure, failure]:g}")
    return T


def states_that_can_fail_surely(T: sp.csr_matrix, failure: int) -> np.ndarray:
    """Boolean mask: states absorbed by ``failure`` with probability 1 (finite MFPT).

    A state has infinite MFPT if it can reach a state from which failure is unreachable
    (reverse search from failure, then reverse search from the unreachable set).
    """
    n = T.shape[0]
    reverse = T.T.tocsr()
    reaches_failure = np.zeros(n, dtype=bool)
    reaches_failure[csgraph.breadth_first_order(reverse, failure, directed=True, return_predecessors=False)] = True
    trapped = np.flatnonzero(~reaches_failure)
    if trapped.size == 0:
        return reaches_failure
    # every state that can reach a trapped state has infinite MFPT too
    reaches_trap = np.zeros(n, dtype=bool)
    source = n  # a virtual node pointing (in reverse) to all trapped states
    extra = sp.csr_matrix((np.ones(trapped.size), (np.full(trapped.size, source), trapped)), shape=(n + 1, n + 1))
    grown = sp.bmat([[reverse, None], [None, sp.csr_matrix((1, 1))]]).tocsr() + extra
    reaches_trap[[i for i in csgraph.breadth_first_order(grown, source, directed=True,
                                                         return_predecessors=False) if i < n]] = True
    return ~reaches_trap


@dataclass
class MFPTResult:
    """Per-state MFPT (``inf`` where failure is not certain; 0 at the failure state) and diagnostics."""

    mfpt: np.ndarray
    failure: int
    method: str
    infinite_states: np.ndarray
    eigen_estimate: float | None = None
    lambda2: float | None = None
    lambda3_ratio: float | None = None
    quasi_stationary: np.ndarray | None = None
    solver: dict = field(default_factory=dict)

    def mean(self, start=None) -> float:
        """MFPT from a start distribution over states (default: the quasi-stationary one if
        computed, else uniform over the transient states)."""
        n = self.mfpt.size
        if start is None:
            start = (self.quasi_stationary if self.quasi_stationary is not None
                     else (np.arange(n) != self.failure).astype(np.float64))
        p = np.asarray(start, dtype=np.float64)
        if p.shape != (n,) or np.any(p < 0) or p.sum() <= 0:
            raise ValueError(f"start must be {n} non-negative weights with a positive sum")
        p = p / p.sum()
        finite = np.isfinite(self.mfpt)
        if np.any(p[~finite] > 0):
            return float("inf")
        return float(p[finite] @ self.mfpt[finite])

    def report(self) -> dict:
        """JSON-ready summary."""
        finite = self.mfpt[np.isfinite(self.mfpt)]
        return {"method": self.method, "states": int(self.mfpt.size), "failure": self.failure,
                "infinite_states": int(self.infinite_states.size),
                "infinite_note": (f"{self.infinite_states.size} states can avoid failure forever (MFPT infinite), "
                                  f"e.g. state {int(self.infinite_states[0])}") if self.infinite_states.size else "",
                "mfpt_min": float(np.min(finite[finite > 0])) if np.any(finite > 0) else None,
                "mfpt_max": float(finite.max()) if finite.size else None,
                "mfpt_from_quasi_stationary": self.mean() if self.quasi_stationary is not None else None,
                "eigen_estimate": self.eigen_estimate, "lambda2": self.lambda2, "lambda3_ratio": self.lambda3_ratio,
                "solver": self.solver}


def _transient_block(T: sp.csr_matrix, keep: np.ndarray) -> sp.csr_matrix:
    return T[keep][:, keep].tocsr()


def dominant_eigen(Q: sp.csr_matrix, k: int = 3, max_seconds: float = EIGEN_MAX_SECONDS,
                   max_restarts: int = EIGEN_MAX_RESTARTS) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` eigenvalues of ``Q`` of largest modulus (descending) and the left Perron vector.

    Dense below 200 states, ARPACK above, bounded by ``max_seconds`` of wall time and
    ``max_restarts`` restarts: past either it raises :class:`EigenLimitError`.
    """
    n = Q.shape[0]
    if n <= max(k + 2, 200):
        values, vectors = np.linalg.eig(Q.T.toarray())
    else:
        QT = Q.T.tocsr()
        deadline = time.perf_counter() + max_seconds

        def matvec(x):
            # ARPACK calls back into Python for every product: the one place a wall-time cap can act
            if time.perf_counter() > deadline:
                raise EigenLimitError(f"the eigen estimate of {n} states ran past its limit of {max_seconds:g} s "
                                      f"(EIGEN_MAX_SECONDS); use method='auto' for the exact MFPT")
            return QT @ x

        operator = spla.LinearOperator(QT.shape, matvec=matvec, dtype=np.float64)
        try:
            values, vectors = spla.eigs(operator, k=min(k, n - 2), which="LM", tol=1e-10, maxiter=max_restarts)
        except spla.ArpackNoConvergence:
            raise EigenLimitError(f"the eigen estimate of {n} states did not converge in {max_restarts} ARPACK "
                                  f"restarts (EIGEN_MAX_RESTARTS); use method='auto' for the exact MFPT") from None
    order = np.argsort(-np.abs(values))
    values, vectors = values[order], vectors[:, order]
    perron = np.abs(np.real(vectors[:, 0]))
    return values[:k], perron / perron.sum() if perron.sum() > 0 else perron


def _krylov_solve(A: sp.csr_matrix, b: np.ndarray, rtol: float) -> tuple[np.ndarray, dict]:
    """Solve A x = b with BiCGSTAB, falling back to GMRES; checks the true residual."""
    start = time.perf_counter()
    info, x, used = -1, None, None
    # bounded work: a chain that almost never fails is near-singular, and no Krylov method
    # resolves it; better to say so in seconds (the eigen estimate is the tool there)
    for name, solver, kwargs in (("bicgstab", spla.bicgstab, {"maxiter": 5_000}),
                                 ("gmres", spla.gmres, {"restart": 50, "maxiter": 100})):
        x0 = x if x is not None and np.all(np.isfinite(x)) else None
        x, info = solver(A, b, x0=x0, rtol=rtol, atol=0.0, **kwargs)
        used = name
        if info == 0 and np.all(np.isfinite(x)):
            break
    residual = float(np.linalg.norm(A @ x - b) / np.linalg.norm(b)) if np.all(np.isfinite(x)) else np.inf
    if not np.isfinite(residual) or residual > max(1e3 * rtol, RESIDUAL_TOLERANCE):
        raise MFPTSolveError(f"Krylov solve of (I - Q) t = 1 did not converge (relative residual {residual:.2e}); "
                             f"the chain may fail extremely rarely: try method='auto'")
    return x, {"solver": used, "converged": info == 0, "relative_residual": residual,
               "seconds": time.perf_counter() - start}


def _relative_residual(A: sp.csr_matrix, x: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(A @ x - b) / np.linalg.norm(b))


def _capped_factor(A: sp.csr_matrix, fill_cap: float):
    """SuperLU factor of ``A`` holding at most ``fill_cap`` x nnz(A) nonzeros (and the memory budget).

    SuperLU's ILU with drop tolerance 0 keeps every entry until the area cap is reached, so under the
    cap this is the exact LU (same ordering, COLAMD); over it, an incomplete one.
    """
    cap = min(float(fill_cap), memory_budget() / (FACTOR_BYTES_PER_NONZERO * max(A.nnz, 1)))
    if not cap >= 1.0:
        raise ValueError(f"fill_cap must be >= 1 (nonzeros of the factors per nonzero of I - Q), got {fill_cap!r}")
    return spla.spilu(A.tocsc(), drop_tol=0.0, fill_factor=cap), cap


def graph_depth(A: sp.spmatrix, enough: int) -> int:
    """Breadth-first depth of ``A``'s symmetrised pattern from a pseudo-peripheral state (two sweeps from the
    middle state's component), counted up to ``enough`` (a longer depth returns ``enough``)."""
    pattern = A.tocsr(copy=True)
    pattern.data = np.ones_like(pattern.data)
    pattern = (pattern + pattern.T).tocsr()
    node = A.shape[0] // 2
    for _ in range(2):
        order, predecessors = csgraph.breadth_first_order(pattern, node, directed=False, return_predecessors=True)
        node = int(order[-1])                  # a state of the last level: as far as the search went
    depth = 0
    while depth < enough and predecessors[node] >= 0:
        node, depth = int(predecessors[node]), depth + 1
    return depth


def graph_dimension_is_low(A: sp.spmatrix) -> tuple[bool, int]:
    """(whether ``A``'s graph is at most :data:`DIRECT_MAX_DIMENSION`-dimensional, the depth counted)."""
    n = A.shape[0]
    needed = int(np.ceil(n ** (1.0 / DIRECT_MAX_DIMENSION)))
    depth = graph_depth(A, needed)
    return n <= 2 or depth >= needed, depth


def _direct_first(A: sp.csr_matrix, b: np.ndarray, rtol: float, start: float, depth: int):
    """Complete sparse LU (COLAMD) of a low-dimensional chain with one refinement step; None where SuperLU
    runs out of memory or the answer misses ``rtol`` (the probe path then takes over)."""
    try:
        factor = spla.splu(A.tocsc())
    except MemoryError:
        return None
    except RuntimeError as exc:   # SuperLU: "Factor is exactly singular"
        raise NearlyNeverFailsError(_never_fails_message("auto", f"the LU factor of I - Q is singular ({exc})")) from None
    x = factor.solve(b)
    residual = _relative_residual(A, x, b) if np.all(np.isfinite(x)) else np.inf
    if rtol < residual <= 1e-3:
        x = x + factor.solve(b - A @ x)
        residual = _relative_residual(A, x, b) if np.all(np.isfinite(x)) else np.inf
    if not residual <= max(rtol, RESIDUAL_TOLERANCE):
        return None
    return x, {"solver": "splu", "path": "direct-first", "graph_depth": depth,
               "fill": (factor.L.nnz + factor.U.nnz) / A.nnz, "converged": True,
               "relative_residual": residual, "seconds": time.perf_counter() - start}


def _auto_solve(A: sp.csr_matrix, b: np.ndarray, rtol: float, fill_cap: float) -> tuple[np.ndarray, dict]:
    """Direct-first LU, or probe, capped LU, preconditioned GMRES (see the module docstring); returns x and
    the solver record."""
    start = time.perf_counter()
    if not float(fill_cap) >= 1.0:
        raise ValueError(f"fill_cap must be >= 1 (nonzeros of the factors per nonzero of I - Q), got {fill_cap!r}")
    fits = DIRECT_FILL_GUESS * FACTOR_BYTES_PER_NONZERO * A.nnz <= memory_budget()
    low, depth = graph_dimension_is_low(A) if fits and fill_cap >= FILL_CAP else (False, None)
    if low:                  # a lowered fill_cap asks for the capped LU of the probe path
        solved = _direct_first(A, b, rtol, start, depth)
        if solved is not None:
            return solved
    x, info = spla.bicgstab(A, b, rtol=rtol, atol=0.0, maxiter=PROBE_ITERATIONS)
    if info == 0 and np.all(np.isfinite(x)) and _relative_residual(A, x, b) <= rtol:
        return x, {"solver": "bicgstab", "path": "krylov", "converged": True,
                   "relative_residual": _relative_residual(A, x, b), "seconds": time.perf_counter() - start}
    try:
        factor, cap = _capped_factor(A, fill_cap)
    except RuntimeError as exc:   # SuperLU: "Factor is exactly singular"
        raise NearlyNeverFailsError(_never_fails_message("auto", f"the LU factor of I - Q is singular ({exc})")) from None
    fill = (factor.L.nnz + factor.U.nnz) / A.nnz
    x = factor.solve(b)
    for _ in range(2):     # iterative refinement: an exact factor gains the last digits in one step
        residual = _relative_residual(A, x, b) if np.all(np.isfinite(x)) else np.inf
        if residual <= rtol:
            return x, {"solver": "splu", "path": "direct", "fill": fill, "fill_cap": cap, "converged": True,
                       "relative_residual": residual, "seconds": time.perf_counter() - start}
        if residual > 1e-3:
            break          # an incomplete factor: refinement would crawl, precondition instead
        x = x + factor.solve(b - A @ x)
    preconditioner = spla.LinearOperator(A.shape, matvec=factor.solve, dtype=np.float64)
    x0 = x if np.all(np.isfinite(x)) else None
    x, info = spla.gmres(A, b, x0=x0, M=preconditioner, rtol=rtol, atol=0.0, restart=50, maxiter=20)
    residual = _relative_residual(A, x, b) if np.all(np.isfinite(x)) else np.inf
    if residual > max(1e3 * rtol, RESIDUAL_TOLERANCE):
        raise MFPTSolveError(f"ILU-preconditioned GMRES on (I - Q) t = 1 did not converge (relative residual "
                           f"{residual:.2e}, LU fill capped at {cap:.3g} x nnz); the chain may fail extremely "
                           f"rarely: raise fill_cap or use method='eigen'")
    return x, {"solver": "ilu-gmres", "path": "krylov-ilu", "fill": fill, "fill_cap": cap, "converged": info == 0,
               "relative_residual": residual, "seconds": time.perf_counter() - start}


def _never_fails_message(method: str, what: str) -> str:
    return (f"the chain almost never fails: (I - Q) t = 1 is numerically singular (method {method!r}: {what}), so its "
            f"MFPT is beyond what float64 resolves (about 1e9 steps or more); treat it as never failing, or mesh "
            f"with a wider disturbance spread")


def _check_solution(A: sp.csr_matrix, b: np.ndarray, x: np.ndarray, method: str) -> float:
    """The relative residual of ``x`` after the checks every method's answer passes (module docstring)."""
    if not np.all(np.isfinite(x)):
        raise NearlyNeverFailsError(_never_fails_message(method, f"{int(np.sum(~np.isfinite(x)))} of {x.size} "
                                                                 f"MFPTs came out NaN or infinite"))
    residual = _relative_residual(A, x, b)
    low = float(x.min())
    if low < 1.0 - 1e-6 or residual > RESIDUAL_TOLERANCE:
        scale = float(np.max(np.abs(x)))
        what = (f"relative residual {residual:.2e} > {RESIDUAL_TOLERANCE:g}, smallest MFPT {low:.3g}, largest "
                f"|MFPT| {scale:.3g}")
        if scale > 1e3 * RESIDUAL_TOLERANCE / np.finfo(float).eps or low < 1.0 - 1e-6:
            raise NearlyNeverFailsError(_never_fails_message(method, what))
        raise MFPTSolveError(f"no trustworthy MFPT from method {method!r} ({what}): the chain is ill-conditioned; "
                             f"try method='auto'")
    return residual


def absorbing_mfpt(T, failure: int = 0, method: str = "auto", rtol: float = 1e-10,
                   eigen: bool = True, fill_cap: float = FILL_CAP) -> MFPTResult:
    """Mean first passage time to the absorbing ``failure`` state from every state.

    ``method``: "auto" (exact, default: the solver the chain calls for, see the module
    docstring; ``fill_cap`` bounds its LU, the path taken is ``result.solver["path"]``),
    "krylov" (exact: unpreconditioned BiCGSTAB/GMRES), "direct" (exact, uncapped sparse LU,
    for reference) or "eigen" (the thesis' ``1 / (1 - lambda_2)`` for every transient state).
    ``eigen=True`` also computes lambda_2, |lambda_3| / lambda_2 and the quasi-stationary
    distribution (dense eig below 200 states, ARPACK above, capped at :data:`EIGEN_MAX_SECONDS`:
    past it these stay None and ``result.solver["eigen"]`` says why; with ``method="eigen"``
    it raises :class:`EigenLimitError`). Raises ValueError naming a bad row or index.

    Every answer is checked (finite, ``t >= 1``, relative residual <= :data:`RESIDUAL_TOLERANCE`):
    a chain that almost never fails raises :class:`NearlyNeverFailsError` on every method, another
    failed check :class:`MFPTSolveError` (both ValueErrors with one-line messages).
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    T = check_transition_matrix(T, failure)
    n = T.shape[0]
    sure = states_that_can_fail_surely(T, failure)
    if n > 1 and not np.any(np.delete(T[:, failure].toarray().ravel(), failure) > 0):
        raise ValueError(f"no state of the chain reaches the failure state {failure} (column {failure} of the "
                         f"transition matrix is zero outside row {failure}): every MFPT would be infinite")
    transient = sure.copy()
    transient[failure] = False
    mfpt = np.full(n, np.inf)
    mfpt[failure] = 0.0
    result = MFPTResult(mfpt, failure, method, np.flatnonzero(~sure))
    eigen_note = ""
    if eigen or method == "eigen":
        keep = np.flatnonzero(np.arange(n) != failure)
        try:
            values, perron = dominant_eigen(_transient_block(T, keep)) if keep.size else (None, None)
        except EigenLimitError as exc:
            if method == "eigen":
                raise
            values, eigen_note = None, str(exc)
        if values is not None:
            lam2 = float(np.real(values[0]))
            result.lambda2 = lam2
            result.lambda3_ratio = float(abs(values[1]) / abs(values[0])) if values.size > 1 and values[0] != 0 else None
            result.eigen_estimate = float("inf") if lam2 >= 1 - 1e-12 else 1.0 / (1.0 - lam2)
            qsd = np.zeros(n)
            qsd[keep] = perron
            result.quasi_stationary = qsd
    idx = np.flatnonzero(transient)
    note = {"eigen": eigen_note} if eigen_note else {}
    result.solver = dict(note)
    if idx.size == 0:
        return result
    if method == "eigen":
        gap = 1.0 - result.lambda2
        if not gap >= EIGEN_GAP_FLOOR:
            raise NearlyNeverFailsError(_never_fails_message("eigen", f"1 - lambda_2 = {gap:.2e} < {EIGEN_GAP_FLOOR:g}"))
        mfpt[idx] = result.eigen_estimate
        return result
    A = (sp.identity(idx.size, format="csr") - _transient_block(T, idx)).tocsr()
    b = np.ones(idx.size)
    try:
        mfpt[idx], solver = _solve(A, b, method, rtol, fill_cap)
    except NearlyNeverFailsError:
        raise
    except MFPTSolveError as exc:   # a failed solve on a chain whose lambda_2 is 1 to rounding: say which it is
        gap = None if result.lambda2 is None else 1.0 - result.lambda2
        if gap is not None and gap < NEVER_FAILS_GAP:
            raise NearlyNeverFailsError(_never_fails_message(
                method, f"1 - lambda_2 = {gap:.2e} and the solve failed: {str(exc).split(';')[0]}")) from None
        raise
    result.solver = {**solver, **note}
    return result


def _solve(A: sp.csr_matrix, b: np.ndarray, method: str, rtol: float, fill_cap: float) -> tuple[np.ndarray, dict]:
    """``(I - Q) t = 1`` by ``method`` ("direct", "auto", "krylov"), its answer checked (:func:`_check_solution`)."""
    if method == "direct":
        start = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", spla.MatrixRankWarning)   # a singular I - Q: NaN, refused below
            x = spla.spsolve(A.tocsc(), b)
        solver = {"solver": "spsolve", "path": "direct", "seconds": time.perf_counter() - start}
    elif method == "auto":
        x, solver = _auto_solve(A, b, rtol, fill_cap)
    else:
        x, solver = _krylov_solve(A, b, rtol)
        solver["path"] = "krylov"
    x = np.asarray(x, dtype=np.float64)
    solver["relative_residual"] = _check_solution(A, b, x, method)
    return x, solver


def cumulative_transition_mass(T, failure: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Thesis Fig. 5.5: column sums of ``T`` without the failure state, sorted descending and
    accumulated. Returns (fraction of states, fraction of transition mass); a point (x, y) says
    that a fraction x of the states receives a fraction y of all transitions."""
    T = sp.csr_matrix(T)
    mass = np.asarray(T.sum(axis=0)).ravel()
    mass = np.sort(np.delete(mass, failure))[::-1]
    if mass.size == 0 or mass.sum() <= 0:
        raise ValueError("no transitions between non-failure states")
    return np.arange(1, mass.size + 1) / mass.size, np.cumsum(mass) / mass.sum()
