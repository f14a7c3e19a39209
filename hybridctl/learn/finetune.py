"""Fine-tuning a trained deep-RL policy by direct policy search (thesis Ch. 6, Algorithm 8).

Take any deterministic torch policy (a Stable-Baselines3 agent read without unpickling, our
own SAC / SSAC / ARS checkpoints, or an ``nn.Module``), keep its observation normaliser
frozen, and improve its weights theta by random search. Each update draws n Gaussian
directions delta_k, rolls out theta + sigma delta_k and theta - sigma delta_k on the same env
seed, and steps (the author's code, sgillen/policy_refinement; ARS's step without top-b)

    theta <- theta + alpha / (n sigma_R + 1e-6) * sum_k (R+_k - R-_k) delta_k

with sigma_R the std of all 2n returns, alpha and sigma on linear schedules. Returns may carry
the mesh-dimension term of eq. 6.1 / 6.2 (``reward="mesh-mean"``): R / D for R >= 0 and R * D
for R < 0, D the mean of the lower and upper mesh dimension of the episode's normalised
observations (:class:`~hybridctl.analysis.PostProcessor`).

>>> tuner = FineTune("Pendulum-v1", "sb3:models/policies/ppo-pendulum/model.zip")
>>> before = tuner.evaluate(100)                         # deterministic returns, failure rate
>>> tuner.learn(out="runs/ft-pendulum-sac")          # 200 updates; progress, CSV, checkpoints
>>> tuner.learn(out="runs/ft-pendulum-sac", resume=True)
>>> tuner.save_sb3("runs/ft-pendulum-sac/model.zip")     # SB3's own PPO/SAC/... .load reads it
>>> FineTune.load("runs/ft-pendulum-sac/final")          # a hybridctl checkpoint

Rollouts run in fixed chunks of ``chunk_size`` perturbed policies: one batched forward of the
chunk's policies (``torch.func.vmap`` over their weights) per env step, over the chunk's envs
(gymnasium envs; a hybridctl system's batched torch env for sac/ssac sources). Chunks are
spread over a :mod:`hybridctl.parallel` backend; because the chunks do not depend on the
backend or the number of workers, a seed gives the same run on every backend.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import gymnasium as gym
import numpy as np
import torch
from torch.func import functional_call, vmap

from ..analysis.postprocess import FORMS as POSTPROCESS_FORMS
from ..analysis.postprocess import KINDS as POSTPROCESS_KINDS
from ..analysis.postprocess import PostProcessor
from ..envs.mujoco_batch import MujocoBatchEnv
from ..envs.mujoco_batch import supports as batch_supports
from ..parallel import BACKENDS, cached_env, make_backend
from ..systems import known_systems
from ..systems import load as load_system
from . import checkpoint as ckpt
from .ars import make_env as _make_env
from .ars import recorded_env_id, recorded_env_kwargs
from .config_check import check_types
from .robustness import wilson_interval
from .base import Learner
from .checkpoint import PROGRESS_FILE, Saved
from .config_check import check_fields
from .run import EvalResult, check_finite, set_torch_threads

SELECTIONS = ("action", "all", "last")
DIMENSION_SETTINGS = ("author", "ch4")
SOURCE_KINDS = ("sb3", "ars", "sac", "ssac")


@dataclass
class FineTuneConfig:
    """Every fine-tuning setting, with the thesis' value and its source (one setting for all results)."""

    updates: int = 200                 # thesis Sec. 6.2.1: 200 update steps
    n_directions: int = 64             # n, thesis Sec. 6.2.1 (all kept: no top-b)
    step_size_start: float = 0.02      # alpha = [0.02, 0.002], thesis Sec. 6.2.1, linear schedule
    step_size_end: float = 0.002
    noise_start: float = 0.025         # sigma = [0.025, 0.0025], thesis Sec. 6.2.1, linear schedule
    noise_end: float = 0.0025
    select: str = "action"             # parameters perturbed: "action" (hybridctl default: the action path),
    #                                    "all" (the author's code), "last" (last layer, thesis ablation)
    reward: str = "identity"           # "identity" or a dimension kind ("mesh-mean": eq. 6.1 / 6.2)
    reward_form: str = "auto"          # "divide" (eq. 6.1), "multiply" (eq. 6.2), "auto": by the return's sign
    dimension_settings: str = "author"  # "author": f 1.2, d0 1, no transient cut, clip [0, n/2], on the policy's
    #                                     normalised observations (policy_refinement); "ch4": the Ch. 4 defaults
    episode_steps: int | None = None   # None: the env's own limit
    seed: int = 0
    chunk_size: int = 64               # hybridctl: perturbed policies per batched rollout task (fixed, so the
    #                                    result does not depend on the backend or the worker count; 2n / chunk_size
    #                                    tasks per update: lower it when there are more workers than tasks)
    backend: str = "processes"         # "serial", "processes" (local, default), "ray"
    workers: int | None = None         # None: every core (processes) or the cluster's CPUs (ray)
    address: str | None = None         # Ray cluster address (backend "ray")
    checkpoint_every: int = 10         # updates between atomic checkpoints
    checkpoint_minutes: float = 5.0    # hybridctl: also a checkpoint at least every this many minutes
    eval_episodes: int = 100           # thesis Sec. 6.3: 100 Monte Carlo trials per agent
    torch_threads: int = 1             # hybridctl: one thread per process (two ran SB3 11x slower here)

    def validate(self) -> None:
        """Raise ValueError naming the first invalid field."""
        check_types(self)
        check_fields(self, positive=("step_size_start", "step_size_end", "noise_start", "noise_end"),
                     integers_from_1=("updates", "n_directions", "chunk_size", "checkpoint_every", "eval_episodes",
                                      "torch_threads"), integers_from_0=("seed",))
        for name, allowed in (("select", SELECTIONS), ("reward", POSTPROCESS_KINDS), ("reward_form", POSTPROCESS_FORMS),
                              ("dimension_settings", DIMENSION_SETTINGS), ("backend", BACKENDS)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"FineTuneConfig.{name} must be one of {allowed}, got {getattr(self, name)!r}")
        if self.workers is not None and self.workers < 1:
            raise ValueError(f"FineTuneConfig.workers must be None (every core) or an integer >= 1, got "
                             f"{self.workers!r}")
        if self.episode_steps is not None and (not isinstance(self.episode_steps, int) or self.episode_steps < 1):
            raise ValueError(f"FineTuneConfig.episode_steps must be None or an integer >= 1, got "
                             f"{self.episode_steps!r}")

    def schedule(self, update: int) -> tuple[float, float]:
        """(step size, noise) at ``update`` (0-based): linear from the start to the end values."""
        frac = update / max(self.updates - 1, 1)
        frac = min(max(frac, 0.0), 1.0)
        return (self.step_size_start + (self.step_size_end - self.step_size_start) * frac,
                self.noise_start + (self.noise_end - self.noise_start) * frac)

    def postprocessor(self, obs_dim: int, normalised: bool) -> PostProcessor:
        """The return post-processor of these settings for ``obs_dim`` observations.

        "author": f 1.2, d0 1, whole episode, clip [0, n/2], on observations already
        normalised by the policy (``normalised``; else by the episode's own statistics).
        "ch4": f 1.5, d0 0.01, the first 200 steps dropped, clip [1, n/2], the episode's own statistics.
        """
        if self.dimension_settings == "author":
            zeros, ones = (0.0,) * obs_dim, (1.0,) * obs_dim
            return PostProcessor(self.reward, transient_steps=0, form=self.reward_form, scale_factor=1.2,
                                 initial_box=1.0, clip_low=0.0, mean=zeros if normalised else None,
                                 std=ones if normalised else None)
        return PostProcessor(self.reward, form=self.reward_form)


