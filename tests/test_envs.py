"""Gymnasium environments: API checks, exactness against System.step, autoreset, success test."""

import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

from hybridctl import systems
from hybridctl.envs import STATE_BOUND, SwingupEnv, TorchVectorEnv, env_id, is_balanced

ALL = systems.known_systems()
IDS = ["hybridctl/AcrobotSwingup-v0", "hybridctl/AcrobotUrdfSwingup-v0", "hybridctl/CartpoleSwingup-v0",
       "hybridctl/DoubleCartpoleSwingup-v0", "hybridctl/FurutaSwingup-v0", "hybridctl/PendulumSwingup-v0",
       "hybridctl/ReactionWheelSwingup-v0"]
# By design the action space is in physical units [-limit, limit], not [-1, 1].
NORMALISED_ACTIONS_HINT = "symmetric and normalized space"


def manual_decision(system, x, u, substeps):
    """States after holding u for ``substeps`` calls of the validated System.step on the
    batched torch path (a lone state is stepped as a batch of two copies: one float64 state
    alone would take the plain-float path, which this is compared against)."""
    x, u = torch.as_tensor(x, dtype=torch.float64), torch.as_tensor(u, dtype=torch.float64)
    single = x.shape[0] == 1
    if single:
        x, u = x.expand(2, -1), u.expand(2, -1)
    for _ in range(substeps):
        x = system.step(x, u)
    return x[:1] if single else x


def run_to_end(env, actions):
    """Step a vector env with fixed actions until every sub-env has ended once."""
    for _ in range(env.max_decisions):
        out = env.step(actions)
    return out


# ------------------------------------------------------------------ registration
def test_ids_registered_without_time_limit():
    assert [env_id(name) for name in ALL] == IDS
    env = gym.make(IDS[0])
    assert env.spec.max_episode_steps is None
    wrapper = env
    while wrapper is not wrapper.unwrapped:
        assert not isinstance(wrapper, gym.wrappers.TimeLimit)
        wrapper = wrapper.env
    env.reset(seed=0)
    steps = 0
    while True:
        steps += 1
        _, _, terminated, truncated, info = env.step(np.zeros(1, np.float32))
        if terminated or truncated:
            break
    assert (steps, terminated, truncated) == (50, False, True) and "success" in info


def test_importing_hybridctl_does_not_import_envs():
    code = "import sys, hybridctl; assert 'hybridctl.envs' not in sys.modules and 'gymnasium' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("name", ALL)
def test_check_env(name):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(gym.make(env_id(name)).unwrapped)
        check_env(SwingupEnv(name))
        check_env(SwingupEnv(systems.load(name), decision_period=2 * systems.load(name).dt))
    unexpected = [str(w.message) for w in caught if NORMALISED_ACTIONS_HINT not in str(w.message)]
    assert unexpected == []


# ------------------------------------------------------------------ single env
@pytest.mark.parametrize("name", ["acrobot", "pendulum"])  # euler and runge_kutta2
def test_single_env_equals_manual_step_loop(name, rng):
    env = SwingupEnv(name)
    system = env.system
    assert env.decision_period == system.swingup_period
    assert env.substeps * system.dt == pytest.approx(system.swingup_period)
    assert env.max_decisions == round(system.episode_duration / system.swingup_period)
    obs, _ = env.reset(seed=1)
    total = 0.0
    for k in range(env.max_decisions):
        # The env steps one state on plain floats; the batched torch path agrees to rounding
        # per decision (compared from the same start each decision: the swing is chaotic).
        x = torch.tensor(obs)[None]
        action = rng.uniform(-1.5, 1.5, size=system.n_actions).astype(np.float32) * system.action_limit
        obs, reward, terminated, truncated, info = env.step(action)
        clipped = np.clip(action.astype(np.float64), -system.action_limit, system.action_limit)
        x = manual_decision(system, x, clipped[None], env.substeps)
        np.testing.assert_allclose(obs, x[0].numpy(), rtol=1e-12, atol=1e-12)
        assert reward == pytest.approx(float(system.reward(x)[0]), rel=1e-12, abs=1e-12)
        assert obs.dtype == np.float64 and not terminated
        assert truncated == (k == env.max_decisions - 1)
        assert ("success" in info) == truncated
        total += reward
    assert total <= 2.0 * env.max_decisions  # acrobot: tip height <= 2, so return <= 100
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(system.n_actions))


