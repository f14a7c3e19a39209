"""Soft Actor-Critic (Haarnoja et al. 2018) on batched torch swing-up envs, as in thesis Ch. 3.

CleanRL-style: the algorithm reads top to bottom in this file (config, networks,
replay, :meth:`SAC.gradient_step`, :meth:`SAC.learn`); the API is Stable-Baselines3
style (``SAC(env).learn(...)``, ``predict``, ``save`` / ``SAC.load``).

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
* :meth:`SAC.extra_checkpoint_state` / :meth:`SAC.load_extra_checkpoint_state` --
  extra tensors (e.g. a gate's state dict) stored in ``model.pt``;
* ``config_class`` -- a dataclass derived from :class:`SACConfig` for extra settings.

``learn(callback=f)`` calls ``f(agent, locals_dict)`` after every round; returning
False stops training (a final checkpoint is still written).
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import math
import time
import warnings
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from . import checkpoint as ckpt

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


# ========================================================================== networks

OBS_TRANSFORMS = ("none", "angle_sincos")


class ObsTransform(nn.Module):
    """Observation features fed to every network (part of the deterministic policy module).

    ``"none"``: the raw state (thesis). ``"angle_sincos"``: each angle (``angle_indices``)
    replaced by its sine and cosine, so unwrapped angles (the envs do not wrap) map to
    the same features as their wrapped values. Stateless: no statistics to fit.
    """

    def __init__(self, kind: str, n_states: int, angle_indices: list[int] = ()):
        super().__init__()
        if kind not in OBS_TRANSFORMS:
            raise ValueError(f"obs transform must be one of {OBS_TRANSFORMS}, got {kind!r}")
        self.kind, self.n_states = kind, int(n_states)
        self.angle_indices = [int(i) for i in angle_indices] if kind == "angle_sincos" else []
        other = [i for i in range(self.n_states) if i not in self.angle_indices]
        self.register_buffer("angle_idx", torch.tensor(self.angle_indices, dtype=torch.long), persistent=False)
        self.register_buffer("other_idx", torch.tensor(other, dtype=torch.long), persistent=False)
        self.out_dim = self.n_states + len(self.angle_indices)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        if self.kind == "none":
            return obs
        angles = obs.index_select(-1, self.angle_idx)
        return torch.cat([angles.sin(), angles.cos(), obs.index_select(-1, self.other_idx)], dim=-1)

    def describe(self) -> dict:
        """What normalization.json holds."""
        if self.kind == "none":
            return {"type": "none"}
        return {"type": "angle_sincos", "n_states": self.n_states, "angle_indices": self.angle_indices,
                "features": "[sin(angles), cos(angles), other states]"}


def mlp(in_dim: int, out_dim: int, hidden_layers: int, hidden_size: int) -> nn.Sequential:
    """in -> hidden_layers x (Linear(hidden_size) + ReLU) -> Linear(out) (author's seagul MLP)."""
    layers: list[nn.Module] = []
    width = in_dim
    for _ in range(hidden_layers):
        layers += [nn.Linear(width, hidden_size), nn.ReLU()]
        width = hidden_size
    layers.append(nn.Linear(width, out_dim))
    return nn.Sequential(*layers)


_LOG_2PI = math.log(2 * math.pi)


class Actor(nn.Module):
    """Squashed Gaussian policy: ``a = action_scale * tanh(mu + sigma eps)`` (thesis eq. 2.16).

    One MLP outputs (mu, log sigma) (author code); log sigma is clamped to
    [log_std_min, log_std_max].
    """

    def __init__(self, transform: ObsTransform, action_dim: int, action_scale: torch.Tensor,
                 hidden_layers: int, hidden_size: int, log_std_min: float, log_std_max: float):
        super().__init__()
        self.transform, self.action_dim = transform, int(action_dim)
        self.net = mlp(transform.out_dim, 2 * action_dim, hidden_layers, hidden_size)
        self.register_buffer("action_scale", action_scale.clone().float())
        self.log_std_min, self.log_std_max = float(log_std_min), float(log_std_max)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(mu, log sigma), each (B, m)."""
        mu, log_std = self.net(self.transform(obs)).split(self.action_dim, dim=-1)
        return mu, log_std.clamp(self.log_std_min, self.log_std_max)

    def sample(self, obs: torch.Tensor, eps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Reparameterised action (B, m) and its log density (B,) for standard-normal ``eps``.

        log pi(a|s) = log N(u; mu, sigma) - sum log(action_scale (1 - tanh(u)^2)), with
        log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)) (numerically stable). The
        log action_scale term (as in CleanRL) only shifts the entropy by a constant.
        """
        mu, log_std = self(obs)
        u = mu + log_std.exp() * eps
        logp = (-0.5 * eps.pow(2) - log_std - 0.5 * _LOG_2PI).sum(-1)
        logp = logp - (self.action_scale.log() + 2 * (math.log(2) - u - F.softplus(-2 * u))).sum(-1)
        return self.action_scale * torch.tanh(u), logp

    def deterministic(self, obs: torch.Tensor) -> torch.Tensor:
        """``action_scale * tanh(mu)`` (thesis Sec. 3.4.2: eps set to zero)."""
        return self.action_scale * torch.tanh(self(obs)[0])


class QNetwork(nn.Module):
    """Q(s, a): MLP on [features(s), a / action_scale] (actions scaled to [-1, 1])."""

    def __init__(self, transform: ObsTransform, action_dim: int, action_scale: torch.Tensor,
                 hidden_layers: int, hidden_size: int):
        super().__init__()
        self.transform = transform
        self.net = mlp(transform.out_dim + action_dim, 1, hidden_layers, hidden_size)
        self.register_buffer("action_scale", action_scale.clone().float())

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([self.transform(obs), action / self.action_scale], dim=-1)).squeeze(-1)


