"""Box meshes and the mesh dimension (thesis Ch. 4, Algorithms 5 and 6).

A *box mesh* of a state set covers state space with axis-aligned boxes of side
``d`` (after normalising every coordinate) and keeps the occupied ones: the key
of a state is ``round(s_normalised / d)`` (thesis Alg. 5). Its size as ``d``
shrinks gives the *mesh dimension*, the slope of ``-log(size)`` over ``log(d)``
(a box-counting dimension; thesis Sec. 4.2.2):

* **lower** mesh dimension: the least-squares slope over the whole curve, flat
  (saturated) ends included, so it tends to underestimate;
* **upper** mesh dimension: the greatest slope between neighbouring points of the
  curve, so it tends to overestimate.

>>> from hybridctl.analysis import box_mesh_size, mesh_dimension
>>> box_mesh_size(states, d=0.1)                 # occupied boxes, exact
>>> md = mesh_dimension(states[200:])            # thesis defaults: f 1.5, d0 1e-2, 4/5 stop, d_min 1e-9
>>> md.lower, md.upper, md.slope(1e-3, 1e-1)     # bounds, and a fit over a chosen window
>>> md.plot(path="mesh_curve.png")

Counting is exact and vectorised: the integer keys of a row are packed into as
few 64-bit words as their ranges allow, and the distinct rows are counted by a
sort. There is no Python loop over points (the thesis used a dict of tuples).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Thesis Sec. 4.2.2-4.2.3 and appendix of Ch. 4 (implementation notes, Ch. 4).
SCALE_FACTOR = 1.5        # f: d is divided / multiplied by f between meshes
INITIAL_BOX_SIZE = 1e-2   # d0
STOP_FRACTION = 0.8       # stop shrinking d once the mesh holds 4/5 of the points (thesis appendix)
MIN_BOX_SIZE = 1e-9       # d_min "to avoid numerical errors" (thesis appendix)
# Integer keys beyond this magnitude cannot be packed exactly into int64 words.
_MAX_KEY = 2 ** 62


def _as_states(states, name: str = "states") -> np.ndarray:
    """A finite float64 array of shape (n, k), or a ValueError naming ``name``."""
    x = np.asarray(states, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2:
        raise ValueError(f"{name} must have shape (n_points, n_dims), got shape {x.shape}")
    if x.shape[0] == 0:
        raise ValueError(f"{name} is empty: a box mesh needs at least one point")
    if x.shape[1] == 0:
        raise ValueError(f"{name} has no coordinates (shape {x.shape})")
    if not np.all(np.isfinite(x)):
        bad = np.argwhere(~np.isfinite(x))[0]
        raise ValueError(f"{name} contains NaN or inf (first at row {bad[0]}, column {bad[1]})")
    return x


def normalization(states, mean=None, std=None) -> tuple[np.ndarray, np.ndarray]:
    """The (mean, std) used to normalise ``states``: the given statistics, else the data's own.

    A coordinate whose standard deviation is 0 (constant in the data) is scaled by 1
    instead, so it keeps a single key rather than dividing by zero.
    """
    x = _as_states(states)
    mean = x.mean(axis=0) if mean is None else np.broadcast_to(np.asarray(mean, dtype=np.float64), x.shape[1:])
    std = x.std(axis=0) if std is None else np.broadcast_to(np.asarray(std, dtype=np.float64), x.shape[1:])
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(std))):
        raise ValueError("mean and std must be finite")
    if np.any(std < 0):
        raise ValueError(f"std must be >= 0 in every coordinate, got {std}")
    return np.array(mean), np.where(std > 0, std, 1.0)


def box_keys(states, d: float, mean=None, std=None) -> np.ndarray:
    """Integer box keys ``round((s - mean) / std / d)`` of every state (thesis Alg. 5), int64 (n, k).

    ``mean`` / ``std`` default to the data's own statistics (see :func:`normalization`);
    pass a policy's running statistics to mesh several trajectories on one grid.
    """
    x = _as_states(states)
    mean, std = normalization(x, mean, std)
    return _keys_of_normalised(np.asfortranarray((x - mean) / std), _check_box_size(d))


def _keys_of_normalised(unit: np.ndarray, d: float) -> np.ndarray:
    scaled = unit / d
    largest = np.max(np.abs(scaled))
    if largest >= _MAX_KEY:
        raise ValueError(f"box size d={d:g} is too small for these states: keys exceed 2^62 "
                         f"(largest normalised |s|/d = {largest:.3g})")
    return np.rint(scaled, out=scaled).astype(np.int64)


def _check_box_size(d) -> float:
    d = float(d)
    if not (np.isfinite(d) and d > 0):
        raise ValueError(f"box size d must be a finite number > 0, got {d!r}")
    return d


def _pack_words(keys: np.ndarray) -> np.ndarray:
    """Pack integer key rows exactly into as few int64 words per row as the column ranges allow."""
    offset = keys - keys.min(axis=0)
    spans = [int(s) + 1 for s in offset.max(axis=0)]
    words, current, radix = [], None, 1
    for col, span in enumerate(spans):
        if span == 1:
            continue  # constant column: carries no information
        if current is not None and radix * span < _MAX_KEY:
            current = current * span + offset[:, col]
            radix *= span
        else:
            if current is not None:
                words.append(current)
            current, radix = offset[:, col].copy(), span
    if current is not None:
        words.append(current)
    if not words:
        return np.zeros((keys.shape[0], 1), dtype=np.int64)
    return np.stack(words, axis=1)


_MIX1, _MIX2 = np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)


def _mix64(z: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser on uint64 arrays (wrapping arithmetic)."""
    z = z ^ (z >> np.uint64(30))
    z = z * _MIX1
    z = z ^ (z >> np.uint64(27))
    z = z * _MIX2
    return z ^ (z >> np.uint64(31))


