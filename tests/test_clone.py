"""Cloning a tracked swing-up into an actor (hybridctl.learn.clone) and SSAC's --init that fit starts from."""

import math

import numpy as np
import pytest
import torch

from hybridctl import systems
from hybridctl.drake.trajopt import TrackingGains, TrajectoryTracker
from hybridctl.learn.clone import (CloneConfig, TrackingSwingup, balanced_fraction, clone_into_actor,
                                   tracker_demonstrations)
from hybridctl.learn.networks import Actor, ObsTransform
from hybridctl.systems.switched import NeverGate, SwitchedController, closed_loop_rollout


def random_gains(system, rows=12, period=0.05, seed=0):
    rng = np.random.default_rng(seed)
    n, m = system.n_states, system.n_actions
    return TrackingGains(period=period, x0=rng.normal(size=(rows, n)), u0=rng.normal(size=(rows, m)),
                         K=5 * rng.normal(size=(rows, m, n)), k0=0.1 * rng.normal(size=(rows, m)), solve_time=0.0, key="t")


def test_the_torch_tracker_is_the_drake_blocks_law():
    """Row k at decision k (the last row past the end), angles wrapped, clipped: the Drake TrajectoryTracker's
    command, to rounding, on states far off the table and past its end."""
    system = systems.load("acrobot")
    gains = random_gains(system)
    drake_block = TrajectoryTracker(system, None, gains)
    tracker = TrackingSwingup(gains, system)
    rng = np.random.default_rng(1)
    x = rng.uniform(-8, 8, size=(64, system.n_states))
    h = torch.as_tensor(rng.integers(0, 20, size=64))
    u, h_next = tracker(torch.as_tensor(x), h)
    expected = np.array([drake_block.command(k * gains.period, xi) for k, xi in zip(h.numpy(), x)])
    np.testing.assert_allclose(u.numpy(), expected, rtol=0, atol=1e-12)
    assert (h_next == h + 1).all() and (np.abs(expected) == system.action_limit).any()   # some clipped


def test_noise_free_demonstrations_are_the_trackers_own_rollout():
    """With no noise the one-decision loop of the demonstrations visits exactly the states the tracker's closed-loop
    rollout does, and labels each with the action it took."""
    system = systems.load("acrobot")
    gains = random_gains(system, period=system.swingup_period)
    tracker = TrackingSwingup(gains, system)
    controller = SwitchedController.for_system(system, swingup=tracker, gate=NeverGate(),
                                               decision_period=system.swingup_period)
    starts = system.sample_initial_states(6, np.random.default_rng(2))
    data = tracker_demonstrations(system, tracker, controller, starts, 5, CloneConfig(noise=(0.0,)))
    run = closed_loop_rollout(system, controller, torch.as_tensor(starts), 5)
    visited = run.states[:, :5].transpose(0, 1).reshape(-1, system.n_states)     # decision-major, as collected
    torch.testing.assert_close(data["states"], visited, rtol=0, atol=1e-12)
    h = torch.arange(5).repeat_interleave(6)
    torch.testing.assert_close(data["actions"], tracker(visited, h)[0], rtol=0, atol=1e-12)
    noisy = tracker_demonstrations(system, tracker, controller, starts, 5, CloneConfig(noise=(0.3,)))
    assert not torch.allclose(noisy["states"][6:], visited[6:])                 # the noise moved the runs


def test_cloning_fits_the_labels_it_was_given():
    """The actor's squashed mean moves to a smooth target it did not fit before; its log-std to the target std."""
    system = systems.load("acrobot")
    torch.manual_seed(0)
    actor = Actor(ObsTransform("angle_sincos", 4, system.angle_indices), 1,
                  torch.tensor([system.action_limit], dtype=torch.float32), 2, 64, -20.0, 2.0)
    states = torch.as_tensor(system.sample_initial_states(4000, np.random.default_rng(3)))   # every angle
    actions = system.action_limit * torch.tanh(2 * states[:, :1].sin() - states[:, 1:2].cos())   # periodic in them
    info = clone_into_actor(actor, states, actions, CloneConfig(steps=400, std=0.2))
    assert info["held_out_rmse"] < info["held_out_rmse_before"] / 4 and info["held_out_rmse"] < 0.1
    with torch.no_grad():
        _, log_std = actor(states[:100].float())
    assert abs(float(log_std.mean()) - math.log(0.2)) < 0.1


def test_balanced_fraction_reads_the_success_window_in_seconds():
    system = systems.load("acrobot")
    goal = np.tile(system.goal, (3, 1))
    from hybridctl.systems.switched import AlwaysGate, ZeroSwingup
    lqr = SwitchedController.for_system(system, swingup=ZeroSwingup(), gate=AlwaysGate())
    window = system.success.lookback * system.swingup_period          # 2 s on the acrobot
    assert balanced_fraction(system, lqr, goal, window + 0.5)["fraction"] == 1.0
    assert balanced_fraction(system, lqr, goal, window - 0.5)["fraction"] == 0.0      # too short to tell
    hanging = np.tile(system.initial_state.nominal, (3, 1))
    passive = SwitchedController.for_system(system, swingup=ZeroSwingup(), gate=NeverGate())
    assert balanced_fraction(system, passive, hanging, window + 0.5)["fraction"] == 0.0


@pytest.mark.parametrize("field, value", [("rollouts", 0), ("noise", ()), ("noise", (1.5,)), ("lr", 0.0),
                                          ("dagger_rounds", -1), ("held_out", 0.7)])
def test_clone_settings_are_checked(field, value):
    with pytest.raises(ValueError, match=f"CloneConfig.{field}"):
        CloneConfig(**{field: value})


def test_ssac_init_goes_on_from_a_checkpoint_with_its_replay_and_gate_data(tmp_path):
    """--init on SSAC: the networks, the replay buffers and the gate data of the checkpoint go on (fit starts SSAC from
    its clone so); the counters go on, so the budget is the total."""
    from hybridctl.experiments.training import train_and_evaluate
    from hybridctl.learn import SSAC
    tiny = dict(num_envs=8, exploration_steps=200, steps_per_update=200, updates_per_round=1, replay_batch_size=128,
                minibatch_size=64, buffer_size=20_000, needle_buffer_size=5_000, log_every=400, checkpoint_every=400,
                tensorboard=False, gate_refit_every=400, gate_refit_steps=20, gate_warm_samples=300,
                gate_warm_fit_steps=20)
    first = train_and_evaluate("ssac", "acrobot", out=tmp_path / "a", settings={**tiny, "total_steps": 400},
                               eval_episodes=1, progress=False, report=None)
    made = SSAC.load(tmp_path / "a" / "final")
    made.checkpointer.restore(tmp_path / "a" / "final", bulky=True)
    second = train_and_evaluate("ssac", "acrobot", out=tmp_path / "b", settings={**tiny, "total_steps": 800},
                                init=tmp_path / "a" / "final", eval_episodes=1, progress=False, report=None)
    assert first.evaluation["env_steps"] == 400 and second.evaluation["env_steps"] == 800
    # the second run's own 400 steps add to the first run's buffers (without them it would hold at most its own)
    assert second.agent.replay.size > made.replay.size > 0
    assert len(second.agent.gate_data) >= len(made.gate_data) > 0    # the warm start's labelled states too
