"""Switched Soft Actor-Critic (thesis Ch. 3, Algorithms 2-4): learn a swing-up and a gate around an LQR.

The controller has three parts (thesis Sec. 3.3): the gate G(s) in [0, 1] (a
:class:`~hybridctl.learn.gate.GateNet`) with hysteresis (LQR on above 0.9, off
below 0.5), Drake's LQR about the upright, and the SAC policy as the swing-up.
SSAC is SAC (:mod:`hybridctl.learn.sac`) on the switched env, plus:

1. **Warm start** (Alg. 2): before any episode, states sampled near and far from
   the goal are labelled by saturated-LQR rollouts and the gate is fitted on them
   (weighted BCE, thesis eq. 3.3).
2. **Rollouts** (Alg. 3): every decision runs gate + LQR + held swing-up action in
   a :class:`~hybridctl.envs.SwitchedVectorEnv` (the LQR acts every 0.01 s).
3. **Needle buffer** (Alg. 4 lines 5-7): every transition of an episode that
   passes the success test T(s) (thesis eq. 3.2) is also stored in D_n, drawn
   with probability ``needle_prob`` (paper 0.5, author code 0.2).
4. **Gate data** (Alg. 4 line 8): the states of an episode's decisions that began
   under the LQR, labelled with the episode's T(s), are added to the gate data
   set D_g, which also keeps the warm-start data. Every ``gate_refit_every`` env
   steps the gate is refitted on minibatches drawn from all of D_g.

>>> from hybridctl.learn import SSAC
>>> agent = SSAC("acrobot", seed=0)                 # warm-starts the gate (~1 min)
>>> agent.learn(out="runs/ssac-acrobot")
>>> agent.predict(state)                           # swing-up action only
>>> agent.act(state)                               # what the switched controller does

Settings: ``SSACConfig()`` holds the thesis' values except three measured
changes (Polyak 0.9, sin/cos of angles as inputs, gate data relabelled from visited
states); ``SSACConfig.variant("paper")`` is the thesis throughout and
``SSACConfig.variant("author")`` the author's code (needle 0.2, gate refit every
2.5e4 steps, gamma 0.99, 16 updates per round, quadratic reward).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..envs import SwitchedVectorEnv
from ..systems import System
from ..systems import load as load_system
from ..systems.control import cost_to_go, hysteresis, saturate
from ..systems.spec import REWARD_KINDS
from .gate import GateConfig, GateNet, fit_gate, label_states, warm_start_gate
from .optim import adam
from .checkpoint import Saved
from .config_check import check_fields
from .sac import SAC, SACConfig, set_lr
from .sac_grads import CompiledGrads
from .gate_data import GateDataset, RelabelPool

GATE_DATA_FILE = "gate_data.pt"
REWARDS = REWARD_KINDS  # one list of reward kinds, in the spec module

# the thesis' own values where hybridctl's defaults differ (SSACConfig comments say why)
PAPER = {"polyak": 0.995, "obs_transform": "none", "gate_relabel_per_refit": 0, "gate_class_weight_from": "all",
         "reward": "tip_height"}
# where the author's code differs from the paper (implementation notes, Ch. 3)
AUTHOR_CODE = {**PAPER, "needle_prob": 0.2, "gate_refit_every": 25_000, "gamma": 0.99, "updates_per_round": 16,
               "reward": "quadratic"}


@dataclass
class SSACConfig(SACConfig):
    """SAC's settings (thesis appendix) plus the gate and needle-buffer settings of SSAC."""

    polyak: float = 0.9                  # hybridctl (thesis 0.995): SSAC acrobot pilot, seed 0, 3e5 steps: mean
    #                                      return 88.2 (0.9 + angle_sincos) vs 23.3 (thesis values)
    obs_transform: str = "angle_sincos"  # hybridctl (thesis: raw state); the envs do not wrap angles
    needle_prob: float = 0.5             # thesis Sec. 3.3 p_d = 0.5 (author code 0.2)
    reward: str | None = None            # None: the system spec's reward.kind (thesis eq. 3.1 "tip_height" for
    #                                      every shipped system); "quadratic": author script -0.1 |q - q_goal|^2;
    #                                      "tip_height_centered": minus 0.1 x_cart^2 (System.reward). A system
    #                                      name is loaded with this reward.kind; a System must already have it
    gate_refit_every: int = 50_000       # thesis appendix: gate refit every 5e4 steps (author code 2.5e4)
    gate_refit_steps: int = 2000         # hybridctl: Adam steps per refit (~2 s), minibatches from all of D_g
    gate_warm_samples: int = 100_000     # hybridctl: LQR-labelled warm-start states (2.5e7 LQR steps;
    #                                      thesis: the gate alone trained for 1e6 steps first)
    gate_warm_fit_steps: int = 5000      # hybridctl: Adam steps on the warm-start data
    gate_lr: float = 3e-3                # hybridctl; thesis appendix 1e-5. Seed-1 pilot gate data, 3000 steps from
    #                                      scratch: lr 1e-3 handed over nowhere, 3e-3 recalled 55 % of positive
    #                                      episode states at 1.8 % false hand-overs
    gate_positive_weight: float = 0.01   # thesis eq. 3.3: w in c_w = n_total / n_positive * w
    gate_class_weight_from: str = "warm"  # hybridctl: c_w of eq. 3.3 from the warm-start data's class balance,
    #                                       kept for refits; "all" (thesis): from all of D_g. With "all", c_w
    #                                       falls towards w = 0.01 as D_g fills with (mostly positive) LQR-active
    #                                       states, and then no state reaches p > 0.9 (seed 1 pilot: hand-overs
    #                                       went from 51 % of control periods to 0 after the first refit)
    gate_batch_size: int = 4096          # hybridctl: gate minibatch
    gate_data_max: int = 2_000_000       # hybridctl: D_g capacity (oldest episode data dropped first)
    gate_cost_feature: bool = True       # hybridctl: log(1 + V / cost_scale) as a gate input (gate.py)
    gate_relabel_per_refit: int = 4000   # hybridctl: before each refit, this many swing-up decision states the
    #                                      episodes visited (with V < gate_relabel_cost * cost_scale) are labelled
    #                                      by LQR rollouts (as the warm start, Alg. 2) and added to D_g; 0 = thesis
    #                                      only (D_g grows from LQR-active decisions alone, which never teaches
    #                                      the gate states the LQR has not yet been handed)
    gate_relabel_cost: float = 1.0       # hybridctl: candidate states have LQR cost-to-go V < this * gate.cost_scale
    gate_lqr_labels: str = "episode"      # thesis Alg. 4 line 8: LQR-active decision states are labelled T(s), the
    #                                      episode's success; "rollout" (hybridctl, cart-pole): they join the
    #                                      relabel pool and are labelled by LQR rollouts, what the gate predicts. An
    #                                      episode can fail after the LQR held the pole (a cart still 0.1 m out
    #                                      at 10 s; a hand-back): cart-pole pilot, 4.5e5 steps, 45 % of episode
    #                                      labels near the goal were 0 while LQR rollouts from the same region
    #                                      balanced 4000 of 4000, and the gate's p(goal) fell from 1.0 to 0.22
    gate_refit_overlap: bool = True      # hybridctl: a due refit runs on a second thread while the round's gradient
    #                                      steps run (neither reads what the other writes, so the numbers are those
    #                                      of refitting after them, tested); False: after them, on one thread
    variant_name: str = "hybridctl"      # which preset the config started from (informational)

    def describe_budget(self) -> str:
        """The run's budget in a run's account (the gate's warm start comes first)."""
        return super().describe_budget() + " (warm-starting the gate first)"

    def validate(self) -> None:
        """Raise ValueError naming the first invalid field."""
        super().validate()
        check_fields(self, integers_from_1=("gate_refit_every", "gate_refit_steps", "gate_warm_samples",
                                            "gate_warm_fit_steps", "gate_batch_size", "gate_data_max"),
                     integers_from_0=("gate_relabel_per_refit",),
                     positive=("gate_relabel_cost", "gate_lr", "gate_positive_weight"))
        if self.gate_warm_samples < 2:
            raise ValueError(f"SSACConfig.gate_warm_samples must be >= 2, got {self.gate_warm_samples}")
        if self.gate_lqr_labels not in ("episode", "rollout"):
            raise ValueError(f"SSACConfig.gate_lqr_labels must be 'episode' or 'rollout', got {self.gate_lqr_labels!r}")
        if self.gate_lqr_labels == "rollout" and self.gate_relabel_per_refit == 0:
            raise ValueError("SSACConfig.gate_lqr_labels='rollout' needs gate_relabel_per_refit >= 1 (the states "
                             "are labelled by that many LQR rollouts per refit)")
        if self.gate_class_weight_from not in ("warm", "all"):
            raise ValueError(f"SSACConfig.gate_class_weight_from must be 'warm' or 'all', "
                             f"got {self.gate_class_weight_from!r}")
        if self.reward is not None and self.reward not in REWARDS:
            raise ValueError(f"SSACConfig.reward must be None (the spec's) or one of {REWARDS}, got {self.reward!r}")
        if self.variant_name not in ("hybridctl", "paper", "author"):
            raise ValueError(f"SSACConfig.variant_name must be 'hybridctl', 'paper' or 'author', "
                             f"got {self.variant_name!r}")
        self.gate_config().validate()

    @classmethod
    def variant(cls, name: str = "hybridctl", **overrides) -> "SSACConfig":
        """``"hybridctl"``: the defaults (thesis values except polyak, obs_transform and gate
        relabelling, see the field comments); ``"paper"``: the thesis' values throughout;
        ``"author"``: the author's code where it differs from the paper."""
        if name == "hybridctl":
            return cls(**overrides)
        if name == "paper":
            return cls(**{**PAPER, "variant_name": "paper", **overrides})
        if name == "author":
            return cls(**{**AUTHOR_CODE, "variant_name": "author", **overrides})
        raise ValueError(f"variant must be 'hybridctl', 'paper' or 'author', got {name!r}")

    def gate_config(self) -> GateConfig:
        """The :class:`GateConfig` these settings describe (seeded with ``seed``)."""
        return GateConfig(warm_samples=self.gate_warm_samples, warm_fit_steps=self.gate_warm_fit_steps,
                          refit_steps=self.gate_refit_steps, batch_size=self.gate_batch_size,
                          cost_feature=self.gate_cost_feature, lr=self.gate_lr,
                          positive_weight=self.gate_positive_weight, seed=self.seed)