# ============================================================================ the policy being tuned

class AffineNormalizer:
    """A frozen ``(obs - mean) / std`` observation normaliser (ARS checkpoints); picklable."""

    def __init__(self, mean, std):
        self.mean, self.std = np.asarray(mean, dtype=np.float64), np.asarray(std, dtype=np.float64)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """The normalised observation(s)."""
        return (np.asarray(obs, dtype=np.float64) - self.mean) / self.std

    def to_dict(self) -> dict:
        """JSON-ready statistics."""
        return {"type": "affine", "mean": self.mean.tolist(), "std": self.std.tolist()}


class ScaledModule(torch.nn.Module):
    """``mid + half * net(z)`` clipped to [low, high]: an ARS torch policy in env units."""

    def __init__(self, net: torch.nn.Module | None, obs_dim: int, act_dim: int, low, high):
        super().__init__()
        self.net = net
        if net is None:  # ARS's linear policy: action = M z, M (act_dim, obs_dim)
            self.weight = torch.nn.Parameter(torch.zeros(act_dim, obs_dim, dtype=torch.float64))
        low, high = torch.as_tensor(low, dtype=torch.float64), torch.as_tensor(high, dtype=torch.float64)
        self.register_buffer("low", low)
        self.register_buffer("high", high)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """The action for normalised observations ``z``."""
        if self.net is None:
            y = z @ self.weight.T
        else:
            y = (self.high + self.low) / 2 + (self.high - self.low) / 2 * self.net(z)
        return torch.clamp(y, self.low, self.high)