def _count_word_rows(words: np.ndarray) -> int:
    """Distinct rows of an (n, w) array of 64-bit words (int64, or float64 holding integers)."""
    if words.shape[1] == 1:
        flat = np.sort(words[:, 0])
        return int(1 + np.count_nonzero(flat[1:] != flat[:-1]))
    bits = np.ascontiguousarray(words).view(np.uint64)
    h = _mix64(bits[:, 0])
    for col in range(1, bits.shape[1]):
        h = _mix64(h ^ bits[:, col])
    order = np.argsort(h)
    h = h[order]
    same = h[1:] == h[:-1]
    if same.any():
        rows = bits[order]
        if not np.array_equal(rows[1:][same], rows[:-1][same]):  # a hash collision: count exactly
            packed = bits.view(np.dtype((np.void, 8 * bits.shape[1])))
            return int(np.unique(packed).size)
    return int(1 + np.count_nonzero(~same))


def count_distinct_rows(keys: np.ndarray) -> int:
    """Number of distinct rows of an integer array (exact).

    Rows are packed into int64 words; one word is sorted directly. Several words are
    hashed to 64 bits and sorted, and rows that share a hash are checked to be equal:
    only if two different rows collide (astronomically rare) does it fall back to a
    byte-wise ``np.unique`` of the rows, so the count is always exact.
    """
    keys = np.asarray(keys)
    if keys.shape[0] == 0:
        return 0
    return _count_word_rows(_pack_words(keys.astype(np.int64, copy=False)))


