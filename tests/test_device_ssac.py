"""SSAC keeps every tensor, generator and network on its configured device, its gate included
(tests/device_trap.py): the warm start's LQR rollouts, the gate's fits and refits, the relabel
pool and the switched env.

The trap works on the thread that enters it (torch's default device is per thread), so the runs
here refit on the training thread (``gate_refit_overlap=False``): the refits are inside the trap.
"""

import numpy as np
import pytest
import torch

from device_trap import HostSyncs, device_trap
from hybridctl import systems
from hybridctl.learn.gate import (GateConfig, GateNet, _CompiledGateStep, _gate_grads, fit_gate, gate_metrics,
                                  warm_start_gate, warm_start_states)
from hybridctl.learn.optim import adam
from hybridctl.learn.gate_data import RelabelPool
from hybridctl.learn.ssac import SSAC

# small enough for seconds: 200 warm-start states, refits at 200 and 400 env steps, each relabelling
# 16 pooled states (gate_relabel_cost 1e9 pools every swing-up decision state)
TINY = dict(total_steps=400, num_envs=4, exploration_steps=100, steps_per_update=100, hidden_size=16,
            replay_batch_size=32, minibatch_size=16, seed=3, compile="off",
            gate_warm_samples=200, gate_warm_fit_steps=10, gate_batch_size=64,
            gate_refit_every=200, gate_refit_steps=5, gate_relabel_per_refit=16, gate_relabel_cost=1e9,
            gate_refit_overlap=False)


@pytest.mark.parametrize("system", ["acrobot", "cartpole"])
def test_ssac_warm_starts_trains_and_refits_with_every_tensor_on_its_device(system):
    """The warm start (LQR rollouts, gate fit, metrics), the switched env's decisions, the relabel
    pool, the refits (relabelling rollouts included) all inside the trap: a tensor made without a
    device would be a meta tensor and fail the run."""
    with device_trap():
        agent = SSAC(system, **TINY)
        agent.learn(progress=False)
        action = agent.act(np.asarray(agent.system.goal))  # the switched controller's inference, too
    assert agent.num_gate_refits == 2 and agent.num_gate_relabelled == 32
    assert agent.gate_info["warm_start"]["n"] == 200
    assert {t.device.type for t in (*agent.gate.parameters(), *agent.gate.buffers())} == {"cpu"}
    assert agent.env.gate is agent.gate and agent.gate_generator.device.type == "cpu"
    assert np.all(np.isfinite(action))


def test_warm_start_and_fit_gate_run_on_the_given_device():
    """warm_start_gate(device=...) and fit_gate on a gate moved to the device, with a generator
    there, make no tensor off it."""
    acrobot = systems.load("acrobot")
    config = GateConfig(warm_samples=200, warm_fit_steps=10, batch_size=64)
    with device_trap():
        gate, states, labels, info = warm_start_gate(acrobot, config, device="cpu")
        refit = GateNet(acrobot, device="cpu")
        generator = torch.Generator(device="cpu").manual_seed(0)
        losses = fit_gate(refit, torch.as_tensor(states, device="cpu"), labels, 5, batch_size=64,
                          generator=generator, class_weight=2.0)
        metrics = gate_metrics(refit, states, labels)
    assert info["n"] == metrics["n"] == 200 and len(losses) == 5 and all(np.isfinite(losses))
    assert {p.device.type for p in gate.parameters()} == {"cpu"}


def test_the_compiled_fit_step_keeps_its_class_weight_on_the_gates_device():
    """fit_gate(compiled=True)'s step: c_w and the fused Adam step on the gate's device. Its graph
    runs eagerly here (the same function; compiling it takes a minute, tests/test_compiled.py)."""
    acrobot = systems.load("acrobot")
    states = torch.as_tensor(warm_start_states(acrobot, 64, np.random.default_rng(0)), dtype=torch.float32)
    labels = torch.arange(64) % 2 == 0
    with device_trap():
        gate = GateNet(acrobot, device="cpu")
        step = _CompiledGateStep(gate, adam(gate.parameters(), 1e-3), c_w=2.0)
        step.grads = _gate_grads
        losses = [step(states, labels) for _ in range(3)]
    assert step.c_w.device.type == "cpu" and all(np.isfinite(losses))


