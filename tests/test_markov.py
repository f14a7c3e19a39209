"""Absorbing Markov chains: exact MFPT, the eigenvalue estimate, infinite MFPT, bad input."""

import numpy as np
import pytest
import scipy.sparse as sp

from hybridctl.analysis.markov import absorbing_mfpt, check_transition_matrix


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
    """Upward drift over 300 states: MFPT ~1e32, beyond any iterative solve; say so, and the eigen
    estimate calls it infinite (lambda_2 within 1e-12 of 1)."""
    T = birth_death(300, 0.45, 0.35)
    with pytest.raises(RuntimeError, match="did not converge"):
        absorbing_mfpt(T, eigen=False)
    assert absorbing_mfpt(T, method="eigen").eigen_estimate == np.inf
