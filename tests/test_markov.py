"""Absorbing Markov chains: exact MFPT, the eigenvalue estimate, infinite MFPT, bad input."""

import numpy as np
import pytest
import scipy.sparse as sp

from hybridctl.analysis.markov import (METHODS, RESIDUAL_TOLERANCE, NearlyNeverFailsError, absorbing_mfpt,
                                       check_transition_matrix)
from hybridctl.limits import LimitError


def birth_death(n, p_up, p_down):
    """States 0 (failure, absorbing), 1..n; from i: up w.p. p_up (reflecting at n), down w.p. p_down, stay else."""
    rows, cols, vals = [0], [0], [1.0]
    for i in range(1, n + 1):
        up = min(i + 1, n)
        for j, v in ((up, p_up), (i - 1, p_down), (i, 1 - p_up - p_down)):
            rows.append(i), cols.append(j), vals.append(v)
    return sp.csr_matrix((vals, (rows, cols)), shape=(n + 1, n + 1))


def test_single_state_geometric():
    T = np.array([[1.0, 0.0], [0.1, 0.9]])
    r = absorbing_mfpt(T)
    assert r.mfpt[1] == pytest.approx(10.0) and r.eigen_estimate == pytest.approx(10.0)
    assert r.mfpt[0] == 0.0


def test_birth_death_matches_dense_solve_and_direct():
    T = birth_death(300, 0.35, 0.4)          # drift towards failure: MFPT grows about linearly
    Q = T.toarray()[1:, 1:]
    exact = np.linalg.solve(np.eye(300) - Q, np.ones(300))
    for method in ("krylov", "direct"):
        r = absorbing_mfpt(T, method=method)
        np.testing.assert_allclose(r.mfpt[1:], exact, rtol=1e-7)
    assert np.all(np.diff(exact) > 0)           # farther from failure takes longer


def test_eigen_estimate_is_exact_from_the_quasi_stationary_distribution():
    T = birth_death(40, 0.4, 0.3)
    r = absorbing_mfpt(T)
    assert r.mean(r.quasi_stationary) == pytest.approx(r.eigen_estimate, rel=1e-6)
    assert r.mean() == pytest.approx(r.eigen_estimate, rel=1e-6)   # default start: the QSD
    assert 0 < r.lambda3_ratio < 1
    # ... but not from the state next to failure
    assert r.mfpt[1] < 0.9 * r.eigen_estimate


def test_never_failing_states_are_infinite_and_reported():
    # 1 -> failure or 2; {3, 4} closed and never fail; 2 can fall into {3, 4}
    T = np.zeros((5, 5))
    T[0, 0] = 1
    T[1, [0, 2]] = 0.5
    T[2, [0, 1, 3]] = [0.2, 0.7, 0.1]
    T[3, 4] = T[4, 3] = 1.0
    r = absorbing_mfpt(T)
    assert np.isinf(r.mfpt[[2, 3, 4]]).all() and np.isinf(r.mfpt[1])   # 1 reaches 2, which can escape
    np.testing.assert_array_equal(r.infinite_states, [1, 2, 3, 4])
    assert "avoid failure forever" in r.report()["infinite_note"]
    T2 = T.copy()
    T2[2] = [0.2, 0.8, 0, 0, 0]                 # now 1 and 2 fail surely; 3, 4 still closed
    r2 = absorbing_mfpt(T2)
    assert np.isfinite(r2.mfpt[[1, 2]]).all() and np.isinf(r2.mfpt[[3, 4]]).all()
    np.testing.assert_allclose(r2.mfpt[1:3], np.linalg.solve(np.eye(2) - T2[1:3, 1:3], np.ones(2)))
    assert r2.mean([0, 1, 0, 0, 0]) == pytest.approx(r2.mfpt[1]) and r2.mean([0, 0, 0, 1, 0]) == np.inf


