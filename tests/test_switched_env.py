"""The switched env (gate + LQR inside each decision) against the Drake hybrid diagram."""

import numpy as np
import pytest
import torch

from hybridctl import drake, systems
from hybridctl.envs import SwitchedVectorEnv


class TanhPolicy(torch.nn.Module):
    """A fixed smooth swing-up-like policy (deterministic, no training needed)."""

    def __init__(self, limit):
        super().__init__()
        self.limit = limit
        self.weights = torch.nn.Parameter(torch.tensor([[0.3, -0.8, 1.5, 0.4]], dtype=torch.float64),
                                          requires_grad=False)

    def forward(self, x):
        return self.limit * torch.tanh(x @ self.weights.T)


def test_switched_env_equals_drake_hybrid_diagram():
    system = systems.load("acrobot")
    policy = TanhPolicy(system.action_limit)
    # A loose gate (scale 1e5) over-trusts the saturated LQR: from this start the run
    # switches six times, both ways, so the test exercises the hysteresis in both directions.
    gate = drake.CostToGoGate(system, scale=1e5)
    x0 = np.array([1.2, -0.4, 0.5, -1.0])
    env = SwitchedVectorEnv(system, num_envs=2, gate=gate)
    obs, _ = env.reset(seed=0, options={"state": np.stack([x0, x0])})
    states, modes = [obs[0].numpy()], []
    for _ in range(env.max_decisions):
        obs, _, term, trunc, info = env.step(policy(obs))
        states.append(info["final_obs"][0].numpy() if bool(info["_final_obs"][0]) else obs[0].numpy())
        modes.append(float(info["lqr_fraction"][0]))
    traj = drake.simulate(drake.build_hybrid_diagram(system, swingup=policy, gate=gate), x0,
                          duration=system.episode_duration)
    drake_decisions = traj.x[::env.substeps]
    # Per step the two agree to ~1e-15; the swinging acrobot is chaotic and amplifies that
    # to ~1e-9 after ~9 s, so compare the first 8 s (40 decisions, four mode switches).
    compared = 41
    np.testing.assert_allclose(np.array(states)[:compared], drake_decisions[:compared], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.array(states), drake_decisions, rtol=1e-6, atol=1e-6)
    switches = np.flatnonzero(np.diff(traj.gate))
    assert np.sum(switches < compared * env.substeps) >= 4 and 0 < np.mean(modes) < 1
    assert bool(trunc[0]) and not bool(term[0])


def test_mode_resets_to_swingup_at_episode_start():
    system = systems.load("acrobot", duration=0.4)
    always_on = lambda x: torch.ones(x.shape[0], 1, dtype=x.dtype)  # noqa: E731
    env = SwitchedVectorEnv(system, num_envs=3, gate=always_on, seed=1)
    env.reset(seed=1)
    _, _, _, _, info = env.step(torch.zeros(3, 1))
    assert bool(env.mode.all()) and not bool(info["lqr_at_start"].any())
    _, _, _, trunc, info = env.step(torch.zeros(3, 1))
    assert bool(trunc.all()) and bool(info["lqr_at_start"].all())
    assert not bool(env.mode.any())  # autoreset restarted the episodes in swing-up


def test_bad_thresholds_and_gate():
    system = systems.load("acrobot")
    with pytest.raises(ValueError, match="gate_off < gate_on"):
        SwitchedVectorEnv(system, 2, gate=drake.CostToGoGate(system), gate_on=0.4, gate_off=0.6)
    with pytest.raises(TypeError, match="gate must be"):
        SwitchedVectorEnv(system, 2, gate=3)
