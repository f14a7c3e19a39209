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

The update is antithetic random search (:mod:`hybridctl.learn.random_search`, shared with ARS:
all directions kept, the schedules per update); the episodes come from
:mod:`hybridctl.learn.rollouts` (shared with ARS and the failure rates): chunks of perturbed
policies, one batched forward of the chunk's policies (``torch.func.vmap`` over their weights)
per env step, over the chunk's envs (gymnasium envs, the MuJoCo batch stepper, or a hybridctl
system's batched torch dynamics for sac/ssac and APG-family sources, on ``device``). Chunks are spread over a
:mod:`hybridctl.parallel` backend, by default enough of them to give each of its workers two;
the policy, its normaliser and the post-processor go to the backend once per update
(``backend.put``). A chunk's numbers do not depend on its size (2 rows or more, measured bit for
bit), so a seed gives the same run on every backend and worker count. This file holds
what is fine-tuning's own: the settings and schedules, the learner, the SB3 export; the sources
(:func:`~hybridctl.learn.finetune_sources.load_policy`), the parameter selection and the frozen
normaliser are in :mod:`hybridctl.learn.finetune_sources`.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import gymnasium as gym
import numpy as np
import torch

from ..analysis.postprocess import FORMS as POSTPROCESS_FORMS
from ..analysis.postprocess import KINDS as POSTPROCESS_KINDS
from ..analysis.postprocess import PostProcessor
from ..envs.mujoco_batch import supports as batch_supports
from ..parallel import BACKENDS, make_backend
from ..systems import load as load_system
from ..systems.switched import CostToGoGate, NeverGate, SwitchedController
from . import checkpoint as ckpt
from .checkpoint import PROGRESS_FILE, Saved
from .chunk_tasks import (AUTO_CHUNK_MAX, AUTO_CHUNK_MAX_ACCELERATOR, ChunkInputs, ChunkTask, Shipped, chunk_slices,
                          is_recurrent, normalise, unflatten)
from .config_check import check_fields, check_types
from .finetune_sources import SELECTIONS, TunablePolicy, load_policy, source_kinds
from .random_search import RandomSearchLearner
from .robustness import wilson_interval  # noqa: F401 (re-exported: hybridctl.learn.finetune.wilson_interval)
from .rollout_envs import make_env, recorded_env_id, recorded_env_kwargs
from .rollout_results import evaluation_seeds
from .rollouts import rollouts
from .run import EvalResult
from .config_check import check_device_field

DIMENSION_SETTINGS = ("author", "ch4")


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
    chunk_size: int | None = None      # hybridctl: perturbed policies per batched rollout task; None ("auto"):
    #                                    near-equal chunks of 2 to 64 rows (4,096 for a system on an accelerator),
    #                                    at least 2 tasks per backend worker; an int: chunks of that size. Any size
    #                                    >= 2 gives the same numbers bit for bit (measured): a one-row chunk of a
    #                                    system's float64 CPU rollout takes System.step's plain-float path, which
    #                                    can differ in the last bit
    backend: str = "processes"         # "serial", "processes" (local, default), "ray"
    workers: int | None = None         # None: every core (processes) or the cluster's CPUs (ray)
    address: str | None = None         # Ray cluster address (backend "ray")
    device: str = "cpu"                # hybridctl: where a hybridctl system's rollouts run (system sources: the
    #                                    policy, gate and batched dynamics; "cuda:0" on a GPU); gymnasium and MuJoCo
    #                                    envs step on the host, so their rollouts stay on the CPU
    checkpoint_every: int = 10         # updates between atomic checkpoints
    checkpoint_minutes: float = 5.0    # hybridctl: also a checkpoint at least every this many minutes
    eval_episodes: int = 100           # thesis Sec. 6.3: 100 Monte Carlo trials per agent
    torch_threads: int = 1             # hybridctl: one thread per process (two ran SB3 11x slower here)

    def validate(self) -> None:
        """Raise ValueError naming the first invalid field."""
        check_types(self)
        check_fields(self, positive=("step_size_start", "step_size_end", "noise_start", "noise_end"),
                     integers_from_1=("updates", "n_directions", "checkpoint_every", "eval_episodes",
                                      "torch_threads"), integers_from_0=("seed",))
        if self.chunk_size is not None and self.chunk_size < 1:
            raise ValueError(f"FineTuneConfig.chunk_size must be None (auto: from the backend's workers) or an "
                             f"integer >= 1, got {self.chunk_size!r}")
        # a Ray cluster's workers may have a GPU this machine lacks: checked there
        check_device_field(self, available=self.backend != "ray")
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


