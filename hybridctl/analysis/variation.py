"""Variation estimators of fractal dimension for time series (thesis Sec. 4.2.4).

Gneiting, Sevcikova & Percival (2012), "Estimators of fractal dimension",
Statistical Science 27:247-277, eq. 4.2-4.3 of the thesis:

    V_p(l) = 1 / (2 (n - l)) * sum_{i=l}^{n-1} |X_i - X_{i-l}|^p
    D_p    = 2 - (log V_p(2) - log V_p(1)) / (p log 2)

``p = 1`` is the *madogram*, ``p = 2`` the *variogram*. For a vector series
``|.|`` is the Euclidean norm of the increment (``norm="l2"``, the default; "l1"
is also accepted). The estimate is 1.5 for Brownian motion and 1.0 for a smooth
curve; values lie in [1, 2] for curves up to sampling noise.

``legacy=True`` reproduces the author's public code: the L1 norm of the increment
and no exponent p, so its "variogram" equals ``1 + madogram / 2`` (Brownian motion
gives 1.75). Use it only to compare with published numbers (the CoRL 2020 tables).
"""

from __future__ import annotations

import numpy as np

MIN_LENGTH = 3  # V(2) needs at least three points


def _as_series(x, name: str = "x") -> np.ndarray:
    s = np.asarray(x, dtype=np.float64)
    if s.ndim == 1:
        s = s[:, None]
    if s.ndim != 2:
        raise ValueError(f"{name} must be a series of shape (n,) or (n, n_dims), got shape {s.shape}")
    if s.shape[0] < MIN_LENGTH:
        raise ValueError(f"{name} needs at least {MIN_LENGTH} samples for the lag-2 variation, got {s.shape[0]}")
    if not np.all(np.isfinite(s)):
        bad = np.argwhere(~np.isfinite(s))[0]
        raise ValueError(f"{name} contains NaN or inf (first at sample {bad[0]}, column {bad[1]})")
    return s


def power_variation(x, lag: int, p: float, norm: str = "l2", legacy: bool = False) -> float:
    """V_p(lag) = mean over i of |X_i - X_{i-lag}|^p / 2 (thesis eq. 4.2).

    ``legacy=True``: the author's code (L1 norm, exponent not applied).
    """
    s = _as_series(x)
    if not (isinstance(lag, (int, np.integer)) and 1 <= lag < s.shape[0]):
        raise ValueError(f"lag must be an integer in [1, {s.shape[0] - 1}], got {lag!r}")
    if not (np.isfinite(p) and p > 0):
        raise ValueError(f"p must be a number > 0, got {p!r}")
    diff = s[lag:] - s[:-lag]
    if legacy:
        return float(np.abs(diff).sum(axis=1).mean() / 2)
    if norm == "l2":
        size = np.sqrt(np.einsum("ij,ij->i", diff, diff))
    elif norm == "l1":
        size = np.abs(diff).sum(axis=1)
    else:
        raise ValueError(f"norm must be 'l2' or 'l1', got {norm!r}")
    return float(np.mean(size ** p) / 2)


def variation_dimension(x, p: float = 1.0, norm: str = "l2", legacy: bool = False) -> float:
    """Variation estimator of order ``p`` of the fractal dimension of the series ``x``
    (thesis eq. 4.3; Gneiting et al. 2012).

    ``x``: shape (n,) or (n, n_dims), n >= 3, finite. Documented value: a series whose
    lag-1 and lag-2 increments are all zero (constant) has dimension 1.0, the value of a
    smooth curve; a series constant at lag 2 but not at lag 1 (period-2 oscillation)
    raises ValueError, as its dimension is undefined.
    """
    v1 = power_variation(x, 1, p, norm, legacy)
    v2 = power_variation(x, 2, p, norm, legacy)
    if v1 == 0 and v2 == 0:
        return 1.0
    if v2 == 0 or v1 == 0:
        raise ValueError(f"variation dimension undefined: V_p(1) = {v1:g}, V_p(2) = {v2:g} "
                         "(one lag has no variation, e.g. a period-2 series)")
    return float(2.0 - (np.log(v2) - np.log(v1)) / (p * np.log(2.0)))


def madogram(x, norm: str = "l2", legacy: bool = False) -> float:
    """Madogram estimate of fractal dimension (variation estimator with p = 1)."""
    return variation_dimension(x, 1.0, norm, legacy)


def variogram(x, norm: str = "l2", legacy: bool = False) -> float:
    """Variogram estimate of fractal dimension (variation estimator with p = 2).

    ``legacy=True`` reproduces the author's code, which returns ``1 + madogram / 2``.
    """
    return variation_dimension(x, 2.0, norm, legacy)
