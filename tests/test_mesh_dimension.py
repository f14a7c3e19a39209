"""Box meshes, mesh dimension and variation estimators (thesis Ch. 4) on sets of known dimension."""

import numpy as np
import pytest

from hybridctl.analysis import (box_keys, box_mesh_size, count_distinct_rows, madogram, mesh_dimension,
                                power_variation, variation_dimension, variogram)
from hybridctl.analysis.mesh import box_mesh_size_dict


def middle_slope(md):
    """Slope over the scaling range: meshes of 20 to n/20 boxes, away from both saturated ends."""
    inside = (md.sizes >= 20) & (md.sizes <= md.n_points / 20)
    return md.slope(md.box_sizes[inside].min(), md.box_sizes[inside].max())


# ----------------------------------------------------------------------------- box meshes

def test_box_count_matches_the_dict_of_tuples(rng):
    x = rng.normal(size=(3000, 7)).cumsum(axis=0)
    for d in (1e-3, 0.05, 0.3, 2.0):
        assert box_mesh_size(x, d) == box_mesh_size_dict(x, d)


def test_box_count_on_a_known_grid():
    # 4 x 3 grid of distinct points, each repeated: normalised by the given stats (0, 1)
    grid = np.array([[i, j] for i in range(4) for j in range(3)], dtype=float)
    x = np.repeat(grid, 5, axis=0)
    assert box_mesh_size(x, 1.0, mean=0.0, std=1.0) == 12
    assert box_mesh_size(x, 2.0, mean=0.0, std=1.0) == len({(round(a / 2), round(b / 2)) for a, b in grid})
    assert box_mesh_size(x, 100.0, mean=0.0, std=1.0) == 1


def test_keys_use_given_statistics():
    x = np.array([[10.0, 0.0], [12.0, 1.0]])
    keys = box_keys(x, 0.5, mean=[10.0, 0.0], std=[2.0, 1.0])
    np.testing.assert_array_equal(keys, [[0, 0], [2, 2]])


def test_many_columns_and_hash_path_are_exact(rng):
    # 30 coordinates with wide ranges force several packed words (the hashed path)
    base = rng.integers(-10 ** 6, 10 ** 6, size=(500, 30))
    keys = np.concatenate([base, base[:200], base[:50]])
    assert count_distinct_rows(keys) == 500
    assert count_distinct_rows(keys[:1]) == 1


def test_constant_coordinate_does_not_divide_by_zero(rng):
    x = np.c_[rng.normal(size=1000), np.full(1000, 3.0)]
    assert box_mesh_size(x, 0.1) == box_mesh_size(x[:, :1], 0.1)


@pytest.mark.parametrize("bad, message", [
    (np.zeros((0, 3)), "empty"),
    (np.array([[0.0, np.nan]]), "NaN"),
    (np.zeros((2, 2, 2)), "shape"),
])
def test_bad_states_raise(bad, message):
    with pytest.raises(ValueError, match=message):
        box_mesh_size(bad, 0.1)


def test_bad_box_size_raises(rng):
    with pytest.raises(ValueError, match="box size d"):
        box_mesh_size(rng.normal(size=(5, 2)), 0.0)
    with pytest.raises(ValueError, match="too small"):
        box_mesh_size(np.array([[0.0], [1e10]]), 1e-12, mean=0.0, std=1.0)


# ----------------------------------------------------------------------------- mesh dimension

# Expected precision of the scaling-range slope: 0.1 for curves; for 2-D sets of 2e4 points the
# finite-size edge term (N(d) ~ A/d^2 + P/d) keeps the slope near 1.8 over the scaling range
# (measured 1.78; a flat torus of 1e5 points gives 1.81, curvature acting like edges), so 0.25.
@pytest.mark.parametrize("name, make, n, true_dim, slope_tolerance", [
    ("line in 3-D", lambda n, r: np.outer(r.uniform(size=n), [1.0, 2.0, -1.0]), 20000, 1.0, 0.1),
    ("smooth closed curve (limit cycle)",
     lambda n, r: np.c_[np.sin(np.linspace(0, 60, n)), np.cos(np.linspace(0, 60, n)), np.sin(np.linspace(0, 120, n))],
     20000, 1.0, 0.1),
    ("plane in 3-D", lambda n, r: r.uniform(size=(n, 2)) @ np.array([[1.0, 0.5, 0.2], [0.0, 1.0, -1.0]]),
     20000, 2.0, 0.25),
    ("solid cube", lambda n, r: r.uniform(size=(n, 3)), 60000, 3.0, None),
])
def test_mesh_dimension_brackets_known_sets(name, make, n, true_dim, slope_tolerance, rng):
    md = mesh_dimension(make(n, rng))
    assert md.lower <= true_dim + 0.1, name
    assert md.upper >= true_dim - 0.1, name
    if slope_tolerance is not None:  # the cube has too few points per box for a scaling range
        assert middle_slope(md) == pytest.approx(true_dim, abs=slope_tolerance), name
    assert np.all(np.diff(md.box_sizes) > 0) and np.all(np.diff(md.sizes) <= 0)
    assert md.sizes[-1] == 1