# ============================================================================ the algorithm

class FineTune(RandomSearchLearner):
    """Direct policy search over a trained policy's weights (Alg. 8): ``learn`` / ``predict`` /
    ``evaluate`` / ``save`` / ``load`` / ``save_sb3``.

    Args:
        env: a gymnasium env id (or a hybridctl system name for sac/ssac/APG-family sources), or a factory.
        policy: a source string ("sb3:PATH", "ars:PATH", "sac:PATH", "ssac:PATH", or an APG family's
            "ce-apg:PATH", "papg:PATH", ...: recurrent, see :func:`load_policy`), a
            :class:`TunablePolicy`, or an ``nn.Module`` mapping observations to actions.
        config: :class:`FineTuneConfig` (the thesis' single setting by default); ``overrides``
            replace its fields.
        trust: allow unpickling a VecNormalize ``.pkl`` (only for files you trust).
        normalizer: an ``.npz`` of observation statistics for an sb3 source.
    """

    algorithm_name = "FineTune"
    train_names = ()                       # `hybridctl finetune`, not a `train` sub-command
    config_class = FineTuneConfig
    budget_field, unit = "updates", "update"
    display_name, theta_name = "fine-tuning", "fine-tuned theta"   # the NaN guards' messages
    step_eps = 1e-6   # the author's step: alpha / (n sigma_R + 1e-6)
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
        self._start(config or FineTuneConfig(), env, env_kwargs, overrides)
        if isinstance(policy, str):
            if not isinstance(env, str):
                raise ValueError("a policy source string needs an env id, not a factory; pass a TunablePolicy")
            policy = load_policy(policy, env, trust=trust, normalizer=normalizer)
        elif isinstance(policy, torch.nn.Module):
            policy = TunablePolicy(policy)
        if not isinstance(policy, TunablePolicy):
            raise TypeError(f"policy must be a source string, a TunablePolicy or an nn.Module, got "
                            f"{type(policy).__name__}")
        if policy.system is None and torch.device(self.config.device).type != "cpu":
            raise ValueError(f"FineTuneConfig.device {self.config.device!r} applies to a hybridctl system's rollouts "
                             f"(sac/ssac/APG-family sources, whose dynamics are torch); {self.env_name} steps on "
                             f"the host, so "
                             f"its rollouts run on the CPU: leave device 'cpu'")
        self.tunable = policy
        self.tunable.module.eval()
        self.names = self.tunable.parameter_names(self.config.select)
        if not self.names:
            raise ValueError(f"select={self.config.select!r} selects no parameters of {policy.source}")
        self.obs_dim = self._obs_dim()
        self.theta0 = self._flat_params()
        self.theta = self.theta0.copy()

    # -- parameters ------------------------------------------------------------------------
    def _obs_dim(self) -> int:
        if self.tunable.system is not None:
            return load_system(self.tunable.system, **self.tunable.system_overrides).n_states
        probe = make_env(self.env, self.env_kwargs)
        try:
            return int(np.prod(probe.observation_space.shape))
        finally:
            probe.close()

    def _flat_params(self) -> np.ndarray:
        params = dict(self.tunable.module.named_parameters())
        return np.concatenate([params[n].detach().double().reshape(-1).numpy() for n in self.names]).copy()

    def _write_theta(self) -> None:
        """Put theta into the module's parameters (for saving, predict, export)."""
        params = dict(self.tunable.module.named_parameters())
        device = params[self.names[0]].device   # the learner's copy of the module (the CPU; workers move theirs)
        rows = unflatten(self.tunable.module, self.names,
                         torch.as_tensor(self.theta[None], dtype=torch.float64, device=device))
        with torch.no_grad():
            for name, value in rows.items():
                params[name].copy_(value[0])

    # -- rollouts ------------------------------------------------------------------------
    def _postprocessor(self, reward: str | None = None) -> PostProcessor:
        cfg = dataclasses.replace(self.config, reward=reward) if reward is not None else self.config
        return cfg.postprocessor(self.obs_dim, normalised=self.tunable.normalizer is not None)

    def _rollouts(self, thetas: np.ndarray, seeds: list[int], backend, postprocessor: PostProcessor,
                  max_steps: int | None = None, keep_states: bool = False) -> list[dict]:
        """One episode per (theta row, seed), in chunks spread over ``backend``
        (:class:`~hybridctl.learn.rollouts.ChunkTask`: a system's torch dynamics on ``device`` for
        sac/ssac/APG-family sources, the MuJoCo batch stepper where it applies, else gymnasium envs).

        The chunks: ``chunk_size`` rows each, or ("auto", None) :func:`~hybridctl.learn.rollouts.chunk_slices`
        from the backend's worker count. The policy, gate, normaliser and post-processor go to the
        backend once (``backend.put``: Ray keeps one copy in its object store) and every task carries
        the reference, not a copy."""
        module, gate = self._shipped()
        engine = "auto" if batch_supports(self.env, self.env_kwargs) else "backend"
        device = self.config.device if self.tunable.system is not None else "cpu"
        largest = AUTO_CHUNK_MAX if torch.device(device).type == "cpu" else AUTO_CHUNK_MAX_ACCELERATOR
        inputs = backend.put(ChunkInputs(module, self.names, self.tunable.normalizer, postprocessor, gate))
        tasks = [ChunkTask(self.env, self.env_kwargs, inputs, thetas[rows], seeds[rows],
                           max_steps or self.config.episode_steps, self.tunable.system, keep_states, engine, device,
                           self.tunable.system_overrides, self.tunable.decision_period)
                 for rows in chunk_slices(len(seeds), self.config.chunk_size, getattr(backend, "workers", 1), largest)]
        return rollouts(tasks, backend)

    def _shipped(self) -> tuple[Shipped, Shipped | None]:
        """The policy and gate (a :class:`~hybridctl.systems.switched.Gate`; None: no gate) as bytes for the
        workers, made once: the parameters they keep are never changed (the perturbed ones travel in the
        chunks' theta rows)."""
        if getattr(self, "_shipped_pair", None) is None:
            gate = self.tunable.gate
            self._shipped_pair = (Shipped(self.tunable.module), None if gate is None else Shipped(gate))
        return self._shipped_pair

    def perturbed_rollouts(self, thetas: np.ndarray, seeds: list[int], backend) -> list[dict]:
        """The update's training episodes, returns with the config's reward (dimension term or not)."""
        return self._rollouts(thetas, seeds, backend, self._postprocessor())

    def schedule(self, update: int) -> tuple[float, float]:
        """(step size, noise) of ``update``: the config's linear schedules (:meth:`FineTuneConfig.schedule`)."""
        return self.config.schedule(update)

    def update_row(self, step_size: float, noise: float) -> dict:
        """The scheduled step size and noise in the progress row."""
        return {"step_size": step_size, "noise": noise}

    def run_description(self) -> str:
        """The progress bar's label."""
        return f"fine-tune {self.env_name}"

    # -- use ---------------------------------------------------------------------------------
    def predict(self, obs: np.ndarray, deterministic: bool = True, state: np.ndarray | None = None):
        """The fine-tuned policy's (maximum-likelihood) action for one or a batch of observations.

        A recurrent policy (an APG-family source) returns ``(action, next state)``, as SB3's
        recurrent policies do: ``state`` is the previous call's (None: the zero state of a new episode).
        """
        if not deterministic:
            raise ValueError("fine-tuned policies act deterministically (maximum-likelihood actions); "
                             "deterministic=False is not supported")
        self._write_theta()
        module = self.tunable.module
        z = normalise(self.tunable.normalizer, np.asarray(obs, dtype=np.float64))
        first = next(module.parameters())
        z = torch.as_tensor(z, dtype=first.dtype, device=first.device)
        with torch.no_grad():
            if not is_recurrent(module):
                return module(z).double().cpu().numpy()
            h = module.initial_state(z.shape[0] if z.dim() > 1 else 1) if state is None else \
                torch.as_tensor(state, dtype=first.dtype, device=first.device)
            h = h[0] if z.dim() == 1 and h.dim() > 1 else h
            action, h = module(z, h)
            return action.double().cpu().numpy(), h.double().cpu().numpy()

    def tuned_module(self) -> torch.nn.Module:
        """A copy of the policy module with the fine-tuned weights (normalised observations -> actions),
        e.g. the swing-up block of a Drake diagram (``experiments.build_named_diagram(system, "finetune:PATH")``)."""
        self._write_theta()
        module = copy.deepcopy(self.tunable.module).eval()
        for p in module.parameters():
            p.requires_grad_(False)
        return module

    def controller(self, system=None) -> SwitchedController:
        """The tuned swing-up (:meth:`tuned_module`) with its source's gate (none, the spec's cost-to-go gate,
        or the learned gate), hysteresis and decision period and the LQR of ``system`` (default: the
        source's system); a source that drives no hybridctl system (sb3, ars, a module) has no controller."""
        if self.tunable.system is None:
            raise ckpt.CheckpointError(f"FineTune of {self.tunable.source} on {self.env_name} holds no swing-up of "
                                       f"a hybridctl system (a sac/ssac/APG-family source has one)")
        system = load_system(self.tunable.system, **self.tunable.system_overrides) if system is None else system
        if self.tunable.system != system.name:
            raise ValueError(f"this FineTune tunes {self.tunable.source} on {self.env_name}; a controller of "
                             f"{system.name} needs a source of that system")
        gate_meta = self.tunable.meta.get("gate") or {}
        gate = self.tunable.gate   # None: no gate; the spec's cost-to-go gate (of ``system``) or the learned gate
        gate = NeverGate() if gate is None else CostToGoGate(system) if isinstance(gate, CostToGoGate) else gate
        return SwitchedController.for_system(system, swingup=self.tuned_module(), gate=gate,
                                             gate_on=gate_meta.get("gate_on"), gate_off=gate_meta.get("gate_off"),
                                             decision_period=self.tunable.decision_period)

    def fine_tuning_task(self) -> dict:
        """The source's training task (fine-tuning a fine-tuned policy goes on on the same task)."""
        return dict(self.tunable.system_overrides)

    def run_evaluation(self, episodes: int, seed: int, theta: np.ndarray | None = None,
                       backend=None, episode_steps: int | None = None, keep_states: bool = False) -> EvalResult:
        """``evaluate(episodes, seed=, ...)``: deterministic episodes of theta (default the current; ``theta0`` is the pretrained agent):
        raw returns, episode lengths, early terminations with a 95 % Wilson interval, the mesh-mean
        dimension of each episode (author's settings) and, for systems, the thesis success rate."""
        n = episodes
        seeds = evaluation_seeds(seed, n)
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
            raise ckpt.CheckpointError(f"{file}: 'source' must be a string KIND:PATH with KIND one of {source_kinds()}, "
                                       f"got {type(source).__name__}")
        record = meta.get("system") if isinstance(meta.get("system"), dict) else {}
        env = system if system is not None else recorded_env_id(record.get("name"), file, "system.name")
        if isinstance(source, str) and isinstance(env, str):
            found_at = recorded_source_path(source, found)
            if found_at != source:   # read from where it was found; the record keeps its own name for it
                source = dataclasses.replace(load_policy(found_at, env, trust=trust), source=source)
        return cls(env, source, config, env_kwargs=recorded_env_kwargs(record.get("kwargs"), file,
                                                                       "system.kwargs"), trust=trust)


def recorded_source_path(source: str, checkpoint: Path) -> str:
    """A recorded ``KIND:PATH`` with a relative PATH made findable from any working folder: as it is
    where it exists from here, else from the nearest folder above ``checkpoint`` that holds it (the
    records name paths from the repository root), else the package's own shipped model
    (``models/...``, also in an installed wheel); unchanged where none holds it (the error then names it)."""
    from ..systems.spec import MODELS_DIR
    kind, sep, path = str(source).partition(":")
    relative = Path(path)
    if not sep or not path or relative.is_absolute() or relative.exists():
        return source
    for folder in Path(checkpoint).resolve().parents:
        if (folder / relative).exists():
            return f"{kind}:{folder / relative}"
    if relative.parts[:1] == ("models",) and (MODELS_DIR.parent / relative).exists():
        return f"{kind}:{MODELS_DIR.parent / relative}"
    return source