def test_random_sparse_chain_krylov_equals_direct(rng):
    n, k = 3000, 5
    rows = np.repeat(np.arange(1, n), k)
    cols = rng.integers(0, n, size=rows.size)
    vals = rng.uniform(size=rows.size)
    T = sp.csr_matrix((vals, (rows, cols)), shape=(n, n)).tolil()
    T[0, 0] = 1.0
    T = T.tocsr()
    T = sp.diags(1 / np.asarray(T.sum(axis=1)).ravel()) @ T
    a, b = absorbing_mfpt(T, eigen=False), absorbing_mfpt(T, method="direct", eigen=False)
    finite = np.isfinite(b.mfpt)
    np.testing.assert_array_equal(np.isfinite(a.mfpt), finite)
    np.testing.assert_allclose(a.mfpt[finite], b.mfpt[finite], rtol=1e-7)
    assert a.solver["relative_residual"] < 1e-8


@pytest.mark.parametrize("T, failure, message", [
    (np.array([[1.0, 0.0], [0.5, 0.4]]), 0, "row 1 sums to 0.9"),
    (np.array([[1.0, 0.0], [-0.1, 1.1]]), 0, "negative entry -0.1 at row 1"),
    (np.array([[1.0, 0.0], [0.5, 0.5]]), 2, "failure index"),
    (np.array([[0.5, 0.5], [0.5, 0.5]]), 0, "not absorbing"),
    (np.array([[1.0, 0.0], [np.nan, 1.0]]), 0, "row 1 contains NaN"),
    (np.ones((2, 3)) / 3, 0, "square"),
])
def test_bad_matrices_are_named(T, failure, message):
    with pytest.raises(ValueError, match=message):
        check_transition_matrix(T, failure)


def test_bad_method():
    with pytest.raises(ValueError, match="method"):
        absorbing_mfpt(np.eye(2), method="montecarlo")


def test_near_singular_chain_fails_fast_with_a_message():
    """Upward drift over 300 states: MFPT ~1e32, beyond any solve in float64; every method says so in one
    line (before issue 50 the eigen estimate returned inf and the others differed)."""
    T = birth_death(300, 0.45, 0.35)
    for method in METHODS:
        with pytest.raises(NearlyNeverFailsError, match="almost never fails") as info:
            absorbing_mfpt(T, method=method)
        assert "\n" not in str(info.value)
    with pytest.raises(RuntimeError):           # still a RuntimeError for callers that caught the old errors
        absorbing_mfpt(T, method="krylov", eigen=False)


def rarely_failing(n, p_up, p_down, eps):
    """Birth-death chain whose only way to failure is a step of probability ``eps`` from state 1."""
    T = birth_death(n, p_up, p_down).tolil()
    T[1, 0], T[1, 1] = eps, T[1, 1] + p_down - eps
    return T.tocsr()


@pytest.mark.parametrize("method", METHODS)
def test_a_chain_that_almost_never_fails_is_refused_on_every_method(method):
    """Issue 50: failure probability 1e-16 per visit to state 1 (MFPT ~1e16 steps). ``method="direct"``
    returned -1.9e16 for every state without a word; now every method raises the same one-line error."""
    T = rarely_failing(10, 0.45, 0.35, 1e-16)
    with pytest.raises(NearlyNeverFailsError, match="almost never fails") as info:
        result = absorbing_mfpt(T, method=method)
        assert not np.any(result.mfpt[1:] < 1), result.mfpt        # what the old code returned, for the record
    assert "\n" not in str(info.value) and isinstance(info.value, ValueError)


@pytest.mark.parametrize("method", METHODS)
def test_every_returned_mfpt_passes_its_checks(method):
    """A chain that fails rarely but within float64's reach: every method returns MFPT >= 1, finite, with
    its residual recorded (the eigen estimate: from the quasi-stationary distribution)."""
    T = rarely_failing(10, 0.45, 0.35, 1e-6)
    result = absorbing_mfpt(T, method=method)
    assert np.all(np.isfinite(result.mfpt)) and np.all(result.mfpt[1:] >= 1)
    if method != "eigen":
        assert result.solver["relative_residual"] <= RESIDUAL_TOLERANCE
        exact = np.linalg.solve(np.eye(10) - T.toarray()[1:, 1:], np.ones(10))
        np.testing.assert_allclose(result.mfpt[1:], exact, rtol=1e-6)


