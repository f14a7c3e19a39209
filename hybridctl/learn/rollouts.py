"""One rollout module: the episodes of antithetic random search (ARS, fine-tuning) and of the
robustness measures, with one result format.

What to roll out is a list of tasks (plain, picklable objects) for a :mod:`hybridctl.parallel`
backend; :func:`rollouts` runs them and returns one result dict per episode, in task order.
Two execution strategies, kept apart because each reproduces its learner's numbers bit for bit:

* :class:`RolloutTask` -- ONE episode of a flat-parameter policy (:class:`PolicySpec`: ARS's
  linear map, a torch module loaded by ``vector_to_parameters``, or a fixed function) behind a
  frozen affine normalisation, with optional action / observation noise and pushes
  (thesis Sec. 4.3). One task per backend job (:func:`run_episode`, a gymnasium env), or a
  whole batch stepped together on the MuJoCo batch stepper
  (:class:`~hybridctl.envs.mujoco_batch.MujocoBatchEnv`, :func:`run_episodes_batched`,
  ``engine="auto"``). ARS and :func:`~hybridctl.learn.robustness.failure_rates` use it.
* :class:`ChunkTask` -- a chunk of B episodes of a torch module whose named parameters
  come from the rows of ``thetas``: one ``torch.func.vmap`` forward of ``functional_call`` per
  env step, over gymnasium envs, the MuJoCo batch stepper (one thread), or a hybridctl
  system's batched torch dynamics (SSAC: gate + LQR inside; a recurrent APG-family swing-up with the
  spec's cost-to-go gate and its hidden state carried per episode), the latter on any torch device
  with no copy to the host until the chunk ends. What every chunk of a batch reads and none
  changes (the policy, its normaliser, the post-processor: :class:`ChunkInputs`) is shipped
  once per batch (``backend.put``; the tasks carry the reference). :func:`chunk_slices` splits
  a batch into chunks, by default from the backend's worker count. Fine-tuning uses it.

Every result: ``finite`` (False: only ``steps`` follows), ``return`` (post-processed by the
task's :class:`~hybridctl.analysis.PostProcessor`, e.g. the dimension reward), ``raw_return``,
``steps``, ``terminated``, ``success`` (the thesis success test on a hybridctl system, else
None), ``dimension``, ``reason``, ``sum`` / ``sumsq`` / ``count`` (of the episode's states but
the last: ARS's running normalisation), and on request ``states`` (what the post-processor saw:
observations, normalised by the frozen normaliser in a chunk) and ``dimensions``
(:func:`measure_dimensions`).

The env side (:func:`make_env`, and :func:`recorded_env_id` / :func:`recorded_env_kwargs` for
ids read from files) lives here too.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import gymnasium as gym
import numpy as np
import torch
from torch.func import functional_call, vmap

from ..analysis.mesh import mesh_dimension
from ..analysis.postprocess import MIN_POINTS, TRANSIENT_STEPS, PostProcessor
from ..analysis.variation import madogram, variogram
from ..envs import env_id
from ..envs.mujoco_batch import MujocoBatchEnv
from ..envs.mujoco_batch import supports as batch_supports
from ..parallel import cached_env
from ..systems import known_systems
from ..systems import load as load_system
from . import checkpoint as ckpt

# ----------------------------------------------------------------------------- envs


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
    """``value`` (``file``'s ``key``) if it is None or safe keyword arguments of an env
    (:func:`hybridctl.learn.checkpoint_schema.check_env_kwargs`).

    Raises :class:`~hybridctl.learn.checkpoint.CheckpointError` naming the file and the key otherwise.
    """
    return ckpt.check_env_kwargs(value, file, key)   # known keys, plain values, render_mode never "human"


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



# ----------------------------------------------------------------------------- policies

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


class Shipped:
    """A torch module sent to workers as plain pickled bytes, decoded once per worker.

    A module inside a task would otherwise travel by torch's shared-memory file descriptors,
    whose hand-over hangs after a process pool was rebuilt (a worker killed); bytes always
    arrive. The bytes are made by this process from its own module, never read from a file.
    """

    _decoded: dict[str, torch.nn.Module] = {}

    def __init__(self, module: torch.nn.Module | None):
        import hashlib
        import pickle

        self.blob = pickle.dumps(module) if module is not None else None
        self.key = hashlib.sha1(self.blob).hexdigest() if self.blob is not None else ""

    def get(self) -> torch.nn.Module | None:
        """The module (built from the bytes once per process)."""
        import pickle

        if self.blob is None:
            return None
        if self.key not in Shipped._decoded:
            Shipped._decoded.clear()   # one module at a time per worker
            Shipped._decoded[self.key] = pickle.loads(self.blob)
        return Shipped._decoded[self.key]


@dataclass
class ChunkInputs:
    """What every chunk of one batch of rollouts reads and none changes (plain, picklable): shipped
    once per batch with ``backend.put`` (Ray: one copy in the object store), the tasks carry the
    reference (:attr:`ChunkTask.inputs`)."""

    shipped: Shipped              # the policy module (non-perturbed parameters at their values)
    names: list[str]              # the perturbed parameters, in the order of a theta row
    normalizer: Any               # frozen observation normaliser (None: observations as they are)
    postprocessor: PostProcessor
    gate: Shipped | str | None = None   # SSAC's gate, or COST_TO_GO_GATE (the spec's, built in the worker): the
    #                                     switched dynamics, gate + LQR inside the rollout; None: no gate


def shared_value(value: Any) -> Any:
    """The value behind ``backend.put(value)``'s result, in a worker: ``ray.get`` of a Ray object
    reference (Ray resolves references only where they are a task's own argument, not inside
    one), the value itself from every other backend (their ``put`` is the identity)."""
    ray = sys.modules.get("ray")   # a Ray reference exists only where ray is imported already
    if ray is not None and isinstance(value, getattr(ray, "ObjectRef", ())):
        return ray.get(value)
    return value


@dataclass
class ChunkTask:
    """Episodes of ``len(seeds)`` policies (rows of ``thetas``), one per env seed (plain, picklable)."""

    env: Any
    env_kwargs: dict | None
    inputs: Any                   # a ChunkInputs, or the reference backend.put returned for it
    thetas: np.ndarray            # (B, P) float64
    seeds: list[int]
    max_steps: int | None
    system: str | None = None     # a hybridctl system's name: its batched torch dynamics (sac/ssac policies)
    keep_states: bool = False
    engine: str = "auto"          # "auto": the MuJoCo batch stepper where it applies; "backend": gymnasium envs
    device: str = "cpu"           # where a system's rollout runs (gymnasium and MuJoCo envs step on the host)
    system_overrides: dict | None = None   # the system's spec overrides (a checkpoint's reward, starts)
    decision_period: float | None = None   # a system's swing-up decision period (None: the spec's swingup_period)

    @property
    def shared(self) -> ChunkInputs:
        """The batch's shared inputs (fetched from the object store where :attr:`inputs` is a reference)."""
        return shared_value(self.inputs)

    @property
    def module(self) -> torch.nn.Module:
        """The policy module (non-perturbed parameters at their values; perturbed ones come from thetas)."""
        return self.shared.shipped.get()

    @property
    def names(self) -> list[str]:
        """The perturbed parameters' names, in the order of a theta row."""
        return self.shared.names

    @property
    def normalizer(self):
        """The frozen observation normaliser (None: none)."""
        return self.shared.normalizer

    @property
    def postprocessor(self) -> PostProcessor:
        """The return post-processor."""
        return self.shared.postprocessor


AUTO_CHUNK_MAX = 64
"""Largest chunk :func:`chunk_slices` makes by itself on the CPU (the fixed size of earlier versions):
more rows gain a CPU worker little, and smaller chunks leave other workers something to do."""
AUTO_CHUNK_MAX_ACCELERATOR = 4096
"""Largest automatic chunk of a system's rollouts on an accelerator, where one wide batch is the point."""
TASKS_PER_WORKER = 2
"""Automatic chunking gives every worker at least this many tasks (where there are rows enough), so a
worker that finishes early finds another."""


def chunk_slices(total: int, chunk_size: int | None, workers: int = 1, largest: int = AUTO_CHUNK_MAX) -> list[slice]:
    """The row ranges of the chunks of a batch of ``total`` rollouts.

    ``chunk_size`` an int: consecutive chunks of that many rows (the last one shorter). None
    ("auto"): near-equal chunks (sizes differ by at most one), enough that each of the backend's
    ``workers`` gets :data:`TASKS_PER_WORKER` of them, none larger than ``largest`` and none of a
    single row (where ``total`` >= 2). Chunks of 2 rows or more give the same numbers bit for bit
    whatever their size (measured on gymnasium, MuJoCo and system envs); a one-row chunk of a
    system's float64 CPU rollout takes :meth:`~hybridctl.systems.System.step`'s plain-float path,
    which can differ from the batched one in the last bit.
    """
    if total < 1:
        return []
    if chunk_size is not None:
        return [slice(i, min(i + chunk_size, total)) for i in range(0, total, chunk_size)]
    chunks = max(-(-total // largest), TASKS_PER_WORKER * max(1, int(workers)))
    chunks = max(1, min(chunks, total // 2))
    base, extra = divmod(total, chunks)
    bounds = np.cumsum([0] + [base + 1] * extra + [base] * (chunks - extra))
    return [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


def unflatten(module: torch.nn.Module, names: list[str], thetas: torch.Tensor) -> dict[str, torch.Tensor]:
    """{name: (B, *shape)} from flat rows (B, P), in each parameter's dtype."""
    params = dict(module.named_parameters())
    out, start = {}, 0
    for name in names:
        p = params[name]
        out[name] = thetas[:, start:start + p.numel()].reshape(thetas.shape[0], *p.shape).to(p.dtype)
        start += p.numel()
    return out


def batched_actions(module: torch.nn.Module, params: dict[str, torch.Tensor], obs: torch.Tensor) -> torch.Tensor:
    """Actions (B, act) of B policies (module with ``params`` row b) for observations (B, obs): one vmapped forward."""
    with torch.no_grad():
        return vmap(lambda p, o: functional_call(module, p, (o,)))(params, obs)


def batched_recurrent_actions(module: torch.nn.Module, params: dict[str, torch.Tensor], obs: torch.Tensor,
                              state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(actions (B, act), next states (B, hidden)) of B recurrent policies, ``module(obs, state) -> (action,
    state)`` with ``params`` row b, for observations (B, obs) and their states (B, hidden): one vmapped forward."""
    with torch.no_grad():
        return vmap(lambda p, o, h: functional_call(module, p, (o, h)))(params, obs, state)


def is_recurrent(module: torch.nn.Module) -> bool:
    """True for a policy that carries a state: ``forward(x, state) -> (action, state)`` with
    ``initial_state(batch)`` (an APG-family :class:`~hybridctl.learn.apg.ClosedLoopPolicy`)."""
    return callable(getattr(module, "initial_state", None))


# ----------------------------------------------------------------------------- one result format

def episode_result(states: np.ndarray, raw_return: float, shifted_return: float, steps: int, terminated: bool,
                   postprocessor: PostProcessor, *, finite: bool = True, success: bool | None = None,
                   keep_states: bool = False, measure: bool = False) -> dict:
    """The result of one episode of ``states`` (steps + 1 rows), in the one format of this module.

    ``shifted_return`` is what the post-processor gets (ARS: the raw return less ``reward_shift``
    per step; fine-tuning: the raw return); ``finite`` False (or a NaN/inf state or return)
    gives ``{"finite": False, "steps": steps}``.
    """
    if not finite or not math.isfinite(raw_return) or not np.all(np.isfinite(states)):
        return {"finite": False, "steps": steps}
    processed, info = postprocessor(states, float(shifted_return))
    out = {"finite": True, "return": float(processed), "raw_return": float(raw_return), "steps": int(steps),
           "terminated": bool(terminated), "success": success, "dimension": info["dimension"],
           "reason": info["reason"], "sum": states[:-1].sum(axis=0), "sumsq": (states[:-1] ** 2).sum(axis=0),
           "count": states.shape[0] - 1}
    if keep_states:
        out["states"] = states
    if measure:
        out["dimensions"] = measure_dimensions(states, postprocessor.transient_steps)
    return out


# ----------------------------------------------------------------------------- episode tasks

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


def rollouts(tasks: list[RolloutTask] | list[ChunkTask], backend, engine: str = "auto",
             nthread: int | None = None) -> list[dict]:
    """Every episode of ``tasks`` on ``backend``: one result dict per episode, in task order.

    Chunk tasks: one backend job per chunk (:func:`run_chunk`). Episode tasks: batched on this
    machine's MuJoCo threads (``engine="auto"``, :func:`batchable` tasks and a local backend;
    ``nthread`` threads, default every core), else one :func:`run_episode` per job (always on a
    Ray backend, which may reach a cluster's CPUs).
    """
    if tasks and isinstance(tasks[0], ChunkTask):
        return [r for chunk in backend.map(run_chunk, tasks) for r in chunk]
    if engine == "auto" and getattr(backend, "name", "serial") != "ray" and batchable(tasks):
        threads = nthread or (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count())
        return run_episodes_batched(tasks, max(1, int(threads or 1)))
    return backend.map(run_episode, tasks)


def evaluation_seeds(seed: int, episodes: int) -> list[int]:
    """The env seeds of ``episodes`` held-out episodes (evaluations, failure rates) from ``seed``."""
    return [int(s) for s in np.random.default_rng(seed).integers(0, 2 ** 31 - 1, size=episodes)]


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



# ----------------------------------------------------------------------------- chunk tasks

def run_chunk(task: ChunkTask) -> list[dict]:
    """Roll out one episode per row of ``task.thetas``; one result dict per row, in row order."""
    torch.set_num_threads(1)
    task = dataclasses.replace(task, inputs=task.shared)   # fetched once per task (Ray: from the object store)
    if task.system is not None:
        return _run_system_chunk(task)
    if task.engine == "auto" and batch_supports(task.env, task.env_kwargs):
        return _run_mujoco_chunk(task)
    n = len(task.seeds)
    envs = cached_env(("finetune", repr(task.env), repr(task.env_kwargs), task.max_steps, n),
                      lambda: [make_env(task.env, task.env_kwargs, task.max_steps) for _ in range(n)])
    module, params = _host_policy(task)
    space = envs[0].action_space
    obs = np.stack([np.asarray(e.reset(seed=int(s))[0], dtype=np.float64).reshape(-1) for e, s in zip(envs, task.seeds)])
    z = normalise(task.normalizer, obs)
    history = [z.copy()]          # normalised observations of every member at each step (one copy per step)
    returns, rewards, steps = np.zeros(n), np.zeros(n), np.zeros(n, dtype=int)
    active, terminated, finite, success = np.ones(n, bool), np.zeros(n, bool), np.ones(n, bool), [None] * n
    limit = task.max_steps or math.inf
    while active.any():
        actions = _host_actions(module, params, z)
        actions = actions.astype(space.dtype, copy=False).reshape((n, *space.shape))
        stepped = np.flatnonzero(active)
        for i in stepped:
            o, r, term, trunc, info = envs[i].step(actions[i])
            obs[i], rewards[i] = o, r
            if term or trunc:
                active[i], terminated[i] = False, bool(term)
                if "success" in info:
                    success[i] = bool(info["success"])
        returns[stepped] += rewards[stepped]
        z = _after_step(task, obs, returns, steps, stepped, finite, active, limit, history)
    return _chunk_results(task, history, returns, steps, terminated, finite, success)


def _host_policy(task: ChunkTask) -> tuple[torch.nn.Module, dict[str, torch.Tensor]]:
    """The policy module on the CPU and the chunk's parameter rows for it: gymnasium and MuJoCo envs
    step on the host, so their policies run there (their observations and actions are numpy)."""
    module = task.module.to("cpu")
    rows = torch.as_tensor(task.thetas, dtype=torch.float64, device="cpu")
    return module, unflatten(module, task.names, rows)


def _host_actions(module: torch.nn.Module, params: dict[str, torch.Tensor], z: np.ndarray) -> np.ndarray:
    """The chunk's actions (numpy) for normalised observations ``z`` (numpy) on the host."""
    dtype = next(module.parameters()).dtype
    return batched_actions(module, params, torch.as_tensor(z, dtype=dtype, device="cpu")).numpy()


def _after_step(task: ChunkTask, obs, returns, steps, stepped, finite, active, limit, history) -> np.ndarray:
    """Book-keeping after the ``stepped`` episodes took a step (their rewards already in ``returns``):
    count the step, stop non-finite and over-long episodes, record and return the normalised observations."""
    steps[stepped] += 1
    bad = stepped[~(np.isfinite(obs[stepped]).all(axis=1) & np.isfinite(returns[stepped]))]
    finite[bad], active[bad] = False, False
    active &= steps < limit
    z = normalise(task.normalizer, obs)
    history.append(z.copy())
    return z


def _chunk_results(task: ChunkTask, history, returns, steps, terminated, finite, success) -> list[dict]:
    """One result per episode of a chunk; member i's episode is states[: steps[i] + 1, i]."""
    states = np.stack(history)    # (T + 1, n, obs)
    return [episode_result(states[: steps[i] + 1, i], returns[i], returns[i], int(steps[i]), bool(terminated[i]),
                           task.postprocessor, finite=bool(finite[i]), success=None if success is None else success[i],
                           keep_states=task.keep_states) for i in range(len(steps))]


def _run_mujoco_chunk(task: ChunkTask) -> list[dict]:
    """:func:`run_chunk` on a Hopper/Walker2d/HalfCheetah v5 env: the chunk's episodes stepped together
    on :class:`~hybridctl.envs.mujoco_batch.MujocoBatchEnv` (one thread; the backend's workers run the
    chunks side by side). Bit-identical to the gymnasium loop of :func:`run_chunk` (tested)."""
    n = len(task.seeds)
    env = cached_env(("finetune-batch", task.env, repr(task.env_kwargs), n),
                     lambda: MujocoBatchEnv(task.env, num_envs=n, nthread=1, env_kwargs=task.env_kwargs))
    module, params = _host_policy(task)
    space = env.action_space
    obs = env.reset(task.seeds)
    z = normalise(task.normalizer, obs)
    history = [z.copy()]
    returns, steps = np.zeros(n), np.zeros(n, dtype=int)
    active, terminated, finite = np.ones(n, bool), np.zeros(n, bool), np.ones(n, bool)
    limit = task.max_steps or env.max_episode_steps or math.inf
    while active.any():
        actions = _host_actions(module, params, z)
        actions = actions.astype(space.dtype, copy=False).reshape((n, *space.shape))
        stepped = np.flatnonzero(active)
        o, r, term, _ = env.step(actions[stepped], ids=stepped)
        obs[stepped] = o
        terminated[stepped] = term
        active[stepped[term]] = False
        returns[stepped] += r
        z = _after_step(task, obs, returns, steps, stepped, finite, active, limit, history)
    return _chunk_results(task, history, returns, steps, terminated, finite, None)


COST_TO_GO_GATE = "cost-to-go"
"""A chunk's gate that is the spec's LQR cost-to-go gate (:class:`~hybridctl.systems.control.CostToGoGate`,
the APG family's takeover), built by each worker from its own system rather than shipped."""


def _system_decision(system, gate: torch.nn.Module | str | None, device: torch.device,
                     decision_period: float | None = None
                     ) -> tuple[Callable[[torch.Tensor, torch.Tensor, torch.Tensor], tuple], int, int]:
    """(decide, substeps, decisions per episode) of ``system``'s swing-up env: ``decide(x, u, mode)`` ->
    ``(x_next, diverged, mode)`` is one decision of :class:`~hybridctl.envs.TorchVectorEnv` (the action
    held over the substeps) or, with a ``gate`` (SSAC's, or :data:`COST_TO_GO_GATE`), of
    :class:`~hybridctl.envs.SwitchedVectorEnv` (gate + LQR inside, at the env's default K, thresholds
    and gate stride: the Drake diagram's), on ``device``; a decision lasts ``decision_period`` (None:
    the spec's swing-up period)."""
    from ..envs.single import advance, decision_schedule
    from ..envs.switched import switched_decision
    from ..systems.control import CostToGoGate
    _, substeps, decisions = decision_schedule(system, decision_period)
    if isinstance(gate, str):
        if gate != COST_TO_GO_GATE:
            raise ValueError(f"a chunk's gate must be a torch module, {COST_TO_GO_GATE!r} or None, got {gate!r}")
        gate = CostToGoGate(system).to(device)
    if gate is None:
        return (lambda x, u, mode: (*advance(system, x, u, substeps), mode)), substeps, decisions
    K = torch.as_tensor(system.lqr()[0], dtype=torch.float64, device=device)
    stride = max(1, int(round(system.control_period / system.dt)))
    gate_dtype = next((p.dtype for p in gate.parameters()), torch.float64)

    def decide(x, u, mode):
        with torch.no_grad():
            x, diverged, mode, _ = switched_decision(system, gate, x, u, mode, K, substeps, stride, gate_dtype,
                                                     system.gate.on, system.gate.off)
        return x, diverged, mode
    return decide, substeps, decisions


def _run_system_chunk(task: ChunkTask) -> list[dict]:
    """A hybridctl system's swing-up: the chunk's episodes on its batched torch dynamics (SSAC: gate + LQR
    inside; a recurrent policy's state starts at zero and is carried per episode), on ``task.device``, the
    semantics of its :class:`~hybridctl.envs.TorchVectorEnv` (actions
    clipped, reward 0 and the last finite state on divergence, truncation after the episode's decisions,
    the thesis success test on the last states of a truncated episode).

    No copy to the host until the chunk ends: returns, step counts, terminations and states stay on the
    device; every episode starts together, so the loop runs a known number of decisions (the episode
    length or ``max_steps``) and asks the device nothing about which episodes still run.
    """
    from ..systems.success import is_balanced
    device = torch.device(task.device)
    if device.type == "cuda":
        from .config_check import check_device_available
        check_device_available("the rollout device", device)
    system = load_system(task.system, **(task.system_overrides or {}))
    n = len(task.seeds)
    gate = task.shared.gate
    gate = gate.get().to(device) if isinstance(gate, Shipped) else gate
    decide, _, decisions = _system_decision(system, gate, device, task.decision_period)
    module = task.module.to(device)
    recurrent = is_recurrent(module)
    hidden = module.initial_state(n).to(device) if recurrent else None
    dtype = next(module.parameters()).dtype
    params = unflatten(module, task.names, torch.as_tensor(task.thetas, dtype=torch.float64, device=device))
    x0 = np.concatenate([system.sample_initial_states(1, np.random.default_rng(int(s))) for s in task.seeds])
    x = torch.as_tensor(x0, dtype=torch.float64, device=device)
    horizon = int(min(task.max_steps or decisions, decisions))
    states = torch.empty((horizon + 1, n, x.shape[1]), dtype=torch.float64, device=device)
    states[0] = x
    mode = torch.zeros(n, dtype=torch.bool, device=device)           # every episode starts in swing-up
    returns = torch.zeros(n, dtype=torch.float64, device=device)
    steps = torch.zeros(n, dtype=torch.long, device=device)
    active = torch.ones(n, dtype=torch.bool, device=device)
    terminated = torch.zeros(n, dtype=torch.bool, device=device)
    bad_action = torch.zeros((), dtype=torch.bool, device=device)
    limit = system.action_limit
    for k in range(horizon):
        if recurrent:
            u, hidden = batched_recurrent_actions(module, params, x.to(dtype), hidden)
            u = u.to(torch.float64)
        else:
            u = batched_actions(module, params, x.to(dtype)).to(torch.float64)
        bad_action |= ~torch.isfinite(u).all()
        x, diverged, mode = decide(x, u.clamp(-limit, limit), mode)
        reward = torch.where(diverged, 0.0, system.reward(x))
        returns = torch.where(active, returns + reward, returns)
        steps += active.long()
        states[k + 1] = x
        terminated |= active & diverged
        active &= ~diverged
    # one copy to the host per chunk
    states_np, returns_np = states.cpu().numpy(), returns.cpu().numpy()
    steps_np, terminated_np = steps.cpu().numpy(), terminated.cpu().numpy()
    if bad_action.cpu().numpy():
        raise ValueError(f"actions must be finite (clipped to [-{limit}, {limit}]); got NaN or Inf")
    # the env's success test: an episode truncated after its decisions, balanced over its last states
    success = np.zeros(n, dtype=bool)
    if horizon == decisions:
        success = ~terminated_np & np.asarray(is_balanced(states_np.transpose(1, 0, 2), system), dtype=bool)
    return [episode_result(states_np[: steps_np[i] + 1, i], float(returns_np[i]), float(returns_np[i]),
                           int(steps_np[i]), bool(terminated_np[i]), task.postprocessor,
                           finite=bool(np.isfinite(returns_np[i])), success=bool(success[i]),
                           keep_states=task.keep_states) for i in range(n)]


def normalise(normalizer, obs: np.ndarray) -> np.ndarray:
    """``normalizer(obs)`` as float64 (a frozen observation normaliser; None: ``obs`` itself)."""
    return obs if normalizer is None else np.asarray(normalizer(obs), dtype=np.float64)