class SSAC(SAC):
    """Switched SAC: the SAC swing-up learner on a :class:`SwitchedVectorEnv` with a learned gate.

    Args:
        env_or_system: a system name or System (a SwitchedVectorEnv is built around a
            warm-started gate and the LQR; the reward is the spec's ``reward.kind``, or
            ``config.reward`` for a system name), or
            a ready :class:`~hybridctl.envs.SwitchedVectorEnv` (its gate is used and
            refitted; pass ``gate_data`` to refit on its data too).
        config: an :class:`SSACConfig` (default: the thesis' values).
        gate: a GateNet to use instead of warm-starting one.
        gate_data: (states, labels) to start D_g with (the warm-start data set).
        progress: show a progress bar while warm-starting the gate.
        **overrides: config fields, e.g. ``SSAC("acrobot", seed=1, needle_prob=0.2)``.

    Attributes beyond SAC's: ``gate`` (GateNet), ``gate_data`` (:class:`GateDataset`),
    ``relabel_pool`` (:class:`RelabelPool`), ``gate_info`` (warm-start and latest refit metrics),
    ``num_gate_refits``.

    Device: the gate, its optimizer and generator, the relabel pool, the warm start's and the
    relabelling's LQR rollouts and every refit run on ``config.device`` (a given gate is moved
    there; a given SwitchedVectorEnv must be there); D_g stays on the host and is copied to the
    device once per refit.
    """

    config_class = SSACConfig
    algorithm_name = "SSAC"
    train_order = 1
    compatible_algorithms = ("SSAC",)
    log_int_columns = (*SAC.log_int_columns, "gate_data", "gate_refits")
    # beyond SAC's checkpoint: the gate, its optimizer, RNG and counters (model.pt "extra"), and the
    # gate data set D_g with the pool of states waiting to be relabelled (gate_data.pt, for resume)
    saved = (*SAC.saved, Saved("extra.gate", "gate", "state"),
             Saved("extra.gate_opt", "gate_opt", "state", optional=True),
             Saved("extra.gate_generator", "gate_generator", "rng", optional=True),
             *(Saved(f"extra.gate_counters.{key}", attr, optional=True, load=int) for key, attr in (
                 ("refits", "num_gate_refits"), ("episodes", "num_gate_episodes"),
                 ("relabelled", "num_gate_relabelled"), ("next_refit", "_next_refit"))),
             Saved("", "gate_data", "state", file=GATE_DATA_FILE, bulky=True),
             Saved("relabel_pool", "_relabel_pool", "tensor", file=GATE_DATA_FILE, bulky=True, optional=True))

    @classmethod
    def extend_log_columns(cls, columns: tuple[str, ...]) -> tuple[str, ...]:
        """SAC's columns plus the gate data size, the refits so far and the LQR's share of control."""
        return (*super().extend_log_columns(columns), "gate_data", "gate_refits", "lqr_share")

    def __init__(self, env_or_system, config: SSACConfig | None = None, gate: GateNet | None = None,
                 gate_data: tuple[Any, Any] | None = None, **overrides):
        cfg = dataclasses.replace(config if config is not None else SSACConfig(), **overrides)
        cfg.validate()
        self._init_gate, self._init_gate_data, self.gate_info = gate, gate_data, {}
        super().__init__(env_or_system, config=cfg)
        if self.config.reward is None:  # record the reward trained on (config.json; older readers need a kind)
            self.config = dataclasses.replace(self.config, reward=self.system.reward_kind)
        self.gate = self.env.gate
        self.gate_opt = adam(self.gate.parameters(), cfg.gate_lr)
        self.gate_generator = torch.Generator(device=self.device).manual_seed(cfg.seed + 7919)
        self.gate_data = GateDataset(self.obs_dim, cfg.gate_data_max)
        if self._init_gate_data is not None:
            self.gate_data.add(*self._init_gate_data, warm=True)
        self._init_gate_data = None
        horizon = self.staging.horizon
        self._lqr_at_start = torch.zeros((cfg.num_envs, horizon), dtype=torch.bool, device=self.device)
        self.num_gate_refits = 0
        self.num_gate_episodes = 0
        self.num_gate_relabelled = 0
        self._next_refit = cfg.gate_refit_every
        self._pending_refit: _Background | bool | None = None  # a refit started before the round's updates
        # swing-up decision states near the goal, waiting to be labelled by LQR rollouts
        S = self.system.lqr()[1] / self.system.gate.cost_scale
        self._cost_matrix = torch.as_tensor(S, dtype=torch.float32, device=self.device)
        self._goal = torch.as_tensor(self.system.goal, dtype=torch.float32, device=self.device)
        self.relabel_pool = RelabelPool(self.obs_dim, max(50_000, cfg.gate_relabel_per_refit), self.device)
        # the LQR's share of control periods, summed on the device (read once per log row)
        self._lqr_share_sum = torch.zeros((), dtype=torch.float64, device=self.device)
        self._lqr_share_n = 0

    @property
    def _relabel_pool(self) -> torch.Tensor:
        """The states waiting in :attr:`relabel_pool`, oldest first (the checkpoint's ``relabel_pool``)."""
        return self.relabel_pool.states()

    @_relabel_pool.setter
    def _relabel_pool(self, states: torch.Tensor) -> None:
        self.relabel_pool.replace(states)

    # ------------------------------------------------------------------ construction
    def _make_env(self, env_or_system, cfg: SSACConfig):
        # the gate lives on the learner's device: the env's decisions, the refits and their
        # generator all run there (a given gate is moved there in place, as it is refitted in place)
        device = torch.device(cfg.device)
        if isinstance(env_or_system, SwitchedVectorEnv):
            _check_reward(env_or_system.system, cfg)
            if not _same_device(env_or_system.device, device):
                raise ValueError(f"SSAC with device={cfg.device!r} needs its SwitchedVectorEnv on that device "
                                 f"(the gate runs in the env's decisions and is refitted on the learner's), "
                                 f"got an env on {str(env_or_system.device)!r}")
            if self._init_gate is not None:
                env_or_system.set_gate(self._init_gate)
            return env_or_system
        system = _system_with_reward(env_or_system, cfg)
        gate = self._init_gate
        if gate is None:
            gate, states, labels, info = warm_start_gate(system, cfg.gate_config(), device=device)
            self._init_gate_data = (states, labels)
            self.gate_info = {"warm_start": info}
        return SwitchedVectorEnv(system, cfg.num_envs, gate=gate, device=device, seed=cfg.seed)

    @classmethod
    def _construct_for_load(cls, env, config: SSACConfig, found: Path) -> "SSAC":
        # the checkpoint holds the gate's weights: skip the warm start, start from an empty gate
        if isinstance(env, SwitchedVectorEnv):
            return cls(env, config=config)
        system = _system_with_reward(env, config)
        return cls(system, config=config, gate=GateNet(system, cost_feature=config.gate_cost_feature,
                                                       device=config.device))

    # ====================================================== SSAC additions to SAC
    def store_transitions(self, obs, actions, rewards, next_obs, dones, infos) -> None:
        """SAC's replay + staging, and which decisions began under the LQR (gate data)."""
        t = self.staging.length.clamp(max=self.staging.horizon - 1)
        lqr = infos.get("lqr_at_start")
        if "lqr_fraction" in infos:  # summed on the device: no read-back per step
            fraction = torch.as_tensor(infos["lqr_fraction"], device=self.device)
            self._lqr_share_sum += fraction.sum().double()
            self._lqr_share_n += int(fraction.numel())
        if lqr is not None:
            self._lqr_at_start[torch.arange(len(t), device=self.device), t] = torch.as_tensor(
                lqr, device=self.device).bool()
        super().store_transitions(obs, actions, rewards, next_obs, dones, infos)
        if self.config.gate_relabel_per_refit and lqr is not None:
            swingup = ~torch.as_tensor(lqr, device=self.device).bool()
            err = self.system.state_error(obs.double()).float()
            cost = cost_to_go(err, self._cost_matrix)
            keep = swingup & (cost < self.config.gate_relabel_cost)
            self.relabel_pool.add(obs, keep)  # queued under the mask, on the device

    def on_episodes_end(self, ended: torch.Tensor, infos: dict) -> None:
        """Alg. 4 line 8: LQR-active decision states of the ended episodes, labelled T(s), go to D_g."""
        rows = ended & ~self.staging.overflow
        if not bool(rows.any()):
            return
        steps = torch.arange(self.staging.horizon, device=self.device)
        in_episode = steps[None, :] < self.staging.length[rows][:, None]
        mask = in_episode & self._lqr_at_start[rows]
        if self.config.gate_lqr_labels == "rollout":  # labelled by LQR rollouts at the next refit
            states = self.staging.data["obs"][rows][mask]
            if states.numel():
                self.relabel_pool.add(states)
                self.num_gate_episodes += int(mask.any(-1).sum())
            self._lqr_at_start[ended] = False
            return
        success = torch.as_tensor(infos["success"], device=self.device)[rows].bool()
        labels = success[:, None].expand_as(mask)[mask]
        if labels.numel():
            self.gate_data.add(self.staging.data["obs"][rows][mask], labels)
            self.num_gate_episodes += int(mask.any(-1).sum())
        self._lqr_at_start[ended] = False

    def before_update_round(self) -> None:
        """Alg. 4 lines 18-19: refit the gate on all of D_g every ``gate_refit_every`` env steps.

        A due refit starts here, before the round's gradient steps, and is finished (the env
        switches with the new gate) in :meth:`on_update_round`. With ``gate_refit_overlap`` it runs
        on a second thread meanwhile: the refit reads D_g, the gate, its optimizer and its own
        generator, the gradient steps read the replay and the SAC networks with the agent's
        generator, and the env is not stepped until both are done, so the numbers are those of
        the one-thread order (tested)."""
        if self.num_timesteps < self._next_refit:
            return
        self._next_refit = (self.num_timesteps // self.config.gate_refit_every + 1) * self.config.gate_refit_every
        self._pending_refit = _Background(self._fit_gate_on_data) if self.config.gate_refit_overlap else True

    def on_update_round(self) -> None:
        """Finish the refit started by :meth:`before_update_round` (or run it now, without overlap)."""
        pending, self._pending_refit = self._pending_refit, None
        if pending is None:
            return
        info = pending.result() if isinstance(pending, _Background) else self._fit_gate_on_data()
        if info:
            self.env.set_gate(self.gate)

    def train(self, run, total: int, backend) -> None:
        """:meth:`SAC.train`; a refit still running when training stops on an error is waited for."""
        try:
            super().train(run, total, backend)
        finally:
            pending, self._pending_refit = self._pending_refit, None
            if isinstance(pending, _Background):
                pending.wait()

    def refit_gate(self, steps: int | None = None) -> dict:
        """Refit the gate on minibatches from the whole gate data set (after relabelling pooled
        swing-up states) and switch the env to it; returns the metrics ({} without positive data)."""
        info = self._fit_gate_on_data(steps)
        if info:
            self.env.set_gate(self.gate)
        return info

    def _fit_gate_on_data(self, steps: int | None = None) -> dict:
        """:meth:`refit_gate` without touching the env (what the refit thread runs)."""
        cfg = self.config
        relabelled = self._relabel_visited_states()
        if len(self.gate_data) == 0 or not bool(self.gate_data.labels.any()):
            return {}
        losses = fit_gate(self.gate, self.gate_data.states, self.gate_data.labels,
                          cfg.gate_refit_steps if steps is None else steps, cfg.gate_lr,
                          cfg.gate_positive_weight, cfg.gate_batch_size, self.gate_generator, self.gate_opt,
                          class_weight=self._class_weight(), compiled=isinstance(self._grads, CompiledGrads))
        self.num_gate_refits += 1
        episode = slice(self.gate_data.n_warm, None)
        info = {"loss": losses[-1], "data": len(self.gate_data), **relabelled, "episode_rows": len(self.gate_data) - self.gate_data.n_warm,
                "episode_positive_fraction": float(self.gate_data.labels[episode].float().mean())
                if len(self.gate_data) > self.gate_data.n_warm else math.nan}
        self.gate_info["last_refit"] = info
        return info

    def _class_weight(self) -> float | None:
        """c_w for refits: eq. 3.3 on the warm-start rows ("warm"), or None (whole D_g, "all")."""
        data = self.gate_data
        if self.config.gate_class_weight_from == "all" or data.n_warm == 0:
            return None
        n_pos = int(data.labels[:data.n_warm].sum())
        return (data.n_warm / n_pos) * self.config.gate_positive_weight if n_pos else None

    def _relabel_visited_states(self) -> dict:
        """Label up to ``gate_relabel_per_refit`` pooled swing-up states by LQR rollouts, add them to D_g."""
        n = self.config.gate_relabel_per_refit
        n_pool = len(self.relabel_pool) if n else 0
        if n_pool == 0:
            return {}
        rows = torch.randperm(n_pool, generator=self.gate_generator, device=self.device)[:n]
        states = self.relabel_pool.states()[rows].double()
        self.relabel_pool.clear()
        labels = label_states(self.system, states, self.config.gate_config())  # LQR rollouts on the device
        self.gate_data.add(states, labels)
        self.num_gate_relabelled += len(labels)
        return {"relabelled": int(len(labels)), "relabelled_positive": int(labels.sum())}

    # ================================================================= inference
    def act(self, states, deterministic: bool = True):
        """What the switched controller commands from ``states`` with a fresh gate mode
        (swing-up until the gate says > gate_on): numpy/torch (n,) or (B, n) in, same out.

        Inside a running episode the hysteresis needs the mode's history: use
        :class:`~hybridctl.envs.SwitchedVectorEnv` or the Drake diagram for rollouts.
        """
        is_torch = isinstance(states, torch.Tensor)
        # on the agent's device (numpy: float64, as before); torch out on the input's device
        x = states.to(self.device) if is_torch else torch.as_tensor(np.asarray(states, dtype=np.float64),
                                                                   device=self.device)
        swingup = self.predict(x, deterministic=deterministic)
        xb = x.reshape(-1, self.obs_dim)
        with torch.no_grad():
            p = self.gate(xb.to(torch.float32)).reshape(-1)
            lqr = self.env.lqr(xb.to(self.env.dtype)).to(swingup.dtype)
        # a fresh mode is swing-up (False): the hysteresis hands over only above gate_on
        lqr_on = hysteresis(p, torch.zeros_like(p, dtype=torch.bool), self.env.gate_on, self.env.gate_off)
        out = torch.where(lqr_on[:, None], lqr, swingup.reshape(-1, self.action_dim))
        out = saturate(out, float(self.action_scale.max())).reshape(swingup.shape)
        return out.to(states.device) if is_torch else out.cpu().numpy()

    def make_eval_env(self, num_envs: int, seed: int):
        """A SwitchedVectorEnv with a frozen copy of the current gate (on the agent's device) and the same LQR."""
        return SwitchedVectorEnv(self.system, num_envs, gate=self._frozen_gate(self.device),
                                 K=self.env._K.cpu().numpy(),
                                 gate_on=self.env.gate_on, gate_off=self.env.gate_off,
                                 decision_period=self.env.decision_period, device=self.device, seed=seed)

    def gate_module(self) -> GateNet:
        """A frozen copy of the current gate on the CPU (for a Drake ``Gate`` block)."""
        return self._frozen_gate("cpu")

    def _frozen_gate(self, device) -> GateNet:
        """A copy of the current gate on ``device``, in eval mode, without gradients."""
        gate = copy.deepcopy(self.gate).to(device).eval()
        for p in gate.parameters():
            p.requires_grad_(False)
        return gate

    # ============================================================ checkpoints
    def checkpoint_meta(self) -> dict:
        """SAC's config.json plus the gate: layers, inputs, hysteresis, LQR gain, warm-start/refit metrics."""
        return {**super().checkpoint_meta(), "gate": {
            "hidden": [m.out_features for m in self.gate.net if isinstance(m, torch.nn.Linear)][:-1],
            "cost_feature": self.gate.cost_feature, "gate_on": self.env.gate_on, "gate_off": self.env.gate_off,
            "K": self.env._K.cpu().tolist(), "info": self.gate_info}}

    def after_restore(self, found: Path, meta: dict, bulky: bool) -> None:
        """The env switches with the restored gate; the running episodes' LQR flags are dropped."""
        super().after_restore(found, meta, bulky)
        set_lr(self.gate_opt, self.config.gate_lr)
        self.gate.eval()
        self.env.set_gate(self.gate)
        self.gate_info = meta.get("gate", {}).get("info", {})
        self._lqr_at_start.zero_()

    def _log_row(self, steps_per_s: float) -> dict:
        row = super()._log_row(steps_per_s)
        row["gate_data"] = len(self.gate_data)
        row["gate_refits"] = self.num_gate_refits
        row["lqr_share"] = float(self._lqr_share_sum) / max(self._lqr_share_n, 1)  # one read-back a row
        self._lqr_share_sum.zero_()
        self._lqr_share_n = 0
        return row


class _Background:
    """``fn()`` on a daemon thread; :meth:`result` waits and returns its value or raises its
    exception. torch releases the GIL inside its kernels, so the thread's work runs on another core
    while the caller's torch work goes on. The thread uses the caller's number of torch threads
    (OpenMP keeps that setting per thread; a new thread would start from the core count)."""

    def __init__(self, fn):
        self._value, self._error = None, None
        self._thread = threading.Thread(target=self._run, args=(fn, torch.get_num_threads()),
                                        name="ssac-gate-refit", daemon=True)
        self._thread.start()

    def _run(self, fn, torch_threads: int) -> None:
        try:
            torch.set_num_threads(torch_threads)
            self._value = fn()
        except BaseException as error:  # noqa: BLE001 - handed to the caller by result()
            self._error = error

    def wait(self) -> None:
        """Block until the thread is done (its result or error is kept)."""
        self._thread.join()

    def result(self):
        """The function's return value (raises its exception)."""
        self.wait()
        if self._error is not None:
            raise self._error
        return self._value


def _same_device(a: torch.device, b: torch.device) -> bool:
    """Whether two devices are the same (a CUDA device without index is the current one)."""
    a, b = torch.device(a), torch.device(b)
    if a.type != b.type:
        return False
    if a.type == "cuda" and (a.index is None) != (b.index is None):
        current = torch.cuda.current_device()
        return (current if a.index is None else a.index) == (current if b.index is None else b.index)
    return a.index == b.index


def _check_reward(system: System, config: SSACConfig) -> None:
    """An explicit ``config.reward`` must be the reward the system was loaded with."""
    if config.reward is not None and system.reward_kind != config.reward:
        raise ValueError(f"SSACConfig.reward={config.reward!r}, but system {system.name!r} was loaded with "
                         f"reward.kind={system.reward_kind!r}: load it with systems.load({system.name!r}, "
                         f"**{{'reward.kind': {config.reward!r}}}) or leave reward=None")


def _system_with_reward(system, config: SSACConfig) -> System:
    """The System to train on: a name is loaded (with ``config.reward`` as its reward.kind when set);
    a System is used as it is (its reward must match an explicit ``config.reward``)."""
    if isinstance(system, str):
        return load_system(system, **({"reward.kind": config.reward} if config.reward is not None else {}))
    if not isinstance(system, System):
        raise TypeError(f"SSAC needs a system name, a System or a SwitchedVectorEnv, got {type(system).__name__}")
    _check_reward(system, config)
    return system
