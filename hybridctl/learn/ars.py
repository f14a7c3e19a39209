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
skeleton (:mod:`hybridctl.learn.run`); the antithetic update and its loop from
:mod:`hybridctl.learn.random_search` (shared with fine-tuning); the episodes from
:mod:`hybridctl.learn.rollouts` (shared with fine-tuning and the failure rates). This file
holds what is ARS's own: the settings, the policies, the running normalisation (V2), top-b.

Rollouts run on a backend from :mod:`hybridctl.parallel` ("processes" by
default, "serial", or "ray"). Directions and env seeds come from
``SeedSequence([seed, epoch, ...])``, and results are combined in task order, so a
seed gives the same run on every backend, and a resumed run continues exactly.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import gymnasium as gym
import numpy as np
import torch

from ..analysis.postprocess import KINDS as POSTPROCESS_KINDS
from ..analysis.postprocess import TRANSIENT_STEPS, PostProcessor
from ..parallel import BACKENDS, make_backend
from ..systems import known_systems
from ..systems import load as load_system
from . import checkpoint as ckpt
from .checkpoint import PROGRESS_FILE, Saved
from .config_check import check_fields, check_types
from .random_search import RandomSearchLearner
from .episode_tasks import RolloutTask, batchable, run_episode, run_episodes_batched  # noqa: F401 (re-exported)
from .flat_policy import FrozenPolicy, PolicySpec
from .rollout_envs import ACCEPTED_IDS, make_env, recorded_env_id, recorded_env_kwargs  # noqa: F401 (re-exported)
from .rollout_results import evaluation_seeds
from .rollouts import rollouts
from .run import EvalResult, seeded


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

class ARS(RandomSearchLearner):
    """ARS V2-t with optional dimension post-processing: ``learn`` / ``predict`` / ``evaluate`` / ``save`` / ``load``."""

    algorithm_name = "ARS"
    train_order = 2
    config_class = ARSConfig
    budget_field, unit = "epochs", "epoch"
    display_name, theta_name = "ARS", "ARS theta"   # the NaN guards' messages
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
        self._start(config or ARSConfig(), env, env_kwargs, overrides)
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
        probe.close()
        self.theta = self.policy.initial_theta()
        self.stats = RunningStats(obs_dim)

    def training_record(self) -> dict:
        """eval.json's training counters: epochs, env steps, wall time."""
        return {"epochs": self.epoch, "env_steps": self.env_steps, "train_wall_time_s": self.wall_time}

    # -- rollouts ------------------------------------------------------------------------
    def _tasks(self, thetas, seeds: list[int], max_steps: int | None = None,
                reward_shift: float | None = None, postprocessor: PostProcessor | None = None,
                **options) -> list[RolloutTask]:
        """One :class:`~hybridctl.learn.rollouts.RolloutTask` per (theta row, seed), with the current
        normalisation; ``options``: keep_states, measure, action_noise, obs_noise, push."""
        cfg = self.config
        mean, std = self.stats.mean, self.stats.std
        return [RolloutTask(self.env, self.env_kwargs, self.policy, th, mean, std, s, max_steps or cfg.episode_steps,
                            cfg.reward_shift if reward_shift is None else reward_shift,
                            postprocessor or cfg.postprocessor(), **options)
                for th, s in zip(thetas, seeds)]

    def perturbed_rollouts(self, thetas: np.ndarray, seeds: list[int], backend) -> list[dict]:
        """The epoch's training episodes (with the config's action and observation noise), batched on the
        MuJoCo stepper or one per task on ``backend`` (``config.engine``)."""
        cfg = self.config
        tasks = self._tasks(thetas, seeds, action_noise=cfg.train_action_noise, obs_noise=cfg.train_obs_noise)
        return rollouts(tasks, backend, cfg.engine, cfg.workers)

    def schedule(self, update: int) -> tuple[float, float]:
        """ARS's step size and noise: the config's constants."""
        return self.config.step_size, self.config.noise

    def top_directions(self) -> int:
        """b: the config's ``top_directions``."""
        return self.config.top_directions

    def after_rollouts(self, results: list[dict]) -> None:
        """V2: update the normalisation after the epoch, in task order."""
        for res in results:
            self.stats.add(res["sum"], res["sumsq"], res["count"])

    def train_epoch(self, backend) -> dict:
        """One ARS V2-t update (:meth:`~hybridctl.learn.random_search.RandomSearchLearner.train_update`):
        2N rollouts, top-b directions, step scaled by the kept returns' std, then the normalisation."""
        return self.train_update(backend)

    def run_description(self) -> str:
        """The progress bar's label."""
        return f"ARS {self.env_name}"

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
        seeds = evaluation_seeds(seed, n)
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
