"""The base learner of the APG family: the state every method shares (members, CEM mean and std,
the best member, Adam moments, observation statistics, counters), one checkpoint layout, the
epoch loop on the training skeleton (:meth:`hybridctl.learn.run.Run.updates`), the APG phase
(in this process, or split over a parallel backend: :mod:`.split`), evaluation and the trained
policy. A method (:mod:`.methods`) writes only what differs: its epoch update, which member is
the result, its member count, presets and config checks.

Device (``APGConfig.device``): the population, the members, the CEM mean and std, the Adam
moments, the observation statistics, the epoch's generator and every rollout live there; the
initial members are drawn on the CPU from the seed and moved. The host gets copies once per
epoch (the progress row, the best score) and at evaluation; checkpoints load onto the
configured device whatever device wrote them.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from ... import systems as systems_mod
from ...parallel import make_backend
from ...systems import System, known_systems
from ...systems.success import stabilisation
from ...systems.switched import SwitchedController
from .. import checkpoint as ckpt
from ..base import Learner
from ..checkpoint import PROGRESS_FILE, Saved
from ..policies import Policy
from ..run import EvalResult
from .config import APGConfig, lr_schedule
from .core import (APGProblem, BatchedAdam, ClosedLoopPolicy, Phase, apg_iteration, apg_phase, population_returns,
                   takeover_controller)
from .split import split_apg_phase

__all__ = ["APGFamily", "EpochStep"]


class EpochStep(NamedTuple):
    """What a method's :meth:`APGFamily.epoch_update` returns for the shared book-keeping."""

    finals: torch.Tensor       # the members after the epoch [K, P] (float64)
    history: torch.Tensor      # the epoch's training returns [iterations, K] (the logged mean)
    scores: torch.Tensor       # the ranking scores [K] (-inf: diverged)
    elite: torch.Tensor        # the elite members' indices
    grad_norm: float           # the median finite gradient norm (NaN: none)
    obs_sums: list | None      # the epoch's observation sums for the normalisation