class DeterministicPolicy(nn.Module):
    """A frozen copy of the actor: states (B, n) -> ``action_scale * tanh(mu)`` (B, m).

    Includes the observation transform, so it is all a Drake ``TorchPolicy`` block
    needs. Accepts any floating dtype (computes in float32, returns the input's dtype);
    a 1-D state (n,) gives (m,).
    """

    def __init__(self, actor: Actor):
        super().__init__()
        self.actor = copy.deepcopy(actor).eval()
        for p in self.actor.parameters():
            p.requires_grad_(False)

    def forward(self, states: torch.Tensor) -> torch.Tensor:
        states = torch.as_tensor(states)
        dtype = states.dtype if states.is_floating_point() else torch.float32
        param = next(self.actor.parameters())
        return self.actor.deterministic(states.to(device=param.device, dtype=param.dtype)).to(dtype)


# ============================================================================ replay

REPLAY_FIELDS = ("obs", "actions", "rewards", "next_obs", "dones")


class ReplayBuffer:
    """Preallocated torch ring buffer of transitions (float32, on one device).

    Fields: obs (C, n), actions (C, m), rewards (C,), next_obs (C, n), dones (C,)
    (1.0 = terminated: no bootstrap). :meth:`add` takes a batch (k rows, oldest first);
    when full, the oldest rows are overwritten.
    """

    def __init__(self, capacity: int, obs_dim: int, action_dim: int, device: str | torch.device = "cpu"):
        self.capacity, self.device = int(capacity), torch.device(device)
        shapes = {"obs": (obs_dim,), "actions": (action_dim,), "rewards": (), "next_obs": (obs_dim,), "dones": ()}
        self.data = {k: torch.zeros((self.capacity, *s), dtype=torch.float32, device=self.device)
                     for k, s in shapes.items()}
        self.ptr = 0   # next row to write
        self.size = 0  # rows filled

    def __len__(self) -> int:
        return self.size

    def add(self, obs, actions, rewards, next_obs, dones) -> None:
        """Append k transitions (each argument has k rows)."""
        batch = dict(zip(REPLAY_FIELDS, (obs, actions, rewards, next_obs, dones)))
        k = int(batch["rewards"].shape[0])
        if k == 0:
            return
        if k > self.capacity:  # only the newest rows fit
            batch = {f: v[-self.capacity:] for f, v in batch.items()}
            k = self.capacity
        idx = (self.ptr + torch.arange(k, device=self.device)) % self.capacity
        for f, v in batch.items():
            self.data[f].index_copy_(0, idx, v.to(device=self.device, dtype=torch.float32))
        self.ptr = (self.ptr + k) % self.capacity
        self.size = min(self.size + k, self.capacity)

    def get(self, idx: torch.Tensor) -> dict[str, torch.Tensor]:
        """Rows ``idx`` of every field."""
        return {f: v[idx] for f, v in self.data.items()}

    def state_dict(self) -> dict[str, Any]:
        """The filled rows, oldest first (what replay.pt stores)."""
        order = torch.arange(self.size, device=self.device)
        if self.size == self.capacity:
            order = (order + self.ptr) % self.capacity
        return {"size": self.size, **{f: v[order].cpu() for f, v in self.data.items()}}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Replace the content with ``state`` (oldest first); keeps the newest rows that fit."""
        self.ptr = self.size = 0
        self.add(*(state[f] for f in REPLAY_FIELDS))


def sample_mixed(main: ReplayBuffer, needle: ReplayBuffer, batch_size: int, needle_prob: float,
                 generator: torch.Generator | None = None) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Draw ``batch_size`` rows with replacement; each row from ``needle`` with prob ``needle_prob``.

    Thesis Sec. 3.3: "with probability p_d we sample from D_n". Rows come from the main
    buffer only while the needle buffer is empty (or ``needle_prob`` is 0). Returns the
    batch and the (B,) bool mask of rows taken from the needle buffer.
    """
    if main.size == 0:
        raise RuntimeError("cannot sample from an empty replay buffer")
    dev = main.device
    idx = torch.randint(main.size, (batch_size,), generator=generator, device=dev)
    batch = main.get(idx)
    if needle_prob <= 0 or needle.size == 0:
        return batch, torch.zeros(batch_size, dtype=torch.bool, device=dev)
    from_needle = torch.rand(batch_size, generator=generator, device=dev) < needle_prob
    k = int(from_needle.sum())
    if k:
        nidx = torch.randint(needle.size, (k,), generator=generator, device=dev)
        for f, v in needle.get(nidx).items():
            batch[f][from_needle] = v
    return batch, from_needle


