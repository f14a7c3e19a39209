"""What the learners on a batched torch swing-up env with a replay buffer share (SAC, SSAC): env set-up,
episode statistics, inference, evaluation, and the checkpoint's config / progress / load. The algorithms
(:mod:`.sac`, :mod:`.ssac`) keep only their own parts; the analytic policy gradients (:mod:`.apg`) run on the
same envs with their own loop.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections import deque
from pathlib import Path

import numpy as np
import torch

from . import checkpoint as ckpt
from ..envs import TorchVectorEnv
from ..systems import System
from ..systems.switched import LearnedGate, NeverGate, SwitchedController
from .base import Learner
from .checkpoint import PROGRESS_FILE, Saved
from .run import EvalResult, set_torch_threads


def progress_entry(key: str, attr: str, **options) -> Saved:
    """A :class:`Saved` entry of progress.json."""
    return Saved(key, attr, file=PROGRESS_FILE, **options)


def _recent(values) -> deque:
    return deque(values, maxlen=100)


class VectorEnvAgent(Learner):
    """Base of the learners that act on a TorchVectorEnv-like env (see :class:`~hybridctl.learn.SAC`).

    Subclasses call :meth:`_setup` first in ``__init__``, implement :meth:`policy_actions`
    and :meth:`normalization`, and extend ``saved`` with their own state.
    """

    config_class = None
    log_key = "env_steps"
    # the progress counters and episode statistics of every such learner (progress.json)
    saved = (progress_entry("env_steps", "num_timesteps", load=int),
             progress_entry("episodes", "num_episodes", optional=True, load=int),
             progress_entry("wall_time", "wall_time", optional=True, load=float),
             progress_entry("mean_return", "mean_return", restore=False),
             progress_entry("best_mean_return", "best_mean_return", optional=True,
                            load=lambda v: -math.inf if v is None else float(v)),
             progress_entry("success_rate", "success_rate", restore=False),
             progress_entry("recent_returns", "recent_returns", optional=True, save=list, load=_recent),
             progress_entry("recent_successes", "recent_successes", optional=True, save=list, load=_recent),
             progress_entry("env_rng_state", "env_rng_state", optional=True))

    def _setup(self, env_or_system, config, overrides: dict):
        """Threads, env, dimensions, action scale and counters; returns the validated config
        (``num_envs`` taken from a ready env)."""
        cfg = dataclasses.replace(config if config is not None else self.config_class(), **overrides)
        set_torch_threads(cfg.torch_threads)  # before any work, the env's and subclasses' set-up included
        self.env = self._make_env(env_or_system, cfg)
        if self.env.num_envs != cfg.num_envs:
            cfg = dataclasses.replace(cfg, num_envs=int(self.env.num_envs))
        cfg.validate()
        self.config = cfg
        self.system = self.env.system
        self.device = torch.device(cfg.device)
        self.obs_dim = int(self.env.single_observation_space.shape[0])
        self.action_dim = int(self.env.single_action_space.shape[0])
        high = np.asarray(self.env.single_action_space.high, dtype=np.float64)
        low = np.asarray(self.env.single_action_space.low, dtype=np.float64)
        if not np.allclose(high, -low) or not np.all(np.isfinite(high)) or np.any(high <= 0):
            raise ValueError(f"{self.algorithm_name} needs a symmetric, finite action box, got [{low}, {high}]")
        self.action_scale = torch.as_tensor(high, dtype=torch.float32, device=self.device)
        self.num_timesteps = self.num_episodes = 0
        self.wall_time = 0.0
        self.best_mean_return = -math.inf
        self.recent_returns: deque[float] = _recent([])
        self.recent_successes: deque[bool] = _recent([])
        self.log_rows: list[dict] = []
        self._obs: torch.Tensor | None = None
        self._env_seed: int | None = cfg.seed  # reset(seed=...) on the first learn(); None after a load
        return cfg

    @staticmethod
    def _make_env(env_or_system, cfg):
        if isinstance(env_or_system, (str, System)):
            return TorchVectorEnv(env_or_system, cfg.num_envs, device=cfg.device, seed=cfg.seed)
        env = env_or_system
        for attr in ("system", "num_envs", "single_observation_space", "single_action_space"):
            if not hasattr(env, attr):
                raise TypeError(f"env must be a system name, a System or a TorchVectorEnv-like vector env "
                                f"(missing attribute {attr!r}), got {type(env).__name__}")
        mode = getattr(env, "metadata", {}).get("autoreset_mode")
        if mode is not None and "same" not in str(getattr(mode, "value", mode)).lower():
            raise ValueError(f"the learner needs a vector env with same-step autoreset (final_obs in infos), got {mode}")
        return env

    def training_record(self) -> dict:
        """eval.json's training counters: env steps, wall time, the last 100 training episodes' return and success."""
        return {"env_steps": self.num_timesteps, "train_wall_time_s": self.wall_time,
                "train_mean_return_last100": self.mean_return, "train_success_rate_last100": self.success_rate}

    # ------------------------------------------------------------------ episode statistics
    @property
    def progress_count(self) -> int:
        """Env steps so far (the progress.csv key)."""
        return self.num_timesteps

    @property
    def mean_return(self) -> float:
        """Mean return of the last 100 episodes (NaN before the first one ends)."""
        return float(np.mean(self.recent_returns)) if self.recent_returns else math.nan

    @property
    def success_rate(self) -> float:
        """Fraction of the last 100 episodes that passed the thesis success test."""
        return float(np.mean(self.recent_successes)) if self.recent_successes else math.nan

    def _record_episodes(self, returns: list[float], ended: torch.Tensor, infos: dict) -> None:
        """Add the ended episodes' returns and success flags (``infos["success"]``) to the statistics."""
        success = infos.get("success")
        succ = (torch.as_tensor(success, device=self.device)[ended].tolist() if success is not None
                else [False] * len(returns))
        self.recent_returns.extend(returns)
        self.recent_successes.extend(bool(s) for s in succ)
        self.num_episodes += len(returns)

    def _note_best(self) -> None:
        """best_mean_return: the best mean of the last 100 returns once 10 episodes ended."""
        if math.isfinite(self.mean_return) and len(self.recent_returns) >= 10:
            self.best_mean_return = max(self.best_mean_return, self.mean_return)

    def plot_curves(self, log) -> None:
        """training_curves.png in the log folder, from every progress row."""
        from ..viz.training import plot_training_curves  # matplotlib: only when plotting

        plot_training_curves(self.log_rows, log.dir / "training_curves.png",
                             title=f"{self.algorithm_name} on {self.system.name}")

    # ------------------------------------------------------------------ inference and evaluation
    def policy_actions(self, x: torch.Tensor, deterministic: bool) -> torch.Tensor:
        """Actions (B, m) for float32 states (B, n) on the agent's device (the subclass's policy)."""
        raise NotImplementedError

    def predict(self, obs, deterministic: bool = True):
        """Actions for states ``obs`` (n,) or (B, n): numpy in -> numpy out, torch in -> torch out.

        The output has the input's floating dtype (float32 for integer input).
        """
        is_torch = isinstance(obs, torch.Tensor)
        x = obs if is_torch else torch.as_tensor(np.asarray(obs), device=self.device)   # one copy, to the agent's device
        dtype = x.dtype if x.is_floating_point() else torch.float32
        single = x.ndim == 1
        x = x.to(device=self.device, dtype=torch.float32).reshape(-1, self.obs_dim)
        with torch.no_grad():
            a = self.policy_actions(x, deterministic)
        a = a[0] if single else a
        if is_torch:
            return a.to(device=obs.device, dtype=dtype)
        return a.cpu().to(dtype).numpy()

    def make_eval_env(self, num_envs: int, seed: int):
        """A fresh vector env like the training env, for :meth:`evaluate` (override for switched envs)."""
        return TorchVectorEnv(self.system, num_envs, decision_period=getattr(self.env, "decision_period", None),
                              device=self.device, seed=seed)

    def run_evaluation(self, episodes: int, seed: int, deterministic: bool = True) -> EvalResult:
        """``evaluate(episodes, seed=, deterministic=True)``: ``episodes`` fresh episodes (initial states
        from the spec, numpy seed ``seed``) with the deterministic policy (``deterministic=False``:
        sampled actions); mean/std/min return, success rate and the returns."""
        env = self.make_eval_env(int(episodes), seed)
        obs, _ = env.reset(seed=seed)
        total = torch.zeros(episodes, dtype=torch.float64)
        running = torch.ones(episodes, dtype=torch.bool)
        success = torch.zeros(episodes, dtype=torch.bool)
        for _ in range(int(env.max_decisions)):
            actions = self.predict(obs.to(torch.float32), deterministic=deterministic).to(torch.float64)
            obs, rewards, terminated, truncated, infos = env.step(actions)
            total += torch.where(running, rewards.double().cpu(), torch.zeros_like(total))
            ended = (terminated | truncated).cpu() & running
            success |= ended & torch.as_tensor(infos["success"]).cpu().bool()
            running &= ~ended
            if not bool(running.any()):
                break
        return EvalResult.from_returns(total.numpy(), success_rate=float(success.float().mean()), first={
            "episodes": int(episodes), "seed": int(seed), "deterministic": bool(deterministic)})

    # ------------------------------------------------------------------ the controller
    def deterministic_policy(self) -> torch.nn.Module:
        """A frozen CPU copy of the deterministic policy (B, n) -> (B, m) (the subclass's)."""
        raise NotImplementedError

    def gate_module(self) -> torch.nn.Module | None:
        """A frozen CPU copy of the learned gate (SSAC's); None: the policy swings up alone (SAC)."""
        return None

    def controller(self, system: System | None = None) -> SwitchedController:
        """The learned swing-up (:meth:`deterministic_policy`) with the learned gate and its hysteresis
        (:meth:`gate_module`; without one, :class:`~hybridctl.systems.switched.NeverGate`) and the LQR of
        ``system`` (default: the one it trained on), at the spec's swing-up period."""
        system = self.system if system is None else system
        if (system.n_states, system.n_actions) != (self.obs_dim, self.action_dim):
            raise ckpt.CheckpointError(f"the {self.algorithm_name} policy has obs/action dims {self.obs_dim}/"
                                       f"{self.action_dim}, {system.name} has {system.n_states}/{system.n_actions}")
        gate = self.gate_module()
        return SwitchedController.for_system(system, swingup=self.deterministic_policy(),
                                             gate=NeverGate() if gate is None else LearnedGate(gate),
                                             gate_on=getattr(self.env, "gate_on", None),
                                             gate_off=getattr(self.env, "gate_off", None))

    @classmethod
    def deploy_overrides(cls, config: dict) -> dict:
        """The CPU, one env, the torch threads as they are and replay buffers of one minibatch: a
        controller needs the policy (and gate) only."""
        batch = config.get("minibatch_size")
        small = {"buffer_size": batch, "needle_buffer_size": batch} if isinstance(batch, int) else {}
        return {**super().deploy_overrides(config), "num_envs": 1, "torch_threads": torch.get_num_threads(), **small}

    # ------------------------------------------------------------------ checkpoints
    @property
    def env_rng_state(self) -> dict | None:
        """The training env's numpy RNG state (checkpointed so a resumed run draws the same starts)."""
        try:
            return self.env.np_random.bit_generator.state
        except AttributeError:
            return None

    @env_rng_state.setter
    def env_rng_state(self, state: dict | None) -> None:
        if state is None:
            return
        try:
            self.env.np_random.bit_generator.state = state
        except (AttributeError, TypeError, ValueError):
            warnings.warn("could not restore the env's RNG state; episodes will differ", stacklevel=2)

    def checkpoint_extra(self) -> dict:
        """config.json beside algorithm, system and config: dimensions, action scale, decision period."""
        return {"obs_dim": self.obs_dim, "action_dim": self.action_dim, "action_scale": self.action_scale.tolist(),
                "decision_period": getattr(self.env, "decision_period", None)}

    def check_checkpoint(self, found: Path, meta: dict, normalization: dict, force: bool = False) -> None:
        """The checkpoint must come from this plant (system name and spec values, see
        :func:`~hybridctl.learn.checkpoint.check_plant`; ``force``: a warning) and use this
        observation normalisation."""
        ckpt.check_plant(found, meta.get("system"), self.system, force)
        if normalization != self.normalization():
            raise ckpt.CheckpointError(f"checkpoint {found} normalization {normalization} differs from the agent's "
                                       f"{self.normalization()} (config obs_transform)")

    def after_restore(self, found: Path, meta: dict, bulky: bool) -> None:
        """The env restarts its episodes on the next learn()."""
        self._obs, self._env_seed = None, None

    @classmethod
    def from_checkpoint(cls, found: Path, meta: dict, config, system, force: bool):
        """:meth:`~hybridctl.learn.base.Learner.load`'s learner: on ``system`` (None: a TorchVectorEnv of
        the recorded system with its spec overrides; a system name, a System or a vector env), which
        must be the system the checkpoint was trained on (name here; spec values when restored)."""
        saved_system = meta["system"]["name"]
        env = system
        if env is None:
            env = ckpt.recorded_system(found, saved_system, meta["system"].get("overrides", {}))
        env_system = env if isinstance(env, str) else env.name if isinstance(env, System) else env.system.name
        if env_system != saved_system and not force:
            raise ckpt.CheckpointError(f"checkpoint {found} was trained on system {saved_system!r}, "
                                       f"but the env is system {env_system!r} ({ckpt.FORCE_HINT})")
        agent = cls._construct_for_load(env, config, found)
        if (agent.obs_dim, agent.action_dim) != (meta.get("obs_dim"), meta.get("action_dim")):
            raise ckpt.CheckpointError(f"checkpoint {found} has obs/action dims {meta.get('obs_dim')}/"
                                       f"{meta.get('action_dim')}, the env {agent.obs_dim}/{agent.action_dim}")
        return agent

    @classmethod
    def _construct_for_load(cls, env, config, found: Path):
        """Hook for :meth:`load`: build the agent whose weights ``found`` then restores
        (subclasses skip expensive set-up that the checkpoint overwrites anyway)."""
        return cls(env, config=config)
