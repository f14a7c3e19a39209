"""Gate learning (thesis Sec. 3.3, Algorithm 2)."""

import math

import numpy as np
import pytest
import torch

from hybridctl import systems
from hybridctl.learn.gate import (GateConfig, GateNet, fit_gate, gate_loss, gate_metrics, label_states,
                                  positive_class_weight, warm_start_gate, warm_start_states)


@pytest.fixture(scope="module")
def acrobot():
    return systems.load("acrobot")


def test_gate_is_periodic_in_angles(acrobot):
    gate = GateNet(acrobot)
    x = torch.tensor([[1.0, -0.5, 0.3, 2.0]])
    shifted = x + torch.tensor([[2 * np.pi, -4 * np.pi, 0.0, 0.0]])
    torch.testing.assert_close(gate(x), gate(shifted), rtol=1e-5, atol=1e-6)
    with torch.no_grad():
        assert gate(x).shape == (1, 1) and 0 < gate(x).item() < 1


def test_labels_from_lqr_rollouts(acrobot):
    states = np.array([acrobot.goal, acrobot.goal + [0.01, -0.01, 0.0, 0.0], [-np.pi / 2, 0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(label_states(acrobot, states, GateConfig()), [True, True, False])


def test_warm_start_states_cover_near_and_far(acrobot):
    states = warm_start_states(acrobot, 1000, np.random.default_rng(0))
    err = np.abs(acrobot.state_error(states))
    near, far = acrobot.gate.warm_near, acrobot.gate.warm_far
    assert np.all(err[:500] <= near + 1e-12) and np.any(err[500:, 3] > near[3])
    assert np.all(err <= far + 1e-9)


def test_class_weight_makes_the_gate_conservative(acrobot):
    """A smaller positive weight (thesis w = 0.01) gives fewer hand-overs than w = 1 on the same data."""
    rng = np.random.default_rng(1)
    states = warm_start_states(acrobot, 6000, rng)
    labels = label_states(acrobot, states, GateConfig())
    handovers = {}
    for w in (0.01, 1.0):
        torch.manual_seed(0)
        gate = GateNet(acrobot)
        losses = fit_gate(gate, states, labels, steps=400, lr=3e-3, positive_weight=w,
                          generator=torch.Generator().manual_seed(0))
        assert losses[-1] < losses[0]
        handovers[w] = gate_metrics(gate, states, labels)["handovers"]
    assert handovers[0.01] < handovers[1.0]


def test_warm_start_gate_returns_data_and_metrics(acrobot):
    config = GateConfig(warm_samples=4000, warm_fit_steps=200)
    torch.manual_seed(123)
    rng_state = torch.random.get_rng_state()
    gate, states, labels, info = warm_start_gate(acrobot, config)
    assert torch.equal(torch.random.get_rng_state(), rng_state)     # seeded by its own seed only
    again = warm_start_gate(acrobot, config)[0]
    assert all(torch.equal(a, b) for a, b in zip(gate.state_dict().values(), again.state_dict().values()))
    assert states.shape == (4000, 4) and labels.shape == (4000,) and labels.any()
    assert {"false_handover_rate", "recall", "positive_fraction"} <= set(info)
    assert info["positive_fraction"] == pytest.approx(labels.mean())


def test_fit_gate_bad_input(acrobot):
    gate = GateNet(acrobot)
    with pytest.raises(ValueError, match="equal length"):
        fit_gate(gate, np.zeros((3, 4)), np.zeros(2, dtype=bool), steps=1)
    bad = np.full((8, 4), np.nan)
    with pytest.raises(FloatingPointError, match="gate loss"):
        fit_gate(gate, bad, np.ones(8, dtype=bool), steps=1)


def test_label_horizon_is_a_system_fact():
    """The spec sets how long the LQR may take to balance a labelled state; the config can override it."""
    import dataclasses
    from hybridctl.learn.gate import label_horizon
    cartpole = systems.load("cartpole")
    assert label_horizon(systems.load("acrobot"), GateConfig()) == 2.5       # thesis
    assert label_horizon(cartpole, GateConfig()) == 10.0                      # the slower cart (spec source)
    assert label_horizon(cartpole, dataclasses.replace(GateConfig(), label_horizon=3.0)) == 3.0
    near = warm_start_states(cartpole, 400, np.random.default_rng(0))[:200]
    assert label_states(cartpole, near, GateConfig()).mean() > 0.5            # 88 % measured on 2000 states


def test_gate_features_are_the_wrapped_error_and_the_cost_to_go(acrobot):
    """The features are the control module's wrapped state error and log(1 + V / cost_scale)."""
    from hybridctl.systems.control import cost_to_go
    gate = GateNet(acrobot)
    x = torch.tensor([[1.0 + 2 * np.pi, -0.5, 0.3, 2.0]], dtype=torch.float64)
    err = torch.as_tensor(acrobot.state_error(x.numpy().copy()), dtype=torch.float32)
    S = torch.as_tensor(acrobot.lqr()[1] / acrobot.gate.cost_scale, dtype=torch.float32)
    expected = torch.cat([err / gate.feature_scale, torch.log1p(cost_to_go(err, S)).unsqueeze(-1)], dim=-1)
    torch.testing.assert_close(gate.features(x), expected, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(gate.feature_scale, torch.as_tensor(acrobot.gate.warm_far, dtype=torch.float32))


def test_gate_metrics_threshold_comes_from_the_system(acrobot):
    states = warm_start_states(acrobot, 400, np.random.default_rng(3))
    labels = label_states(acrobot, states, GateConfig())
    gate = GateNet(acrobot)
    with torch.no_grad():
        gate.net[-1].weight.zero_()
        gate.net[-1].bias.fill_(float(np.log(0.8 / 0.2)))   # p = 0.8 everywhere
    assert gate_metrics(gate, states, labels)["handovers"] == 0                # acrobot gate.on = 0.9
    assert gate_metrics(gate, states, labels, on=0.7)["handovers"] == 400
    assert acrobot.gate.on == 0.9
    with pytest.raises(ValueError, match="on="):
        gate_metrics(torch.nn.Sequential(torch.nn.Linear(4, 1), torch.nn.Sigmoid()).double(), states, labels)


def test_fit_gate_minimises_the_eq_3_3_loss(acrobot):
    """fit_gate's losses are gate_loss with the class weight of eq. 3.3 on the whole data set."""
    states = warm_start_states(acrobot, 500, np.random.default_rng(4))
    labels = label_states(acrobot, states, GateConfig())
    c_w = positive_class_weight(labels, 0.01)
    assert c_w == pytest.approx(len(labels) / labels.sum() * 0.01)
    gate = GateNet(acrobot)
    losses = fit_gate(gate, states, labels, steps=1, batch_size=500, lr=0.0,
                      generator=torch.Generator().manual_seed(0))
    # one step at lr 0 on a batch drawn with replacement: the loss is the weighted BCE of that batch
    rows = torch.randint(500, (500,), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        batch = float(gate_loss(gate, torch.as_tensor(states, dtype=torch.float32)[rows], torch.as_tensor(labels)[rows],
                                c_w))
    assert losses[0] == pytest.approx(batch, rel=1e-6) and math.isfinite(batch)