@dataclass
class TunablePolicy:
    """What fine-tuning needs from a trained agent: a deterministic torch policy of normalised
    observations (actions in env units), its frozen observation normaliser, and where it came from.

    ``module`` may define ``parameter_names(select)`` (SB3 policies do: the action path, all, or
    the last layer); otherwise "action" and "all" are every parameter and "last" the last
    ``nn.Linear``'s. ``system``: a hybridctl system name when the policy drives that system's
    swing-up (sac/ssac sources: rollouts on its batched torch env); ``gate``: SSAC's gate.
    """

    module: torch.nn.Module
    normalizer: Callable[[np.ndarray], np.ndarray] | None = None
    source: str = "module"
    sb3: Any = None                 # the SB3Agent for sb3 sources (written back by save_sb3)
    system: str | None = None
    gate: torch.nn.Module | None = None
    meta: dict = field(default_factory=dict)

    def parameter_names(self, select: str) -> list[str]:
        """Names of the parameters perturbed under ``select`` (see :data:`SELECTIONS`)."""
        if select not in SELECTIONS:
            raise ValueError(f"select must be one of {SELECTIONS}, got {select!r}")
        own = getattr(self.module, "parameter_names", None)
        if callable(own):
            return list(own(select))
        names = [n for n, p in self.module.named_parameters()]
        if select == "last":
            linears = [n for n, m in self.module.named_modules() if isinstance(m, torch.nn.Linear)]
            if linears:
                prefix = linears[-1] + "."
                names = [n for n in names if n.startswith(prefix)]
            else:
                names = names[-1:]
        return names


def parse_source(text: str) -> tuple[str, str]:
    """"sb3:PATH" -> ("sb3", "PATH"); the kinds are :data:`SOURCE_KINDS`."""
    kind, sep, path = str(text).partition(":")
    if not sep or kind not in SOURCE_KINDS or not path:
        raise ValueError(f"--policy must be KIND:PATH with KIND one of {SOURCE_KINDS} (e.g. sb3:runs/agent/model.zip), "
                         f"got {text!r}")
    return kind, path


def load_policy(source: str, env: str, trust: bool = False, normalizer: str | None = None) -> TunablePolicy:
    """The :class:`TunablePolicy` of ``source`` ("sb3:PATH", "ars:PATH", "sac:PATH", "ssac:PATH") for ``env``.

    sb3: a Stable-Baselines3 zip read without unpickling (:func:`hybridctl.learn.sb3.load_sb3`;
    its normaliser from ``normalizer`` or a ``vecnormalize.npz`` beside it; a pickle only with
    ``trust``). ars: an ARS checkpoint, its running statistics frozen. sac / ssac: a hybridctl
    checkpoint of a system (``env`` must be that system's name); ssac keeps its gate and LQR.
    Raises CheckpointError / ValueError naming the file or what does not fit the env.
    """
    kind, path = parse_source(source)
    if kind == "sb3":
        from .sb3 import load_sb3  # reading a zip needs only torch; SB3 itself is optional
        agent = load_sb3(path, normalizer=normalizer, trust=trust)
        probe = _make_env(env)
        try:
            agent.check_env(probe)
        finally:
            probe.close()
        return TunablePolicy(agent.policy, agent.normalizer, source, sb3=agent,
                             meta={"algo": agent.algo, "path": str(path)})
    if kind == "ars":
        from .ars import ARS
        agent = ARS.load(path)
        spec = agent.policy
        module = ScaledModule(spec.module, spec.obs_dim, spec.act_dim, spec.low, spec.high)
        if spec.module is None:
            with torch.no_grad():
                module.weight.copy_(torch.as_tensor(agent.theta.reshape(spec.act_dim, spec.obs_dim)))
        else:
            spec.actor(agent.theta)  # loads theta into the module's weights
        tunable = TunablePolicy(module, AffineNormalizer(agent.stats.mean, agent.stats.std), source,
                                meta={"algo": "ars", "trained_env": agent.env_name})
        _check_gym_spaces(tunable, env, spec.obs_dim, spec.act_dim, path)
        return tunable
    # sac / ssac: our swing-up checkpoints drive a system
    if env not in known_systems():
        raise ValueError(f"a {kind}: policy drives a hybridctl system; env must be one of {known_systems()}, "
                         f"got {env!r}")
    from .export import load_controller
    policy, gate, meta = load_controller(path, load_system(env))
    if kind == "ssac" and gate is None:
        raise ckpt.CheckpointError(f"{path} is a {meta.get('algorithm')} checkpoint without a gate; use sac:{path}")
    return TunablePolicy(policy, None, source, system=env, gate=gate if kind == "ssac" else None,
                         meta={"algo": kind, "trained_algorithm": meta.get("algorithm"),
                               "gate": {k: v for k, v in (meta.get("gate") or {}).items() if k in ("gate_on", "gate_off")}})


def _check_gym_spaces(tunable: TunablePolicy, env: str, obs_dim: int, act_dim: int, path) -> None:
    probe = _make_env(env)
    try:
        got = (int(np.prod(probe.observation_space.shape)), int(np.prod(probe.action_space.shape)))
    finally:
        probe.close()
    if got != (obs_dim, act_dim):
        raise ValueError(f"{path} has {obs_dim} observations and {act_dim} actions; env {env} has {got[0]} "
                         f"observations and {got[1]} actions")


