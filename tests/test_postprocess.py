"""Reward post-processors (thesis eq. 4.4-4.5, 6.2) and the DimensionReward gymnasium wrapper."""

import gymnasium as gym
import numpy as np
import pytest

from hybridctl.analysis import PostProcessor, madogram, mesh_dimension
from hybridctl.envs import DimensionReward


def walk(n, dims, seed=0):
    return np.random.default_rng(seed).normal(size=(n, dims)).cumsum(axis=0)


def test_identity_leaves_the_return_alone():
    value, info = PostProcessor("identity")(walk(50, 3), 12.5)
    assert value == 12.5 and info["dimension"] == 1.0


def test_mesh_lower_divides_by_the_clipped_dimension_after_the_transient():
    states = walk(1200, 6)
    value, info = PostProcessor("mesh-lower")(states, 100.0)
    expected = np.clip(mesh_dimension(states[200:]).lower, 1, 3)
    assert info["dimension"] == pytest.approx(expected) and value == pytest.approx(100.0 / expected)
    assert info["raw_dimension"] == pytest.approx(mesh_dimension(states[200:]).lower)


def test_mesh_upper_is_clipped_to_half_the_state_count():
    noise = np.random.default_rng(1).normal(size=(1000, 4))   # upper slope far above 2
    value, info = PostProcessor("mesh-upper")(noise, 10.0)
    assert info["raw_dimension"] > 2 and info["dimension"] == 2.0 and value == 5.0


def test_smooth_gait_measures_lower_than_a_noisy_one():
    t = np.arange(1200) * 0.05
    gait = np.c_[np.sin(t), np.cos(t), np.sin(2 * t), np.cos(2 * t)]
    noisy = gait + 0.3 * np.random.default_rng(2).normal(size=gait.shape)
    for kind in ("mesh-lower", "madogram", "variogram"):
        pp = PostProcessor(kind)
        assert pp.dimension(gait)[1]["raw_dimension"] < pp.dimension(noisy)[1]["raw_dimension"], kind
    for kind in ("madogram", "variogram"):   # mesh-lower of 1000 points clips both to 1
        assert PostProcessor(kind)(gait, 100.0)[0] > PostProcessor(kind)(noisy, 100.0)[0], kind


def test_variation_kinds_use_the_estimators():
    states = walk(800, 3)
    value, info = PostProcessor("madogram")(states, 30.0)
    assert info["dimension"] == pytest.approx(madogram(states[200:]))
    assert value == pytest.approx(30.0 / info["dimension"])


def test_negative_returns_multiply():
    states = walk(800, 3)
    dim = PostProcessor("madogram").dimension(states)[0]
    assert PostProcessor("madogram", form="multiply")(states, -10.0)[0] == pytest.approx(-10.0 * dim)
    auto = PostProcessor("madogram", form="auto")
    assert auto(states, -10.0)[0] == pytest.approx(-10.0 * dim)     # more negative when D is larger
    assert auto(states, 10.0)[0] == pytest.approx(10.0 / dim)


def test_too_short_episode_gets_the_worst_value_and_says_why():
    value, info = PostProcessor("mesh-lower")(walk(150, 8), 40.0)
    assert info["dimension"] == 4.0 and value == 10.0 and "too short" in info["reason"]
    assert PostProcessor("variogram").dimension(walk(205, 2))[0] == 2.0


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="kind"):
        PostProcessor("fractal")
    with pytest.raises(ValueError, match="form"):
        PostProcessor("madogram", form="add")
    with pytest.raises(ValueError, match="NaN"):
        PostProcessor("mesh-lower").dimension(np.full((300, 2), np.nan))
    with pytest.raises(ValueError, match="shape"):
        PostProcessor("madogram").dimension(np.zeros(300))


class WalkEnv(gym.Env):
    """A 3-D random walk as observations, reward 1 per step, 400 steps."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (3,))
    action_space = gym.spaces.Box(-1.0, 1.0, (1,))

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t, self.x = 0, np.zeros(3)
        return self.x.copy(), {}

    def step(self, action):
        self.t += 1
        self.x = self.x + self.np_random.normal(size=3)
        return self.x.copy(), 1.0, False, self.t >= 400, {}


@pytest.mark.parametrize("kind", ["identity", "mesh-lower", "variogram"])
def test_wrapper_pays_the_processed_return_at_the_end(kind):
    env = DimensionReward(WalkEnv(), kind)
    obs, _ = env.reset(seed=3)
    observations, rewards, done = [obs], [], False
    while not done:
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        observations.append(obs)
        rewards.append(reward)
        done = terminated or truncated
    expected, _ = PostProcessor(kind)(np.stack(observations), 400.0)
    assert sum(rewards) == pytest.approx(expected)
    assert info["raw_return"] == 400.0
    if kind != "identity":
        assert all(r == 0.0 for r in rewards[:-1]) and info["dimension"] >= 1
        assert info["postprocess"]["raw_dimension"] is not None
