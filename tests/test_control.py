"""systems.control: each control law written once, the same for numpy and torch, and used by every engine."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hybridctl import systems
from hybridctl.systems import control


@pytest.fixture(scope="module")
def acrobot():
    return systems.load("acrobot")


def test_wrap_angles_numpy_equals_torch_and_lands_in_minus_pi_pi(rng):
    err = rng.uniform(-20, 20, size=(1000, 4))
    wrapped = control.wrap_angles(err.copy(), [0, 1])
    torch_wrapped = control.wrap_angles(torch.as_tensor(err), [0, 1]).numpy()
    np.testing.assert_array_equal(wrapped, torch_wrapped)
    assert np.all(wrapped[:, :2] >= -np.pi) and np.all(wrapped[:, :2] < np.pi)
    np.testing.assert_array_equal(wrapped[:, 2:], err[:, 2:])  # velocities untouched
    np.testing.assert_allclose(np.cos(wrapped[:, :2]), np.cos(err[:, :2]), atol=1e-9)
    assert control.wrap_angle(3 * np.pi / 2) == pytest.approx(-np.pi / 2)


def test_lqr_command_and_cost_to_go_numpy_equal_torch(acrobot, rng):
    K, S = acrobot.lqr()
    err = rng.normal(size=(500, 4))
    np.testing.assert_allclose(control.lqr_command(err, K),
                               control.lqr_command(torch.as_tensor(err), torch.as_tensor(K)).numpy(), rtol=1e-12)
    V = control.cost_to_go(err, S)
    np.testing.assert_allclose(V, np.einsum("ni,ij,nj->n", err, S, err), rtol=1e-12)
    assert np.all(V > 0)  # S is positive definite


@pytest.mark.parametrize("mode_type", ["torch", "numpy", "float"])
def test_hysteresis_switches_on_above_on_off_below_off_and_holds_between(mode_type):
    p = [0.95, 0.95, 0.7, 0.7, 0.3, 0.3]
    mode = [False, True, False, True, False, True]
    expected = [True, True, False, True, False, False]
    if mode_type == "torch":
        out = control.hysteresis(torch.tensor(p), torch.tensor(mode), 0.9, 0.5).tolist()
    elif mode_type == "numpy":
        out = control.hysteresis(np.array(p), np.array(mode), 0.9, 0.5).tolist()
    else:
        out = [bool(control.hysteresis(pi, float(mi), 0.9, 0.5)) for pi, mi in zip(p, mode)]
    assert out == expected


def test_divergence_and_saturation():
    x = np.array([[0.0, 1.0], [np.nan, 0.0], [2e6, 0.0], [control.DIVERGENCE_BOUND, 0.0]])
    assert control.is_diverged(x).tolist() == [False, True, True, False]
    assert control.is_diverged(torch.as_tensor(x)).tolist() == [False, True, True, False]
    np.testing.assert_array_equal(control.saturate(np.array([-30.0, 3.0, 30.0]), 25.0), [-25.0, 3.0, 25.0])
    assert control.saturate(torch.tensor([-30.0, 30.0]), 25.0).tolist() == [-25.0, 25.0]


def test_the_engines_share_the_law(acrobot, rng):
    """The Drake LQR block, the switched env's LQR and the cost-to-go gate give the same numbers."""
    from hybridctl.drake import LQRController
    from hybridctl.envs import SwitchedVectorEnv

    states = acrobot.goal + rng.normal(scale=0.3, size=(20, 4))
    gate = control.CostToGoGate(acrobot)
    env = SwitchedVectorEnv(acrobot, 20, gate=gate, seed=0)
    drake_lqr = np.stack([LQRController(acrobot)(x) for x in states])
    env_lqr = env.lqr(torch.as_tensor(states)).numpy()
    # one formula, two array libraries: numpy's and torch's matrix-vector kernels may round the
    # same sum differently (1 ulp, seen on an AVX-512 machine), so equal to 1e-12, not bit for bit
    np.testing.assert_allclose(drake_lqr, env_lqr, rtol=1e-12, atol=0)
    p_numpy = np.concatenate([gate(x) for x in states])
    p_torch = gate(torch.as_tensor(states)).numpy()[:, 0]
    np.testing.assert_allclose(p_numpy, p_torch, rtol=1e-12)
    assert env.gate_on == acrobot.gate.on and env.gate_off == acrobot.gate.off


def test_typed_sections_read_the_spec(acrobot):
    assert (acrobot.gate.on, acrobot.gate.off, acrobot.gate.label_horizon) == (0.9, 0.5, 2.5)
    assert acrobot.success.eps == 0.1 and acrobot.success.lookback == 10
    np.testing.assert_allclose(acrobot.initial_state.nominal, [-np.pi / 2, 0, 0, 0])
    assert acrobot.swingup.controller == "energy_acrobot" and acrobot.swingup.gains["k_p"] == 50.0
    pendulum = systems.load("pendulum")
    assert pendulum.gate.warm_near is None
    with pytest.raises(ValueError, match="gate.warm_near"):
        pendulum.gate.spread("warm_near")
    assert systems.load("acrobot", label_horizon=4.0).gate.label_horizon == 4.0
    with pytest.raises(systems.SpecError, match="gate.label_horizon"):
        systems.load("acrobot", label_horizon=-2.5)
    with pytest.raises(systems.SpecError, match="gate.warm_near"):
        systems.load("acrobot", warm_near=[0.5, 1.0, 5.0])


def test_nudged_nominal_state_moves_only_the_first_angle(acrobot):
    x0 = acrobot.nudged_nominal_state()
    np.testing.assert_allclose(x0 - acrobot.initial_state.nominal, [1e-3, 0, 0, 0])
    cart = systems.load("cartpole").nudged_nominal_state(0.01)
    np.testing.assert_allclose(cart - systems.load("cartpole").initial_state.nominal, [0, 0.01, 0, 0])


def test_accelerations_are_the_velocity_part_of_the_derivatives(acrobot, rng):
    x = torch.as_tensor(rng.normal(size=(50, 4)))
    u = torch.as_tensor(rng.normal(size=(50, 1)))
    qdd = acrobot.dynamics.accelerations(x[:, :2], x[:, 2:], u)
    torch.testing.assert_close(qdd, acrobot.derivatives(x, u)[:, 2:], rtol=1e-12, atol=1e-12)