class APGFamily(Learner):
    """What every Ch. 7 method shares (see the module docstring); not built directly:
    :class:`~.methods.APG` picks the method's class from ``config.method``.

    A method class sets ``method`` (its ``APGConfig.method``) and ``preset_settings`` and
    writes :meth:`epoch_update` and :meth:`keep_best`; it may override :meth:`member_count`,
    :meth:`unroll`, :meth:`check_config` and ``default_policy``.
    """

    # every method's checkpoints: algorithm "APG" (set, and registered, by the entry point .methods.APG),
    # the method in config.json
    config_class = APGConfig
    budget_field, unit, uses_backend = "epochs", "epoch", True
    warm_starts = True              # --init: go on from another run's policy, e.g. with another reward
    log_key = "epoch"
    log_columns = ("epoch", "iterations", "env_steps", "physics_steps", "lr", "mean_return", "best_return",
                   "elite_score", "grad_norm", "nan_grads", "large_grads", "diverged", "sigma", "wall_time",
                   "steps_per_s")
    log_int_columns = ("epoch", "iterations", "env_steps", "physics_steps", "nan_grads", "large_grads", "diverged")
    saved = (Saved("mean", "mean", "tensor"), Saved("std", "std", "tensor"), Saved("members", "members", "tensor"),
             Saved("best", "best", "tensor"), Saved("adam_m", "adam.m", "tensor"), Saved("adam_v", "adam.v", "tensor"),
             Saved("adam_t", "adam.t", "tensor"), Saved("stats", "stats", "tensor"),
             Saved("obs_mean", "pop.obs_mean", "param"), Saved("obs_std", "pop.obs_std", "param"),
             Saved("best_score", "best_score", load=float),
             Saved("epoch", "epoch", file=PROGRESS_FILE, load=int),
             Saved("iterations", "iterations", file=PROGRESS_FILE, load=int),
             Saved("env_steps", "env_steps", file=PROGRESS_FILE, load=int),
             Saved("nan_grads", "nan_grads", file=PROGRESS_FILE, load=int),
             Saved("large_grads", "large_grads", file=PROGRESS_FILE, load=int),
             Saved("wall_time", "wall_time", file=PROGRESS_FILE, load=float),
             Saved("history", "history", file=PROGRESS_FILE, optional=True, load=list))

    method: str                                  # the APGConfig.method of a method class
    default_policy = "best"                      # policy() without ``which``: "best" member or CEM "mean"
    preset_settings: dict = {"thesis": {}, "reduced": {"population": 8, "elites": 3}}
    """A method's settings in :meth:`APGConfig.preset` ("reduced": after :data:`.config.REDUCED`)."""

    # ------------------------------------------------------------------ what a method may override
    @classmethod
    def member_count(cls, config: APGConfig) -> int:
        """K, the members trained side by side: the population."""
        return config.population

    @classmethod
    def unroll(cls, config: APGConfig) -> int:
        """Policy steps of one APG update: the whole episode (full BPTT)."""
        return config.horizon

    @classmethod
    def check_config(cls, config: APGConfig) -> None:
        """The method's own checks of a config (:meth:`APGConfig.validate` calls them); ValueError."""

    def epoch_update(self, lr: float) -> EpochStep:
        """The method's update of one epoch at learning rate ``lr``."""
        raise NotImplementedError

    def keep_best(self, finals: torch.Tensor, scores: torch.Tensor, top: int) -> None:
        """Update ``best`` / ``best_score`` from this epoch's members (``top``: the best index)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ state
    def __init__(self, system: str | System, config: APGConfig | None = None, **overrides):
        self.config = dataclasses.replace(config or APGConfig(method=self.method), **overrides)
        self.config.validate()
        cfg = self.config
        self.system = self._system(system, cfg)
        self.K = self.member_count(cfg)
        self.problem = APGProblem.build(self.system, cfg, self.K)
        # the checkpointer reads tensor files onto ``self.device`` (torch.load's map_location)
        self.pop, self.dtype, self.device = self.problem.pop, self.problem.dtype, self.problem.device
        self.period, self.substeps, self.takeover = self.problem.period, self.problem.substeps, self.problem.takeover
        P = self.pop.n_params
        # CEM / CE-APG: theta = 0 with std sigma_0 (the author's zero-initialised weights); PAPG/APG: members
        # start as the population's own perturbed-zero initialisation
        self.mean = torch.zeros(P, dtype=torch.float64, device=self.device)
        self.std = torch.full((P,), float(cfg.init_std), dtype=torch.float64, device=self.device)
        self.members = self.pop.to_flat().double()
        self.best = self.members[0].clone()
        self.best_score = -math.inf
        self.adam = BatchedAdam(self.K, P, (cfg.beta1, cfg.beta2), device=self.device)
        self.stats = torch.zeros(2 * self.pop.obs_dim + 1, dtype=torch.float64,   # sum, sum of squares, count
                                 device=self.device)
        self.epoch = self.iterations = self.env_steps = self.nan_grads = self.large_grads = 0
        self.wall_time = 0.0
        self.history: list[dict] = []
        self.log_rows: list[dict] = []
        self.last_scores = torch.full((self.K,), -math.inf, dtype=torch.float64, device=self.device)
        self._backend = None    # the worker pool of a split APG phase (opened on first use)

    def __getnewargs_ex__(self):
        """copy / pickle rebuild the instance through ``__new__`` with the config (its method's class)."""
        return (), {"config": self.config}

    @staticmethod
    def _system(system: str | System, cfg: APGConfig) -> System:
        """The system with the config's Ch. 7 reward (as spec overrides, recorded in the spec)."""
        reward = {"reward__kind": cfg.reward_kind, "reward__alive_bonus": float(cfg.alive_bonus),
                  "reward__velocity_penalty": float(cfg.velocity_penalty),
                  "reward__position_weight": float(cfg.position_weight),
                  "reward__linear_velocity_weight": float(cfg.linear_velocity_weight),
                  "reward__cost_to_go_weight": float(cfg.cost_to_go_weight)}
        if isinstance(system, System):
            base = system.name if system.name in known_systems() else str(system.spec.path)
            return systems_mod.load(base, **{**system.spec.overrides, **reward})
        if not isinstance(system, str):
            raise ValueError(f"system must be a name ({', '.join(known_systems())}) or a System, got {system!r}")
        return systems_mod.load(system, **reward)

    @property
    def progress_count(self) -> int:
        """CE / PAPG epochs so far (the progress.csv key)."""
        return self.epoch

    @classmethod
    def run_label(cls, config) -> str:
        """The method's name ("papg", "ce-apg") in a run's account."""
        return config.method

    def training_record(self) -> dict:
        """eval.json's training counters: method, epochs, APG iterations, env steps, gradient guards, wall time."""
        return {"method": self.config.method, "epochs": self.epoch, "iterations": self.iterations,
                "env_steps": self.env_steps, "nan_grads": self.nan_grads, "large_grads": self.large_grads,
                "train_wall_time_s": self.wall_time}

    # ------------------------------------------------------------------ randomness
    def _generator(self, epoch: int) -> torch.Generator:
        """The torch generator of ``epoch`` on the learner's device (from the seed alone: a resumed run
        continues exactly; a CUDA generator draws other numbers than the CPU's from the same seed)."""
        seed = int(np.random.SeedSequence([self.config.seed, epoch]).generate_state(1)[0])
        return torch.Generator(device=self.device).manual_seed(seed)

    def starts(self, n: int, seed_words) -> torch.Tensor:
        """n start states [n, n_states]: hanging down +- U(-start_noise, start_noise), or the spec's spread."""
        return self.problem.starts(n, seed_words)

    # ------------------------------------------------------------------ the APG phase
    def apg_step(self, theta: torch.Tensor, x0: torch.Tensor, lr: float, adam: BatchedAdam | None = None,
                 state=None, horizon: int | None = None):
        """One batched APG update of the members ``theta`` [K, P] from starts x0 (:func:`~.core.apg_iteration`;
        ``adam`` default the learner's, stepped in place), its guards counted in ``nan_grads`` /
        ``large_grads``. Returns (new theta, per-member mean returns [K] (-inf where diverged),
        gradient norms [K], applied mask [K], final x, final recurrent state)."""
        it = apg_iteration(self.problem, theta, x0, lr, adam or self.adam, state, horizon,
                           f"at epoch {self.epoch}, iteration {self.iterations}")
        self.nan_grads += it.nan_grads
        self.large_grads += it.large_grads
        return it.theta, it.scores, it.norms, it.ok, it.x, it.state

    def run_apg_phase(self, theta: torch.Tensor, lr: float, adam: BatchedAdam) -> Phase:
        """The epoch's APG phase of the members ``theta`` with ``adam`` (:func:`~.core.apg_phase`), in this
        process or (config ``backend`` not "serial", more than one member) as chunks of members on
        the backend (:func:`~.split.split_apg_phase`); the counters are advanced here."""
        cfg = self.config
        if cfg.backend == "serial" or self.K == 1:
            phase = apg_phase(self.problem, theta, adam, lr, self.epoch, self.iterations, self.unroll(cfg))
        else:
            if self._backend is None:
                self._backend = make_backend(cfg.backend, workers=cfg.workers, address=cfg.address)
            system = self.system.name if self.system.name in known_systems() else str(self.system.spec.path)
            phase = split_apg_phase(self._backend, self.problem, system, theta, adam, lr, self.epoch, self.iterations,
                                    self.unroll(cfg))
        self.iterations += phase.iterations
        self.env_steps += phase.env_steps
        self.nan_grads += phase.nan_grads
        self.large_grads += phase.large_grads
        return phase

    def close_backend(self) -> None:
        """Close the worker pool of the split APG phase, if one is open (``learn`` does it when it ends)."""
        backend, self._backend = self._backend, None
        if backend is not None:
            backend.close()

    # ------------------------------------------------------------------ one epoch
    def train_epoch(self) -> dict:
        """One epoch of the method (:meth:`epoch_update`), then the shared book-keeping: the members,
        the best member, the observation statistics, the progress row."""
        cfg = self.config
        lr = lr_schedule(cfg, self.epoch)
        nan_before, large_before = self.nan_grads, self.large_grads
        step = self.epoch_update(lr)
        scores = step.scores
        self.members = step.finals
        self.last_scores = scores          # this epoch's ranking scores [K] (-inf: diverged)
        top = int(torch.argmax(torch.nan_to_num(scores, nan=-math.inf)))
        self.keep_best(step.finals, scores, top)
        if cfg.normalize and step.obs_sums is not None:
            o_sum, o_sq, count = step.obs_sums
            self.stats += torch.cat([o_sum, o_sq, torch.tensor([float(count)], dtype=torch.float64,
                                                               device=self.device)])
            self._apply_stats()
        self.epoch += 1
        finite = step.history[torch.isfinite(step.history)]
        return {"epoch": self.epoch, "iterations": self.iterations, "env_steps": self.env_steps,
                "physics_steps": self.env_steps * self.substeps, "lr": lr,
                "mean_return": float(finite.mean()) if finite.numel() else float("nan"),
                "best_return": float(scores[top]), "elite_score": float(scores[step.elite].mean()),
                "grad_norm": step.grad_norm, "nan_grads": self.nan_grads - nan_before,
                "large_grads": self.large_grads - large_before,
                "diverged": int((~torch.isfinite(scores)).sum()), "sigma": float(self.std.mean())}

    def _apply_stats(self) -> None:
        """Freeze the running observation mean/std into the policies (std 1 where below 1e-4)."""
        d = self.pop.obs_dim
        count = float(self.stats[-1])
        if count < 2:
            return
        mean = self.stats[:d] / count
        var = (self.stats[d:2 * d] / count - mean ** 2).clamp_min(0.0)
        std = torch.where(var < 1e-8, torch.ones_like(var), var.sqrt())
        self.pop.set_normalization(mean, std)

    def run_description(self) -> str:
        """The progress bar's label."""
        return f"{self.config.method} {self.system.name}"

    def train(self, run, target: int, backend) -> None:
        """The APG family's loop inside ``learn``'s run: one epoch at a time (the population split
        over ``backend``, default the config's, opened when first needed), a checkpoint every
        ``checkpoint_every`` epochs and at least every ``checkpoint_minutes``."""
        if backend is not None:
            self._backend = backend
        try:
            run.updates(target, self._timed_epoch, 1, self.config.checkpoint_every,
                        lambda row: {"ret": f"{row['best_return']:.1f}", "gnorm": f"{row['grad_norm']:.2g}",
                                     "nan": self.nan_grads, "sps": f"{row['steps_per_s']:.0f}"})
        finally:
            if backend is None:
                self.close_backend()
            else:
                self._backend = None

    def _timed_epoch(self) -> dict:
        """One epoch's row, with ``episode_steps`` the epoch's env steps (so that :meth:`Run.updates`'s
        steps per second count every member's and batch's steps)."""
        before = self.env_steps
        row = self.train_epoch()
        row["episode_steps"] = self.env_steps - before
        return row

    # ------------------------------------------------------------------ use
    def policy(self, which: str | None = None) -> Policy:
        """The trained policy: ``"best"`` (the best member) or ``"mean"`` (the CEM mean), with the frozen
        normalisation; default the method's ``default_policy`` (apg/shapg/papg "best", cem/ce-apg "mean")."""
        which = which or self.default_policy
        if which not in ("best", "mean"):
            raise ValueError(f"which must be 'best' or 'mean', got {which!r}")
        theta = self.mean if which == "mean" else self.best
        return Policy(self.pop.resized(1, theta.to(self.dtype)[None]))

    def closed_loop_policy(self, which: str | None = None) -> ClosedLoopPolicy:
        """:meth:`policy` with the observation, on raw states (for Drake's RecurrentTorchPolicy)."""
        return ClosedLoopPolicy(self.system, self.policy(which), self.config.observation)

    def controller(self, system: System | None = None) -> SwitchedController:
        """The trained recurrent swing-up (:meth:`closed_loop_policy`) at its own decision period, under the
        spec's cost-to-go gate (hysteresis) and LQR of ``system`` (default: the one it trained on), the
        takeover it trains through (thesis Ch. 7): :func:`~.core.takeover_controller`, the gate every
        integrator step, as in training."""
        system = self.system if system is None else system
        if system.name != self.system.name:
            raise ValueError(f"this {self.config.method} policy was trained on {self.system.name}, not {system.name}")
        return takeover_controller(system, self.period).replace(swingup=self.closed_loop_policy())

    def fine_tuning_task(self) -> dict:
        """Its reward (the system's overrides) and its starts (hanging down +- ``start_noise`` on every
        state; the spec's spread when ``start_noise`` is None); refused for a policy trained without
        the LQR takeover (fine-tuning runs it inside the switched controller)."""
        if self.config.takeover != "lqr":
            raise ValueError(f"this {self.config.method} policy was trained without the LQR takeover (takeover="
                             f"{self.config.takeover!r}); fine-tuning inside the switched controller needs one "
                             f"trained through it (hybridctl train {self.config.method} {self.system.name} "
                             f"--takeover lqr)")
        overrides = dict(self.system.spec.overrides)
        if self.config.start_noise is not None:
            noise = float(self.config.start_noise)
            n = self.system.n_states
            overrides.update(initial_state__low=[-noise] * n, initial_state__high=[noise] * n)
        return overrides

    def run_evaluation(self, episodes: int, seed: int, which: str | None = None,
                       horizon: int | None = None, keep_states: bool = False) -> EvalResult:
        """``evaluate(episodes, seed=, ...)``: returns of the trained policy on held-out starts, and the stabilisation rate: the share of
        episodes whose last second (of policy-step states) stays within the spec's success eps of
        the goal (thesis eq. 3.2 with lookback = one second; the L2 norm over every coordinate, a
        cart's position and the velocities included). ``upright_rate``: the share whose angle
        errors alone all stay below eps over the last second (the pole held up, the cart anywhere).
        ``best_training_return``: the best member's training score (the author's metric)."""
        n = episodes
        which = which or self.default_policy
        policy = self.policy(which)
        x0 = self.starts(n, [seed, 2])
        with torch.no_grad():
            returns, _, _, _, states = population_returns(self.system, policy.population, x0,
                                                          horizon or self.config.horizon, self.substeps,
                                                          self.config.observation, keep_states=True,
                                                          takeover=self.takeover)
        r = returns[0].double().cpu().numpy()   # the evaluation's one copy to the host
        s = states[0].double().cpu().numpy()
        balanced, upright = stabilisation(s, self.system, lookback=max(1, int(round(1.0 / self.period))))
        out = EvalResult.from_returns(r[np.isfinite(r)], success_rate=float(balanced.mean()),
                                      upright_rate=float(upright.mean()),
                                      first={"episodes": n, "seed": seed}, which=which,
                                      diverged=int((~np.isfinite(r)).sum()), best_training_return=self.best_score)
        if keep_states:
            out["states"] = s
        return out

    # ------------------------------------------------------------------ checkpoints
    def warm_started(self) -> None:
        """Started from another run's checkpoint (``--init``): its best score was a return under that run's
        reward, so the best policy is chosen anew from this run's epochs (policy, normalisation, Adam's
        moments and the counters carry over: interactions count from the first run)."""
        self.best_score = -math.inf

    def checkpoint_extra(self) -> dict:
        """config.json beside algorithm, system (its record, the config's reward settings among its
        overrides) and config: the method, the policy's architecture, substeps and control period."""
        return {"method": self.config.method, "policy": self.pop.describe(), "substeps": self.substeps,
                "period": self.period}

    def normalization(self) -> dict:
        """normalization.json: the frozen observation mean and std."""
        return {"type": "frozen_mean_std", "mean": self.pop.obs_mean.tolist(), "std": self.pop.obs_std.tolist()}

    @classmethod
    def from_checkpoint(cls, found: Path, meta: dict, config: APGConfig, system, force: bool) -> "APGFamily":
        """:meth:`~hybridctl.learn.base.Learner.load`'s learner: the recorded method's class, on ``system``
        (None: the recorded one, rebuilt from its name and spec overrides; the config's reward
        settings are applied again). When today's spec of that system differs from the recorded
        plant, loading is refused naming the values (``force``: a warning), as for another
        algorithm's checkpoint."""
        record = meta["system"]
        if system is None:
            overrides = {k: v for k, v in (record.get("overrides") or {}).items() if not k.startswith("reward__")}
            system = ckpt.recorded_system(found, record["name"], overrides)
        agent = cls(system, config)  # the method's class (config.method); applies the config's reward settings
        if "spec_hash" in record:
            ckpt.check_plant(found, record, agent.system, force)
        return agent
