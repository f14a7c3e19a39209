"""Drake hybrid systems as Poincare maps: the RimlessWheel apex map by a witness on an observer."""

import pickle

import numpy as np
import pytest

from hybridctl.analysis import GaussianDisturbance, RimlessWheel, build_mesh
from hybridctl.drake import DrakeRimlessWheelMap


def test_drake_wheel_matches_the_analytic_map():
    rng = np.random.default_rng(0)
    w, slopes = rng.uniform(0.3, 2.5, 12), rng.normal(0.15, 0.06, 12)
    analytic = RimlessWheel().step_many(w[:, None], slopes)
    drake = DrakeRimlessWheelMap().step_many(w[:, None], list(slopes))     # accuracy 1e-6: 7.6e-7 measured
    np.testing.assert_array_equal(np.isnan(drake), np.isnan(analytic))
    np.testing.assert_allclose(drake[~np.isnan(drake)], analytic[~np.isnan(analytic)], atol=2e-6)


def test_the_accuracy_reaches_the_integrator():
    """``accuracy`` sets the integrator's own target, not only the context's (which Drake's Simulator overrides
    with its 1e-4 default): at 1e-10 the wheel is within 1e-9 of the analytic map, which 1e-4 is not."""
    rng = np.random.default_rng(1)
    w, slopes = rng.uniform(0.3, 2.5, 8), rng.normal(0.15, 0.06, 8)
    analytic = RimlessWheel().step_many(w[:, None], slopes)
    ok = ~np.isnan(analytic)
    errors = {}
    for accuracy in (1e-4, 1e-10):
        wheel = DrakeRimlessWheelMap(accuracy=accuracy)
        drake = wheel.step_many(w[:, None], list(slopes))
        assert wheel._parts[0].get_integrator().get_target_accuracy() == accuracy
        errors[accuracy] = np.abs(drake[ok] - analytic[ok]).max()
    assert errors[1e-10] < 1e-9 < errors[1e-4], errors


def test_failure_when_the_wheel_rolls_back():
    wheel = DrakeRimlessWheelMap()
    assert wheel.step([0.3], -0.2) is None and RimlessWheel().step([0.3], -0.2) is None
    assert wheel.step([-1.0], 0.1) is None


def test_pickles_without_drake_objects_and_rebuilds():
    wheel = DrakeRimlessWheelMap()
    first = wheel.step([1.29], 0.15)
    clone = pickle.loads(pickle.dumps(wheel))
    assert clone._parts is None
    np.testing.assert_array_equal(clone.step([1.29], 0.15), first)


@pytest.mark.slow   # Drake plants built in 2 worker processes (~30-60 s); the Drake map and its pickling stay, serially
def test_drake_mesh_in_worker_processes_equals_the_analytic_mesh():
    """A coarse mesh built from Drake simulations in 2 processes has the analytic mesh's chain."""
    slopes = GaussianDisturbance(0.15, 0.06, 7, rule="quantiles")
    seed = [[RimlessWheel().fixed_point(0.15)]]
    analytic = build_mesh(RimlessWheel(), seed, slopes, 0.05, progress=False)
    drake = build_mesh(DrakeRimlessWheelMap(), seed, slopes, 0.05, backend="processes", workers=2, batch_size=4,
                       progress=False, in_process_below=0)
    assert drake.rounds["backend"] >= 1
    np.testing.assert_array_equal(drake.successors, analytic.successors)
    assert drake.mfpt().mean(drake.seed_distribution()) == pytest.approx(
        analytic.mfpt().mean(analytic.seed_distribution()), rel=1e-9)


def test_spokes_must_be_whole():
    with pytest.raises(ValueError, match="spokes"):
        DrakeRimlessWheelMap(half_angle=0.4)


def test_compass_gait_has_a_passive_gait_and_falls_uphill():
    from hybridctl.drake import DrakeCompassGaitMap
    walker = DrakeCompassGaitMap()
    gait = walker.gait(steps=40)
    np.testing.assert_allclose(gait, [-0.0927, 0.4239, -1.9771], atol=2e-3)
    np.testing.assert_allclose(walker.step(gait, 0.0525), gait, atol=1e-5)     # a fixed point of the map
    assert walker.step(gait, -0.3) is None                                      # a steep uphill step: falls back
    clone = pickle.loads(pickle.dumps(walker))
    np.testing.assert_array_equal(clone.step(gait, 0.06), walker.step(gait, 0.06))