# --------------------------------------------------------------------------- method="auto" (issue 29)
def mesh_like(side, seed=0):
    """Small mesh-like chain: 2-D lattice, 8 successors one cell around a slowly turning, contracting image."""
    rng = np.random.default_rng(seed)
    n = side * side
    rel = np.stack(np.unravel_index(np.arange(n), (side, side)), axis=1) - (side - 1) / 2
    turn = np.array([[np.cos(0.05), np.sin(0.05)], [-np.sin(0.05), np.cos(0.05)]])
    target = np.rint((side - 1) / 2 + 0.995 * rel @ turn)[:, None, :] + np.rint(rng.normal(size=(n, 8, 2)))
    fails = np.any((target < 0) | (target > side - 1), axis=2) | (rng.uniform(size=(n, 8)) < 1e-4)
    index = np.ravel_multi_index(np.clip(target, 0, side - 1).astype(np.int64).transpose(2, 0, 1), (side, side)) + 1
    return normalised(np.repeat(np.arange(1, n + 1), 8), np.where(fails, 0, index).ravel(), np.ones(8 * n), n + 1)


def uniform(n, seed=0):
    """Small chain with random sparse rows: 5 successors uniform over all states (failure included)."""
    rng = np.random.default_rng(seed)
    rows = np.repeat(np.arange(1, n), 5)
    return normalised(rows, rng.integers(0, n, size=rows.size), rng.uniform(size=rows.size), n)


def normalised(rows, cols, vals, n):
    T = sp.csr_matrix((np.r_[1.0, vals], (np.r_[0, rows], np.r_[0, cols])), shape=(n, n))
    return (sp.diags(1 / np.asarray(T.sum(axis=1)).ravel()) @ T).tocsr()


@pytest.mark.parametrize("T, path", [(mesh_like(30), "direct-first"), (uniform(2000), "krylov")], ids=["mesh", "uniform"])
def test_auto_equals_spsolve_and_picks_its_path(T, path):
    auto, direct = absorbing_mfpt(T, eigen=False), absorbing_mfpt(T, method="direct", eigen=False)
    finite = np.isfinite(direct.mfpt)
    assert finite[1:].all() and np.median(direct.mfpt[1:]) > 50       # long failure times, all finite
    np.testing.assert_allclose(auto.mfpt[finite], direct.mfpt[finite], rtol=1e-9)
    assert auto.method == "auto" and auto.solver["path"] == path and auto.solver["relative_residual"] <= 1e-10


def test_auto_falls_back_to_ilu_gmres_under_a_tiny_fill_cap():
    T = mesh_like(30)
    capped, direct = absorbing_mfpt(T, eigen=False, fill_cap=1.5), absorbing_mfpt(T, method="direct", eigen=False)
    assert capped.solver["path"] == "krylov-ilu" and capped.solver["fill"] <= 1.5 + 1e-9
    np.testing.assert_allclose(capped.mfpt[1:], direct.mfpt[1:], rtol=1e-8)
    assert absorbing_mfpt(T, eigen=False).solver["fill"] > 1.5    # the default cap: the exact LU


def test_eigen_diagnostics_past_their_cap_are_left_out_with_a_note(monkeypatch):
    import hybridctl.analysis.markov as markov
    monkeypatch.setattr(markov.dominant_eigen, "__defaults__", (3, 0.0, markov.EIGEN_MAX_RESTARTS))
    r = absorbing_mfpt(mesh_like(20))
    assert r.eigen_estimate is None and "EIGEN_MAX_SECONDS" in r.solver["eigen"] and np.isfinite(r.mfpt).all()


def _no_failure_path():
    T = np.eye(3)
    T[1, [1, 2]] = T[2, [1, 2]] = 0.5
    return T


