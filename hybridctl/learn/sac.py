"""Soft Actor-Critic (Haarnoja et al. 2018) on batched torch swing-up envs, as in thesis Ch. 3.

CleanRL-style: the algorithm reads top to bottom in this file (config,
:meth:`SAC.gradient_step`, :meth:`SAC.update`, :meth:`SAC.learn`); the networks live in
:mod:`.networks`, the replay in :mod:`.replay`, the run log, checkpoints, resume and
callbacks in :mod:`.run`, the two ways to the losses' gradients (autograd, compiled graphs) in
:mod:`.sac_grads`. The API is Stable-Baselines3 style (``SAC(env).learn(...)``,
``predict``, ``save`` / ``SAC.load``).

>>> from hybridctl.learn import SAC
>>> agent = SAC("acrobot", total_steps=200_000, seed=1)
>>> agent.learn(out="runs/sac-acrobot")            # progress.csv, checkpoints, curves
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
* :meth:`SAC.before_update_round` -- called at the start of every round (before its updates);
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
import math
import time
import warnings
from dataclasses import dataclass, fields
from pathlib import Path

import torch
import torch.nn.functional as F
from torch.func import functional_call

from . import checkpoint as ckpt
from ..limits import check_at_most
from ..systems import System
from ..systems.compiled import COMPILE_MODES, wants_compile
from .networks import (OBS_TRANSFORMS, Actor, DeterministicPolicy, ObsTransform, QNetwork, squashed_sample,
                       twin_q_values)
from .replay import REPLAY_FIELDS, EpisodeStaging, ReplayBuffer, sample_mixed
from .config_check import check_types
from .optim import FusedAdamStep, adam as _adam
from .checkpoint import Saved
from .config_check import check_device_available, check_device_field, check_fields  # noqa: F401 (re-exported)
from .run import check_finite, seeded
from .sac_grads import CompiledGrads, EagerGrads
from .vector_agent import VectorEnvAgent, progress_entry

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
    actor_delay: int = 0                # hybridctl: env steps before the first policy step (the critics and alpha
    #                                     train from the start): a run started from a cloned policy keeps it while
    #                                     the critics learn its values (0: SAC as published)
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
    compile: str = "auto"               # hybridctl: "on" = torch.compile the losses' forward and backward (one
    #                                     fused graph each, gradients by torch.func) and the env's decision;
    #                                     "off" = eager autograd; "auto" = "on" when a learn() call has >= 2e5
    #                                     env steps to go (compiling costs 15-70 s), with an eager fallback
    torch_threads: int = 1              # hybridctl measurement (2 cores): 2 threads give no speed-up on these
    #                                     tiny ops (~2.4 ms per gradient step either way); 1 leaves a core free
    checkpoint_every: int = 100_000     # env steps between checkpoints in log_dir/checkpoint (0: none)
    checkpoint_minutes: float = 5.0     # hybridctl: also a checkpoint at least every this many minutes of wall
    #                                     time, so a kill loses minutes at most (0: by env steps only)
    log_every: int = 10_000             # env steps between progress.csv rows
    save_replay: bool = True            # checkpoints in learn() include replay.pt (resume restores the buffers)
    tensorboard: bool = True            # also write TensorBoard scalars when torch.utils.tensorboard imports

    def __post_init__(self):
        # accept integral floats such as total_steps=2e6
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type in ("int", int) and isinstance(value, float) and value.is_integer():
                setattr(self, f.name, int(value))

    def describe_budget(self) -> str:
        """The run's budget in a run's account."""
        return f"{self.total_steps} env steps, seed {self.seed}"

    def validate(self) -> None:
        """Raise ValueError naming the first invalid field."""
        check_types(self)
        check_fields(self, integers_from_1=("steps_per_update", "updates_per_round", "replay_batch_size",
                                            "minibatch_size", "hidden_layers", "hidden_size", "buffer_size",
                                            "needle_buffer_size", "num_envs", "torch_threads", "log_every"),
                     integers_from_0=("total_steps", "exploration_steps", "actor_delay", "checkpoint_every", "seed"),
                     positive=("lr", "alpha_lr", "alpha_init"), unit_interval=("gamma", "polyak", "needle_prob"))
        if isinstance(self.alpha, str):
            if self.alpha != "auto":
                raise ValueError(f"SACConfig.alpha must be a number >= 0 or 'auto', got {self.alpha!r}")
        elif not (math.isfinite(self.alpha) and self.alpha >= 0):
            raise ValueError(f"SACConfig.alpha must be a number >= 0 or 'auto', got {self.alpha!r}")
        if not self.log_std_min < self.log_std_max:
            raise ValueError(f"SACConfig needs log_std_min < log_std_max, got {self.log_std_min}, {self.log_std_max}")
        if self.compile not in COMPILE_MODES:
            raise ValueError(f"SACConfig.compile must be one of {COMPILE_MODES}, got {self.compile!r}")
        if self.obs_transform not in OBS_TRANSFORMS:
            raise ValueError(f"SACConfig.obs_transform must be one of {OBS_TRANSFORMS}, got {self.obs_transform!r}")
        check_device_field(self)
        name = type(self).__name__
        for key in ("buffer_size", "needle_buffer_size"):
            check_at_most(f"{name}.{key}", getattr(self, key), MAX_BUFFER_SIZE, why="transitions held in memory",
                          force_flag=None)
        # a minibatch is drawn from the filled part of the buffer: a smaller buffer can never fill one
        if self.buffer_size < self.minibatch_size:
            raise ValueError(f"{name}.buffer_size ({self.buffer_size}) must be >= minibatch_size "
                             f"({self.minibatch_size}): a minibatch is drawn from the buffer")
        if self.needle_prob > 0 and self.needle_buffer_size < self.minibatch_size:
            raise ValueError(f"{name}.needle_buffer_size ({self.needle_buffer_size}) must be >= minibatch_size "
                             f"({self.minibatch_size}) when needle_prob > 0")

    def exploration_note(self, total_steps: int | None = None) -> str | None:
        """A one-line note when a run of ``total_steps`` (default ``total_steps``) env steps ends within
        the exploration phase: it takes uniform random actions only and makes no gradient step. None
        otherwise. Not an error: a smoke test may do it on purpose."""
        total = self.total_steps if total_steps is None else total_steps
        if total > self.exploration_steps:
            return None
        return (f"note: {total:,} env steps are no more than exploration_steps ({self.exploration_steps:,}): the run "
                f"takes uniform random actions only and makes no gradient step (lower exploration_steps, CLI "
                f"--exploration-steps, to learn)")

    @property
    def gradient_steps_per_update(self) -> int:
        """Minibatches per replay batch: ceil(replay_batch_size / minibatch_size) (paper: 32)."""
        return -(-self.replay_batch_size // self.minibatch_size)


# ============================================================================= agent


MAX_BUFFER_SIZE = 100_000_000
"""Transitions of one replay (or needle) buffer (``buffer_size``, ``needle_buffer_size``): 1e8 rows of
the acrobot's transitions are about 4.4 GB; 100x the default 1e6, which holds half a thesis run."""