def test_map_is_a_pure_function_of_state_and_slope():
    """Whatever ran before in a process, the same (state, slope) gives bit-identical results."""
    used = DrakeRimlessWheelMap()
    for w, g in ((2.0, 0.3), (0.5, 0.0), (1.1, 0.2)):
        used.step([w], g)
    np.testing.assert_array_equal(used.step([1.29], 0.1), DrakeRimlessWheelMap().step([1.29], 0.1))


CHATTERING = ([-0.231, 0.0101, -0.1938], 0.0291)   # legs together, heel strikes in a Zeno sequence: ran for minutes
# (at integrator accuracy 1e-4, where the maps ran before their accuracy reached the integrator: 24,650 strikes
# by the 50,000-step guard; at the default 1e-7 the walker rolls back after 9 strikes, in 0.05 s)
CHATTERS = 1e-4


@pytest.mark.timeout(60)
def test_compass_gait_falling_start_returns_within_the_guard():
    """Before the guard this step never returned (a probe ran 900 s); now it is a fall in well under a second."""
    import time
    from hybridctl.drake import DrakeCompassGaitMap
    walker = DrakeCompassGaitMap()
    start = time.monotonic()
    assert walker.step(*CHATTERING) is None
    assert time.monotonic() - start < 5.0
    assert walker.last_failure == "heel-strike guard" and walker.guard_trips["heel-strike guard"] == 1


@pytest.mark.timeout(60)
def test_compass_gait_integrator_step_and_wall_time_guards():
    from hybridctl.drake import DrakeCompassGaitMap
    walker = DrakeCompassGaitMap(max_integrator_steps=200, accuracy=CHATTERS)
    walker.max_strikes = None
    assert walker.step(*CHATTERING) is None and walker.last_failure == "integrator-step guard"
    walker = DrakeCompassGaitMap(wall_limit=0.05, accuracy=CHATTERS)      # chatters for about 5 s unguarded
    walker.max_strikes = None
    assert walker.step(*CHATTERING) is None and walker.last_failure == "wall-time guard"
    assert walker.guard_trips["wall-time guard"] == 1
    assert walker.step([-0.0927, -0.1, -1.9771], 0.05) is None and walker.last_failure == "rolled back"


def test_compass_gait_parameters_are_set_and_checked():
    from hybridctl.drake import DrakeCompassGaitMap
    default = DrakeCompassGaitMap().gait(steps=30)
    heavy = DrakeCompassGaitMap(mass_hip=10.0, mass_leg=5.0, length_leg=1.0, center_of_mass_leg=0.5, gravity=9.81)
    np.testing.assert_array_equal(heavy.gait(steps=30), default)
    long_legs = DrakeCompassGaitMap(length_leg=1.1, center_of_mass_leg=0.55).gait(steps=30)
    # scaled legs: the same angles, rates slower by sqrt(1.1) (the parameters reach the plant)
    np.testing.assert_allclose(long_legs, default * [1, 1.1 ** -0.5, 1.1 ** -0.5], atol=1e-6)
    assert np.abs(DrakeCompassGaitMap(mass_hip=12.0).gait(steps=30) - default).max() > 1e-3
    np.testing.assert_allclose(DrakeCompassGaitMap(slope=0.06).gait(steps=30), [-0.1099, 0.4361, -2.0680], atol=1e-3)
    for kwargs, name in (({"mass_hip": -1.0}, "mass_hip"), ({"mass_leg": 0.0}, "mass_leg"),
                         ({"length_leg": 1e3}, "length_leg"), ({"gravity": float("nan")}, "gravity"),
                         ({"slope": 1.0}, "slope"), ({"center_of_mass_leg": 1.5}, "center_of_mass_leg"),
                         ({"hip_pd": (1.0, 2.0)}, "hip_pd"), ({"wall_limit": 0.0}, "wall_limit")):
        with pytest.raises(ValueError, match=f"^{name} must"):
            DrakeCompassGaitMap(**kwargs)


def test_compass_gait_hip_pd_changes_the_gait():
    """A PD on the inter-leg angle (through CompassGait's hip torque input) walks a period-2 gait of its own."""
    from hybridctl.drake import DrakeCompassGaitMap
    walker = DrakeCompassGaitMap(hip_pd=(10.0, 1.0, -0.4))
    gait = walker.gait(steps=40)
    np.testing.assert_allclose(gait, [-0.5277, 0.5455, -1.1780], atol=2e-3)
    np.testing.assert_allclose(walker.step(walker.step(gait, 0.0525), 0.0525), gait, atol=1e-5)
    clone = pickle.loads(pickle.dumps(walker))
    np.testing.assert_array_equal(clone.step(gait, 0.06), walker.step(gait, 0.06))