def test_single_env_seeding_and_initial_state():
    env = SwingupEnv("acrobot")
    first, _ = env.reset(seed=5)
    again, _ = env.reset(seed=5)
    np.testing.assert_array_equal(first, again)
    np.testing.assert_array_equal(first, env.system.sample_initial_states(1, np.random.default_rng(5))[0])
    x0 = np.array([0.1, 0.2, 0.3, 0.4])
    np.testing.assert_array_equal(env.reset(options={"state": x0})[0], x0)
    for bad in (np.zeros(3), [np.nan, 0, 0, 0], [0, 0, 0, 10 * STATE_BOUND]):
        with pytest.raises(ValueError, match="options"):
            env.reset(options={"state": bad})


def test_single_env_bad_arguments():
    env = SwingupEnv("acrobot")
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(1))
    env.reset(seed=0)
    for bad in (np.array([np.nan]), np.array([np.inf]), np.zeros(2), np.zeros((1, 1))):
        with pytest.raises(ValueError, match="action"):
            env.step(bad)
    for period in (0.015, 0.3, -0.2, 0.0, float("nan")):
        with pytest.raises(ValueError, match="decision_period"):
            SwingupEnv("acrobot", decision_period=period)
    with pytest.raises(ValueError, match="render_mode"):
        SwingupEnv("acrobot", render_mode="human")
    with pytest.raises(ValueError, match="spec_overrides"):
        SwingupEnv(systems.load("acrobot"), dt=0.005)
    assert SwingupEnv("acrobot", decision_period=0.01, dt=0.005).substeps == 2


def test_single_env_divergence_terminates():
    env = SwingupEnv("acrobot")
    x0 = np.array([0.0, 0.0, 1e5, -1e5])  # finite, but Euler at dt 0.01 blows up at once
    env.reset(options={"state": x0})
    obs, reward, terminated, truncated, info = env.step(np.zeros(1))
    assert (terminated, truncated, reward, info) == (True, False, 0.0, {"success": False})
    np.testing.assert_array_equal(obs, x0)  # the last finite decision-rate state


# ------------------------------------------------------------------ success test
def test_is_balanced_shapes_and_rule():
    system = systems.load("acrobot")
    b, eps = system.success_lookback, system.success_eps
    at_goal = np.tile(system.goal, (b + 5, 1))
    assert is_balanced(at_goal, system)
    wrapped = at_goal + np.array([2 * np.pi, -2 * np.pi, 0, 0])  # angles are compared wrapped
    assert is_balanced(torch.tensor(wrapped), system)
    early_miss = at_goal.copy()
    early_miss[4, 2] += 2 * eps  # outside the lookback window: ignored
    late_miss = at_goal.copy()
    late_miss[-b, 2] += 2 * eps
    np.testing.assert_array_equal(is_balanced(np.stack([early_miss, late_miss]), system), [True, False])
    assert not is_balanced(at_goal[: b - 1], system)  # too few decision-rate states


def test_success_at_goal_with_zero_action_and_not_from_hanging():
    # The upright pendulum holds with u = 0 for the whole episode (error ~1e-14).
    system = systems.load("pendulum")
    env = TorchVectorEnv(system, 4, seed=0)
    start = np.stack([system.goal, system.goal, np.zeros(2), np.zeros(2)])
    env.reset(options={"state": start})
    _, _, terminated, truncated, infos = run_to_end(env, torch.zeros(4, 1))
    assert truncated.all() and not terminated.any()
    assert infos["_success"].all()
    assert infos["success"].tolist() == [True, True, False, False]


