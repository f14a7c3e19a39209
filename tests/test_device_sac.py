"""SAC keeps every tensor, generator and network on its configured device (tests/device_trap.py)."""

import pytest

from device_trap import device_trap
from hybridctl.learn.sac import SAC

TINY = dict(total_steps=400, num_envs=4, exploration_steps=100, steps_per_update=100, hidden_size=16,
            replay_batch_size=32, minibatch_size=16, seed=3,
            compile="off")


@pytest.mark.parametrize("system", ["pendulum", "acrobot"])
def test_sac_trains_with_every_tensor_on_its_device(system):
    """Networks built inside ``seeded`` (CPU, then moved) and every buffer, draw and env tensor on
    ``device``: a tensor made without a device would be a meta tensor and fail the run."""
    with device_trap():
        agent = SAC(system, **TINY)
        agent.learn(progress=False)
    assert agent.num_gradient_steps > 0
    assert {p.device.type for p in agent.actor.parameters()} == {"cpu"}


def test_the_trap_catches_a_tensor_made_without_a_device():
    """The trap itself: a tensor made without a device cannot meet a real one."""
    import torch
    real = torch.zeros(2)
    with device_trap(), pytest.raises(RuntimeError, match="meta"):
        real + torch.ones(2)
    with device_trap(), pytest.raises(RuntimeError, match="without a device"):
        torch.Generator()


def test_predict_and_the_exported_policy_put_numpy_states_on_the_agents_device():
    """numpy states go straight to the agent's device (before: a tensor made without a device)."""
    import numpy as np
    from hybridctl.learn.networks import DeterministicPolicy
    agent = SAC("pendulum", **TINY)
    states = np.zeros((3, agent.obs_dim), dtype=np.float32)
    with device_trap():
        actions = agent.predict(states)
        exported = DeterministicPolicy(agent.actor)(states)
    assert actions.shape == (3, agent.action_dim) and exported.shape == (3, agent.action_dim)