class _BoxCounter:
    """Box counts of one normalised state set at any d (the state set is scanned once for ranges).

    Per d: keys ``rint(u / d) - rint(min u / d)`` (>= 0), packed into float64 words by one
    matrix product with mixed-radix multipliers; every word stays below 2^53, so the
    float arithmetic is exact. Falls back to the int64 path when a single coordinate's
    key range reaches 2^53.
    """

    _EXACT = 2 ** 53

    def __init__(self, unit: np.ndarray):
        self.unit = np.ascontiguousarray(unit)
        self.lo, self.hi = self.unit.min(axis=0), self.unit.max(axis=0)
        self._buffer = np.empty_like(self.unit)

    def __call__(self, d: float) -> int:
        if self.unit.shape[0] == 1:
            return 1
        kmin, kmax = np.rint(self.lo / d), np.rint(self.hi / d)
        largest = max(np.max(np.abs(kmin)), np.max(np.abs(kmax)))
        if largest >= _MAX_KEY:
            raise ValueError(f"box size d={d:g} is too small for these states: keys exceed 2^62 "
                             f"(largest normalised |s|/d = {largest:.3g})")
        spans = kmax - kmin + 1
        if np.max(spans) >= self._EXACT:
            return count_distinct_rows(_keys_of_normalised(self.unit, d))
        multipliers = self._multipliers(spans)
        if multipliers.shape[1] == 0:
            return 1
        keys = np.divide(self.unit, d, out=self._buffer)
        np.rint(keys, out=keys)      # round first, then shift: ties round as in box_keys
        keys -= kmin
        return _count_word_rows(keys @ multipliers)

    def _multipliers(self, spans: np.ndarray) -> np.ndarray:
        """(k, w) mixed-radix multipliers: each word packs consecutive coordinates, product of spans < 2^53."""
        columns: list[list[tuple[int, float]]] = []
        radix = self._EXACT
        for col, span in enumerate(spans):
            if span == 1:
                continue  # one key in this coordinate: carries no information
            if radix * span >= self._EXACT:
                columns.append([])
                radix = 1.0
            columns[-1].append((col, radix))
            radix *= span
        m = np.zeros((len(spans), len(columns)))
        for word, entries in enumerate(columns):
            for col, weight in entries:
                m[col, word] = weight
        return m


def box_mesh_size(states, d: float, mean=None, std=None) -> int:
    """Number of occupied boxes of side ``d`` (normalised units) in the box mesh of ``states``.

    Exact and vectorised. ``states``: array (n_points, n_dims), finite. ``mean`` and ``std``:
    normalisation statistics (default: the data's own; a zero std counts as 1).
    """
    x = _as_states(states)
    mean, std = normalization(x, mean, std)
    return _BoxCounter((x - mean) / std)(_check_box_size(d))


@dataclass
class MeshDimension:
    """The mesh-size curve of a state set and the dimensions read off it (thesis Alg. 6).

    ``box_sizes`` ascending, ``sizes`` the mesh size at each; ``lower`` the least-squares
    slope of ``-log(size)`` over ``log(d)``, ``upper`` the greatest neighbour slope.
    """

    box_sizes: np.ndarray
    sizes: np.ndarray
    lower: float
    upper: float
    n_points: int
    note: str = ""
    settings: dict = field(default_factory=dict)

    def slope(self, d_low: float | None = None, d_high: float | None = None) -> float:
        """Least-squares slope of ``-log(size)`` over ``log(d)`` for ``d_low <= d <= d_high``
        (the thesis' "hand fit" over the well-behaved middle of the curve)."""
        d_low = self.box_sizes[0] if d_low is None else d_low
        d_high = self.box_sizes[-1] if d_high is None else d_high
        keep = (self.box_sizes >= d_low) & (self.box_sizes <= d_high)
        if keep.sum() < 2:
            raise ValueError(f"fewer than 2 mesh sizes with {d_low:g} <= d <= {d_high:g}; the curve spans "
                             f"d in [{self.box_sizes[0]:g}, {self.box_sizes[-1]:g}]")
        return _fit_slope(np.log(self.box_sizes[keep]), -np.log(self.sizes[keep]))

    def as_dict(self) -> dict:
        """JSON-ready summary."""
        return {"lower": self.lower, "upper": self.upper, "n_points": self.n_points, "note": self.note,
                "box_sizes": self.box_sizes.tolist(), "sizes": self.sizes.tolist(), "settings": self.settings}

    def plot(self, ax=None, path=None, label: str | None = None):
        """Plot log(size) over log(d) with the lower-dimension fit; save to ``path`` if given."""
        import matplotlib.pyplot as plt

        own = ax is None
        if own:
            fig, ax = plt.subplots(figsize=(5, 3.6), constrained_layout=True)
        log_d, log_m = np.log(self.box_sizes), np.log(self.sizes)
        line, = ax.plot(log_d, log_m, "o-", ms=3,
                        label=label or f"lower {self.lower:.2f}, upper {self.upper:.2f}")
        intercept = np.mean(-log_m) - self.lower * np.mean(log_d)
        ax.plot(log_d, -(self.lower * log_d + intercept), ":", color=line.get_color(), lw=1)
        ax.set(xlabel="log d (box size)", ylabel="log mesh size")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        if path is not None:
            ax.figure.savefig(path, dpi=120)
        if own:
            plt.close(ax.figure)
        return ax.figure