def test_success_with_lqr_acting_every_dt():
    # The acrobot drifts from its unstable upright under u = 0, so hold it with LQR every dt.
    system = systems.load("acrobot")
    K, _ = system.lqr()
    env = SwingupEnv(system, decision_period=system.dt)
    obs, _ = env.reset(options={"state": system.goal + np.array([0.05, -0.05, 0.0, 0.0])})
    while True:
        obs, _, terminated, truncated, info = env.step(-K @ system.state_error(obs))
        if terminated or truncated:
            break
    assert truncated and info["success"]


# ------------------------------------------------------------------ vector env
def test_vector_env_4096_acrobots_full_episode():
    n_envs = 4096
    env = TorchVectorEnv("acrobot", n_envs, seed=0)
    assert env.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    assert env.observation_space.shape == (n_envs, 4) and env.action_space.shape == (n_envs, 1)
    assert env.single_action_space.high[0] == 25.0
    obs, _ = env.reset()
    assert obs.shape == (n_envs, 4) and obs.dtype == torch.float64
    assert env.observation_space.contains(obs.numpy())
    actions = torch.as_tensor(env.action_space.sample())
    for k in range(1, env.max_decisions + 1):
        obs, rewards, terminated, truncated, infos = env.step(actions)
        assert rewards.shape == (n_envs,) and rewards.dtype == torch.float64
        assert terminated.dtype == truncated.dtype == torch.bool
        assert not terminated.any()
        assert bool(truncated.all()) == (k == 50) and bool(truncated.any()) == (k == 50)
        assert (rewards <= 2.0).all()
    assert env.max_decisions == 50 and (env.episode_steps == 0).all()
    assert infos["_final_obs"].all() and infos["_success"].all()
    env.close()
    env.close()


def test_vector_env_rows_equal_single_env():
    env = TorchVectorEnv("pendulum", 3, seed=2)
    obs, _ = env.reset()
    singles = [SwingupEnv("pendulum") for _ in range(3)]
    for single, x0 in zip(singles, obs.numpy()):
        single.reset(options={"state": x0})
    actions = torch.tensor([[-3.0], [0.5], [1.5]])
    for _ in range(10):
        obs, rewards, *_ = env.step(actions)
        for i, single in enumerate(singles):
            single_obs, single_reward, *_ = single.step(actions[i].numpy())
            np.testing.assert_allclose(obs[i].numpy(), single_obs, rtol=1e-12, atol=1e-12)   # torch vs floats
            assert rewards[i].item() == pytest.approx(single_reward, rel=1e-12, abs=1e-12)


def test_same_step_autoreset():
    system = systems.load("acrobot", duration=1.0)  # 5 decisions
    env = TorchVectorEnv(system, 8, seed=3)
    draws = np.random.default_rng(3)
    obs, _ = env.reset()
    np.testing.assert_array_equal(obs.numpy(), system.sample_initial_states(8, draws))
    actions = torch.full((8, 1), 2.0)
    for _ in range(4):
        before, *_ = env.step(actions)
    obs, rewards, terminated, truncated, infos = env.step(actions)
    assert truncated.all() and not terminated.any()
    expected_final = manual_decision(system, before, actions, env.substeps)
    torch.testing.assert_close(infos["final_obs"], expected_final, rtol=0, atol=0)
    assert infos["_final_obs"].all()
    np.testing.assert_array_equal(rewards.numpy(), system.reward(expected_final).numpy())
    np.testing.assert_array_equal(obs.numpy(), system.sample_initial_states(8, draws))  # fresh starts
    assert (env.episode_steps == 0).all()
    obs, _, _, truncated, infos = env.step(actions)
    assert not truncated.any() and not infos["_final_obs"].any() and not infos["_success"].any()


