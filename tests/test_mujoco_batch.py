"""The batched MuJoCo stepper reproduces gymnasium's Hopper/Walker2d/HalfCheetah v5 ``env.step``
bit for bit (observations, rewards, terminations, info); needs the `mujoco` extra."""

import numpy as np
import pytest

pytest.importorskip("mujoco")
pytest.importorskip("mujoco.batch")

import gymnasium as gym  # noqa: E402

from hybridctl.envs.mujoco_batch import MujocoBatchEnv, supports  # noqa: E402

ENVS = [("Hopper-v5", {}), ("Walker2d-v5", {}), ("HalfCheetah-v5", {}),
        ("Hopper-v5", {"exclude_current_positions_from_observation": False, "healthy_reward": 0.5,
                       "ctrl_cost_weight": 0.01, "terminate_when_unhealthy": False})]


def gym_reference(env_id, kwargs, seeds, actions, pushes=None):
    """Each seed's trajectory through the gymnasium env itself (pushes set on data.xfrc_applied[1])."""
    env = gym.make(env_id, **kwargs).unwrapped
    out = {"obs0": [], "obs": [], "reward": [], "terminated": [], "x_velocity": []}
    for b, seed in enumerate(seeds):
        obs, _ = env.reset(seed=seed)
        out["obs0"].append(obs)
        rows = {k: [] for k in ("obs", "reward", "terminated", "x_velocity")}
        for t in range(actions.shape[1]):
            if pushes is not None:
                env.data.xfrc_applied[1, :3] = pushes[b, t]
            obs, reward, terminated, _, info = env.step(actions[b, t])
            env.data.xfrc_applied[1, :3] = 0.0
            for k, v in (("obs", obs), ("reward", reward), ("terminated", terminated),
                         ("x_velocity", info["x_velocity"])):
                rows[k].append(v)
        for k, v in rows.items():
            out[k].append(v)
    env.close()
    return {k: np.array(v) for k, v in out.items()}


@pytest.mark.parametrize("env_id,kwargs", ENVS)
@pytest.mark.parametrize("nthread", [1, 2])
def test_identical_to_gymnasium(env_id, kwargs, nthread):
    seeds, steps = [0, 1, 2, 7], 150
    batch = MujocoBatchEnv(env_id, num_envs=len(seeds), nthread=nthread, env_kwargs=kwargs)
    rng = np.random.default_rng(3)
    actions = rng.uniform(-1.0, 1.0, (len(seeds), steps, batch.nu))
    ref = gym_reference(env_id, kwargs, seeds, actions)
    obs0 = batch.reset(seeds)
    np.testing.assert_array_equal(obs0, ref["obs0"])
    for t in range(steps):
        obs, reward, terminated, info = batch.step(actions[:, t])
        np.testing.assert_array_equal(obs, ref["obs"][:, t], err_msg=f"step {t}")
        np.testing.assert_array_equal(reward, ref["reward"][:, t], err_msg=f"step {t}")
        np.testing.assert_array_equal(terminated, ref["terminated"][:, t], err_msg=f"step {t}")
        np.testing.assert_array_equal(info["x_velocity"], ref["x_velocity"][:, t])
    if "Cheetah" not in env_id and kwargs.get("terminate_when_unhealthy", True):
        assert ref["terminated"].any(), "the random actions should make some episode unhealthy"


def test_subsets_pushes_and_explicit_states():
    """Stepping a subset leaves the others alone; pushes act for one step; explicit qpos/qvel work."""
    seeds, steps = [4, 5, 6], 40
    batch = MujocoBatchEnv("Hopper-v5", num_envs=5, nthread=2)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-0.5, 0.5, (3, steps, 3))
    pushes = np.zeros((3, steps, 3))
    pushes[:, 2] = [[30.0, 0.0, 0.0], [-20.0, 0.0, 10.0], [0.0, 0.0, -40.0]]
    ref = gym_reference("Hopper-v5", {}, seeds, actions, pushes)
    qpos, qvel = batch.reset_states(seeds)
    ids = np.array([0, 2, 4])
    batch.reset([9] * 5)                         # the others hold some other state
    batch.set_state(qpos, qvel, ids)
    other = batch.observe([1, 3])
    for t in range(steps):
        push = pushes[:, t] if t == 2 else None
        obs, reward, terminated, _ = batch.step(actions[:, t], ids=ids, push=push)
        np.testing.assert_array_equal(obs, ref["obs"][:, t])
        np.testing.assert_array_equal(reward, ref["reward"][:, t])
        np.testing.assert_array_equal(terminated, ref["terminated"][:, t])
    np.testing.assert_array_equal(batch.observe([1, 3]), other)
    assert not np.allclose(ref["obs"][:, 3], gym_reference("Hopper-v5", {}, seeds, actions)["obs"][:, 3])
    assert np.all(batch.xfrc_applied == 0.0)


def test_bad_input():
    assert supports("Hopper-v5") and not supports("Hopper-v4") and not supports("Ant-v5") and not supports(3)
    with pytest.raises(ValueError, match="env_id"):
        MujocoBatchEnv("Ant-v5")
    with pytest.raises(ValueError, match="num_envs"):
        MujocoBatchEnv("Hopper-v5", num_envs=0)
    batch = MujocoBatchEnv("Hopper-v5", num_envs=2)
    batch.reset([0, 1])
    with pytest.raises(ValueError, match="actions"):
        batch.step(np.zeros((2, 4)))
    with pytest.raises(ValueError, match="ids"):
        batch.step(np.zeros((1, 3)), ids=[2])
    with pytest.raises(ValueError, match="push"):
        batch.step(np.zeros((2, 3)), push=np.zeros((2, 2)))
    with pytest.raises(ValueError, match="sorted"):
        batch.step(np.zeros((2, 3)), ids=[1, 0])