def test_circle_has_dimension_one(rng):
    t = rng.uniform(size=20000)
    md = mesh_dimension(np.c_[np.cos(2 * np.pi * t), np.sin(2 * np.pi * t)])
    assert middle_slope(md) == pytest.approx(1.0, abs=0.1)


def test_curve_follows_algorithm_6(rng):
    md = mesh_dimension(rng.uniform(size=(5000, 2)), f=2.0, d0=0.01, stop_fraction=0.8)
    ratios = md.box_sizes[1:] / md.box_sizes[:-1]
    np.testing.assert_allclose(ratios, 2.0)
    assert 0.01 in md.box_sizes
    assert md.sizes[0] >= 0.8 * 5000 or md.box_sizes[0] / 2 < md.settings["d_min"]
    assert md.sizes[-1] == 1 and md.sizes[-2] > 1


def test_vectorised_and_dict_curves_agree(rng):
    x = rng.normal(size=(2000, 17)).cumsum(axis=0)
    fast, slow = mesh_dimension(x), mesh_dimension(x, method="dict")
    np.testing.assert_array_equal(fast.sizes, slow.sizes)
    assert (fast.lower, fast.upper) == (slow.lower, slow.upper)
    with pytest.raises(ValueError, match="method"):
        mesh_dimension(x, method="kdtree")


def test_lower_and_upper_are_the_fit_and_the_steepest_step(rng):
    md = mesh_dimension(rng.normal(size=(4000, 3)).cumsum(axis=0))
    x, y = np.log(md.box_sizes), -np.log(md.sizes)
    assert md.lower == pytest.approx(np.polyfit(x, y, 1)[0])
    assert md.upper == pytest.approx(np.max(np.diff(y) / np.diff(x)))
    assert md.upper >= md.lower


def test_constant_and_single_point_have_dimension_zero():
    for states in (np.ones((300, 4)), np.zeros((1, 4))):
        md = mesh_dimension(states)
        assert (md.lower, md.upper) == (0.0, 0.0) and "dimension 0" in md.note


def test_mesh_dimension_bad_settings(rng):
    x = rng.normal(size=(100, 2))
    with pytest.raises(ValueError, match="f"):
        mesh_dimension(x, f=1.0)
    with pytest.raises(ValueError, match="d_min"):
        mesh_dimension(x, d0=1e-3, d_min=1e-2)
    with pytest.raises(ValueError, match="stop_fraction"):
        mesh_dimension(x, stop_fraction=0.0)


def test_mesh_curve_plot(tmp_path, rng):
    md = mesh_dimension(rng.normal(size=(2000, 2)).cumsum(axis=0))
    md.plot(path=tmp_path / "curve.png")
    assert (tmp_path / "curve.png").stat().st_size > 1000
    assert set(md.as_dict()) >= {"lower", "upper", "box_sizes", "sizes"}


# ----------------------------------------------------------------------------- variation estimators

def test_brownian_motion_is_one_and_a_half(rng):
    for shape in ((20000,), (20000, 3)):
        walk = rng.normal(size=shape).cumsum(axis=0)
        assert madogram(walk) == pytest.approx(1.5, abs=0.03)
        assert variogram(walk) == pytest.approx(1.5, abs=0.03)


def test_smooth_curves_are_one():
    t = np.linspace(0, 20, 10000)
    assert madogram(np.sin(t)) == pytest.approx(1.0, abs=1e-3)
    assert variogram(np.c_[np.sin(t), np.cos(3 * t), t]) == pytest.approx(1.0, abs=1e-3)


def test_white_noise_is_two(rng):
    assert madogram(rng.normal(size=20000)) == pytest.approx(2.0, abs=0.03)


def test_power_variation_by_hand():
    x = np.array([0.0, 1.0, 3.0, 6.0])
    assert power_variation(x, 1, 2.0) == pytest.approx((1 + 4 + 9) / (2 * 3))
    assert power_variation(x, 2, 1.0) == pytest.approx((3 + 5) / (2 * 2))
    v = np.array([[0.0, 0.0], [3.0, 4.0], [3.0, 4.0]])
    assert power_variation(v, 1, 1.0) == pytest.approx(5 / 4)            # Euclidean norm of the increment
    assert power_variation(v, 1, 1.0, norm="l1") == pytest.approx(7 / 4)


def test_legacy_reproduces_the_author_code(rng):
    walk = rng.normal(size=(20000, 2)).cumsum(axis=0)
    legacy_variogram = variogram(walk, legacy=True)
    assert legacy_variogram == pytest.approx(1 + madogram(walk, legacy=True) / 2)
    assert legacy_variogram == pytest.approx(1.75, abs=0.03)   # the published tables' scale
    assert variogram(walk) == pytest.approx(1.5, abs=0.03)


def test_variation_edge_cases():
    assert variation_dimension(np.ones((50, 3))) == 1.0          # documented: constant -> 1
    with pytest.raises(ValueError, match="at least 3"):
        madogram(np.array([0.0, 1.0]))
    with pytest.raises(ValueError, match="NaN"):
        madogram(np.array([0.0, np.nan, 1.0]))
    with pytest.raises(ValueError, match="period-2"):
        madogram(np.array([0.0, 1.0, 0.0, 1.0, 0.0]))
    with pytest.raises(ValueError, match="norm"):
        madogram(np.arange(5.0), norm="max")
