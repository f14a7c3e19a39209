"""Augmented Random Search, V2-t (Mania, Guy & Recht 2018), as used in thesis Ch. 4.

Each epoch: draw N Gaussian directions delta_k; roll out the policy with parameters
theta + sigma delta_k and theta - sigma delta_k (the same env seed for both); keep the
b directions with the largest max(r+, r-); step

    theta <- theta + alpha / (b sigma_R) * sum_k (r+_k - r-_k) delta_k

where sigma_R is the standard deviation of the 2b kept returns. Observations are
normalised by the running mean and std of every state visited in training (V2); the
statistics are frozen within an epoch and updated after it. Returns may be
post-processed by trajectory dimension (:class:`~hybridctl.analysis.PostProcessor`,
thesis eq. 4.4-4.5).

Policies: ``"linear"`` (the thesis: action = M (s - mu) / sd, M starts at zero), or
any torch module (``"mlp:64,64"`` builds a tanh MLP; or pass an ``nn.Module``), whose
parameters are flattened into theta.

>>> agent = ARS("Hopper-v5", ARSConfig(postprocess="mesh-lower", seed=0))
>>> agent.learn(total=100, out="runs/ars-hopper")     # progress bar, CSV, checkpoints
>>> agent.learn(total=200, out="runs/ars-hopper", resume=True)   # on from the newest checkpoint
>>> agent.predict(obs)                                       # deterministic action
>>> agent.save("runs/ars-hopper/final"); ARS.load("runs/ars-hopper/final")

The run log, checkpoints, resume, callbacks and the NaN guard come from the training
skeleton (:mod:`hybridctl.learn.run`); this file holds the algorithm.

Rollouts run on a backend from :mod:`hybridctl.parallel` ("processes" by
default, "serial", or "ray"). Directions and env seeds come from
``SeedSequence([seed, epoch, ...])``, and results are combined in task order, so a
seed gives the same run on every backend, and a resumed run continues exactly.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import gymnasium as gym
import numpy as np
import torch

from ..analysis.mesh import mesh_dimension
from ..analysis.postprocess import KINDS as POSTPROCESS_KINDS
from ..analysis.postprocess import MIN_POINTS, TRANSIENT_STEPS, PostProcessor
from ..analysis.variation import madogram, variogram
from ..envs import env_id
from ..envs.mujoco_batch import MujocoBatchEnv
from ..envs.mujoco_batch import supports as batch_supports
from ..parallel import BACKENDS, cached_env, make_backend
from ..systems import known_systems
from ..systems import load as load_system
from . import checkpoint as ckpt
from .config_check import check_types
from .base import Learner
from .checkpoint import PROGRESS_FILE, Saved
from .config_check import check_fields
from .run import EvalResult, check_finite, seeded, set_torch_threads


@dataclass
class ARSConfig:
    """Every ARS setting, with the thesis' value and its source."""

    step_size: float = 0.02          # alpha, thesis Ch. 4 (implementation notes)
    noise: float = 0.025             # sigma (exploration noise), thesis Ch. 4
    n_directions: int = 50           # N, thesis Ch. 4
    top_directions: int = 20         # b, thesis Ch. 4
    epochs: int = 1000               # thesis Ch. 4: 750 identity epochs + 250 with post-processing
    episode_steps: int | None = None  # None: the env's own limit (1000 for the MuJoCo locomotion envs)
    reward_shift: float = 0.0        # subtracted per step in training (Mania et al.: 1 for Hopper/Walker)
    policy: str = "linear"           # "linear" (thesis) or "mlp:H1,H2,..." (torch, tanh hidden units)
    postprocess: str = "identity"    # thesis Sec. 4.2.5: identity, mesh-lower, mesh-upper, mesh-mean, madogram,
    #                                  variogram
    postprocess_form: str = "auto"   # "divide" (eq. 4.4), "multiply" (eq. 6.2), "auto": by the return's sign
    transient_steps: int = TRANSIENT_STEPS  # T_r = 200, thesis Sec. 4.2.5
    train_action_noise: float = 0.0  # std of Gaussian noise on actions in training rollouts; thesis Ch. 5
    #                                  "noise" agents (Sec. 5.3 and its appendix): 0.01
    train_obs_noise: float = 0.0     # std of Gaussian noise on observations seen by the policy in training;
    #                                  thesis Ch. 5 "noise" agents: 0.001
    seed: int = 0
    backend: str = "processes"       # "serial", "processes" (local, default), "ray"
    workers: int | None = None       # None: every core (processes) or the cluster's CPUs (ray)
    address: str | None = None       # Ray cluster address (backend "ray"); None starts a local instance
    checkpoint_every: int = 10       # epochs between atomic checkpoints
    checkpoint_minutes: float = 5.0  # hybridctl: also a checkpoint at least every this many minutes of wall time
    #                                  (checked after each epoch), so a kill loses minutes at most (0: by epochs only)
    eval_episodes: int = 5           # thesis Ch. 4: 5 rollouts per seed for the metrics
    torch_threads: int = 1           # hybridctl: torch threads of the learner's own process (torch policies)
    engine: str = "auto"             # hybridctl: "auto" steps an epoch's rollouts together on the batched MuJoCo
    #                                  stepper (envs.mujoco_batch: Hopper/Walker2d/HalfCheetah v5, linear or fixed
    #                                  policies; bit-identical results) on `workers` threads when the backend is
    #                                  local (serial or processes), else on `backend`;
    #                                  "backend": always one rollout per task on `backend`

    def describe_budget(self) -> str:
        """The run's budget in a run's account."""
        return f"{self.epochs} epochs, seed {self.seed}, post-processor {self.postprocess}, backend {self.backend}"

    def validate(self) -> None:
        """Raise ValueError naming the first invalid field."""
        check_types(self)
        check_fields(self, positive=("step_size", "noise"), integers_from_1=(
            "n_directions", "top_directions", "epochs", "checkpoint_every", "eval_episodes", "torch_threads"),
            integers_from_0=("seed", "transient_steps"), non_negative=("train_action_noise", "train_obs_noise"))
        if self.workers is not None and self.workers < 1:
            raise ValueError(f"ARSConfig.workers must be None (every core) or an integer >= 1, got {self.workers!r}")
        if self.top_directions > self.n_directions:
            raise ValueError(f"ARSConfig.top_directions ({self.top_directions}) must be <= n_directions "
                             f"({self.n_directions})")
        if self.episode_steps is not None and (not isinstance(self.episode_steps, int) or self.episode_steps < 1):
            raise ValueError(f"ARSConfig.episode_steps must be None or an integer >= 1, got {self.episode_steps!r}")
        if self.postprocess not in POSTPROCESS_KINDS:
            raise ValueError(f"ARSConfig.postprocess must be one of {POSTPROCESS_KINDS}, got {self.postprocess!r}")
        if self.engine not in ENGINES:
            raise ValueError(f"ARSConfig.engine must be one of {ENGINES}, got {self.engine!r}")
        if self.backend not in BACKENDS:
            raise ValueError(f"ARSConfig.backend must be one of {BACKENDS}, got {self.backend!r}")
        _parse_policy(self.policy)
        self.postprocessor()

    def postprocessor(self) -> PostProcessor:
        """The reward post-processor these settings describe."""
        return PostProcessor(self.postprocess, transient_steps=self.transient_steps, form=self.postprocess_form)