MFPT_BAD_CASES = [
    # (chain, keyword arguments, exception, message)
    (_no_failure_path(), {}, ValueError, "no state of the chain reaches the failure state 0"),
    (mesh_like(20), {"fill_cap": 0.5}, ValueError, "fill_cap must be >= 1"),
    (mesh_like(20), {"method": "eigen", "_eigen_seconds": 0.0}, LimitError, "ran past its limit of 0 s"),
]


@pytest.mark.parametrize("T, kwargs, error, message", MFPT_BAD_CASES, ids=["no-failure-path", "fill-cap", "eigen-cap"])
def test_mfpt_bad_cases_give_one_line(T, kwargs, error, message, monkeypatch):
    import hybridctl.analysis.markov as markov
    kwargs = dict(kwargs)
    if "_eigen_seconds" in kwargs:
        monkeypatch.setattr(markov.dominant_eigen, "__defaults__", (3, kwargs.pop("_eigen_seconds"), 10))
    with pytest.raises(error, match=message) as info:
        absorbing_mfpt(T, **kwargs)
    assert "\n" not in str(info.value)


def birth_death_line(n, fail=1e-3):
    """1-D birth-death line: down 0.5, up 0.5 - fail, fail to state 0 with ``fail`` (state 1 steps down into it)."""
    i = np.arange(1, n)
    up = np.where(i == n - 1, 0.0, 0.5 - fail)
    rows, cols = np.r_[i, i, i, i], np.r_[i - 1, np.minimum(i + 1, n - 1), np.zeros(n - 1, int), i]
    vals = np.r_[np.full(n - 1, 0.5), up, np.full(n - 1, fail), np.maximum(0.5 - up - fail, 0.0)]
    return normalised(rows, cols, vals, n)


def grid_walk(side, fail=1e-4):
    """2-D grid walk: 4 neighbours, stepping off the grid fails, and ``fail`` per step."""
    r, c = np.unravel_index(np.arange(side * side), (side, side))
    rows, cols, vals = [], [], []
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        rr, cc = r + dr, c + dc
        off = (rr < 0) | (rr >= side) | (cc < 0) | (cc >= side)
        j = np.ravel_multi_index((np.clip(rr, 0, side - 1), np.clip(cc, 0, side - 1)), (side, side)) + 1
        rows.append(np.arange(1, side * side + 1)), cols.append(np.where(off, 0, j)), vals.append(np.full(r.size, 1.0))
    rows.append(np.arange(1, side * side + 1)), cols.append(np.zeros(r.size, int)), vals.append(np.full(r.size, 4 * fail))
    return normalised(np.concatenate(rows), np.concatenate(cols), np.concatenate(vals), side * side + 1)


@pytest.mark.parametrize("T, solver, path", [(birth_death_line(3000), "splu", "direct-first"),
                                             (grid_walk(60), "splu", "direct-first"),
                                             (mesh_like(60), "splu", "direct-first"),
                                             (uniform(3000), "bicgstab", "krylov")],
                         ids=["birth-death", "grid-2d", "mesh-like", "uniform"])
def test_auto_matches_direct_on_every_benchmark_family(T, solver, path):
    """Issue 50 item 5: low-dimensional chains are factored at once (no Krylov probe), random rows probed."""
    auto, direct = absorbing_mfpt(T, eigen=False), absorbing_mfpt(T, method="direct", eigen=False)
    assert np.isfinite(direct.mfpt).all() and direct.mfpt[1:].min() >= 1
    np.testing.assert_allclose(auto.mfpt, direct.mfpt, rtol=1e-9)
    assert auto.solver["solver"] == solver and auto.solver["path"] == path


def test_graph_dimension_tells_lines_and_grids_from_random_rows():
    from hybridctl.analysis.markov import graph_dimension_is_low
    line = sp.identity(2999, format="csr") - birth_death_line(3000)[1:, 1:]
    random_rows = sp.identity(2999, format="csr") - uniform(3000)[1:, 1:]
    assert graph_dimension_is_low(line) == (True, 15)          # depth counted up to ceil(2999 ** (1/3))
    low, depth = graph_dimension_is_low(random_rows)
    assert not low and depth < 10