def test_without_mujoco_the_stepper_names_the_extra_and_callers_fall_back(monkeypatch):
    """With MuJoCo hidden (as on an install without the mujoco extra) the batched stepper is one ImportError that
    says what to install, and ``supports`` says no, so ARS and the failure rates step gymnasium's env instead."""
    import sys

    monkeypatch.setitem(sys.modules, "mujoco", None)
    monkeypatch.setitem(sys.modules, "mujoco.batch", None)
    assert not supports("Hopper-v5")
    with pytest.raises(ImportError, match=r"mujoco >= 3.17 .*pip install -c constraints.txt -e '\.\[mujoco\]'"):
        MujocoBatchEnv("Hopper-v5")


# ----------------------------------------------------------------------------- ARS and failure rates on it

from hybridctl.learn.ars import ARS, ARSConfig, RolloutTask, batchable, run_episode, run_episodes_batched  # noqa: E402
from hybridctl.learn.robustness import failure_rates  # noqa: E402


def _assert_same_results(batched, looped):
    assert len(batched) == len(looped)
    for b, r in zip(batched, looped):
        assert b.keys() == r.keys()
        for key in r:
            np.testing.assert_array_equal(b[key], r[key], err_msg=key)


@pytest.mark.parametrize("env_id", ["Hopper-v5", "Walker2d-v5", "HalfCheetah-v5"])
def test_ars_epochs_are_bit_identical_on_the_batched_stepper(env_id):
    """Two ARS epochs: batched (engine auto, 2 threads) and one gymnasium rollout per task give the same bits."""
    settings = dict(seed=3, n_directions=4, top_directions=2, episode_steps=120, reward_shift=1.0, workers=2)
    batched = ARS(env_id, ARSConfig(backend="serial", **settings))
    looped = ARS(env_id, ARSConfig(backend="serial", engine="backend", **settings))
    for _ in range(2):
        rows = batched.train_epoch(None), looped.train_epoch(looped_pool)
        assert rows[0] == rows[1]
    np.testing.assert_array_equal(batched.theta, looped.theta)
    np.testing.assert_array_equal(batched.stats.sum, looped.stats.sum)
    assert batched.stats.count == looped.stats.count


class _Serial:
    @staticmethod
    def map(f, tasks):
        return [f(t) for t in tasks]


looped_pool = _Serial()


def test_noisy_and_pushed_episodes_are_bit_identical():
    """Observation and action noise and random pushes draw the same numbers in the same order."""
    agent = ARS("Hopper-v5", ARSConfig(backend="serial", seed=0))
    agent.theta = np.random.default_rng(1).normal(scale=0.05, size=agent.theta.size)
    tasks = agent._tasks([agent.theta] * 4, [11, 12, 13, 14], max_steps=150, keep_states=True,
                         action_noise=0.1, obs_noise=0.02, push=(0.2, 40.0))
    assert batchable(tasks)
    _assert_same_results(run_episodes_batched(tasks, nthread=2), [run_episode(t) for t in tasks])
    fixed = [RolloutTask(t.env, t.env_kwargs, t.policy.__class__(t.policy.obs_dim, t.policy.act_dim, t.policy.low,
                                                              t.policy.high, function=lambda z: -0.1 * z[:3]),
                         np.zeros(0), np.zeros(11), np.ones(11), t.seed, 90, 0.0, t.postprocessor) for t in tasks]
    _assert_same_results(run_episodes_batched(fixed), [run_episode(t) for t in fixed])


def test_failure_rates_use_the_batched_stepper_with_the_same_answer():
    agent = ARS("Hopper-v5", ARSConfig(backend="serial", seed=0))
    conditions = {"none": {}, "push": {"push": (0.05, 60.0)}, "action": {"action_noise": 0.3}}
    batched = failure_rates(agent, conditions=conditions, episodes=6, episode_steps=80, backend="serial")
    agent.config.engine = "backend"
    looped = failure_rates(agent, conditions=conditions, episodes=6, episode_steps=80, backend="serial")
    assert batched == looped


# ----------------------------------------------------------------------------- fine-tuning on it

@pytest.mark.parametrize("env_id", ["Hopper-v5", "HalfCheetah-v5"])
def test_finetune_updates_are_bit_identical_on_the_batched_stepper(env_id, monkeypatch):
    """FineTune's chunks on MujocoBatchEnv give the gymnasium loop's bits (float32 policy, float32 actions)."""
    import torch

    import hybridctl.learn.finetune as finetune
    from hybridctl.parallel import make_backend

    def tuner():
        torch.manual_seed(0)
        obs_dim, act_dim = (11, 3) if env_id == "Hopper-v5" else (17, 6)
        net = torch.nn.Sequential(torch.nn.Linear(obs_dim, 16), torch.nn.Tanh(), torch.nn.Linear(16, act_dim),
                                  torch.nn.Tanh())
        return finetune.FineTune(env_id, net, n_directions=3, chunk_size=4, episode_steps=150, seed=1)

    batched, looped = tuner(), tuner()
    rows_b = [batched.train_update(make_backend("serial")) for _ in range(2)]
    monkeypatch.setattr(finetune, "batch_supports", lambda *a, **k: False)
    rows_l = [looped.train_update(make_backend("serial")) for _ in range(2)]
    assert rows_b == rows_l
    np.testing.assert_array_equal(batched.theta, looped.theta)