class EpisodeStaging:
    """Each env's current-episode transitions, so successful episodes can go to the needle buffer.

    Tensors (num_envs, horizon, ...): transition t of env i lives at [i, t]. Rows longer
    than ``horizon`` are marked overflowed and never copied.
    """

    def __init__(self, num_envs: int, horizon: int, obs_dim: int, action_dim: int, device):
        self.horizon = int(horizon)
        shapes = {"obs": (obs_dim,), "actions": (action_dim,), "rewards": (), "next_obs": (obs_dim,), "dones": ()}
        self.data = {k: torch.zeros((num_envs, self.horizon, *s), dtype=torch.float32, device=device)
                     for k, s in shapes.items()}
        self.length = torch.zeros(num_envs, dtype=torch.long, device=device)
        self.overflow = torch.zeros(num_envs, dtype=torch.bool, device=device)
        self._rows = torch.arange(num_envs, device=device)

    def add(self, obs, actions, rewards, next_obs, dones) -> None:
        """One transition per env (each argument has num_envs rows)."""
        t = self.length.clamp(max=self.horizon - 1)
        self.overflow |= self.length >= self.horizon
        for f, v in zip(REPLAY_FIELDS, (obs, actions, rewards, next_obs, dones)):
            self.data[f][self._rows, t] = v.to(dtype=torch.float32, device=self.length.device)
        self.length += 1

    def take(self, rows: torch.Tensor) -> dict[str, torch.Tensor]:
        """Transitions of the envs in the bool mask ``rows`` (overflowed ones skipped), in order."""
        rows = rows & ~self.overflow
        steps = torch.arange(self.horizon, device=self.length.device)
        keep = steps[None, :] < self.length[rows][:, None]
        return {f: v[rows][keep] for f, v in self.data.items()}

    def clear(self, rows: torch.Tensor | None = None) -> None:
        """Start new episodes in the bool mask ``rows`` (all if None)."""
        if rows is None:
            self.length.zero_()
            self.overflow.zero_()
        else:
            self.length[rows] = 0
            self.overflow[rows] = False