def test_next_step_autoreset_ignores_action():
    system = systems.load("acrobot", duration=1.0)
    runs = []
    for reset_action in (0.0, 1e3):
        env = TorchVectorEnv(system, 8, seed=4, autoreset_mode="next_step")
        assert env.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
        draws = np.random.default_rng(4)
        obs, _ = env.reset()
        np.testing.assert_array_equal(obs.numpy(), system.sample_initial_states(8, draws))
        for _ in range(4):
            before, *_ = env.step(torch.ones(8, 1))
        obs, _, terminated, truncated, infos = env.step(torch.ones(8, 1))
        assert truncated.all() and not terminated.any() and "final_obs" not in infos
        torch.testing.assert_close(obs, manual_decision(system, before, torch.ones(8, 1), env.substeps),
                                   rtol=0, atol=0)
        obs, rewards, terminated, truncated, infos = env.step(torch.full((8, 1), reset_action))
        np.testing.assert_array_equal(obs.numpy(), system.sample_initial_states(8, draws))
        assert (rewards == 0).all() and not (terminated | truncated).any() and not infos["_success"].any()
        assert (env.episode_steps == 0).all()
        runs.append(obs)
    torch.testing.assert_close(runs[0], runs[1], rtol=0, atol=0)


@pytest.mark.parametrize("mode", ["same_step", "next_step"])
def test_divergence_is_termination_even_on_the_last_step(mode):
    system = systems.load("acrobot", duration=0.2)  # one decision per episode
    env = TorchVectorEnv(system, 4, seed=0, autoreset_mode=mode)
    start = np.zeros((4, 4))
    start[:2, 2:] = [1e5, -1e5]  # rows 0 and 1 blow up
    env.reset(options={"state": start})
    obs, rewards, terminated, truncated, infos = env.step(torch.zeros(4, 1))
    assert terminated.tolist() == [True, True, False, False]
    assert truncated.tolist() == [False, False, True, True]
    assert rewards[:2].tolist() == [0.0, 0.0] and not infos["success"].any() and infos["_success"].all()
    last_finite = infos["final_obs"] if mode == "same_step" else obs
    np.testing.assert_array_equal(last_finite[:2].numpy(), start[:2])
    assert torch.isfinite(obs).all()


def test_seed_reproducibility():
    system = systems.load("acrobot", duration=1.0)

    def run(env, seed):
        obs = [env.reset(seed=seed)[0]]
        for k in range(12):  # crosses two autoresets
            obs.append(env.step(torch.full((16, 1), float(k % 3 - 1)))[0])
        return torch.stack(obs)

    a = run(TorchVectorEnv(system, 16), seed=11)
    b = run(TorchVectorEnv(system, 16), seed=11)
    c = run(TorchVectorEnv(system, 16), seed=12)
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert not torch.equal(a, c)
    d = TorchVectorEnv(system, 16, seed=11)
    torch.testing.assert_close(d.reset()[0], a[0], rtol=0, atol=0)


def test_vector_env_actions_and_arguments():
    env = TorchVectorEnv("acrobot", 4, dtype=torch.float32, seed=0)
    obs, _ = env.reset()
    assert obs.dtype == torch.float32 and env.observation_space.dtype == np.float32
    for bad in (torch.full((4, 1), torch.nan), torch.full((4, 1), torch.inf), torch.zeros(4), torch.zeros(3, 1)):
        with pytest.raises(ValueError, match="actions"):
            env.step(bad)
    x0 = env.reset(seed=1)[0]
    clipped = env.step(np.full((4, 1), 1e4))[0]
    env.reset(seed=1)
    torch.testing.assert_close(env.step(torch.full((4, 1), 25.0))[0], clipped, rtol=0, atol=0)
    assert not torch.equal(clipped, x0)
    with pytest.raises(ValueError, match="autoreset_mode"):
        TorchVectorEnv("acrobot", 2, autoreset_mode="disabled")
    with pytest.raises(ValueError, match="num_envs"):
        TorchVectorEnv("acrobot", 0)
    with pytest.raises(ValueError, match="options"):
        env.reset(options={"state": np.zeros((3, 4))})
    with pytest.raises(RuntimeError, match="reset"):
        TorchVectorEnv("acrobot", 2).step(torch.zeros(2, 1))