def test_ssac_stores_a_step_without_reading_back_to_the_host():
    """Per env step SSAC adds the LQR flags, the LQR's share and the relabel candidates on the
    device, with no read-back (one would be a GPU sync per step)."""
    acrobot = systems.load("acrobot")
    agent = SSAC(acrobot, gate=GateNet(acrobot), **TINY)
    n = agent.config.num_envs
    obs = torch.as_tensor(np.tile(acrobot.goal, (n, 1)), dtype=torch.float32)  # near the goal: candidates
    zeros, actions = torch.zeros(n), torch.zeros((n, agent.action_dim))
    infos = {"lqr_at_start": torch.tensor([True, False, False, True]),
             "lqr_fraction": torch.tensor([1.0, 0.0, 0.25, 1.0], dtype=torch.float64)}
    with device_trap(), HostSyncs() as syncs:
        agent.store_transitions(obs, actions, zeros, obs, zeros, infos)
    assert syncs.count == 0, syncs.by_name
    assert len(agent.relabel_pool) == 2                       # the two swing-up decisions near the goal
    assert agent._log_row(0.0)["lqr_share"] == 2.25 / 4


def test_the_warm_start_is_the_same_gate_inside_and_outside_the_trap():
    """Naming the device changes no number: the same seed gives the same labels and weights."""
    acrobot = systems.load("acrobot")
    config = GateConfig(warm_samples=200, warm_fit_steps=10, batch_size=64)
    plain = warm_start_gate(acrobot, config)
    with device_trap():
        trapped = warm_start_gate(acrobot, config, device="cpu")
    np.testing.assert_array_equal(plain[2], trapped[2])
    for a, b in zip(plain[0].state_dict().values(), trapped[0].state_dict().values()):
        assert torch.equal(a, b)


def test_relabel_pool_keeps_the_newest_rows_in_order_without_reading_back():
    """The ring buffer holds what the list of kept rows trimmed to its newest ``capacity`` held,
    and adding rows reads nothing back to the host (no sync per env step on a GPU)."""
    rng = np.random.default_rng(0)
    pool, reference = RelabelPool(2, capacity=5, device="cpu"), torch.zeros((0, 2))
    with device_trap():
        for size in (3, 0, 4, 1, 7, 2):
            rows = torch.as_tensor(rng.normal(size=(size, 2)), dtype=torch.float32, device="cpu")
            keep = torch.as_tensor(rng.random(size) < 0.7, device="cpu")
            with HostSyncs() as syncs:
                pool.add(rows, keep)
            assert syncs.count == 0
            reference = torch.cat([reference, rows[keep]])[-5:]
            assert torch.equal(pool.states(), reference)
    pool.clear()
    assert len(pool) == 0 and pool.states().shape == (0, 2)


def test_a_loaded_gate_lands_on_the_learners_device(tmp_path):
    """SSAC.load builds the gate on the configured device (inside the trap) and loads its weights."""
    acrobot = systems.load("acrobot")
    agent = SSAC(acrobot, gate=GateNet(acrobot), **{**TINY, "total_steps": 8})
    agent.save(tmp_path / "ckpt")
    with device_trap():
        loaded = SSAC.load(tmp_path / "ckpt", system=acrobot, device="cpu")
        p = loaded.gate(torch.as_tensor(warm_start_states(acrobot, 4, np.random.default_rng(0)), device="cpu"))
    assert {t.device.type for t in loaded.gate.parameters()} == {"cpu"} and p.shape == (4, 1)
    for a, b in zip(agent.gate.state_dict().values(), loaded.gate.state_dict().values()):
        assert torch.equal(a, b)
