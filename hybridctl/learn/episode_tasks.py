"""One-episode tasks (:class:`RolloutTask`): ONE episode of a flat-parameter policy
(:class:`~hybridctl.learn.flat_policy.PolicySpec`) behind a frozen affine normalisation, with optional action /
observation noise and pushes (thesis Sec. 4.3), on a gymnasium env (:func:`run_episode`, one task per backend
job) or a whole batch stepped together on the MuJoCo batch stepper (:func:`run_episodes_batched`). ARS and
:func:`~hybridctl.learn.robustness.failure_rates` use them, through :func:`hybridctl.learn.rollouts.rollouts`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from ..analysis.postprocess import PostProcessor
from ..envs.mujoco_batch import MujocoBatchEnv
from ..envs.mujoco_batch import supports as batch_supports
from ..parallel import cached_env
from .flat_policy import PolicySpec
from .rollout_envs import make_env
from .rollout_results import episode_result


@dataclass
class RolloutTask:
    """One episode: parameters, frozen normalisation, env seed and settings (plain, picklable)."""

    env: Any
    env_kwargs: dict | None
    policy: PolicySpec
    theta: np.ndarray
    obs_mean: np.ndarray
    obs_std: np.ndarray
    seed: int
    max_steps: int | None
    reward_shift: float
    postprocessor: PostProcessor
    keep_states: bool = False
    action_noise: float = 0.0
    obs_noise: float = 0.0
    measure: bool = False       # also measure the episode's dimensions (evaluation)
    push: tuple | None = None   # (rate, magnitude): per step, with probability rate, a force of that
    #                             magnitude at a random angle in the x-z plane on the root body (thesis Sec. 4.3)


def run_episode(task: RolloutTask) -> dict:
    """Roll out one episode; returns the post-processed and raw return, steps and state statistics."""
    env = cached_env((repr(task.env), repr(task.env_kwargs), task.max_steps),
                     lambda: make_env(task.env, task.env_kwargs, task.max_steps))
    actor = task.policy.actor(task.theta)
    rng = np.random.default_rng(task.seed)
    obs, _ = env.reset(seed=int(task.seed))
    states, raw_return, shifted, steps, terminated = [np.asarray(obs, dtype=np.float64)], 0.0, 0.0, 0, False
    limit = task.max_steps or np.inf
    while steps < limit:
        seen = states[-1] + (task.obs_noise * rng.normal(size=states[-1].shape) if task.obs_noise else 0.0)
        action = actor((seen - task.obs_mean) / task.obs_std)
        if task.action_noise:
            action = np.clip(action + task.action_noise * rng.normal(size=action.shape), task.policy.low,
                             task.policy.high)
        pushed = task.push is not None and rng.random() < task.push[0]
        if pushed:
            _set_push(env, task.push[1] * _unit_xz(rng))
        obs, reward, terminated, truncated, _ = env.step(action)
        if pushed:
            _set_push(env, np.zeros(3))
        steps += 1
        raw_return += float(reward)
        shifted += float(reward) - task.reward_shift
        states.append(np.asarray(obs, dtype=np.float64))
        if terminated or truncated:
            break
    return episode_result(np.stack(states), raw_return, shifted, steps, bool(terminated), task.postprocessor,
                          keep_states=task.keep_states, measure=task.measure)


def batchable(tasks: list[RolloutTask]) -> bool:
    """Whether :func:`run_episodes_batched` can run ``tasks``: one MuJoCo locomotion env id (and kwargs
    and step limit) that :class:`~hybridctl.envs.mujoco_batch.MujocoBatchEnv` reproduces, and a linear
    or fixed (function) policy (a torch policy's module holds one parameter vector at a time)."""
    if not tasks:
        return False
    first = tasks[0]
    return (batch_supports(first.env, first.env_kwargs)
            and all(t.env == first.env and t.env_kwargs == first.env_kwargs and t.max_steps == first.max_steps
                    and t.policy.module is None for t in tasks))


def run_episodes_batched(tasks: list[RolloutTask], nthread: int = 1) -> list[dict]:
    """:func:`run_episode` of every task, all episodes stepped together on MuJoCo threads.

    The results equal :func:`run_episode`'s bit for bit (tested): the same reset states (drawn
    by the gymnasium env from each task's seed), the same per-episode noise draws in the same
    order, the policy's matrix-vector product row by row, and the env's semantics from
    :class:`~hybridctl.envs.mujoco_batch.MujocoBatchEnv`. Needs :func:`batchable` tasks.
    """
    if not batchable(tasks):
        raise ValueError("run_episodes_batched needs tasks on one Hopper/Walker2d/HalfCheetah v5 env (same kwargs and "
                         "step limit) with linear or fixed policies; use run_episode on a backend otherwise")
    first, n = tasks[0], len(tasks)
    env = cached_env(("mujoco-batch", first.env, repr(first.env_kwargs), n, nthread),
                     lambda: MujocoBatchEnv(first.env, num_envs=n, nthread=nthread, env_kwargs=first.env_kwargs))
    limit = first.max_steps or env.max_episode_steps
    if limit is None:
        raise ValueError(f"{first.env} has no time limit: give max_steps")
    obs = env.reset([t.seed for t in tasks])
    act_dim, obs_dim = env.nu, obs.shape[1]
    states = np.empty((n, limit + 1, obs_dim))
    states[:, 0] = obs
    rngs = [np.random.default_rng(t.seed) for t in tasks]
    actors = [t.policy.actor(t.theta) if t.policy.function is not None else None for t in tasks]
    matrices = [t.theta.reshape(act_dim, obs_dim) if t.policy.function is None else None for t in tasks]
    mean = np.stack([t.obs_mean for t in tasks])
    std = np.stack([t.obs_std for t in tasks])
    low, high = first.policy.low, first.policy.high
    obs_noise = np.array([t.obs_noise for t in tasks])
    action_noise = np.array([t.action_noise for t in tasks])
    shift = np.array([t.reward_shift for t in tasks], dtype=np.float64)
    raw, shifted = np.zeros(n), np.zeros(n)
    steps, terminated = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=bool)
    alive = np.ones(n, dtype=bool)
    ids = np.arange(n)
    for k in range(limit):
        idx = ids[alive]
        if idx.size == 0:
            break
        seen = states[idx, k].copy()
        for j, i in enumerate(idx):      # the noise draws of run_episode, in its order, per episode
            if obs_noise[i]:
                seen[j] = seen[j] + obs_noise[i] * rngs[i].normal(size=obs_dim)
        z = (seen - mean[idx]) / std[idx]
        actions = np.empty((idx.size, act_dim))
        for j, i in enumerate(idx):
            actions[j] = actors[i](z[j]) if actors[i] is not None else matrices[i] @ z[j]
        actions = np.clip(actions, low, high)
        push = None
        for j, i in enumerate(idx):
            if action_noise[i]:
                actions[j] = np.clip(actions[j] + action_noise[i] * rngs[i].normal(size=act_dim), low, high)
            if tasks[i].push is not None and rngs[i].random() < tasks[i].push[0]:
                push = np.zeros((idx.size, 3)) if push is None else push
                push[j] = tasks[i].push[1] * _unit_xz(rngs[i])
        obs, reward, term, _ = env.step(actions, ids=idx, push=push)
        steps[idx] += 1
        raw[idx] += reward
        shifted[idx] += reward - shift[idx]
        states[idx, k + 1] = obs
        terminated[idx] = term
        alive[idx[term]] = False
    return [episode_result(states[i, :steps[i] + 1], float(raw[i]), float(shifted[i]), int(steps[i]),
                           bool(terminated[i]), t.postprocessor, keep_states=t.keep_states, measure=t.measure)
            for i, t in enumerate(tasks)]


def _unit_xz(rng: np.random.Generator) -> np.ndarray:
    angle = rng.uniform(0.0, 2 * np.pi)
    return np.array([np.cos(angle), 0.0, np.sin(angle)])


def _set_push(env: gym.Env, force: np.ndarray) -> None:
    """Apply ``force`` (world x, y, z) to the first body after the world in a MuJoCo env."""
    data = getattr(env.unwrapped, "data", None)
    if data is None or not hasattr(data, "xfrc_applied"):
        raise ValueError(f"push disturbances need a MuJoCo env (with data.xfrc_applied); "
                         f"{type(env.unwrapped).__name__} has none")
    data.xfrc_applied[1, :3] = force