# ============================================================================ batched rollouts (run in workers)

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
class ChunkTask:
    """Episodes of ``len(seeds)`` policies (rows of ``thetas``), one per env seed (plain, picklable)."""

    env: Any
    env_kwargs: dict | None
    shipped: Shipped
    names: list[str]
    thetas: np.ndarray            # (B, P) float64
    seeds: list[int]
    normalizer: Any
    max_steps: int | None
    postprocessor: PostProcessor
    system: str | None = None
    gate: Shipped | None = None
    keep_states: bool = False

    @property
    def module(self) -> torch.nn.Module:
        """The policy module (non-perturbed parameters at their values; perturbed ones come from thetas)."""
        return self.shipped.get()


def _unflatten(module: torch.nn.Module, names: list[str], thetas: torch.Tensor) -> dict[str, torch.Tensor]:
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


def run_chunk(task: ChunkTask) -> list[dict]:
    """Roll out one episode per row of ``task.thetas``; one result dict per row, in row order."""
    torch.set_num_threads(1)
    if task.system is not None:
        return _run_system_chunk(task)
    if batch_supports(task.env, task.env_kwargs):
        return _run_mujoco_chunk(task)
    n = len(task.seeds)
    envs = cached_env(("finetune", repr(task.env), repr(task.env_kwargs), task.max_steps, n),
                      lambda: [_make_env(task.env, task.env_kwargs, task.max_steps) for _ in range(n)])
    dtype = next(task.module.parameters()).dtype
    params = _unflatten(task.module, task.names, torch.as_tensor(task.thetas, dtype=torch.float64))
    space = envs[0].action_space
    obs = np.stack([np.asarray(e.reset(seed=int(s))[0], dtype=np.float64).reshape(-1) for e, s in zip(envs, task.seeds)])
    z = _normalise(task.normalizer, obs)
    history = [z.copy()]          # normalised observations of every member at each step (one copy per step)
    returns, rewards, steps = np.zeros(n), np.zeros(n), np.zeros(n, dtype=int)
    active, terminated, finite, success = np.ones(n, bool), np.zeros(n, bool), np.ones(n, bool), [None] * n
    limit = task.max_steps or math.inf
    while active.any():
        actions = batched_actions(task.module, params, torch.as_tensor(z, dtype=dtype)).numpy()
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


def _after_step(task: ChunkTask, obs, returns, steps, stepped, finite, active, limit, history) -> np.ndarray:
    """Book-keeping after the ``stepped`` episodes took a step (their rewards already in ``returns``):
    count the step, stop non-finite and over-long episodes, record and return the normalised observations."""
    steps[stepped] += 1
    bad = stepped[~(np.isfinite(obs[stepped]).all(axis=1) & np.isfinite(returns[stepped]))]
    finite[bad], active[bad] = False, False
    active &= steps < limit
    z = _normalise(task.normalizer, obs)
    history.append(z.copy())
    return z


def _chunk_results(task: ChunkTask, history, returns, steps, terminated, finite, success) -> list[dict]:
    """One result per episode of a chunk; member i's episode is states[: steps[i] + 1, i]."""
    states = np.stack(history)    # (T + 1, n, obs)
    return [_episode_result(task, states[: steps[i] + 1, i], returns[i], int(steps[i]), bool(terminated[i]),
                            bool(finite[i]), None if success is None else success[i]) for i in range(len(steps))]


def _run_mujoco_chunk(task: ChunkTask) -> list[dict]:
    """:func:`run_chunk` on a Hopper/Walker2d/HalfCheetah v5 env: the chunk's episodes stepped together
    on :class:`~hybridctl.envs.mujoco_batch.MujocoBatchEnv` (one thread; the backend's workers run the
    chunks side by side). Bit-identical to the gymnasium loop of :func:`run_chunk` (tested)."""
    n = len(task.seeds)
    env = cached_env(("finetune-batch", task.env, repr(task.env_kwargs), n),
                     lambda: MujocoBatchEnv(task.env, num_envs=n, nthread=1, env_kwargs=task.env_kwargs))
    dtype = next(task.module.parameters()).dtype
    params = _unflatten(task.module, task.names, torch.as_tensor(task.thetas, dtype=torch.float64))
    space = env.action_space
    obs = env.reset(task.seeds)
    z = _normalise(task.normalizer, obs)
    history = [z.copy()]
    returns, steps = np.zeros(n), np.zeros(n, dtype=int)
    active, terminated, finite = np.ones(n, bool), np.zeros(n, bool), np.ones(n, bool)
    limit = task.max_steps or env.max_episode_steps or math.inf
    while active.any():
        actions = batched_actions(task.module, params, torch.as_tensor(z, dtype=dtype)).numpy()
        actions = actions.astype(space.dtype, copy=False).reshape((n, *space.shape))
        stepped = np.flatnonzero(active)
        o, r, term, _ = env.step(actions[stepped], ids=stepped)
        obs[stepped] = o
        terminated[stepped] = term
        active[stepped[term]] = False
        returns[stepped] += r
        z = _after_step(task, obs, returns, steps, stepped, finite, active, limit, history)
    return _chunk_results(task, history, returns, steps, terminated, finite, None)