# ============================================================================= agent


def _adam(params, lr: float) -> torch.optim.Adam:
    """Adam; the fused CPU kernel where available (measured ~25% faster gradient steps here)."""
    params = list(params)
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, TypeError, ValueError):
        return torch.optim.Adam(params, lr=lr)


CSV_COLUMNS = ("env_steps", "episodes", "mean_return", "success_rate", "q_loss", "pi_loss", "alpha",
               "steps_per_s", "wall_time", "gradient_steps", "needle_size")


class SAC:
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
    csv_columns = CSV_COLUMNS

    def __init__(self, env_or_system, config: SACConfig | None = None, **overrides):
        cfg = dataclasses.replace(config if config is not None else self.config_class(), **overrides)
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
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.seed)
            self.actor = Actor(self._transform(), self.action_dim, self.action_scale, cfg.hidden_layers,
                               cfg.hidden_size, cfg.log_std_min, cfg.log_std_max).to(self.device)
            self.q1 = QNetwork(self._transform(), self.action_dim, self.action_scale, cfg.hidden_layers,
                               cfg.hidden_size).to(self.device)
            self.q2 = QNetwork(self._transform(), self.action_dim, self.action_scale, cfg.hidden_layers,
                               cfg.hidden_size).to(self.device)
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
        from ..envs import TorchVectorEnv
        from ..systems import System

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
        if not bool(torch.isfinite(loss)):
            raise FloatingPointError(
                f"{self.algorithm_name}: {name} became {float(loss.detach())} at env step {self.num_timesteps} "
                f"(gradient step {self.num_gradient_steps + 1}, update {self.num_updates + 1}); training "
                f"stopped before applying it. The last good checkpoint (if any) is left intact.")

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

    def extra_checkpoint_state(self) -> dict[str, Any]:
        """Hook: extra tensors/dicts for model.pt (loaded back by :meth:`load_extra_checkpoint_state`)."""
        return {}

    def load_extra_checkpoint_state(self, state: dict[str, Any]) -> None:
        """Hook: restore what :meth:`extra_checkpoint_state` saved."""

    # ======================================================================== learn
    def learn(self, total_steps: int | None = None, progress: bool = True,
              callback: Callable[["SAC", dict], bool | None] | None = None,
              log_dir: str | Path | None = None, resume: bool = False) -> "SAC":
        """Train until ``num_timesteps`` reaches ``total_steps`` (default ``config.total_steps``).

        ``total_steps`` is the run's total (not an increment): a resumed run or a second
        call continues until the agent has taken that many env steps in all (rounded up
        to a multiple of ``num_envs``).

        Args:
            progress: show a tqdm bar (mean return of the last 100 episodes, success
                rate, env steps/s).
            callback: ``callback(agent, locals())`` after every update round; return
                False to stop.
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
        log_dir = Path(log_dir) if log_dir is not None else None
        if resume:
            if log_dir is None:
                raise ValueError("learn(resume=True) needs the log_dir of the run to resume")
            found = ckpt.newest_checkpoint([log_dir / "checkpoint", log_dir / "final"])
            if found is None:
                warnings.warn(f"resume=True but no checkpoint in {log_dir}; starting from scratch", stacklevel=2)
            else:
                self._restore(found, replay=True)
        logger = _RunLogger(log_dir, self, resume=resume) if log_dir is not None else None

        old_threads = torch.get_num_threads()
        torch.set_num_threads(cfg.torch_threads)
        bar = None
        try:
            if self._obs is None:
                obs, _ = self.env.reset(seed=self._env_seed)
                self._env_seed = None
                self._obs = obs.to(device=self.device, dtype=torch.float32)
                self.staging.clear()
                self._episode_return.zero_()
            N = cfg.num_envs
            round_anchor = self.num_rounds * cfg.steps_per_update  # env steps at which the next round is due
            next_log = (self.num_timesteps // cfg.log_every + 1) * cfg.log_every
            next_ckpt = ((self.num_timesteps // cfg.checkpoint_every + 1) * cfg.checkpoint_every
                         if cfg.checkpoint_every else math.inf)
            start_time, wall_base = time.perf_counter(), self.wall_time
            last_log_time, last_log_steps = start_time, self.num_timesteps
            bar = _progress_bar(progress, total, self.num_timesteps)
            stop = False
            while self.num_timesteps < total and not stop:
                # 1. act: uniform during exploration, then the stochastic policy
                obs = self._obs
                explore = self.num_timesteps < cfg.exploration_steps
                actions = self.select_actions(obs, explore)
                # 2. step all envs (same-step autoreset: next_obs of ended rows is a new start)
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
                # 3. store; done = terminated only, so truncation (time limit) bootstraps
                self.store_transitions(obs, actions.to(self.device, torch.float32), rewards.float(), real_next,
                                       terminated.float(), infos)
                self._episode_return += rewards.double()
                if bool(ended.any()):
                    self._end_episodes(ended, infos)
                self._obs = next_obs
                self.num_timesteps += N
                if bar is not None:
                    bar.update(N)
                # 4. update rounds: every steps_per_update env steps, updates_per_round updates
                while self.num_timesteps - round_anchor >= cfg.steps_per_update and not stop:
                    round_anchor += cfg.steps_per_update
                    self.num_rounds += 1
                    if self.num_timesteps >= cfg.exploration_steps:
                        for _ in range(cfg.updates_per_round):
                            self.update()
                    self.on_update_round()
                    if callback is not None and callback(self, locals()) is False:
                        stop = True
                    if bar is not None:
                        bar.set_postfix(self._postfix(), refresh=False)
                # 5. log and checkpoint
                now = time.perf_counter()
                self.wall_time = wall_base + (now - start_time)
                if self.num_timesteps >= next_log or self.num_timesteps >= total or stop:
                    sps = (self.num_timesteps - last_log_steps) / max(now - last_log_time, 1e-9)
                    last_log_time, last_log_steps = now, self.num_timesteps
                    next_log = (self.num_timesteps // cfg.log_every + 1) * cfg.log_every
                    row = self._log_row(sps)
                    if logger is not None:
                        logger.write(row)
                if log_dir is not None and self.num_timesteps >= next_ckpt:
                    next_ckpt = (self.num_timesteps // cfg.checkpoint_every + 1) * cfg.checkpoint_every
                    self.save(log_dir / "checkpoint", include_replay=cfg.save_replay)
                    logger.plot()
            if log_dir is not None:
                self.save(log_dir / "final", include_replay=cfg.save_replay)
                logger.plot()
        finally:
            torch.set_num_threads(old_threads)
            if bar is not None:
                bar.close()
            if logger is not None:
                logger.close()
        return self

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
    def mean_return(self) -> float:
        """Mean return of the last 100 episodes (NaN before the first one ends)."""
        return float(np.mean(self.recent_returns)) if self.recent_returns else math.nan

    @property
    def success_rate(self) -> float:
        """Fraction of the last 100 episodes that passed the thesis success test."""
        return float(np.mean(self.recent_successes)) if self.recent_successes else math.nan

    def _postfix(self) -> dict[str, str]:
        return {"ret": f"{self.mean_return:.2f}", "succ": f"{self.success_rate:.2f}",
                "grad": str(self.num_gradient_steps)}

    def _log_row(self, steps_per_s: float) -> dict:
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
        self.log_rows.append(row)
        return row

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

    def make_eval_env(self, num_envs: int, seed: int):
        """A fresh vector env like the training env, for :meth:`evaluate` (override for switched envs)."""
        from ..envs import TorchVectorEnv

        return TorchVectorEnv(self.system, num_envs, decision_period=getattr(self.env, "decision_period", None),
                              device=self.device, seed=seed)

    def evaluate(self, episodes: int = 100, seed: int = 12345, deterministic: bool = True) -> dict:
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
        returns = total.numpy()
        return {"episodes": int(episodes), "seed": int(seed), "deterministic": bool(deterministic),
                "mean_return": float(returns.mean()), "std_return": float(returns.std()),
                "min_return": float(returns.min()), "success_rate": float(success.float().mean()),
                "returns": returns.tolist()}

    def deterministic_policy(self) -> DeterministicPolicy:
        """A frozen ``torch.nn.Module`` copy of the current policy: (B, n) -> (B, m).

        Includes the observation transform; use it in a Drake ``TorchPolicy`` block.
        Later training does not change it (call again for the newer policy).
        """
        return DeterministicPolicy(self.actor).to("cpu")

    # ============================================================ save and load
    def save(self, path: str | Path, include_replay: bool = False) -> Path:
        """Write a checkpoint directory atomically (see :mod:`hybridctl.learn.checkpoint`).

        ``include_replay`` also writes ``replay.pt`` (main and needle buffers; up to
        ~44 MB per 1e6 acrobot transitions) so that a resumed run keeps its data.
        """
        return ckpt.write_checkpoint_dir(path, lambda d: self._write_checkpoint(d, include_replay))

    def _write_checkpoint(self, d: Path, include_replay: bool) -> None:
        model = {"format": ckpt.FORMAT_VERSION, "actor": self.actor.state_dict(), "q1": self.q1.state_dict(),
                 "q2": self.q2.state_dict(), "q1_target": self.q1_target.state_dict(),
                 "q2_target": self.q2_target.state_dict(), "actor_opt": self.actor_opt.state_dict(),
                 "q_opt": self.q_opt.state_dict(), "log_alpha": self.log_alpha.detach().clone(),
                 "alpha_opt": self.alpha_opt.state_dict() if self.alpha_opt is not None else {},
                 "generator": self.generator.get_state(), "extra": self.extra_checkpoint_state()}
        torch.save(model, d / ckpt.MODEL_FILE)
        spec = getattr(self.system, "spec", None)
        ckpt.write_json(d / ckpt.CONFIG_FILE, {
            "algorithm": self.algorithm_name, "config": dataclasses.asdict(self.config),
            "system": {"name": self.system.name, "overrides": getattr(spec, "overrides", {}) or {}},
            "obs_dim": self.obs_dim, "action_dim": self.action_dim, "action_scale": self.action_scale.tolist(),
            "decision_period": getattr(self.env, "decision_period", None), "versions": ckpt.versions()})
        ckpt.write_json(d / ckpt.NORMALIZATION_FILE, self.actor.transform.describe())
        ckpt.write_json(d / ckpt.PROGRESS_FILE, self._progress_state())
        if include_replay:
            torch.save({"replay": self.replay.state_dict(), "needle": self.needle.state_dict()},
                       d / ckpt.REPLAY_FILE)

    def _progress_state(self) -> dict:
        env_rng = None
        try:
            env_rng = self.env.np_random.bit_generator.state
        except AttributeError:
            pass
        return {"env_steps": self.num_timesteps, "episodes": self.num_episodes,
                "gradient_steps": self.num_gradient_steps, "updates": self.num_updates, "rounds": self.num_rounds,
                "needle_episodes": self.num_needle_episodes, "needle_size": self.needle.size,
                "replay_size": self.replay.size, "wall_time": self.wall_time,
                "mean_return": self.mean_return, "best_mean_return": self.best_mean_return,
                "success_rate": self.success_rate, "recent_returns": list(self.recent_returns),
                "recent_successes": list(self.recent_successes), "env_rng_state": env_rng}

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
            from .. import systems
            env = systems.load(saved_system, **meta["system"].get("overrides", {}))
        from ..systems import System
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
        agent._restore(found, replay=False)
        return agent

    @classmethod
    def _construct_for_load(cls, env, config: SACConfig, found: Path) -> "SAC":
        """Hook for :meth:`load`: build the agent whose weights ``found`` then restores
        (subclasses skip expensive set-up that the checkpoint overwrites anyway)."""
        return cls(env, config=config)

    def _restore(self, found: Path, replay: bool) -> None:
        """Load networks, optimizers, counters and RNG states (and the replay) from ``found``."""
        found = ckpt.resolve_checkpoint_dir(found)
        meta = ckpt.read_json(found / ckpt.CONFIG_FILE)
        if meta.get("system", {}).get("name") != self.system.name:
            raise ckpt.CheckpointError(f"checkpoint {found} was trained on system "
                                       f"{meta.get('system', {}).get('name')!r}, but the env is system "
                                       f"{self.system.name!r}")
        norm = ckpt.read_json(found / ckpt.NORMALIZATION_FILE)
        if norm != self.actor.transform.describe():
            raise ckpt.CheckpointError(f"checkpoint {found} normalization {norm} differs from the agent's "
                                       f"{self.actor.transform.describe()} (config obs_transform)")
        model = ckpt.load_tensors(found / ckpt.MODEL_FILE, self.device)
        for name in ("actor", "q1", "q2", "q1_target", "q2_target", "actor_opt", "q_opt"):
            if name not in model:
                raise ckpt.CheckpointError(f"{found / ckpt.MODEL_FILE} lacks {name!r}")
            getattr(self, name).load_state_dict(model[name])
        with torch.no_grad():
            self.log_alpha.copy_(model["log_alpha"])
        if self.alpha_opt is not None and model.get("alpha_opt"):
            self.alpha_opt.load_state_dict(model["alpha_opt"])
        if "generator" in model:
            self.generator.set_state(model["generator"].cpu())
        self.load_extra_checkpoint_state(model.get("extra", {}))
        prog = ckpt.read_json(found / ckpt.PROGRESS_FILE)
        self.num_timesteps = int(prog["env_steps"])
        self.num_episodes = int(prog.get("episodes", 0))
        self.num_gradient_steps = int(prog.get("gradient_steps", 0))
        self.num_updates = int(prog.get("updates", 0))
        self.num_rounds = int(prog.get("rounds", 0))
        self.num_needle_episodes = int(prog.get("needle_episodes", 0))
        self.wall_time = float(prog.get("wall_time", 0.0))
        best = prog.get("best_mean_return")
        self.best_mean_return = -math.inf if best is None else float(best)
        self.recent_returns = deque(prog.get("recent_returns", []), maxlen=100)
        self.recent_successes = deque(prog.get("recent_successes", []), maxlen=100)
        if prog.get("env_rng_state") is not None:
            try:
                self.env.np_random.bit_generator.state = prog["env_rng_state"]
            except (AttributeError, TypeError, ValueError):
                warnings.warn("could not restore the env's RNG state; episodes will differ", stacklevel=2)
        if replay:
            if (found / ckpt.REPLAY_FILE).is_file():
                buffers = ckpt.load_tensors(found / ckpt.REPLAY_FILE, self.device)
                self.replay.load_state_dict(buffers["replay"])
                self.needle.load_state_dict(buffers["needle"])
            else:
                warnings.warn(f"{found} has no {ckpt.REPLAY_FILE}: the resumed run refills an empty replay "
                              f"buffer", stacklevel=3)
        self._obs, self._env_seed = None, None  # the env restarts its episodes on the next learn()


# ==================================================================== run logging


def _progress_bar(enabled: bool, total: int, initial: int):
    if not enabled:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, unit="step", unit_scale=True, dynamic_ncols=True, smoothing=0.05)


class _RunLogger:
    """progress.csv (+ TensorBoard scalars if available) and training_curves.png in a log dir."""

    def __init__(self, log_dir: Path, agent: SAC, resume: bool):
        self.dir = Path(log_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.agent = agent
        self.csv_path = self.dir / "progress.csv"
        if resume:  # rows up to the checkpoint; the tail written after it was lost with the run
            rows: list[dict] = []
            if self.csv_path.is_file():
                with open(self.csv_path, newline="") as fh:
                    for r in csv.DictReader(fh):
                        try:
                            if int(float(r["env_steps"])) <= agent.num_timesteps:
                                rows.append({k: float(v) if v not in ("", None) else math.nan for k, v in r.items()})
                        except (KeyError, TypeError, ValueError):
                            continue
            agent.log_rows = rows
        tmp = self.csv_path.with_name(self.csv_path.name + ".tmp")
        with open(tmp, "w", newline="") as fh:  # header + earlier rows (resumed, or an earlier learn() call)
            writer = csv.DictWriter(fh, fieldnames=agent.csv_columns, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(_csv_values(r, agent.csv_columns) for r in agent.log_rows)
        tmp.replace(self.csv_path)
        self._fh = open(self.csv_path, "a", newline="")
        self._csv = csv.DictWriter(self._fh, fieldnames=agent.csv_columns, extrasaction="ignore")
        self.tb = None
        if agent.config.tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter
                self.tb = SummaryWriter(str(self.dir / "tb"))
            except Exception:  # noqa: BLE001 - tensorboard is optional
                self.tb = None

    def write(self, row: dict) -> None:
        self._csv.writerow(_csv_values(row, self.agent.csv_columns))
        self._fh.flush()
        if self.tb is not None:
            for k, v in row.items():
                if k != "env_steps" and isinstance(v, (int, float)) and math.isfinite(v):
                    self.tb.add_scalar(f"train/{k}", v, row["env_steps"])

    def plot(self) -> None:
        plot_training_curves(self.agent.log_rows, self.dir / "training_curves.png",
                             title=f"{self.agent.algorithm_name} on {self.agent.system.name}")

    def close(self) -> None:
        self._fh.close()
        if self.tb is not None:
            self.tb.close()


def _csv_values(row: dict, columns=CSV_COLUMNS) -> dict:
    out = {}
    for k in columns:
        v = row.get(k, math.nan)
        out[k] = int(v) if k in ("env_steps", "episodes", "gradient_steps", "needle_size", "gate_data", "gate_refits") and math.isfinite(v) \
            else (f"{v:.6g}" if isinstance(v, float) else v)
    return out


def plot_training_curves(rows: list[dict], path: str | Path, title: str = "") -> Path | None:
    """PNG with mean return, success rate, losses and alpha against env steps (None if no rows)."""
    if not rows:
        return None
    from matplotlib.figure import Figure

    x = np.array([r["env_steps"] for r in rows], dtype=float)
    fig = Figure(figsize=(10, 6.5), layout="constrained")
    axes = fig.subplots(2, 2, sharex=True)
    panels = [("mean_return", "mean return (last 100 episodes)"), ("success_rate", "success rate (last 100)"),
              ("q_loss", "Q loss / policy loss"), ("alpha", "alpha")]
    for ax, (key, label) in zip(axes.flat, panels):
        ax.plot(x, [r.get(key, math.nan) for r in rows], label=key)
        if key == "q_loss":
            ax.plot(x, [r.get("pi_loss", math.nan) for r in rows], label="pi_loss")
            ax.set_yscale("symlog")
            ax.legend()
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    from matplotlib.ticker import EngFormatter

    for ax in axes[1]:
        ax.set_xlabel("env steps")
        ax.xaxis.set_major_formatter(EngFormatter(sep=""))
    if title:
        fig.suptitle(title)
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=90)
    tmp.replace(path)
    return path