def set_lr(optimizer: torch.optim.Optimizer, lr: float) -> None:
    """Set every parameter group's learning rate."""
    for group in optimizer.param_groups:
        group["lr"] = lr


def _call(module: torch.nn.Module, params: dict | None, *args):
    """``module(*args)``, with ``params`` (name -> tensor) in place of its own parameters when given."""
    return module(*args) if params is None else functional_call(module, params, args)


def _next_multiple(value: int, every: int) -> float:
    """The first multiple of ``every`` above ``value`` (inf when ``every`` is 0: never)."""
    return (value // every + 1) * every if every else math.inf


class SAC(VectorEnvAgent):
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
    Env set-up, inference, ``evaluate``, ``load``: :class:`~hybridctl.learn.vector_agent.VectorEnvAgent`.
    """

    config_class = SACConfig
    warm_starts = init_keeps_data = True   # --init: networks, optimisers, replay (SSAC: gate data) go on
    algorithm_name = "SAC"
    train_order = 0
    takes_spec = True
    compatible_algorithms = ("SAC",)  # an SSAC checkpoint holds a whole SAC agent: SAC.load(..., force=True)
    log_columns = ("env_steps", "episodes", "mean_return", "success_rate", "q_loss", "pi_loss", "alpha",
                   "steps_per_s", "wall_time", "gradient_steps", "needle_size")
    log_int_columns = ("env_steps", "episodes", "gradient_steps", "needle_size")
    # the checkpoint, declared once: networks, optimizers, alpha, RNG (model.pt), counters (progress.json),
    # the main and needle buffers (replay.pt, for resume)
    saved = (*VectorEnvAgent.saved,
             *(Saved(name, name, "state") for name in ("actor", "q1", "q2", "q1_target", "q2_target",
                                                         "actor_opt", "q_opt")),
             Saved("log_alpha", "log_alpha", "param"), Saved("alpha_opt", "alpha_opt", "state", optional=True),
             Saved("generator", "generator", "rng", optional=True),
             *(progress_entry(key, f"num_{key}", optional=True, load=int)
               for key in ("gradient_steps", "updates", "rounds", "needle_episodes")),
             progress_entry("needle_size", "needle.size", restore=False),
             progress_entry("replay_size", "replay.size", restore=False),
             Saved("replay", "replay", "state", file=ckpt.REPLAY_FILE, bulky=True),
             Saved("needle", "needle", "state", file=ckpt.REPLAY_FILE, bulky=True))

    def __init__(self, env_or_system, config: SACConfig | None = None, **overrides):
        cfg = self._setup(env_or_system, config, overrides)  # threads, env, dims, action scale, counters
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

        self.generator = torch.Generator(device=self.device)  # every draw of the agent (not the global RNG)
        self.generator.manual_seed(cfg.seed)
        self.num_gradient_steps = self.num_updates = self.num_rounds = self.num_needle_episodes = 0
        self._episode_return = torch.zeros(cfg.num_envs, dtype=torch.float64, device=self.device)
        self._loss_sums = {"q_loss": 0.0, "pi_loss": 0.0, "n": 0}
        self._grads, self._compiled_grads = EagerGrads(self), None  # eager until learn() asks for compiled
        self._q_step, self._actor_step = self.q_opt.step, self.actor_opt.step
        self._owns_env = isinstance(env_or_system, (str, System))

    def _transform(self) -> ObsTransform:
        return ObsTransform(self.config.obs_transform, self.obs_dim, getattr(self.system, "angle_indices", []))

    @property
    def alpha(self) -> torch.Tensor:
        """The entropy coefficient (a 0-d tensor, no gradient)."""
        if not self.auto_alpha:
            return torch.tensor(float(self.config.alpha), device=self.device)
        return self.log_alpha.detach().exp()

    # ================================================================ the SAC update
    def critic_loss(self, q_params, obs, act, rew, next_obs, done, eps, alpha) -> torch.Tensor:
        """Twin soft-Q loss on one minibatch: ``sum_i mse(Q_i(s, a), r + gamma (1 - d) (min Q_targ(s', a') -
        alpha log pi(a'|s')))`` with a' drawn with noise ``eps`` (no bootstrap past a termination).

        ``q_params``: ``(params of q1, params of q2)`` as name -> tensor dicts (a functional call,
        for ``torch.func`` gradients), or None for the networks' own parameters.
        """
        functional = q_params is not None
        with torch.no_grad():  # the soft Bellman target, from the target networks
            next_act, next_logp = self.actor.sample(next_obs, eps)
            targets = (dict(self.q1_target.named_parameters()), dict(self.q2_target.named_parameters())) \
                if functional else None
            q_next = self._twin_q(targets, next_obs, next_act, target=True).min(0).values
            target = rew + self.config.gamma * (1.0 - done) * (q_next - alpha * next_logp)
        q1, q2 = self._twin_q(q_params, obs, act)
        return F.mse_loss(q1, target) + F.mse_loss(q2, target)

    def _twin_q(self, q_params, obs, act, target: bool = False) -> torch.Tensor:
        """(2, B) values of the critics (``target``: the target critics): the modules' own forward
        (``q_params`` None, eager) or both at once with the given weights (:func:`twin_q_values`)."""
        q1, q2 = (self.q1_target, self.q2_target) if target else (self.q1, self.q2)
        if q_params is None:
            return torch.stack([q1(obs, act), q2(obs, act)])
        return twin_q_values(q1, q2, q_params[0], q_params[1], obs, act)

    def actor_loss(self, actor_params, q_params, obs, eps, alpha) -> tuple[torch.Tensor, torch.Tensor]:
        """Policy loss ``mean(alpha log pi - min(Q1, Q2))`` at reparameterised actions (noise ``eps``)
        and the log densities (B,). Parameters as in :meth:`critic_loss` (None: the networks' own)."""
        mu, log_std = _call(self.actor, actor_params, obs)
        new_act, logp = squashed_sample(mu, log_std, eps, self.actor.action_scale)
        q_new = self._twin_q(q_params, obs, new_act).min(0).values
        return (alpha * logp - q_new).mean(), logp

    def gradient_step(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """One Adam step on the Q losses, the policy loss and (auto) alpha, on one minibatch.

        The losses are written once (:meth:`critic_loss`, :meth:`actor_loss`); ``self._grads``
        differentiates them into the parameters' ``.grad`` (:class:`EagerGrads`: autograd through
        the networks; :class:`CompiledGrads` with ``config.compile``: each loss's forward and
        backward as one ``torch.compile``-d ``torch.func.grad_and_value`` graph, the same
        gradients up to rounding). Raises FloatingPointError (before any weight changes) if a
        loss is NaN/Inf.
        """
        obs, act, rew, next_obs, done = (batch[f] for f in REPLAY_FIELDS)
        alpha, gen = self.alpha, self.generator
        eps_next = torch.randn(act.shape, generator=gen, device=act.device)
        q_loss = self._grads.critic(obs, act, rew, next_obs, done, eps_next, alpha)
        self._q_step()
        # policy: minimise alpha log pi - min(Q1, Q2) at reparameterised actions (the critics just updated)
        eps_new = torch.randn(act.shape, generator=gen, device=act.device)
        acting = self.num_timesteps >= self.config.actor_delay
        if acting or self.auto_alpha:   # within actor_delay only the temperature needs the policy's log densities
            pi_loss, logp = self._grads.actor(obs, eps_new, alpha)
        else:
            pi_loss = torch.full((), float("nan"), device=act.device)   # no policy step: none is logged
        if acting:
            self._actor_step()

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

    def _q_param_dicts(self) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """The critics' parameters, detached (torch.func differentiates with respect to them)."""
        return tuple({k: v.detach() for k, v in q.named_parameters()} for q in (self.q1, self.q2))

    def use_compile(self, remaining_steps: int | None) -> bool:
        """Set up eager or compiled gradients (and the agent-built env's decision) for a run of
        ``remaining_steps`` more env steps, as ``config.compile`` says; returns whether compiled.
        ``learn`` calls it; the compiled functions are kept across calls."""
        cfg = self.config
        enabled = wants_compile(cfg.compile, remaining_steps)
        if enabled and self._compiled_grads is None:
            self._compiled_grads = CompiledGrads(self, strict=cfg.compile == "on")
        if enabled:
            self._compiled_grads.refresh()
        self._grads = self._compiled_grads if enabled else EagerGrads(self)
        # compiled: the optimizers' steps without their Python book-keeping too (same numbers)
        self._q_step = FusedAdamStep(self.q_opt) if enabled else self.q_opt.step
        self._actor_step = FusedAdamStep(self.actor_opt) if enabled else self.actor_opt.step
        if self._owns_env and hasattr(self.env, "set_compile"):
            self.env.set_compile(cfg.compile if enabled else "off")
        return enabled

    def update(self) -> None:
        """One thesis "update": a replay batch, one gradient step per minibatch, one Polyak step."""
        cfg = self.config
        batch, _ = sample_mixed(self.replay, self.needle, cfg.replay_batch_size, cfg.needle_prob, self.generator)
        minibatches = zip(*(v.split(cfg.minibatch_size) for v in batch.values()))  # views, in order
        for parts in minibatches:
            losses = self.gradient_step(dict(zip(batch.keys(), parts)))
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

    def before_update_round(self) -> None:
        """Hook: called at the start of every update round, before its updates (``num_timesteps``
        is what :meth:`on_update_round` will see). Default: nothing."""

    def on_update_round(self) -> None:
        """Hook: called after every update round (``steps_per_update`` env steps; during
        exploration the round has no updates). Default: nothing."""

    # ======================================================================== learn
    def train(self, run, total: int, backend) -> None:
        """SAC's loop inside ``learn``'s run (:meth:`~hybridctl.learn.base.Learner.learn`): collect
        ``num_envs`` steps, update every ``steps_per_update`` env steps, log every ``log_every`` and
        checkpoint every ``checkpoint_every`` env steps, until ``num_timesteps`` reaches ``total``
        (rounded up to a multiple of ``num_envs``). The episodes running at a resume are lost: the
        env restarts. Raises FloatingPointError if a loss becomes NaN/Inf (before the step is applied).
        """
        cfg = self.config
        note = cfg.exploration_note(total) if self.num_timesteps < total else None
        if note is not None:  # not an error (a smoke test may want it), but never silent
            warnings.warn(note, stacklevel=3)
        self.use_compile(total - self.num_timesteps)
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
                self.before_update_round()
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
            by_steps = self.num_timesteps >= next_ckpt
            if by_steps:
                next_ckpt = _next_multiple(self.num_timesteps, cfg.checkpoint_every)
            if by_steps or self.num_timesteps < total:  # by time: not at the end (final/ follows)
                run.checkpoint_if_due(by_steps)

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
        self._record_episodes(self._episode_return[ended].tolist(), ended, infos)
        needle_rows = self.is_needle_episode(ended, infos)
        if bool(needle_rows.any()):
            self.num_needle_episodes += int(needle_rows.sum())
            self.needle.add(*self.staging.take(needle_rows).values())
        self.on_episodes_end(ended, infos)
        self.staging.clear(ended)
        self._episode_return[ended] = 0.0

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
        self._note_best()
        return row

    # ================================================================ the policy
    def policy_actions(self, x: torch.Tensor, deterministic: bool) -> torch.Tensor:
        """deterministic: ``action_scale * tanh(mu)``; else a policy sample (global torch RNG:
        inference draws do not move the agent's training generator)."""
        if deterministic:
            return self.actor.deterministic(x)
        return self.actor.sample(x, torch.randn(x.shape[0], self.action_dim, device=self.device))[0]

    def deterministic_policy(self) -> DeterministicPolicy:
        """A frozen ``torch.nn.Module`` copy of the current policy: (B, n) -> (B, m).

        Includes the observation transform; use it in a Drake ``TorchPolicy`` block.
        Later training does not change it (call again for the newer policy).
        """
        return DeterministicPolicy(self.actor).to("cpu")

    def after_restore(self, found: Path, meta: dict, bulky: bool) -> None:
        """The env restarts its episodes; the optimizers take the config's learning rates (a restored
        optimizer state carries the recorded ones: a resume forced to another lr must use it)."""
        super().after_restore(found, meta, bulky)
        set_lr(self.actor_opt, self.config.lr)
        set_lr(self.q_opt, self.config.lr)
        if self.alpha_opt is not None:
            set_lr(self.alpha_opt, self.config.alpha_lr)

    def normalization(self) -> dict:
        """normalization.json: the observation transform (stateless)."""
        return self.actor.transform.describe()