def _run_system_chunk(task: ChunkTask) -> list[dict]:
    """A hybridctl system's swing-up: the chunk's episodes on its batched torch env (SSAC: gate + LQR inside)."""
    from ..envs import SwitchedVectorEnv, TorchVectorEnv
    system = load_system(task.system)
    n = len(task.seeds)
    gate = task.gate.get() if task.gate is not None else None
    if gate is not None:
        env = SwitchedVectorEnv(system, n, gate=gate, dtype=torch.float64)
    else:
        env = TorchVectorEnv(system, n, dtype=torch.float64)
    x0 = np.concatenate([system.sample_initial_states(1, np.random.default_rng(int(s))) for s in task.seeds])
    obs, _ = env.reset(seed=int(task.seeds[0]), options={"state": x0})
    dtype = next(task.module.parameters()).dtype
    params = _unflatten(task.module, task.names, torch.as_tensor(task.thetas, dtype=torch.float64))
    states = [[row] for row in obs.numpy()]
    returns, steps = np.zeros(n), np.zeros(n, dtype=int)
    active, terminated, success = np.ones(n, bool), np.zeros(n, bool), [None] * n
    limit = task.max_steps or math.inf
    while active.any():
        actions = batched_actions(task.module, params, obs.to(dtype)).to(torch.float64)
        obs, rewards, term, trunc, infos = env.step(actions)
        x, r = obs.numpy(), rewards.numpy()
        for i in np.flatnonzero(active):
            returns[i] += float(r[i])
            steps[i] += 1
            states[i].append(x[i])
            if bool(term[i]) or bool(trunc[i]) or steps[i] >= limit:
                active[i], terminated[i] = False, bool(term[i])
                success[i] = bool(infos["success"][i]) if bool(infos["_success"][i]) else False
    return [_episode_result(task, np.stack(states[i]), returns[i], int(steps[i]), bool(terminated[i]),
                            bool(np.isfinite(returns[i])), success[i]) for i in range(n)]


def _normalise(normalizer, obs: np.ndarray) -> np.ndarray:
    return obs if normalizer is None else np.asarray(normalizer(obs), dtype=np.float64)


def _episode_result(task: ChunkTask, states: np.ndarray, raw_return: float, steps: int, terminated: bool,
                    finite: bool, success) -> dict:
    """The training return (post-processed), raw return, dimension and flags of one episode."""
    if not finite or not np.all(np.isfinite(states)):
        return {"finite": False, "steps": steps}
    processed, info = task.postprocessor(states, float(raw_return))
    out = {"finite": True, "return": float(processed), "raw_return": float(raw_return), "steps": steps,
           "terminated": terminated, "success": success, "dimension": info["dimension"], "reason": info["reason"]}
    if task.keep_states:
        out["states"] = states
    return out


# ============================================================================ the algorithm