ENGINES = ("auto", "backend")


def _parse_policy(text: str) -> tuple[int, ...] | None:
    """"linear" -> None; "mlp:64,64" -> (64, 64)."""
    if text == "linear":
        return None
    if text.startswith("mlp:"):
        try:
            sizes = tuple(int(h) for h in text[4:].split(",") if h)
        except ValueError:
            sizes = ()
        if sizes and all(h > 0 for h in sizes):
            return sizes
    raise ValueError(f"ARSConfig.policy must be 'linear' or 'mlp:H1,H2,...' (positive sizes), got {text!r}")


# ----------------------------------------------------------------------------- policies

def mlp_policy(obs_dim: int, act_dim: int, hidden: tuple[int, ...]) -> torch.nn.Module:
    """A tanh MLP with a tanh output (actions in [-1, 1], scaled to the action bounds by the rollout)."""
    layers, width = [], obs_dim
    for h in hidden:
        layers += [torch.nn.Linear(width, h), torch.nn.Tanh()]
        width = h
    layers += [torch.nn.Linear(width, act_dim), torch.nn.Tanh()]
    return torch.nn.Sequential(*layers).double()


class PolicySpec:
    """What a worker needs to rebuild a policy from a flat parameter vector (pickles)."""

    def __init__(self, obs_dim: int, act_dim: int, low: np.ndarray, high: np.ndarray,
                 module: torch.nn.Module | None = None, function: Callable | None = None):
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.low, self.high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
        self.module = module      # None: linear
        self.function = function  # a fixed policy obs -> action (no parameters), e.g. for robustness tests

    @property
    def n_params(self) -> int:
        """Length of theta."""
        if self.function is not None:
            return 0
        if self.module is None:
            return self.obs_dim * self.act_dim
        return sum(p.numel() for p in self.module.parameters())

    def initial_theta(self) -> np.ndarray:
        """Zero for the linear policy (Mania et al.); the module's own initialisation otherwise."""
        if self.module is None:
            return np.zeros(self.n_params)
        return torch.nn.utils.parameters_to_vector(self.module.parameters()).detach().double().numpy().copy()

    def actor(self, theta: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        """action(normalised obs) for these parameters, clipped to the action bounds."""
        if self.function is not None:
            return lambda z: np.clip(np.asarray(self.function(z), dtype=np.float64), self.low, self.high)
        if self.module is None:
            matrix = theta.reshape(self.act_dim, self.obs_dim)
            return lambda z: np.clip(matrix @ z, self.low, self.high)
        torch.nn.utils.vector_to_parameters(torch.as_tensor(theta, dtype=torch.float64), self.module.parameters())
        mid, half = (self.high + self.low) / 2, (self.high - self.low) / 2

        def act(z):
            with torch.no_grad():
                y = self.module(torch.as_tensor(z, dtype=torch.float64)).numpy()
            return mid + half * y
        return act


class FrozenPolicy:
    """A fixed ARS policy with frozen observation normalisation: ``policy(obs) -> action`` (pickles)."""

    def __init__(self, spec: PolicySpec, theta: np.ndarray, obs_mean: np.ndarray, obs_std: np.ndarray):
        # a torch policy gets its own module: the trainer's module is overwritten by every rollout
        self.spec = copy.deepcopy(spec) if spec.module is not None else spec
        self.theta = np.asarray(theta, dtype=np.float64)
        self.obs_mean, self.obs_std = np.asarray(obs_mean, dtype=np.float64), np.asarray(obs_std, dtype=np.float64)
        self._actor = None

    def __getstate__(self):
        return {**self.__dict__, "_actor": None}   # closures do not pickle: rebuilt on first call

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """The action for one observation (clipped to the action bounds)."""
        if self._actor is None:
            self._actor = self.spec.actor(self.theta)
        return self._actor((np.asarray(obs, dtype=np.float64) - self.obs_mean) / self.obs_std)

    def many(self, obs: np.ndarray) -> np.ndarray:
        """Actions (n, act_dim) for observations (n, obs_dim), equal bit for bit to calling the
        policy on each row (the normalisation and the clip are elementwise and run batched; the
        linear map runs row by row, the same matrix-vector product as one call)."""
        z = (np.asarray(obs, dtype=np.float64) - self.obs_mean) / self.obs_std
        if z.ndim != 2 or z.shape[1] != self.spec.obs_dim:
            raise ValueError(f"obs must have shape (n, {self.spec.obs_dim}), got {np.shape(obs)}")
        if self.spec.module is not None or self.spec.function is not None:
            return np.array([self(o) for o in obs], dtype=np.float64).reshape(len(z), self.spec.act_dim)
        matrix = self.theta.reshape(self.spec.act_dim, self.spec.obs_dim)
        z = np.ascontiguousarray(z)
        out = np.empty((z.shape[0], self.spec.act_dim))
        for i in range(z.shape[0]):
            out[i] = matrix @ z[i]
        return np.clip(out, self.spec.low, self.spec.high)


# ----------------------------------------------------------------------------- one rollout (runs in workers)

# An env id read from a FILE (a checkpoint's config.json) is data, never an import:
# gymnasium.make("module:Env-v0") imports `module` before it looks the id up. An id the user passes
# directly (ARS("mymod:Env-v0"), an env on the command line) is the user's own choice and is not checked.
ACCEPTED_IDS = ("a hybridctl system name or an id already registered in gymnasium.registry, "
                "without a 'module:' part")
"""What :func:`recorded_env_id` accepts, as the error messages say it."""


def _shown_value(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def recorded_env_id(value: Any, file: str | Path, key: str = "env") -> str:
    """``value`` (``file``'s ``key``) if it is a safe env id to hand to ``gymnasium.make``.

    Accepted: a hybridctl system name or an id already in ``gymnasium.registry`` (a dict lookup:
    nothing is imported, neither ``gym.make`` nor ``gym.spec`` is called), without a ``module:``
    part. Raises :class:`~hybridctl.learn.checkpoint.CheckpointError` naming the file, the key and
    what is accepted otherwise (a non-string too).
    """
    if not isinstance(value, str):
        raise ckpt.CheckpointError(f"{file}: {key!r} must be a string ({ACCEPTED_IDS}), got "
                                   f"{type(value).__name__} {_shown_value(value)}")
    if ":" in value:
        raise ckpt.CheckpointError(f"{file}: {key!r} is {_shown_value(value)}, whose 'module:' part would import "
                                   f"code named by a file; accepted: {ACCEPTED_IDS} (pass such an id yourself, "
                                   f"e.g. env=..., if you trust its module)")
    if value in known_systems(strict=False) or value in gym.registry:
        return value
    raise ckpt.CheckpointError(f"{file}: {key!r} is {_shown_value(value)}, not {ACCEPTED_IDS} (pass env=... to "
                               f"use another env)")


def recorded_env_kwargs(value: Any, file: str | Path, key: str = "env_kwargs") -> dict | None:
    """``value`` (``file``'s ``key``) if it is None or an object with string keys (the env's keyword arguments).

    Raises :class:`~hybridctl.learn.checkpoint.CheckpointError` naming the file and the key otherwise.
    """
    if value is None:
        return None
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        raise ckpt.CheckpointError(f"{file}: {key!r} must be null or an object of keyword arguments, got "
                                   f"{type(value).__name__} {_shown_value(value)}")
    return value


def make_env(env: str | Callable[[], gym.Env], env_kwargs: dict | None = None,
             max_steps: int | None = None) -> gym.Env:
    """A gymnasium env from an id (hybridctl system names map to their swing-up env) or a factory.

    ``max_steps`` replaces an id's time limit (e.g. 10,000-step robustness episodes); a factory's
    env keeps its own, and rollouts stop at ``max_steps`` anyway.
    """
    if callable(env):
        return env()
    name = env_id(env) if env in known_systems() else env
    kwargs = dict(env_kwargs or {})
    if max_steps is not None:
        kwargs["max_episode_steps"] = max_steps
    return gym.make(name, **kwargs)


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
    return _episode_result(task, np.stack(states), raw_return, shifted, steps, bool(terminated))


def _episode_result(task: RolloutTask, x: np.ndarray, raw_return: float, shifted: float, steps: int,
                    terminated: bool) -> dict:
    """What :func:`run_episode` returns for an episode of observations ``x`` (steps + 1 rows)."""
    if not np.all(np.isfinite(x)) or not math.isfinite(raw_return):
        return {"finite": False, "steps": steps}
    processed, info = task.postprocessor(x, shifted)
    out = {"finite": True, "return": processed, "raw_return": raw_return, "steps": steps,
           "terminated": bool(terminated), "dimension": info["dimension"], "reason": info["reason"],
           "sum": x[:-1].sum(axis=0), "sumsq": (x[:-1] ** 2).sum(axis=0), "count": x.shape[0] - 1}
    if task.keep_states:
        out["states"] = x
    if task.measure:
        out["dimensions"] = measure_dimensions(x, task.postprocessor.transient_steps)
    return out


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
    return [_episode_result(t, states[i, :steps[i] + 1], float(raw[i]), float(shifted[i]), int(steps[i]),
                            bool(terminated[i])) for i, t in enumerate(tasks)]


def rollouts(tasks: list[RolloutTask], backend, engine: str = "auto", nthread: int | None = None) -> list[dict]:
    """:func:`run_episode` of every task: batched on this machine's MuJoCo threads (``engine="auto"``,
    :func:`batchable` tasks and a local backend; ``nthread`` threads, default every core) or on
    ``backend`` (always on a Ray backend, which may reach a cluster's CPUs)."""
    if engine == "auto" and getattr(backend, "name", "serial") != "ray" and batchable(tasks):
        threads = nthread or (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count())
        return run_episodes_batched(tasks, max(1, int(threads or 1)))
    return backend.map(run_episode, tasks)


def measure_dimensions(states: np.ndarray, transient_steps: int = TRANSIENT_STEPS) -> dict:
    """Raw (unclipped) lower/upper mesh dimension, madogram and variogram of the states after the
    transient (thesis Table 4.1 metrics); None where the episode is too short to measure."""
    tail = states[transient_steps:]
    if tail.shape[0] < MIN_POINTS:
        return {"mesh_lower": None, "mesh_upper": None, "madogram": None, "variogram": None}
    md = mesh_dimension(tail)
    return {"mesh_lower": md.lower, "mesh_upper": md.upper, "madogram": madogram(tail), "variogram": variogram(tail)}


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


# ----------------------------------------------------------------------------- running normalisation

class RunningStats:
    """Mean and std of every state seen (merged in task order, so identical on every backend)."""

    def __init__(self, dim: int):
        self.count, self.sum, self.sumsq = 0, np.zeros(dim), np.zeros(dim)

    def add(self, total: np.ndarray, total_sq: np.ndarray, count: int) -> None:
        """Merge sums of ``count`` states."""
        self.sum += total
        self.sumsq += total_sq
        self.count += count

    @property
    def mean(self) -> np.ndarray:
        """Running mean (0 before any data)."""
        return self.sum / self.count if self.count else np.zeros_like(self.sum)

    @property
    def std(self) -> np.ndarray:
        """Running std; 1 where the variance is below 1e-8 (constant coordinates), as in Mania et al."""
        if self.count < 2:
            return np.ones_like(self.sum)
        var = np.maximum(self.sumsq / self.count - self.mean ** 2, 0.0)
        return np.where(var < 1e-8, 1.0, np.sqrt(var))


# ----------------------------------------------------------------------------- the algorithm

class ARS(Learner):
    """ARS V2-t with optional dimension post-processing: ``learn`` / ``predict`` / ``evaluate`` / ``save`` / ``load``."""

    algorithm_name = "ARS"
    config_class = ARSConfig
    budget_field, unit, uses_backend = "epochs", "epoch", True
    takes_gym_envs, warm_starts = True, True
    record_evaluation = {"measure": True}   # eval.json: the raw dimensions of every episode too
    load_keywords = ("policy",)
    log_key = "epoch"
    log_columns = ("epoch", "env_steps", "mean_return", "max_return", "mean_raw_return", "mean_dimension", "sigma_r",
                   "episode_steps", "wall_time", "steps_per_s")
    log_int_columns = ("epoch", "env_steps")
    log_float_format = None   # full precision, as the log always had
    # what a checkpoint holds, declared once: parameters and normalisation sums (model.pt), the
    # torch module's weights at theta (torch policies), counters and the epoch history (progress.json)
    saved = (Saved("theta", "theta", "array"), Saved("stats_sum", "stats.sum", "array"),
             Saved("stats_sumsq", "stats.sumsq", "array"), Saved("stats_count", "stats.count", load=int),
             Saved("module_state", "policy.module", "state", optional=True),
             Saved("epoch", "epoch", file=PROGRESS_FILE, load=int),
             Saved("env_steps", "env_steps", file=PROGRESS_FILE, load=int),
             Saved("wall_time", "wall_time", file=PROGRESS_FILE, load=float),
             Saved("history", "history", file=PROGRESS_FILE, optional=True, load=list))

    def __init__(self, env: str | Callable[[], gym.Env], config: ARSConfig | None = None,
                 env_kwargs: dict | None = None, policy: torch.nn.Module | None = None, **overrides):
        self.config = dataclasses.replace(config or ARSConfig(), **overrides)
        self.config.validate()
        set_torch_threads(self.config.torch_threads)
        self.env, self.env_kwargs = env, env_kwargs
        probe = make_env(env, env_kwargs)
        if not isinstance(probe.action_space, gym.spaces.Box):
            raise ValueError(f"ARS needs a continuous (Box) action space, got {probe.action_space}")
        obs_dim = int(np.prod(probe.observation_space.shape))
        act_dim = int(np.prod(probe.action_space.shape))
        hidden = _parse_policy(self.config.policy)
        if policy is not None:
            module = policy.double()
        elif hidden:
            with seeded(self.config.seed):  # the MLP's initial weights follow the seed, the global RNG is kept
                module = mlp_policy(obs_dim, act_dim, hidden)
        else:
            module = None
        self.policy = PolicySpec(obs_dim, act_dim, probe.action_space.low, probe.action_space.high, module)
        self.env_name = env if isinstance(env, str) else getattr(env, "__name__", repr(env))
        probe.close()
        self.theta = self.policy.initial_theta()
        self.stats = RunningStats(obs_dim)
        self.epoch, self.env_steps, self.wall_time = 0, 0, 0.0
        self.history: list[dict] = []
        self.log_rows: list[dict] = []

    def training_record(self) -> dict:
        """eval.json's training counters: epochs, env steps, wall time."""
        return {"epochs": self.epoch, "env_steps": self.env_steps, "train_wall_time_s": self.wall_time}

    @property
    def progress_count(self) -> int:
        """Epochs so far (the progress.csv key)."""
        return self.epoch

    # -- rollouts ------------------------------------------------------------------------
    def _tasks(self, thetas: list[np.ndarray], seeds: list[int], max_steps: int | None = None,
                reward_shift: float | None = None, postprocessor: PostProcessor | None = None,
                **options) -> list[RolloutTask]:
        """One rollout task per (theta, seed); ``options``: keep_states, action_noise, obs_noise, push."""
        cfg = self.config
        mean, std = self.stats.mean, self.stats.std
        return [RolloutTask(self.env, self.env_kwargs, self.policy, th, mean, std, s, max_steps or cfg.episode_steps,
                            cfg.reward_shift if reward_shift is None else reward_shift,
                            postprocessor or cfg.postprocessor(), **options)
                for th, s in zip(thetas, seeds)]

    def _epoch_draws(self, epoch: int) -> tuple[np.ndarray, list[int]]:
        """Directions (N, n_params) and one env seed per direction for ``epoch`` (from the seed alone)."""
        seq = np.random.SeedSequence([self.config.seed, epoch])
        rng = np.random.default_rng(seq)
        directions = rng.standard_normal((self.config.n_directions, self.policy.n_params))
        seeds = [int(s) for s in rng.integers(0, 2 ** 31 - 1, size=self.config.n_directions)]
        return directions, seeds

    def train_epoch(self, backend) -> dict:
        """One ARS V2-t update: 2N rollouts, top-b directions, step scaled by the kept returns' std."""
        cfg = self.config
        directions, seeds = self._epoch_draws(self.epoch)
        thetas = [self.theta + sign * cfg.noise * d for d in directions for sign in (1.0, -1.0)]
        tasks = self._tasks(thetas, [s for s in seeds for _ in (0, 1)], action_noise=cfg.train_action_noise,
                            obs_noise=cfg.train_obs_noise)
        results = rollouts(tasks, backend, cfg.engine, cfg.workers)
        bad = [i for i, r in enumerate(results) if not r["finite"]]
        if bad:
            raise FloatingPointError(f"ARS epoch {self.epoch}: {len(bad)} rollouts produced NaN/inf states or "
                                     f"rewards (first: direction {bad[0] // 2}); training stopped, the last "
                                     f"checkpoint is intact")
        r = np.array([res["return"] for res in results]).reshape(cfg.n_directions, 2)
        top = np.argsort(-np.max(r, axis=1), kind="stable")[:cfg.top_directions]
        sigma_r = r[top].std()
        step = (r[top, 0] - r[top, 1]) @ directions[top]
        if sigma_r > 0:
            theta = self.theta + cfg.step_size / (cfg.top_directions * sigma_r) * step
            check_finite("ARS theta", theta, f"at epoch {self.epoch + 1}")
            self.theta = theta
        for res in results:  # V2: update the normalisation after the epoch, in task order
            self.stats.add(res["sum"], res["sumsq"], res["count"])
        steps = sum(res["steps"] for res in results)
        self.env_steps += steps
        self.epoch += 1
        return {"epoch": self.epoch, "env_steps": self.env_steps, "mean_return": float(r.mean()),
                "max_return": float(r.max()), "mean_raw_return": float(np.mean([x["raw_return"] for x in results])),
                "mean_dimension": float(np.mean([x["dimension"] for x in results])), "sigma_r": float(sigma_r),
                "episode_steps": steps / len(results)}

    def run_description(self) -> str:
        """The progress bar's label."""
        return f"ARS {self.env_name}"

    def train(self, run, target: int, backend) -> None:
        """ARS's loop inside ``learn``'s run: one epoch (2 x ``n_directions`` rollouts on ``backend``,
        default the config's, opened for the run) per update, a checkpoint every ``checkpoint_every``
        epochs and at least every ``checkpoint_minutes``."""
        own_backend = backend is None
        pool = backend or make_backend(self.config.backend, self.config.workers, self.config.address)
        try:
            run.updates(target, lambda: self.train_epoch(pool), 2 * self.config.n_directions,
                        self.config.checkpoint_every,
                        lambda row: {"ret": f"{row['mean_raw_return']:.1f}", "dim": f"{row['mean_dimension']:.2f}",
                                     "sps": f"{row['steps_per_s']:.0f}"})
        finally:
            if own_backend:
                pool.close()

    # -- use ---------------------------------------------------------------------------------
    def frozen_policy(self) -> "FrozenPolicy":
        """The current policy with its normalisation, as a plain picklable callable obs -> action
        (for section maps and other code that runs the policy in worker processes)."""
        return FrozenPolicy(self.policy, self.theta.copy(), self.stats.mean.copy(), self.stats.std.copy())

    def predict(self, obs: np.ndarray, deterministic: bool = True) -> np.ndarray:
        """The policy's action for ``obs`` (ARS policies are deterministic)."""
        frozen = getattr(self, "_predictor", None)
        # reuse the frozen policy while theta and the normalisation are unchanged (building a torch
        # policy's actor loads its weights, too slow to repeat every step)
        if frozen is None or not (np.array_equal(frozen.theta, self.theta) and np.array_equal(
                frozen.obs_mean, self.stats.mean) and np.array_equal(frozen.obs_std, self.stats.std)):
            frozen = self._predictor = self.frozen_policy()
        return frozen(obs)

    def run_evaluation(self, episodes: int, seed: int, episode_steps: int | None = None,
                       postprocess: str = "identity", backend=None, keep_states: bool = False, measure: bool = False,
                       **noise) -> EvalResult:
        """``evaluate(episodes, seed=, ...)``: deterministic rollouts of the current policy: raw
        returns, episode lengths, dimensions.

        ``measure``: also the raw lower/upper mesh dimension, madogram and variogram of every
        episode (after the transient) and their means (``mean_dimensions``).

        ``noise``: ``action_noise``, ``obs_noise`` (std of Gaussian noise) or ``push``
        (probability per step, magnitude); see :func:`hybridctl.learn.robustness`.
        """
        n = episodes
        seeds = [int(s) for s in np.random.default_rng(seed).integers(0, 2 ** 31 - 1, size=n)]
        pp = PostProcessor(postprocess, transient_steps=self.config.transient_steps)
        tasks = self._tasks([self.theta] * n, seeds, max_steps=episode_steps, reward_shift=0.0, postprocessor=pp,
                            keep_states=keep_states, measure=measure, **noise)
        results = rollouts(tasks, backend or make_backend("serial"), self.config.engine, self.config.workers)
        finite = [r for r in results if r["finite"]]
        returns = np.array([r["raw_return"] for r in finite])
        out = EvalResult.from_returns(  # success_rate None: a gym env has no thesis success test
            returns, first={"episodes": n, "seed": seed}, steps=[r["steps"] for r in results],
            terminated=[r.get("terminated", True) for r in results], nonfinite=n - len(finite),
            dimension=[r["dimension"] for r in finite])
        if keep_states:
            out["states"] = [r["states"] for r in finite]
        if measure:
            out["dimensions"] = [r["dimensions"] for r in finite]
            out["mean_dimensions"] = {
                key: (float(np.mean(vals)) if (vals := [d[key] for d in out["dimensions"] if d[key] is not None])
                      else None) for key in ("mesh_lower", "mesh_upper", "madogram", "variogram")}
        return out

    # -- checkpoints ---------------------------------------------------------------------------
    def before_checkpoint(self) -> None:
        """Rollouts leave perturbed weights in a torch policy's module: put theta's back before saving."""
        if self.policy.module is not None:
            self.policy.actor(self.theta)

    def system_record(self) -> dict:
        """config.json's ``system``: a hybridctl system's record (spec values too) with the env's
        keyword arguments, or a gymnasium env's id and keyword arguments."""
        if isinstance(self.env, str) and self.env in known_systems():
            return {**ckpt.system_record(load_system(self.env)), "kwargs": ckpt.to_jsonable(self.env_kwargs or {})}
        return ckpt.env_record(self.env_name, self.env_kwargs)

    def checkpoint_extra(self) -> dict:
        """config.json beside algorithm, system and config: the policy's dimensions."""
        return {"obs_dim": self.policy.obs_dim, "act_dim": self.policy.act_dim}

    def check_checkpoint(self, found: Path, meta: dict, normalization: dict, force: bool = False) -> None:
        """The checkpoint must come from this env (id and kwargs; a system's spec values too) and
        hold a running-mean-std normalisation of this observation size (``force``: a warning)."""
        problems = []
        recorded = meta.get("system") or {}
        if recorded.get("name") != self.env_name:
            problems.append(f"checkpoint {found} was trained on env {recorded.get('name')!r}; this env is "
                            f"{self.env_name!r}")
        elif (recorded.get("kwargs") or {}) != ckpt.to_jsonable(self.env_kwargs or {}):
            problems.append(f"checkpoint {found} was trained on {self.env_name} with env_kwargs "
                            f"{recorded.get('kwargs')}; this env has {self.env_kwargs}")
        if not ckpt.refuse_unless_forced(problems, force) and "spec_hash" in recorded and isinstance(self.env, str) \
                and self.env in known_systems():
            ckpt.check_plant(found, recorded, load_system(self.env), force)
        if normalization.get("type") != "running_mean_std" or len(normalization.get("mean", [])) != \
                self.policy.obs_dim:
            raise ckpt.CheckpointError(f"{found / ckpt.NORMALIZATION_FILE} is damaged or not an ARS normalisation of "
                                       f"{self.policy.obs_dim} observations: {str(normalization)[:120]}")

    def normalization(self) -> dict:
        """normalization.json: the running mean and std (model.pt holds the exact sums)."""
        return {"type": "running_mean_std", "mean": self.stats.mean, "std": self.stats.std, "count": self.stats.count}

    @classmethod
    def from_checkpoint(cls, found: Path, meta: dict, config, system, force: bool,
                        policy: torch.nn.Module | None = None) -> "ARS":
        """:meth:`~hybridctl.learn.base.Learner.load`'s learner: on ``system`` (a gymnasium env id, a
        system name or an env factory; None: the recorded id, required when it was trained on a
        factory), with ``policy`` when it was trained with a custom torch module. The recorded id is
        data: one with a ``module:`` part (which would import code) is refused."""
        record = meta.get("system")
        if not isinstance(record, dict) or "obs_dim" not in meta:
            raise ckpt.CheckpointError(f"{found / ckpt.CONFIG_FILE} is damaged or not an ARS checkpoint's: it "
                                       f"lacks 'system' or 'obs_dim'")
        env = system if system is not None else recorded_env_id(record.get("name"), found / ckpt.CONFIG_FILE,
                                                                 "system.name")
        env_kwargs = recorded_env_kwargs(record.get("kwargs"), found / ckpt.CONFIG_FILE, "system.kwargs")
        agent = cls(env, config, env_kwargs=env_kwargs, policy=policy)
        if (agent.policy.obs_dim, agent.policy.act_dim) != (meta["obs_dim"], meta["act_dim"]):
            raise ckpt.CheckpointError(
                f"{found} was trained on {record.get('name')} with {meta['obs_dim']} observations and "
                f"{meta['act_dim']} actions; this env has {agent.policy.obs_dim} and {agent.policy.act_dim}")
        return agent