def _fit_slope(x: np.ndarray, y: np.ndarray) -> float:
    if np.ptp(x) == 0:
        return 0.0
    return float(np.polyfit(x, y, 1)[0])


def mesh_dimension(states, f: float = SCALE_FACTOR, d0: float = INITIAL_BOX_SIZE,
                   stop_fraction: float = STOP_FRACTION, d_min: float = MIN_BOX_SIZE,
                   mean=None, std=None, max_meshes: int = 200, method: str = "vectorised") -> MeshDimension:
    """Lower and upper mesh dimension of ``states`` (thesis Algorithm 6).

    From ``d0``, ``d`` is divided by ``f`` until the mesh holds ``stop_fraction`` of the
    points (or ``d`` would fall below ``d_min``), then multiplied by ``f`` from ``d0`` until
    one box holds everything. ``lower`` is the least-squares slope of ``-log(size)`` over
    ``log(d)``; ``upper`` the greatest slope between neighbouring points.

    ``method="dict"`` counts boxes with a Python dict of tuples, as the thesis' code did
    (same result, about 10-50x slower; kept as the reference for tests and benchmarks).

    Documented edge cases (never NaN): a single point, or all points in one box at every
    ``d >= d_min`` (a constant trajectory), has dimension 0 (``note`` says so). Pass the
    states after the transient (the thesis drops the first T_r = 200 steps).
    """
    x = _as_states(states)
    if not (np.isfinite(f) and f > 1):
        raise ValueError(f"f (scale factor) must be > 1, got {f!r}")
    d0, d_min = _check_box_size(d0), _check_box_size(d_min)
    if d_min > d0:
        raise ValueError(f"d_min ({d_min:g}) must be <= d0 ({d0:g})")
    if not (0 < stop_fraction <= 1):
        raise ValueError(f"stop_fraction must be in (0, 1], got {stop_fraction!r}")
    mean, std = normalization(x, mean, std)
    settings = {"f": f, "d0": d0, "stop_fraction": stop_fraction, "d_min": d_min}
    n = x.shape[0]
    unit = (x - mean) / std  # once; each mesh only divides by d
    if method == "vectorised":
        size = _BoxCounter(unit)
    elif method == "dict":
        size = lambda d: _dict_count(unit, d)  # noqa: E731
    else:
        raise ValueError(f"method must be 'vectorised' or 'dict', got {method!r}")

    curve = {d0: size(d0)}
    d = d0
    while curve[d] < stop_fraction * n and d / f >= d_min and len(curve) < max_meshes:
        d /= f
        curve[d] = size(d)
    d = d0
    while curve[d] > 1 and len(curve) < max_meshes:
        d *= f
        curve[d] = size(d)
    box_sizes = np.array(sorted(curve))
    sizes = np.array([curve[b] for b in box_sizes], dtype=np.int64)
    if sizes.max() == 1:
        return MeshDimension(box_sizes, sizes, 0.0, 0.0, n, "all points share one box at every d >= d_min: "
                             "dimension 0", settings)
    log_d, neg_log_m = np.log(box_sizes), -np.log(sizes.astype(np.float64))
    lower = _fit_slope(log_d, neg_log_m)
    upper = float(np.max(np.diff(neg_log_m) / np.diff(log_d)))
    return MeshDimension(box_sizes, sizes, lower, upper, n, "", settings)


def _dict_count(unit: np.ndarray, d: float) -> int:
    mesh: dict[tuple, int] = {}
    for s in np.ascontiguousarray(unit):
        key = tuple(np.round(s / d))
        mesh[key] = mesh.get(key, 0) + 1
    return len(mesh)


def box_mesh_size_dict(states, d: float, mean=None, std=None) -> int:
    """Reference box count with a Python dict of tuples, as in the thesis' code (slow; for checks
    and benchmarks)."""
    x = _as_states(states)
    mean, std = normalization(x, mean, std)
    return _dict_count((x - mean) / std, _check_box_size(d))