class FineTune(Learner):
    """Direct policy search over a trained policy's weights (Alg. 8): ``learn`` / ``predict`` /
    ``evaluate`` / ``save`` / ``load`` / ``save_sb3``.

    Args:
        env: a gymnasium env id (or a hybridctl system name for sac/ssac sources), or a factory.
        policy: a source string ("sb3:PATH", "ars:PATH", "sac:PATH", "ssac:PATH"), a
            :class:`TunablePolicy`, or an ``nn.Module`` mapping observations to actions.
        config: :class:`FineTuneConfig` (the thesis' single setting by default); ``overrides``
            replace its fields.
        trust: allow unpickling a VecNormalize ``.pkl`` (only for files you trust).
        normalizer: an ``.npz`` of observation statistics for an sb3 source.
    """

    algorithm_name = "FineTune"
    config_class = FineTuneConfig
    budget_field, unit, uses_backend = "updates", "update", True
    load_keywords = ("policy", "trust")
    log_key = "update"
    log_columns = ("update", "env_steps", "mean_return", "max_return", "mean_raw_return", "mean_dimension", "sigma_r",
                   "step_size", "noise", "episode_steps", "wall_time", "steps_per_s")
    log_int_columns = ("update", "env_steps")
    log_float_format = None
    saved = (Saved("theta", "theta", "array"),
             Saved("module_state", "tunable.module", "state", optional=True),
             Saved("update", "update", file=PROGRESS_FILE, load=int),
             Saved("env_steps", "env_steps", file=PROGRESS_FILE, load=int),
             Saved("wall_time", "wall_time", file=PROGRESS_FILE, load=float),
             Saved("history", "history", file=PROGRESS_FILE, optional=True, load=list))

    def __init__(self, env: str | Callable[[], gym.Env], policy: str | TunablePolicy | torch.nn.Module,
                 config: FineTuneConfig | None = None, env_kwargs: dict | None = None, trust: bool = False,
                 normalizer: str | None = None, **overrides):
        self.config = dataclasses.replace(config or FineTuneConfig(), **overrides)
        self.config.validate()
        set_torch_threads(self.config.torch_threads)
        self.env, self.env_kwargs = env, env_kwargs
        self.env_name = env if isinstance(env, str) else getattr(env, "__name__", repr(env))
        if isinstance(policy, str):
            if not isinstance(env, str):
                raise ValueError("a policy source string needs an env id, not a factory; pass a TunablePolicy")
            policy = load_policy(policy, env, trust=trust, normalizer=normalizer)
        elif isinstance(policy, torch.nn.Module):
            policy = TunablePolicy(policy)
        if not isinstance(policy, TunablePolicy):
            raise TypeError(f"policy must be a source string, a TunablePolicy or an nn.Module, got "
                            f"{type(policy).__name__}")
        self.tunable = policy
        self.tunable.module.eval()
        self.names = self.tunable.parameter_names(self.config.select)
        if not self.names:
            raise ValueError(f"select={self.config.select!r} selects no parameters of {policy.source}")
        self.obs_dim = self._obs_dim()
        self.theta0 = self._flat_params()
        self.theta = self.theta0.copy()
        self.update, self.env_steps, self.wall_time = 0, 0, 0.0
        self.history: list[dict] = []
        self.log_rows: list[dict] = []

    # -- parameters ------------------------------------------------------------------------
    def _obs_dim(self) -> int:
        if self.tunable.system is not None:
            return load_system(self.tunable.system).n_states
        probe = _make_env(self.env, self.env_kwargs)
        try:
            return int(np.prod(probe.observation_space.shape))
        finally:
            probe.close()

    def _flat_params(self) -> np.ndarray:
        params = dict(self.tunable.module.named_parameters())
        return np.concatenate([params[n].detach().double().reshape(-1).numpy() for n in self.names]).copy()

    @property
    def n_params(self) -> int:
        """Length of theta (the perturbed parameters)."""
        return int(self.theta.size)

    def _write_theta(self) -> None:
        """Put theta into the module's parameters (for saving, predict, export)."""
        rows = _unflatten(self.tunable.module, self.names, torch.as_tensor(self.theta[None], dtype=torch.float64))
        params = dict(self.tunable.module.named_parameters())
        with torch.no_grad():
            for name, value in rows.items():
                params[name].copy_(value[0])

    @property
    def progress_count(self) -> int:
        """Updates so far (the progress.csv key)."""
        return self.update

    # -- rollouts ------------------------------------------------------------------------
    def _postprocessor(self, reward: str | None = None) -> PostProcessor:
        cfg = dataclasses.replace(self.config, reward=reward) if reward is not None else self.config
        return cfg.postprocessor(self.obs_dim, normalised=self.tunable.normalizer is not None)

    def _rollouts(self, thetas: np.ndarray, seeds: list[int], backend, postprocessor: PostProcessor,
                  max_steps: int | None = None, keep_states: bool = False) -> list[dict]:
        """One episode per (theta row, seed), in fixed chunks spread over ``backend``."""
        size = self.config.chunk_size
        module, gate = self._shipped()
        tasks = [ChunkTask(self.env, self.env_kwargs, module, self.names, thetas[i:i + size],
                           seeds[i:i + size], self.tunable.normalizer, max_steps or self.config.episode_steps,
                           postprocessor, self.tunable.system, gate, keep_states)
                 for i in range(0, len(seeds), size)]
        return [r for chunk in backend.map(run_chunk, tasks) for r in chunk]

    def _shipped(self) -> tuple[Shipped, Shipped]:
        """The policy and gate as bytes for the workers, made once: the parameters they keep are never
        changed (the perturbed ones travel in the chunks' theta rows)."""
        if getattr(self, "_shipped_pair", None) is None:
            self._shipped_pair = (Shipped(self.tunable.module), Shipped(self.tunable.gate))
        return self._shipped_pair

    def _update_draws(self, update: int) -> tuple[np.ndarray, list[int]]:
        """Directions (n, P) and one env seed per direction for ``update`` (from the seed alone)."""
        rng = np.random.default_rng(np.random.SeedSequence([self.config.seed, update]))
        directions = rng.standard_normal((self.config.n_directions, self.n_params))
        seeds = [int(s) for s in rng.integers(0, 2 ** 31 - 1, size=self.config.n_directions)]
        return directions, seeds

    def train_update(self, backend) -> dict:
        """One update of Algorithm 8: 2n rollouts, all directions kept, step scaled by the returns' std."""
        cfg = self.config
        alpha, sigma = cfg.schedule(self.update)
        directions, seeds = self._update_draws(self.update)
        thetas = np.stack([self.theta + sign * sigma * d for d in directions for sign in (1.0, -1.0)])
        results = self._rollouts(thetas, [s for s in seeds for _ in (0, 1)], backend, self._postprocessor())
        bad = [i for i, r in enumerate(results) if not r["finite"]]
        if bad:
            raise FloatingPointError(f"fine-tuning update {self.update}: {len(bad)} rollouts produced NaN/inf "
                                     f"(first: direction {bad[0] // 2}); training stopped, the last checkpoint is intact")
        r = np.array([res["return"] for res in results]).reshape(cfg.n_directions, 2)
        sigma_r = float(r.std())
        theta = self.theta + alpha / (cfg.n_directions * sigma_r + 1e-6) * ((r[:, 0] - r[:, 1]) @ directions)
        check_finite("fine-tuned theta", theta, f"at update {self.update + 1}")
        self.theta = theta
        steps = sum(res["steps"] for res in results)
        self.env_steps += steps
        self.update += 1
        return {"update": self.update, "env_steps": self.env_steps, "mean_return": float(r.mean()),
                "max_return": float(r.max()), "mean_raw_return": float(np.mean([x["raw_return"] for x in results])),
                "mean_dimension": float(np.mean([x["dimension"] for x in results])), "sigma_r": sigma_r,
                "step_size": alpha, "noise": sigma, "episode_steps": steps / len(results)}

    def run_description(self) -> str:
        """The progress bar's label."""
        return f"fine-tune {self.env_name}"

    def train(self, run, target: int, backend) -> None:
        """Fine-tuning's loop inside ``learn``'s run: one update (2 x ``n_directions`` rollouts on
        ``backend``, default the config's, opened for the run) at a time, a checkpoint every
        ``checkpoint_every`` updates and at least every ``checkpoint_minutes``. The schedules run
        over ``config.updates``, so a run stopped early and resumed continues them exactly."""
        own = backend is None
        pool = backend or make_backend(self.config.backend, self.config.workers, self.config.address)
        try:
            run.updates(target, lambda: self.train_update(pool), 2 * self.config.n_directions,
                        self.config.checkpoint_every,
                        lambda row: {"ret": f"{row['mean_raw_return']:.1f}", "dim": f"{row['mean_dimension']:.2f}",
                                     "sps": f"{row['steps_per_s']:.0f}"})
        finally:
            if own:
                pool.close()

    # -- use ---------------------------------------------------------------------------------
    def predict(self, obs: np.ndarray, deterministic: bool = True) -> np.ndarray:
        """The fine-tuned policy's (maximum-likelihood) action for one or a batch of observations."""
        if not deterministic:
            raise ValueError("fine-tuned policies act deterministically (maximum-likelihood actions); "
                             "deterministic=False is not supported")
        self._write_theta()
        z = _normalise(self.tunable.normalizer, np.asarray(obs, dtype=np.float64))
        dtype = next(self.tunable.module.parameters()).dtype
        with torch.no_grad():
            return self.tunable.module(torch.as_tensor(z, dtype=dtype)).double().numpy()

    def tuned_module(self) -> torch.nn.Module:
        """A copy of the policy module with the fine-tuned weights (normalised observations -> actions),
        e.g. the swing-up block of a Drake diagram (``experiments.build_named_diagram(system, "finetune:PATH")``)."""
        self._write_theta()
        module = copy.deepcopy(self.tunable.module).eval()
        for p in module.parameters():
            p.requires_grad_(False)
        return module

    def run_evaluation(self, episodes: int, seed: int, theta: np.ndarray | None = None,
                       backend=None, episode_steps: int | None = None, keep_states: bool = False) -> EvalResult:
        """``evaluate(episodes, seed=, ...)``: deterministic episodes of theta (default the current; ``theta0`` is the pretrained agent):
        raw returns, episode lengths, early terminations with a 95 % Wilson interval, the mesh-mean
        dimension of each episode (author's settings) and, for systems, the thesis success rate."""
        n = episodes
        seeds = [int(s) for s in np.random.default_rng(seed).integers(0, 2 ** 31 - 1, size=n)]
        th = self.theta if theta is None else np.asarray(theta, dtype=np.float64)
        pp = dataclasses.replace(self.config, reward="mesh-mean").postprocessor(
            self.obs_dim, normalised=self.tunable.normalizer is not None)
        own = backend is None
        pool = backend or make_backend("serial")
        try:
            results = self._rollouts(np.repeat(th[None], n, axis=0), seeds, pool, pp, episode_steps, keep_states)
        finally:
            if own:
                pool.close()
        finite = [r for r in results if r["finite"]]
        returns = np.array([r["raw_return"] for r in finite])
        successes = [r["success"] for r in finite if r.get("success") is not None]
        out = EvalResult.from_returns(
            returns, success_rate=float(np.mean(successes)) if successes else None,
            first={"episodes": n, "seed": seed}, steps=[r["steps"] for r in results],
            terminated=[r.get("terminated", False) for r in finite], nonfinite=n - len(finite),
            dimension=[r["dimension"] for r in finite])
        fails = sum(bool(r.get("terminated")) for r in finite) + (n - len(finite))
        out["failures"] = int(fails)
        out["failure_rate"] = fails / n
        out["failure_interval"] = wilson_interval(fails, n)
        out["mean_dimension"] = float(np.mean([r["dimension"] for r in finite])) if finite else None
        out["std_dimension"] = float(np.std([r["dimension"] for r in finite])) if finite else None
        if keep_states:
            out["states"] = [r["states"] for r in finite]
        return out

    # -- export and checkpoints ----------------------------------------------------------------
    def save_sb3(self, path: str | Path) -> Path:
        """Write the fine-tuned agent as an SB3 zip (:meth:`~hybridctl.learn.sb3.SB3Agent.save_zip`: rebuilt
        from the parsed fields with the tuned weights, readable by SB3's own ``load``, no pickle of the
        input's kept) and its normaliser as ``vecnormalize.npz`` beside it."""
        if self.tunable.sb3 is None:
            raise ValueError(f"save_sb3 needs an sb3: source; this policy came from {self.tunable.source}")
        self._write_theta()
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        written = self.tunable.sb3.save_zip(path)
        if self.tunable.normalizer is not None and hasattr(self.tunable.normalizer, "save_npz"):
            self.tunable.normalizer.save_npz(path.parent / "vecnormalize.npz")
        return Path(written or path)

    def before_checkpoint(self) -> None:
        """The module holds the last perturbed weights only in workers; put theta in before saving."""
        self._write_theta()

    def system_record(self) -> dict:
        """config.json's ``system``: the env's id and keyword arguments (a gymnasium env or a system's)."""
        return ckpt.env_record(self.env_name, self.env_kwargs)

    def checkpoint_extra(self) -> dict:
        """config.json beside algorithm, system and config: the source, the perturbed parameters."""
        return {"source": self.tunable.source, "source_meta": self.tunable.meta, "names": self.names,
                "n_params": self.n_params, "obs_dim": self.obs_dim}

    def normalization(self) -> dict:
        """normalization.json: the frozen observation normaliser of the pretrained agent."""
        norm = self.tunable.normalizer
        if norm is None:
            return {"type": "none"}
        return ckpt.to_jsonable(norm.to_dict()) if hasattr(norm, "to_dict") else {"type": type(norm).__name__}

    def check_checkpoint(self, found: Path, meta: dict, normalization: dict, force: bool = False) -> None:
        """The checkpoint must come from this env and source, with the same perturbed parameters."""
        problems = []
        trained_on = (meta.get("system") or {}).get("name")
        if trained_on != self.env_name:
            problems.append(f"checkpoint {found} fine-tunes env {trained_on!r}; this env is {self.env_name!r}")
        if meta.get("source") != self.tunable.source:
            problems.append(f"checkpoint {found} fine-tunes {meta.get('source')!r}; this policy is "
                            f"{self.tunable.source!r}")
        ckpt.refuse_unless_forced(problems, force)
        if meta.get("names") != self.names or meta.get("n_params") != self.n_params:
            raise ckpt.CheckpointError(f"checkpoint {found} perturbs {meta.get('n_params')} parameters "
                                       f"({meta.get('config', {}).get('select')!r}); this policy with select="
                                       f"{self.config.select!r} has {self.n_params}")

    @classmethod
    def from_checkpoint(cls, found: Path, meta: dict, config, system, force: bool,
                        policy: TunablePolicy | torch.nn.Module | None = None, trust: bool = False) -> "FineTune":
        """:meth:`~hybridctl.learn.base.Learner.load`'s learner: the source policy is read again
        (``policy`` replaces it, e.g. a module passed in Python; ``trust``: allow unpickling its
        VecNormalize ``.pkl``), on ``system`` (a gymnasium env id or factory; None: the recorded
        id, which is data: one with a ``module:`` part is refused); the checkpoint's theta follows."""
        file = found / ckpt.CONFIG_FILE
        if "source" not in meta:
            raise ckpt.CheckpointError(f"{file} is damaged or not a FineTune checkpoint's: it lacks 'source'")
        source = policy if policy is not None else meta["source"]
        if not isinstance(source, (str, TunablePolicy, torch.nn.Module)):
            raise ckpt.CheckpointError(f"{file}: 'source' must be a string KIND:PATH with KIND one of {SOURCE_KINDS}, "
                                       f"got {type(source).__name__}")
        record = meta.get("system") if isinstance(meta.get("system"), dict) else {}
        env = system if system is not None else recorded_env_id(record.get("name"), file, "system.name")
        return cls(env, source, config, env_kwargs=recorded_env_kwargs(record.get("kwargs"), file,
                                                                       "system.kwargs"), trust=trust)
