"""A robot's goal and spec values checked before they are used.

A goal that is an equilibrium only to a few digits moves to the nearest one (said); a goal far from
every equilibrium is refused in one line."""

from __future__ import annotations

import textwrap
import warnings

import numpy as np
import pytest

from hybridctl import systems
from hybridctl.systems import symbolic

MJCF_PENDULUM = textwrap.dedent("""\
    <mujoco model="pend">
      <worldbody>
        <body name="pole" pos="0 0 1">
          <joint name="hinge" type="hinge" axis="0 1 0" damping="0.01"/>
          <inertial pos="0 0 -0.5" mass="1" diaginertia="0.01 0.01 0.01"/>
        </body>
      </worldbody>
      <actuator>
        <motor name="m" joint="hinge" ctrlrange="-2 2" ctrllimited="true"/>
      </actuator>
    </mujoco>
    """)


@pytest.fixture(autouse=True)
def private_cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv(symbolic.CACHE_ENV, str(tmp_path_factory.getbasetemp() / "cache"))


@pytest.fixture
def mjcf(tmp_path):
    path = tmp_path / "pend.xml"
    path.write_text(MJCF_PENDULUM)
    return path


def test_a_goal_an_equilibrium_only_to_a_few_digits_moves_to_the_nearest_one_and_says_so(mjcf):
    with pytest.warns(UserWarning, match=r"goal \[-3.1416, 0\] is an equilibrium only to .*moved 7.3e-06 to the "
                                         r"nearest equilibrium \[-3.141592654, 0\]"):
        robot = systems.from_drake(str(mjcf), goal=[-3.1416, 0.0], Q=np.eye(2), R=np.eye(1))
    np.testing.assert_allclose(robot.goal, [-np.pi, 0.0], atol=1e-12)
    plant = robot.drake_plant()                       # Drake agrees: an equilibrium with u = 0
    xdot = robot.drake_derivatives(plant, robot.drake_context(plant), robot.goal, np.zeros(1))
    assert np.abs(xdot).max() < 1e-10
    K, _ = robot.lqr()
    assert np.all(np.isfinite(K))
    found, distance = systems.nearest_equilibrium(robot, [3.14159, 0.0])
    np.testing.assert_allclose(found, [np.pi, 0.0], atol=1e-12)
    assert distance == pytest.approx(np.pi - 3.14159, rel=1e-6)
    found, _ = systems.nearest_equilibrium(str(mjcf), [0.001, 0.0])    # a model file, built here
    np.testing.assert_allclose(found, [0.0, 0.0], atol=1e-12)
    exact, distance = systems.nearest_equilibrium(robot, robot.goal)
    assert distance == 0.0 and np.array_equal(exact, robot.goal)


def test_a_goal_far_from_every_equilibrium_is_kept_and_refused_in_one_line(mjcf):
    with warnings.catch_warnings():
        warnings.simplefilter("error")                # no move, no warning
        robot = systems.from_drake(str(mjcf), goal=[-3.0, 0.0], Q=np.eye(2), R=np.eye(1))
    assert robot.goal.tolist() == [-3.0, 0.0]
    with pytest.raises(ValueError, match=r"the goal \[-3.0, 0.0\] is not an equilibrium with u = 0, nor near one") \
            as error:
        robot.lqr()
    assert "\n" not in str(error.value)
    with pytest.raises(systems.EquilibriumError, match=r"\[1, 0\] is not an equilibrium .* none lies within 0.01") \
            as error:
        systems.nearest_equilibrium(robot, [1.0, 0.0])
    assert "\n" not in str(error.value)


def test_shipped_goals_are_exact_equilibria_and_stay_where_they_are():
    for name in ("acrobot", "cartpole"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            system = systems.load(name)
        assert np.array_equal(system.goal, np.asarray(system.spec.get("state.goal"), dtype=float))


def test_initial_state_offsets_that_look_absolute_are_warned_about_and_bad_ones_refused(mjcf):
    def robot(**overrides):
        return systems.from_drake(str(mjcf), goal=[np.pi, 0.0], Q=np.eye(2), R=np.eye(1), nominal=[3.0, 0.0],
                                  **overrides)

    with pytest.warns(UserWarning, match=r"initial_state.low/high are offsets from initial_state.nominal .* hinge: "
                                         r"nominal 3, \[low, high\] = \[2.9, 3.1\] -> starts in \[5.9, 6.1\]"):
        robot(initial_state__low=[2.9, 0.0], initial_state__high=[3.1, 0.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")               # offsets about 0: no warning
        robot(initial_state__low=[-0.1, 0.0], initial_state__high=[0.1, 0.0])
    for overrides, message in [({"initial_state__low": [0.2, 0.0], "initial_state__high": [0.1, 0.0]},
                                "must be <= initial_state.high"),
                               ({"initial_state__low": [0.0, 0.0, 0.0]}, "shape"),
                               ({"initial_state__high": [float("inf"), 0.0]}, "finite")]:
        with pytest.raises(systems.SpecError, match=message) as error:
            robot(**overrides)
        assert "\n" not in str(error.value)
