"""Soft Actor-Critic (Haarnoja et al. 2018) on batched torch swing-up envs, as in thesis Ch. 3.

CleanRL-style: the algorithm reads top to bottom in this file (config,
:meth:`SAC.gradient_step`, :meth:`SAC.update`, :meth:`SAC.learn`); the networks live in
:mod:`.networks`, the replay in :mod:`.replay`, the run log, checkpoints, resume and
callbacks in :mod:`.run`. The API is Stable-Baselines3 style (``SAC(env).learn(...)``,
``predict``, ``save`` / ``SAC.load``).

>>> from hybridctl.learn import SAC
>>> agent = SAC("acrobot", total_steps=200_000, seed=1)
>>> agent.learn(log_dir="runs/sac-acrobot")            # progress.csv, checkpoints, curves
>>> policy = agent.deterministic_policy()              # torch.nn.Module (B, n) -> (B, m)
>>> agent = SAC.load("runs/sac-acrobot/final")

Algorithm (thesis Alg. 4 without the gate; the Q-function form of SAC):

* collection: ``num_envs`` episodes run in one :class:`~hybridctl.envs.TorchVectorEnv`;
  during the first ``exploration_steps`` env steps actions are uniform in the action
  box, afterwards ``a = action_scale * tanh(mu + sigma * eps)``;
* every transition (s, a, r, s', done) goes to the replay buffer; s' is the state the
  dynamics reached (``infos["final_obs"]`` for rows that ended) and done is
  *terminated* only (divergence), so time-limit truncations bootstrap;
* every transition of an episode that ends with ``infos["success"]`` (thesis eq. 3.2)
  is also copied to the *needle* buffer (thesis Sec. 3.3, D_n); each replay row is
  drawn from it with probability ``needle_prob`` (0 for plain SAC);
* every ``steps_per_update`` env steps (one *update round*) the agent makes
  ``updates_per_round`` *updates*. One update = one replay batch of
  ``replay_batch_size`` rows, cut into minibatches of ``minibatch_size``; each
  minibatch is one gradient step on the twin Q losses, the policy loss
  ``alpha log pi - min(Q1, Q2)`` and (``alpha="auto"``) the temperature; the target
  Q networks are Polyak-averaged once per update.

How the thesis wording maps to this. The appendix lists "replay batch size 4096",
"minibatch size 128" and "4 policy/value updates per epoch" every "500 steps per
update". The author's code (seagul ``sac``/``sacn_adaptive``) implements one update
as: draw 4096 rows, then loop over them in minibatches of 128 (32 Adam steps per
network), then one Polyak step. So the paper setting is 4 x 4096 / 128 = 128
gradient steps per 500 env steps (author code: 16 x 32 = 512). This module does the
same; set ``replay_batch_size = minibatch_size`` for one gradient step per update
(then a round makes just ``updates_per_round`` gradient steps).

Extending (SSAC in ``hybridctl.learn.ssac`` subclasses this; nothing here knows
about gates or LQR). Overridable methods, each documented below:

* :meth:`SAC.select_actions` -- the actions sent to the env (exploration / policy);
* :meth:`SAC.store_transitions` -- what goes to the replay buffer and the staging area;
* :meth:`SAC.is_needle_episode` -- which ended episodes go to the needle buffer;
* :meth:`SAC.on_episodes_end` -- called with ``(ended_mask, infos)`` after each step
  in which episodes ended (statistics and needle copies already done);
* :meth:`SAC.on_update_round` -- called after every round (after its updates);
* ``saved`` -- the checkpoint entries (:class:`~hybridctl.learn.run.Saved`): a
  subclass appends its own (e.g. a gate's state dict); :meth:`SAC.checkpoint_meta`
  extends config.json, :meth:`SAC.extend_log_columns` / :meth:`SAC._log_row` the log;
* ``config_class`` -- a dataclass derived from :class:`SACConfig` for extra settings.

``learn(callback=...)`` takes :class:`~hybridctl.learn.run.Callback` objects (hooks
with the agent) or a plain ``f(agent)`` called after every update round; returning
False stops training (a final checkpoint is still written).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
import warnings
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from . import checkpoint as ckpt
from ..envs import TorchVectorEnv
from ..systems import System
from ..systems import load as load_system
from .networks import OBS_TRANSFORMS, Actor, DeterministicPolicy, ObsTransform, QNetwork
from .replay import REPLAY_FIELDS, EpisodeStaging, ReplayBuffer, sample_mixed
from .run import PROGRESS_FILE, EvalResult, Learner, Saved, check_finite, seeded, set_torch_threads

# ============================================================================ config


@dataclass
class SACConfig:
    """Every SAC hyperparameter, with its source. Defaults: thesis appendix (Ch. 3).

    Env steps count decisions summed over the parallel envs (acrobot: one decision
    = 0.2 s; thesis: 2e6 "interactions with the environment").
    """

    # --- schedule -----------------------------------------------------------------
    total_steps: int = 2_000_000        # thesis Sec. 3.4.1 / Table 3.1: 2e6 env interactions
    exploration_steps: int = 50_000     # appendix "Exploration steps" 5e4: uniform random actions, no updates
    steps_per_update: int = 500         # appendix "Steps per update" (author code min_steps_per_update=500)
    updates_per_round: int = 4          # appendix "Policy/value updates per epoch" 4 (author code iters_per_update=16)
    replay_batch_size: int = 4096       # appendix "Replay batch size" (rows drawn per update)
    minibatch_size: int = 128           # appendix "Policy/value minibatch size" (rows per gradient step)
    # --- losses and optimiser --------------------------------------------------------
    lr: float = 1e-3                    # appendix "Initial policy/value learning rate" (Adam, all networks)
    gamma: float = 0.95                 # appendix "Discount" 0.95 (author code: 0.99)
    alpha: float | str = 0.05           # appendix "Entropy coefficient" 0.05; "auto": learned (SAC v2, Haarnoja 2018b)
    alpha_init: float = 0.05            # initial alpha for alpha="auto" (hybridctl choice: the paper value)
    alpha_lr: float = 1e-3              # Adam lr of log alpha for alpha="auto" (hybridctl choice: = lr, as CleanRL)
    target_entropy: float | None = None  # alpha="auto" target; None = -action_dim (Haarnoja 2018b, CleanRL, SB3)
    polyak: float = 0.995               # appendix "Polyak constant": target <- polyak target + (1-polyak) online,
    #                                     once per update (replay batch), as Alg. 4 line 17 and the author code
    # --- networks --------------------------------------------------------------------
    hidden_layers: int = 4              # appendix: "four fully connected layers" (author MLP num_layers=4 hidden)
    hidden_size: int = 32               # appendix: 32 hidden nodes, ReLU
    log_std_min: float = -20.0          # implementation notes / author SACModel LOG_STD_MIN
    log_std_max: float = 2.0            # implementation notes / author SACModel LOG_STD_MAX
    obs_transform: str = "none"         # "none": raw state (thesis, author code); "angle_sincos": angles -> sin, cos
    # --- replay ----------------------------------------------------------------------
    buffer_size: int = 1_000_000        # hybridctl choice (CleanRL/SB3 1e6; author run_ssac 5e5): holds half a 2e6 run
    needle_prob: float = 0.0            # plain SAC 0; SSAC: paper 0.5, author code 0.2 (thesis Sec. 3.3, p_n)
    needle_buffer_size: int = 1_000_000  # author code: same size as the main buffer
    # --- environment -----------------------------------------------------------------
    num_envs: int = 32                  # hybridctl choice: parallel episodes in the TorchVectorEnv (thesis: 1)
    # --- runtime ---------------------------------------------------------------------
    seed: int = 0                       # seeds network init, the agent's torch generator and the env
    device: str = "cpu"                 # networks, replay and env (CPU: tiny networks)
    torch_threads: int = 1              # hybridctl measurement (2 cores): 2 threads give no speed-up on these
    #                                     tiny ops (~2.4 ms per gradient step either way); 1 leaves a core free
    checkpoint_every: int = 100_000     # env steps between checkpoints in log_dir/checkpoint (0: none)
    log_every: int = 10_000             # env steps between progress.csv rows
    save_replay: bool = True            # checkpoints in learn() include replay.pt (resume restores the buffers)
    tensorboard: bool = True            # also write TensorBoard scalars when torch.utils.tensorboard imports

    def __post_init__(self):
        # accept integral floats such as total_steps=2e6
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.type in ("int", int) and isinstance(value, float) and value.is_integer():
                setattr(self, f.name, int(value))

    def validate(self) -> None:
        """Raise ValueError naming the first invalid field."""
        positive = ["steps_per_update", "updates_per_round", "replay_batch_size", "minibatch_size",
                    "hidden_layers", "hidden_size", "buffer_size", "needle_buffer_size", "num_envs",
                    "torch_threads", "log_every"]
        for name in positive:
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
                raise ValueError(f"SACConfig.{name} must be an integer >= 1, got {value!r}")
        for name in ("total_steps", "exploration_steps", "checkpoint_every", "seed"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 0:
                raise ValueError(f"SACConfig.{name} must be an integer >= 0, got {value!r}")
        for name in ("lr", "alpha_lr", "alpha_init"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"SACConfig.{name} must be a finite number > 0, got {getattr(self, name)!r}")
        if not 0.0 <= self.gamma <= 1.0:
            raise ValueError(f"SACConfig.gamma must be in [0, 1], got {self.gamma!r}")
        if not 0.0 <= self.polyak <= 1.0:
            raise ValueError(f"SACConfig.polyak must be in [0, 1], got {self.polyak!r}")
        if not 0.0 <= self.needle_prob <= 1.0:
            raise ValueError(f"SACConfig.needle_prob must be in [0, 1], got {self.needle_prob!r}")
        if isinstance(self.alpha, str):
            if self.alpha != "auto":
                raise ValueError(f"SACConfig.alpha must be a number >= 0 or 'auto', got {self.alpha!r}")
        elif not (math.isfinite(self.alpha) and self.alpha >= 0):
            raise ValueError(f"SACConfig.alpha must be a number >= 0 or 'auto', got {self.alpha!r}")
        if not self.log_std_min < self.log_std_max:
            raise ValueError(f"SACConfig needs log_std_min < log_std_max, got {self.log_std_min}, {self.log_std_max}")
        if self.obs_transform not in OBS_TRANSFORMS:
            raise ValueError(f"SACConfig.obs_transform must be one of {OBS_TRANSFORMS}, got {self.obs_transform!r}")

    @property
    def gradient_steps_per_update(self) -> int:
        """Minibatches per replay batch: ceil(replay_batch_size / minibatch_size) (paper: 32)."""
        return -(-self.replay_batch_size // self.minibatch_size)



# ============================================================================= agent


def _adam(params, lr: float) -> torch.optim.Adam:
    """Adam; the fused CPU kernel where available (measured ~25% faster gradient steps here)."""
    params = list(params)
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, TypeError, ValueError):
        return torch.optim.Adam(params, lr=lr)


def _next_multiple(value: int, every: int) -> float:
    """The first multiple of ``every`` above ``value`` (inf when ``every`` is 0: never)."""
    return (value // every + 1) * every if every else math.inf


def _progress(key: str, attr: str, **kw) -> Saved:
    return Saved(key, attr, file=PROGRESS_FILE, **kw)


class SAC(Learner):
    """Soft Actor-Critic on a batched torch vector env.

    Args:
        env_or_system: a system name (``"acrobot"``), a loaded ``System`` (a
            :class:`~hybridctl.envs.TorchVectorEnv` with ``config.num_envs`` envs and
            ``config.seed`` is built) or a TorchVectorEnv-like vector env with
            ``system``, ``num_envs``, ``max_decisions`` and same-step autoreset.
        config: a :class:`SACConfig` (default: the thesis values).
        **overrides: config fields to replace, e.g. ``SAC("acrobot", seed=3, alpha="auto")``.

    Attributes: ``env``, ``config``, ``actor``, ``q1``, ``q2``, ``q1_target``,
    ``q2_target``, ``replay``, ``needle`` (:class:`ReplayBuffer`), ``num_timesteps``
    (env steps), ``num_episodes``, ``num_gradient_steps``, ``num_updates``, ``num_rounds``.
    """

    config_class = SACConfig
    algorithm_name = "SAC"
    compatible_algorithms = ("SAC", "SSAC")  # an SSAC checkpoint holds a whole SAC agent
    log_key = "env_steps"
    log_columns = ("env_steps", "episodes", "mean_return", "success_rate", "q_loss", "pi_loss", "alpha",
                   "steps_per_s", "wall_time", "gradient_steps", "needle_size")
    log_int_columns = ("env_steps", "episodes", "gradient_steps", "needle_size")
    # what a checkpoint holds (model.pt, progress.json, replay.pt), declared once
    saved = (*(Saved(name, name, "state") for name in ("actor", "q1", "q2", "q1_target", "q2_target",
                                                         "actor_opt", "q_opt")),
             Saved("log_alpha", "log_alpha", "param"), Saved("alpha_opt", "alpha_opt", "state", optional=True),
             Saved("generator", "generator", "rng", optional=True),
             _progress("env_steps", "num_timesteps", load=int),
             *(_progress(key, attr, optional=True, load=int) for key, attr in (
                 ("episodes", "num_episodes"), ("gradient_steps", "num_gradient_steps"), ("updates", "num_updates"),
                 ("rounds", "num_rounds"), ("needle_episodes", "num_needle_episodes"))),
             _progress("needle_size", "needle.size", restore=False), _progress("replay_size", "replay.size", restore=False),
             _progress("wall_time", "wall_time", optional=True, load=float),
             _progress("mean_return", "mean_return", restore=False),
             _progress("best_mean_return", "best_mean_return", optional=True,
                       load=lambda v: -math.inf if v is None else float(v)),
             _progress("success_rate", "success_rate", restore=False),
             _progress("recent_returns", "recent_returns", optional=True, save=list, load=lambda v: deque(v, maxlen=100)),
             _progress("recent_successes", "recent_successes", optional=True, save=list,
                       load=lambda v: deque(v, maxlen=100)),
             _progress("env_rng_state", "env_rng_state", optional=True),
             Saved("replay", "replay", "state", file=ckpt.REPLAY_FILE, bulky=True),
             Saved("needle", "needle", "state", file=ckpt.REPLAY_FILE, bulky=True))

    def __init__(self, env_or_system, config: SACConfig | None = None, **overrides):
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
            raise ValueError(f"SAC needs a symmetric, finite action box, got [{low}, {high}]")
        self.action_scale = torch.as_tensor(high, dtype=torch.float32, device=self.device)
        self.target_entropy = float(-self.action_dim if cfg.target_entropy is None else cfg.target_entropy)

        # networks (initialised from the seed without touching the global torch RNG)
        with seeded(cfg.seed):
            self.actor = Actor(self._transform(), self.action_dim, self.action_scale, cfg.hidden_layers,
                               cfg.hidden_size, cfg.log_std_min, cfg.log_std_max).to(self.device)
            self.q1, self.q2 = (QNetwork(self._transform(), self.action_dim, self.action_scale, cfg.hidden_layers,
                                         cfg.hidden_size).to(self.device) for _ in range(2))
        self.q1_target, self.q2_target = copy.deepcopy(self.q1), copy.deepcopy(self.q2)
        for p in (*self.q1_target.parameters(), *self.q2_target.parameters()):
            p.requires_grad_(False)
        self._q_params = [*self.q1.parameters(), *self.q2.parameters()]
        self._target_params = [*self.q1_target.parameters(), *self.q2_target.parameters()]
        self.actor_opt = _adam(self.actor.parameters(), cfg.lr)
        self.q_opt = _adam(self._q_params, cfg.lr)
        self.auto_alpha = cfg.alpha == "auto"
        alpha0 = cfg.alpha_init if self.auto_alpha else max(float(cfg.alpha), 1e-30)
        self.log_alpha = torch.tensor(math.log(alpha0), device=self.device, requires_grad=self.auto_alpha)
        self.alpha_opt = _adam([self.log_alpha], cfg.alpha_lr) if self.auto_alpha else None

        # replay, needle buffer and the per-env staging area of the current episodes
        self.replay = ReplayBuffer(cfg.buffer_size, self.obs_dim, self.action_dim, self.device)
        self.needle = ReplayBuffer(cfg.needle_buffer_size, self.obs_dim, self.action_dim, self.device)
        horizon = int(getattr(self.env, "max_decisions", 1000))
        self.staging = EpisodeStaging(cfg.num_envs, horizon, self.obs_dim, self.action_dim, self.device)

        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(cfg.seed)
        self.num_timesteps = self.num_episodes = self.num_gradient_steps = 0
        self.num_updates = self.num_rounds = self.num_needle_episodes = 0
        self.wall_time = 0.0
        self.best_mean_return = -math.inf
        self.recent_returns: deque[float] = deque(maxlen=100)
        self.recent_successes: deque[bool] = deque(maxlen=100)
        self.log_rows: list[dict] = []
        self._obs: torch.Tensor | None = None
        self._env_seed: int | None = cfg.seed  # reset(seed=...) on the first learn(); None after a load
        self._episode_return = torch.zeros(cfg.num_envs, dtype=torch.float64, device=self.device)
        self._loss_sums = {"q_loss": 0.0, "pi_loss": 0.0, "n": 0}

    # ------------------------------------------------------------------ construction
    @staticmethod
    def _make_env(env_or_system, cfg: SACConfig):
        if isinstance(env_or_system, (str, System)):
            return TorchVectorEnv(env_or_system, cfg.num_envs, device=cfg.device, seed=cfg.seed)
        env = env_or_system
        for attr in ("system", "num_envs", "single_observation_space", "single_action_space"):
            if not hasattr(env, attr):
                raise TypeError(f"env must be a system name, a System or a TorchVectorEnv-like vector env "
                                f"(missing attribute {attr!r}), got {type(env).__name__}")
        mode = getattr(env, "metadata", {}).get("autoreset_mode")
        if mode is not None and "same" not in str(getattr(mode, "value", mode)).lower():
            raise ValueError(f"SAC needs a vector env with same-step autoreset (final_obs in infos), got {mode}")
        return env

    def _transform(self) -> ObsTransform:
        return ObsTransform(self.config.obs_transform, self.obs_dim, getattr(self.system, "angle_indices", []))

    @property
    def alpha(self) -> torch.Tensor:
        """The entropy coefficient (a 0-d tensor, no gradient)."""
        if not self.auto_alpha:
            return torch.tensor(float(self.config.alpha), device=self.device)
        return self.log_alpha.detach().exp()

    # ================================================================ the SAC update
    def gradient_step(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """One Adam step on the Q losses, the policy loss and (auto) alpha, on one minibatch.

        Raises FloatingPointError (before any weight changes) if a loss is NaN/Inf.
        """
        cfg, gen = self.config, self.generator
        obs, act, rew, next_obs, done = (batch[f] for f in REPLAY_FIELDS)
        alpha = self.alpha
        # soft Bellman target from the target networks (no bootstrap past a termination)
        with torch.no_grad():
            next_act, next_logp = self.actor.sample(next_obs, torch.randn(act.shape, generator=gen, device=act.device))
            q_next = torch.min(self.q1_target(next_obs, next_act), self.q2_target(next_obs, next_act))
            target = rew + cfg.gamma * (1.0 - done) * (q_next - alpha * next_logp)
        q_loss = F.mse_loss(self.q1(obs, act), target) + F.mse_loss(self.q2(obs, act), target)
        self._check_finite("q_loss", q_loss)
        self.q_opt.zero_grad(set_to_none=True)
        q_loss.backward()
        self.q_opt.step()

        # policy: minimise alpha log pi - min(Q1, Q2) at reparameterised actions
        new_act, logp = self.actor.sample(obs, torch.randn(act.shape, generator=gen, device=act.device))
        pi_loss = (alpha * logp - torch.min(self.q1(obs, new_act), self.q2(obs, new_act))).mean()
        self._check_finite("pi_loss", pi_loss)
        self.actor_opt.zero_grad(set_to_none=True)
        pi_loss.backward()
        self.actor_opt.step()

        out = {"q_loss": q_loss.detach(), "pi_loss": pi_loss.detach()}
        if self.auto_alpha:  # temperature: drive the entropy towards target_entropy
            alpha_loss = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
            self._check_finite("alpha_loss", alpha_loss)
            self.alpha_opt.zero_grad(set_to_none=True)
            alpha_loss.backward()
            self.alpha_opt.step()
            out["alpha_loss"] = alpha_loss.detach()
        self.num_gradient_steps += 1
        return out

    def update(self) -> None:
        """One thesis "update": a replay batch, one gradient step per minibatch, one Polyak step."""
        cfg = self.config
        batch, _ = sample_mixed(self.replay, self.needle, cfg.replay_batch_size, cfg.needle_prob, self.generator)
        for start in range(0, cfg.replay_batch_size, cfg.minibatch_size):
            losses = self.gradient_step({f: v[start:start + cfg.minibatch_size] for f, v in batch.items()})
            self._loss_sums["q_loss"] += float(losses["q_loss"])
            self._loss_sums["pi_loss"] += float(losses["pi_loss"])
            self._loss_sums["n"] += 1
        with torch.no_grad():  # target <- polyak target + (1 - polyak) online
            torch._foreach_lerp_(self._target_params, self._q_params, 1.0 - cfg.polyak)
        self.num_updates += 1

    def _check_finite(self, name: str, loss: torch.Tensor) -> None:
        check_finite(f"{self.algorithm_name}: {name}", loss, f"at env step {self.num_timesteps} (gradient step "
                     f"{self.num_gradient_steps + 1}, update {self.num_updates + 1})")

    # ========================================================== collection (hooks)
    def select_actions(self, obs: torch.Tensor, explore: bool) -> torch.Tensor:
        """Actions (N, m) for the env. ``explore``: uniform in the action box (thesis
        "exploration steps"); else a sample from the policy. Override to switch controllers."""
        n = obs.shape[0]
        if explore:
            u = torch.rand((n, self.action_dim), generator=self.generator, device=self.device)
            return (2 * u - 1) * self.action_scale
        with torch.no_grad():
            eps = torch.randn((n, self.action_dim), generator=self.generator, device=self.device)
            return self.actor.sample(obs, eps)[0]

    def store_transitions(self, obs, actions, rewards, next_obs, dones, infos) -> None:
        """Add one vector step (N rows, float32 on the agent's device) to the replay buffer
        and the needle staging area. Override to filter rows (keep the staging in step)."""
        self.replay.add(obs, actions, rewards, next_obs, dones)
        self.staging.add(obs, actions, rewards, next_obs, dones)

    def is_needle_episode(self, ended: torch.Tensor, infos: dict) -> torch.Tensor:
        """(N,) bool: ended episodes whose transitions go to the needle buffer (default:
        the env's thesis success test, ``infos["success"]``)."""
        success = infos.get("success")
        if success is None:
            return torch.zeros_like(ended)
        return ended & torch.as_tensor(success, device=ended.device).bool()

    def on_episodes_end(self, ended: torch.Tensor, infos: dict) -> None:
        """Hook: called after a vector step in which the episodes ``ended`` (N,) bool ended
        (returns/success already recorded, needle copies done). ``self.staging.take(ended)``
        still returns those episodes' transitions here (cleared right after). Default: nothing."""

    def on_update_round(self) -> None:
        """Hook: called after every update round (``steps_per_update`` env steps; during
        exploration the round has no updates). Default: nothing."""

    # ======================================================================== learn
    def learn(self, total_steps: int | None = None, progress: bool = True, callback=None,
              log_dir: str | Path | None = None, resume: bool = False) -> "SAC":
        """Train until ``num_timesteps`` reaches ``total_steps`` (default ``config.total_steps``).

        ``total_steps`` is the run's total (not an increment): a resumed run or a second
        call continues until the agent has taken that many env steps in all (rounded up
        to a multiple of ``num_envs``).

        Args:
            progress: show a tqdm bar (mean return of the last 100 episodes, success
                rate, gradient steps).
            callback: a :class:`~hybridctl.learn.run.Callback`, a list of them, or a
                plain ``f(agent)`` called after every update round; False stops training.
            log_dir: where ``progress.csv``, ``training_curves.png``, the checkpoints
                ``checkpoint/`` (every ``checkpoint_every`` env steps) and ``final/``
                (at the end) go; TensorBoard scalars in ``tb/`` if available. None: no files.
            resume: continue from the newest checkpoint in ``log_dir`` (networks,
                optimizers, counters, RNG states and, if it was saved, the replay). The
                episodes that were running are lost: the env restarts. Without a
                checkpoint there, training starts fresh (with a warning).

        Raises FloatingPointError if a loss becomes NaN/Inf (checkpoints stay as they were).
        """
        cfg = self.config
        total = int(cfg.total_steps if total_steps is None else total_steps)
        with self.run(log_dir, resume, progress, callback, total) as run:
            if self._obs is None:
                obs, _ = self.env.reset(seed=self._env_seed)
                self._env_seed = None
                self._obs = obs.to(device=self.device, dtype=torch.float32)
                self.staging.clear()
                self._episode_return.zero_()
            round_anchor = self.num_rounds * cfg.steps_per_update  # env steps at which the next round is due
            next_log, next_ckpt = (_next_multiple(self.num_timesteps, e) for e in (cfg.log_every, cfg.checkpoint_every))
            start_time, wall_base = time.perf_counter(), self.wall_time
            last_log_time, last_log_steps = start_time, self.num_timesteps
            while self.num_timesteps < total and not run.stopped:
                self.collect()
                run.advance(cfg.num_envs)
                # update rounds: every steps_per_update env steps, updates_per_round updates
                while self.num_timesteps - round_anchor >= cfg.steps_per_update and not run.stopped:
                    round_anchor += cfg.steps_per_update
                    self.num_rounds += 1
                    if self.num_timesteps >= cfg.exploration_steps:
                        for _ in range(cfg.updates_per_round):
                            self.update()
                    self.on_update_round()
                    run.after_update(ret=f"{self.mean_return:.2f}", succ=f"{self.success_rate:.2f}",
                                     grad=str(self.num_gradient_steps))
                # log and checkpoint
                now = time.perf_counter()
                self.wall_time = wall_base + (now - start_time)
                if self.num_timesteps >= next_log or self.num_timesteps >= total or run.stopped:
                    run.log(self._log_row((self.num_timesteps - last_log_steps) / max(now - last_log_time, 1e-9)))
                    last_log_time, last_log_steps = now, self.num_timesteps
                    next_log = _next_multiple(self.num_timesteps, cfg.log_every)
                if self.num_timesteps >= next_ckpt:
                    next_ckpt = _next_multiple(self.num_timesteps, cfg.checkpoint_every)
                    run.checkpoint()
        return self

    def collect(self) -> None:
        """One vector env step: act, step all envs, store the transitions, close ended episodes."""
        obs = self._obs
        # act: uniform during exploration, then the stochastic policy
        actions = self.select_actions(obs, explore=self.num_timesteps < self.config.exploration_steps)
        # step (same-step autoreset: next_obs of ended rows is a new start; final_obs the real next state)
        next_obs, rewards, terminated, truncated, infos = self.env.step(actions)
        next_obs = next_obs.to(device=self.device, dtype=torch.float32)
        real_next = next_obs
        if "_final_obs" in infos:
            ended_rows = torch.as_tensor(infos["_final_obs"], device=self.device)
            final = torch.as_tensor(infos["final_obs"], device=self.device, dtype=torch.float32)
            real_next = torch.where(ended_rows[:, None], final, next_obs)
        terminated = torch.as_tensor(terminated, device=self.device)
        ended = terminated | torch.as_tensor(truncated, device=self.device)
        rewards = torch.as_tensor(rewards, device=self.device)
        # store; done = terminated only, so truncation (time limit) bootstraps
        self.store_transitions(obs, actions.to(self.device, torch.float32), rewards.float(), real_next,
                               terminated.float(), infos)
        self._episode_return += rewards.double()
        if bool(ended.any()):
            self._end_episodes(ended, infos)
        self._obs = next_obs
        self.num_timesteps += self.config.num_envs

    def _end_episodes(self, ended: torch.Tensor, infos: dict) -> None:
        """Record returns and success of the ended rows, copy needle episodes, reset staging."""
        returns = self._episode_return[ended].tolist()
        success = infos.get("success")
        succ = (torch.as_tensor(success, device=self.device)[ended].tolist() if success is not None
                else [False] * len(returns))
        self.recent_returns.extend(returns)
        self.recent_successes.extend(bool(s) for s in succ)
        self.num_episodes += len(returns)
        needle_rows = self.is_needle_episode(ended, infos)
        if bool(needle_rows.any()):
            self.num_needle_episodes += int(needle_rows.sum())
            self.needle.add(*self.staging.take(needle_rows).values())
        self.on_episodes_end(ended, infos)
        self.staging.clear(ended)
        self._episode_return[ended] = 0.0

    # ================================================================== logging
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

    def _log_row(self, steps_per_s: float) -> dict:
        """The progress row now (subclasses add their columns); resets the loss averages."""
        n = self._loss_sums["n"]
        row = {"env_steps": self.num_timesteps, "episodes": self.num_episodes, "mean_return": self.mean_return,
               "success_rate": self.success_rate,
               "q_loss": self._loss_sums["q_loss"] / n if n else math.nan,
               "pi_loss": self._loss_sums["pi_loss"] / n if n else math.nan,
               "alpha": float(self.alpha), "steps_per_s": steps_per_s, "wall_time": self.wall_time,
               "gradient_steps": self.num_gradient_steps, "needle_size": self.needle.size}
        self._loss_sums = {"q_loss": 0.0, "pi_loss": 0.0, "n": 0}
        if math.isfinite(row["mean_return"]) and len(self.recent_returns) >= 10:
            self.best_mean_return = max(self.best_mean_return, row["mean_return"])
        return row

    def plot_curves(self, log) -> None:
        """training_curves.png in the log folder, from every progress row."""
        from ..viz.training import plot_training_curves  # viz loads matplotlib (and pydrake): only when plotting

        plot_training_curves(self.log_rows, log.dir / "training_curves.png",
                             title=f"{self.algorithm_name} on {self.system.name}")

    # ================================================================ inference
    def predict(self, obs, deterministic: bool = True):
        """Actions for states ``obs`` (n,) or (B, n): numpy in -> numpy out, torch in -> torch out.

        deterministic: ``action_scale * tanh(mu)``; else a policy sample (global torch RNG).
        The output has the input's floating dtype (float32 for integer input).
        """
        is_torch = isinstance(obs, torch.Tensor)
        x = obs if is_torch else torch.as_tensor(np.asarray(obs))
        dtype = x.dtype if x.is_floating_point() else torch.float32
        single = x.ndim == 1
        x = x.to(device=self.device, dtype=torch.float32).reshape(-1, self.obs_dim)
        with torch.no_grad():
            if deterministic:
                a = self.actor.deterministic(x)
            else:
                a = self.actor.sample(x, torch.randn(x.shape[0], self.action_dim, device=self.device))[0]
        a = a[0] if single else a
        if is_torch:
            return a.to(device=obs.device, dtype=dtype)
        return a.cpu().to(dtype).numpy()

    def deterministic_policy(self) -> DeterministicPolicy:
        """A frozen ``torch.nn.Module`` copy of the current policy: (B, n) -> (B, m).

        Includes the observation transform; use it in a Drake ``TorchPolicy`` block.
        Later training does not change it (call again for the newer policy).
        """
        return DeterministicPolicy(self.actor).to("cpu")

    def make_eval_env(self, num_envs: int, seed: int):
        """A fresh vector env like the training env, for :meth:`evaluate` (override for switched envs)."""
        return TorchVectorEnv(self.system, num_envs, decision_period=getattr(self.env, "decision_period", None),
                              device=self.device, seed=seed)

    def evaluate(self, episodes: int = 100, seed: int = 12345, deterministic: bool = True) -> EvalResult:
        """Run ``episodes`` fresh episodes (initial states from the spec, numpy seed ``seed``)
        with the deterministic policy; returns mean/std/min return, success rate and the returns."""
        if not isinstance(episodes, (int, np.integer)) or episodes < 1:
            raise ValueError(f"episodes must be an integer >= 1, got {episodes!r}")
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

    # ============================================================ save and load
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

    def checkpoint_meta(self) -> dict:
        """config.json: algorithm, config, system (name and spec overrides), dimensions, decision period."""
        spec = getattr(self.system, "spec", None)
        return {"algorithm": self.algorithm_name, "config": dataclasses.asdict(self.config),
                "system": {"name": self.system.name, "overrides": getattr(spec, "overrides", {}) or {}},
                "obs_dim": self.obs_dim, "action_dim": self.action_dim, "action_scale": self.action_scale.tolist(),
                "decision_period": getattr(self.env, "decision_period", None)}

    def normalization(self) -> dict:
        """normalization.json: the observation transform (stateless)."""
        return self.actor.transform.describe()

    def check_checkpoint(self, found: Path, meta: dict, normalization: dict) -> None:
        """The checkpoint must come from this system and use this observation transform."""
        if meta.get("system", {}).get("name") != self.system.name:
            raise ckpt.CheckpointError(f"checkpoint {found} was trained on system "
                                       f"{meta.get('system', {}).get('name')!r}, but the env is system "
                                       f"{self.system.name!r}")
        if normalization != self.actor.transform.describe():
            raise ckpt.CheckpointError(f"checkpoint {found} normalization {normalization} differs from the agent's "
                                       f"{self.actor.transform.describe()} (config obs_transform)")

    def after_restore(self, found: Path, meta: dict, bulky: bool) -> None:
        """The env restarts its episodes on the next learn()."""
        self._obs, self._env_seed = None, None

    @classmethod
    def load(cls, path: str | Path, env=None, **overrides) -> "SAC":
        """Load a checkpoint directory written by :meth:`save` (or by ``learn``).

        ``env``: None (a TorchVectorEnv of the checkpoint's system, with its spec
        overrides), a system name, a System or a vector env; it must be the system the
        checkpoint was trained on. ``overrides`` replace config fields (e.g. ``num_envs``).
        The replay buffer is not loaded (``learn(resume=True)`` does that).
        """
        found = ckpt.resolve_checkpoint_dir(path)
        meta = ckpt.read_json(found / ckpt.CONFIG_FILE)
        saved_system = meta.get("system", {}).get("name")
        if env is None:
            env = load_system(saved_system, **meta["system"].get("overrides", {}))
        env_system = env if isinstance(env, str) else env.name if isinstance(env, System) else env.system.name
        if env_system != saved_system:
            raise ckpt.CheckpointError(f"checkpoint {found} was trained on system {saved_system!r}, "
                                       f"but the env is system {env_system!r}")
        fields = {f.name for f in dataclasses.fields(cls.config_class)}
        saved = {k: v for k, v in meta["config"].items() if k in fields}
        config = dataclasses.replace(cls.config_class(**saved), **overrides)
        agent = cls._construct_for_load(env, config, found)
        if (agent.obs_dim, agent.action_dim) != (meta.get("obs_dim"), meta.get("action_dim")):
            raise ckpt.CheckpointError(f"checkpoint {found} has obs/action dims {meta.get('obs_dim')}/"
                                       f"{meta.get('action_dim')}, the env {agent.obs_dim}/{agent.action_dim}")
        agent.checkpointer.restore(found, bulky=False)
        return agent

    @classmethod
    def _construct_for_load(cls, env, config: SACConfig, found: Path) -> "SAC":
        """Hook for :meth:`load`: build the agent whose weights ``found`` then restores
        (subclasses skip expensive set-up that the checkpoint overwrites anyway)."""
        return cls(env, config=config)
