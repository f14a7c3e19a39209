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


# ------------------------------------------------------- what a model file states and neither engine applies
def _said(caught, text):
    return [str(w.message) for w in caught if text in str(w.message)]


def test_an_mjcf_gear_and_joint_range_are_warned_about_once_naming_file_actuator_joint_and_attribute(tmp_path):
    path = tmp_path / "pend_gear.xml"
    path.write_text(MJCF_PENDULUM.replace('damping="0.01"', 'damping="0.01" range="-1 1" limited="true"')
                    .replace('ctrlrange="-2 2"', 'gear="10" ctrlrange="-2 2"'))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        robot = systems.from_drake(str(path), goal=[np.pi, 0.0], Q=np.eye(2), R=np.eye(1))
        robot.drake_plant()                          # parsed again: not said again
    gear = _said(caught, "gear 10 is not applied")
    assert gear == [f"model file {path}: actuator 'm' (gear): gear 10 is not applied: Drake and the generated "
                    f"dynamics apply u as joint torque within ctrlrange [-2, 2]"]
    # MJCF angles are degrees unless <compiler angle="radian">: range="-1 1" is +-1 degree
    limits = _said(caught, "position limits")
    assert limits == [f"model file {path}: joint 'hinge' (range) has position limits [-0.0174533, 0.0174533] rad; "
                      f"neither Drake's continuous plant nor the generated dynamics enforce them"]
    assert robot.action_limit == pytest.approx(2.0)


def test_urdf_joint_limits_are_warned_about_once_per_model_and_shipped_models_say_nothing(tmp_path):
    path = tmp_path / "limited.urdf"
    path.write_text(MJCF_URDF_LIMITED)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        robot = systems.from_drake(str(path), goal=[0.0, 0.0], Q=np.eye(2), R=np.eye(1))
        systems.from_drake(str(path), goal=[0.0, 0.0], Q=np.eye(2), R=np.eye(1))
    assert _said(caught, "position limits") == [
        f"model file {path}: joint 'hinge' (<limit lower upper>) has position limits [-0.5, 0.5] rad; neither "
        f"Drake's continuous plant nor the generated dynamics enforce them"]
    # and indeed: at q = 1.0, beyond the upper limit, Drake's plant and the generated dynamics give a free
    # pendulum's acceleration, -g l m sin(q) / (I + m l^2)
    x, u = np.array([1.0, 0.0]), np.zeros(1)
    plant = robot.drake_plant()
    qdd = robot.drake_derivatives(plant, robot.drake_context(plant), x, u)[1]
    assert qdd == pytest.approx(-9.81 * 0.5 * np.sin(1.0) / (0.01 + 0.25), rel=1e-9)
    import torch
    assert float(robot.derivatives(torch.tensor(x[None]), torch.tensor(u[None]))[0, 1]) == pytest.approx(qdd, rel=1e-9)
    for name in ("acrobot_urdf", "furuta", "reaction_wheel"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            systems.load(name).drake_plant()


MJCF_URDF_LIMITED = textwrap.dedent("""\
    <?xml version="1.0"?>
    <robot name="limited">
      <link name="base"/>
      <link name="pole"><inertial><origin xyz="0 0 -0.5"/><mass value="1"/>
        <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
      <joint name="weld" type="fixed"><parent link="world"/><child link="base"/></joint>
      <joint name="hinge" type="revolute"><parent link="base"/><child link="pole"/><axis xyz="0 1 0"/>
        <limit lower="-0.5" upper="0.5" effort="2" velocity="10"/></joint>
      <transmission type="SimpleTransmission" name="t"><actuator name="m"/><joint name="hinge"/></transmission>
    </robot>
    """)


def test_tilted_mjcf_gravity_is_drakes_in_the_generated_dynamics_and_the_upright_goal_is_refused(tmp_path):
    path = tmp_path / "pend_grav.xml"
    path.write_text(MJCF_PENDULUM.replace("<worldbody>", '<option gravity="1 0 -9.81"/>\n  <worldbody>'))
    robot = systems.from_drake(str(path), goal=[np.pi, 0.0], Q=np.eye(2), R=np.eye(1))
    plant = robot.drake_plant()
    assert plant.gravity_field().gravity_vector().tolist() == [1.0, 0.0, -9.81]     # Drake keeps the tilt
    context = robot.drake_context(plant)
    import torch
    for x, u in zip(np.random.default_rng(0).uniform(-3, 3, (5, 2)), np.random.default_rng(1).uniform(-2, 2, (5, 1))):
        ours = robot.derivatives(torch.tensor(x[None]), torch.tensor(u[None])).numpy()[0]
        np.testing.assert_allclose(ours, robot.drake_derivatives(plant, context, x, u), rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match=r"the goal \[3.14159\d*, 0.0\] is not an equilibrium with u = 0, nor near "
                                         r"one") as error:
        robot.lqr()                                   # the upright is no equilibrium under a tilted g
    assert "\n" not in str(error.value)
    found, distance = systems.nearest_equilibrium(robot, [np.pi, 0.0], tolerance=0.2)
    np.testing.assert_allclose(found, [np.pi - np.arctan2(1.0, 9.81), 0.0], atol=1e-9)   # the pole pointing along -g
    assert distance == pytest.approx(np.arctan2(1.0, 9.81), rel=1e-6)
