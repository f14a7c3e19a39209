"""The thesis' Tables 7.1 / 7.2 in direction: CE-APG, PAPG, CEM, APG, short-horizon APG, our SAC and
Stable-Baselines3's PPO and SAC on the same Ch. 7 task of each system, several seeds, one record per run.

Every learner sees the same task: the spec's start distribution, the Ch. 7 reward
(:data:`TASKS`), policy steps of 0.05 s, episodes of ``horizon`` steps. Every trained policy is
scored by the same code, :func:`rollout_metrics`, on the same held-out starts, as a
:class:`~hybridctl.systems.SwitchedController` run by :func:`~hybridctl.systems.closed_loop_rollout` (the
policy alone under :class:`~hybridctl.systems.switched.NeverGate`; an APG-family policy trained through
the LQR takeover under the takeover's own controller, :func:`apg_controller`): the return, the
stabilisation rate (every coordinate within the spec's success eps of the goal over the last
second, thesis eq. 3.2) and the upright rate (the angles alone). The APG family also reports
the best member's training return (the author's metric). Interactions are counted as the
learners count them (K x N x T x iterations for the APG family; env steps for SAC and SB3).

SB3's PPO and SAC (``sb3-ppo``, ``sb3-sac``; the ``sb3`` extra) train through the gymnasium wrapper
:class:`hybridctl.envs.single.SwingupEnv` on the task's spec overrides, period and episode length,
with SB3's default hyperparameters (no tuning for these tasks, stated in the record), and are scored
by the same :func:`rollout_metrics` on the same starts.

Runs are resumable: a run whose ``record.json`` exists is skipped, so an interrupted study
continues where it stopped.

>>> from hybridctl.experiments.apg_study import run_study
>>> records = run_study("runs/ch7/table71", systems=["cartpole"], seeds=[0, 1])
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from .. import io
from ..learn.apg import APG, METHOD_CLASSES, APGConfig
from ..learn.run import EVAL_SEED
from ..learn.sb3 import silent_logger
from ..systems import System, load
from ..systems.success import stabilisation
from ..systems.switched import NeverGate, SwitchedController, ZeroSwingup, closed_loop_rollout
from .training import machine

STUDY_METHODS = ("ce-apg", "papg", "cem", "apg", "shapg", "sac", "sb3-ppo", "sb3-sac")
"""Learners of the study, in the thesis' Table 7.1 order, then our SAC, then Stable-Baselines3's PPO and SAC."""


@dataclass(frozen=True)
class Task:
    """One system's Ch. 7 task: spec overrides (reward kind and settings, period), episode length."""

    overrides: dict
    horizon: int = 100          # policy steps per episode (5 s at 0.05 s)
    source: str = ""


TASKS = {
    "cartpole": Task({"reward__kind": "angle_cosine", "reward__position_weight": 0.1},
                     source="thesis Sec. 7.2.4 (-theta^2) with the smooth 2(1 - cos) option and a cart weight 0.1"),
    "acrobot": Task({"reward__kind": "angle_cosine", "control__swingup_period": 0.05},
                    source="thesis Sec. 7.2.3 (-phi1^2 - phi2^2) with the smooth option; 0.05 s policy steps "
                           "(the author's 0.04 s; the spec's Ch. 3 0.2 s is too coarse for a 5 s swing-up)"),
    "double_cartpole": Task({"reward__kind": "tip_distance"}, source="thesis eqs. 7.5-7.8 (tip distance)"),
}
"""The Ch. 7 task per system (spec overrides, hybridctl's choices named in ``source``)."""


@dataclass
class StudySettings:
    """The learners' budget in the study (hybridctl, sized for a 2-core machine; thesis values in comments).

    Every APG-family learner runs ``iterations`` APG iterations (CEM: as many population
    evaluations) with the thesis' GRU, N = 4 starts, K = 8 members (thesis 24), 3 elites (8);
    SAC runs ``sac_steps`` env steps.
    """

    policy: str = "gru"               # thesis Sec. 7.3.4
    population: int = 8               # thesis 24
    elites: int = 3                   # thesis 8
    batch: int = 4                    # thesis 4
    apg_iterations: int = 50          # per CE epoch; thesis 100
    epochs: int = 12                  # thesis 200 (CE-APG), 2000 (CEM)
    lr_start: float = 1e-3            # thesis 1e-3 -> 1e-6 over all epochs;
    lr_end: float = 1e-5              # fewer epochs here, so the end is higher
    compile: bool = True
    sac_steps: int = 200_000          # a tenth of the APG family's interactions (8 x 4 x 100 x 600 = 1.92e6): ~2-4 min here
    sb3_steps: int = 200_000          # SB3 PPO / SAC env steps, our SAC's budget (PPO ~3 min here; SB3 SAC ~45 min:
    #                                   one gradient step per env step on the CPU, ~75 steps/s measured)
    eval_episodes: int = 16
    eval_seed: int = EVAL_SEED
    horizon: int | None = None        # policy steps per episode; None: the task's (TASKS); thesis 500
    checkpoint_every: int | None = None   # epochs between checkpoints; None: a quarter of the epochs
    equal_interactions: bool = False  # APG as one policy on population x batch starts per iteration (the
    #                                   others' interactions; thesis APG: one policy, batch 4, a 24th of them)
    extra: dict = field(default_factory=dict)   # more APGConfig fields for every APG run

    @classmethod
    def thesis(cls, **changes) -> "StudySettings":
        """The thesis' own budget (Sec. 7.3.7): K 24, K_e 8, N 4, T 500, 100 APG iterations per epoch,
        200 epochs, lr 1e-3 -> 1e-6 (9.6e8 interactions a run), APG at the same interactions, a
        checkpoint every 5 epochs (a run is ~1 h here: it resumes across sessions), no gradient-norm guard
        (the author's)."""
        values = dict(population=24, elites=8, batch=4, apg_iterations=100, epochs=200, lr_start=1e-3, lr_end=1e-6,
                      horizon=500, checkpoint_every=5, equal_interactions=True,
                      # the author's: no bound on a gradient's norm (Adam's step is bounded whatever the norm).
                      # hybridctl's default guard (1e8) skips every T = 500 acrobot gradient of APG (norms
                      # 2e11-3e11 measured) and so would test the guard, not the method
                      extra={"grad_bound": 1e300})
        values.update(changes)
        return cls(**values)

    @property
    def iterations(self) -> int:
        """APG iterations per run (CEM: population evaluations)."""
        return self.apg_iterations * self.epochs


def task_system(name: str) -> System:
    """The system with its Ch. 7 task's spec overrides."""
    if name not in TASKS:
        raise ValueError(f"unknown system {name!r} for the Ch. 7 study; known: {', '.join(TASKS)}")
    return load(name, **TASKS[name].overrides)


def apg_config(method: str, system_name: str, seed: int, settings: StudySettings) -> APGConfig:
    """The APGConfig of one study run (``method`` one of the APG family)."""
    task = TASKS[system_name]
    reward = {k.split("__", 1)[1]: v for k, v in task.overrides.items() if k.startswith("reward__")}
    values = dict(method=method, reward_kind=reward.get("kind", "angle_squared"),
                  alive_bonus=float(reward.get("alive_bonus", 0.0)),
                  velocity_penalty=float(reward.get("velocity_penalty", 0.0)),
                  position_weight=float(reward.get("position_weight", 0.0)),
                  horizon=settings.horizon or task.horizon, start_noise=None, policy=settings.policy,
                  batch=settings.batch,
                  population=settings.population, elites=settings.elites, apg_iterations=settings.apg_iterations,
                  epochs=settings.epochs, lr_start=settings.lr_start, lr_end=settings.lr_end,
                  compile=settings.compile, seed=seed, eval_episodes=settings.eval_episodes,
                  checkpoint_every=settings.checkpoint_every or max(1, settings.epochs // 4))
    values.update(METHOD_CLASSES[method].preset_settings["thesis"])   # apg: one member; shapg: clip, betas
    if method == "apg" and settings.equal_interactions:   # one policy, the population's starts
        values.update(batch=settings.population * settings.batch)
    if method == "cem":      # as many population evaluations as the others' APG iterations
        values.update(epochs=settings.iterations, apg_iterations=1)
    values.update(settings.extra)
    return APGConfig(**values)


def held_out_starts(system: System, episodes: int, seed: int) -> np.ndarray:
    """The evaluation starts: the spec's start distribution, numpy seed (seed, 2) (as APG.evaluate)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 2]))
    return np.asarray(system.sample_initial_states(episodes, rng), dtype=float)


def swingup_alone(system: System, act, period: float) -> SwitchedController:
    """A policy alone as a switched controller on ``system``: the swing-up ``act(x [B, n] float64) -> u``
    (torch or numpy, B x m values; a torch module or :class:`~hybridctl.systems.switched.ZeroSwingup` as it
    is) held ``period`` s, and a :class:`~hybridctl.systems.switched.NeverGate` (the LQR never acts)."""
    if not isinstance(act, (torch.nn.Module, ZeroSwingup)):
        law = act
        act = lambda x: torch.as_tensor(law(x), dtype=torch.float64).reshape(len(x), system.n_actions)  # noqa: E731
    return SwitchedController.for_system(system, swingup=act, gate=NeverGate(), decision_period=period)


def apg_controller(agent) -> SwitchedController:
    """What an APG-family run is scored as: its recurrent swing-up (``closed_loop_policy``) through the LQR
    takeover it trained through (``config.takeover = "lqr"``: the takeover's own controller, its gate and
    LQR every integrator step), else alone (:func:`swingup_alone`)."""
    closed = agent.closed_loop_policy()
    if agent.takeover is not None:
        return agent.takeover.controller.replace(swingup=closed)
    return swingup_alone(agent.system, closed, agent.period)


def rollout_metrics(system: System, controller: SwitchedController, x0: np.ndarray, horizon: int) -> dict:
    """Roll ``controller`` out on ``system`` for ``horizon`` swing-up decisions (its ``decision_period``) from
    ``x0`` (:func:`~hybridctl.systems.closed_loop_rollout`, float64, a diverging row left to run on to Inf /
    NaN); the return (sum of ``System.reward`` after each decision), stabilisation and upright rates over the
    last second, and the rows whose states or return are not finite (``diverged``, left out of the return)."""
    period = controller.decision_period
    run = closed_loop_rollout(system, controller, x0, horizon, on_divergence="propagate", dtype=torch.float64)
    total = torch.zeros(len(x0), dtype=torch.float64)
    for t in range(1, horizon + 1):
        total += system.reward(run.states[:, t].contiguous())
    s = run.states.numpy()
    balanced, upright = stabilisation(s, system, lookback=max(1, int(round(1.0 / period))))
    ok = np.isfinite(s).all(axis=(1, 2)) & np.isfinite(total.numpy())
    r = total.numpy()[ok]
    return {"mean_return": float(r.mean()) if r.size else -math.inf, "std_return": float(r.std()) if r.size else 0.0,
            "stabilised": float(balanced.mean()), "upright": float(upright.mean()), "diverged": int((~ok).sum()),
            "episodes": int(len(x0))}


def _train_apg(method: str, system_name: str, seed: int, settings: StudySettings, out: Path) -> tuple[dict, dict]:
    """Train one APG-family run; (metrics on the held-out starts, training facts)."""
    system = task_system(system_name)
    config = apg_config(method, system_name, seed, settings)
    agent = APG(system, config)
    agent.learn(out=out / "run", progress=False,
                resume=any((out / "run" / name).exists() for name in ("checkpoint", "final")))
    x0 = held_out_starts(agent.system, settings.eval_episodes, settings.eval_seed)
    metrics = rollout_metrics(agent.system, apg_controller(agent), x0, config.horizon)
    facts = {"interactions": agent.env_steps, "iterations": agent.iterations, "epochs": agent.epoch,
             "train_wall_time_s": agent.wall_time, "best_training_return": agent.best_score,
             "which": agent.default_policy, "nan_grads": agent.nan_grads,
             "large_grads": agent.large_grads, "config": dataclasses.asdict(config)}
    return metrics, facts


def task_period(system_name: str) -> float:
    """Seconds each action is held in the Ch. 7 task (the task's ``control__swingup_period`` or the spec's)."""
    return float(TASKS[system_name].overrides.get("control__swingup_period", load(system_name).swingup_period))


def episode_system(system_name: str) -> tuple[System, float]:
    """(the task's system with episodes of ``horizon`` policy steps, the policy period): what the
    env-step learners (our SAC, SB3) train on."""
    task, period = TASKS[system_name], task_period(system_name)
    return load(system_name, **task.overrides, episode__duration=task.horizon * period), period


def _train_sac(system_name: str, seed: int, settings: StudySettings, out: Path) -> tuple[dict, dict]:
    """Train our SAC on the same task (episodes of ``horizon`` policy steps); metrics and facts."""
    from ..learn import SAC, SACConfig

    system, period = episode_system(system_name)
    task = TASKS[system_name]
    agent = SAC(system, SACConfig(seed=seed, total_steps=settings.sac_steps))
    start = time.perf_counter()
    agent.learn(out=out / "run", progress=False)
    wall = time.perf_counter() - start
    x0 = held_out_starts(system, settings.eval_episodes, settings.eval_seed)
    metrics = rollout_metrics(system, swingup_alone(system, lambda x: agent.predict(x.float(), deterministic=True),
                                                    period), x0, task.horizon)
    facts = {"interactions": int(agent.num_timesteps), "train_wall_time_s": wall, "best_training_return": None,
             "which": "deterministic actor", "config": dataclasses.asdict(agent.config)}
    return metrics, facts


SB3_ALGORITHMS = {"sb3-ppo": "PPO", "sb3-sac": "SAC"}
"""Study method -> the Stable-Baselines3 class trained with its default hyperparameters."""


def _train_sb3(method: str, system_name: str, seed: int, settings: StudySettings, out: Path) -> tuple[dict, dict]:
    """Train SB3's PPO or SAC (defaults, ``MlpPolicy``) through the gymnasium wrapper on the same task for
    ``settings.sb3_steps`` env steps; metrics on the held-out starts and training facts. The model is
    saved as ``out/run/model.zip`` (our own file: :func:`hybridctl.learn.load_sb3` reads it without
    unpickling)."""
    try:
        import stable_baselines3 as sb3
    except ImportError as exc:
        raise ImportError(f"{method} needs Stable-Baselines3: pip install -c constraints.txt -e \".[sb3]\"") from exc
    from ..envs.single import SwingupEnv

    system, period = episode_system(system_name)
    env = SwingupEnv(system, decision_period=period)
    model = getattr(sb3, SB3_ALGORITHMS[method])("MlpPolicy", env, seed=seed, device="cpu", verbose=0)
    model.set_logger(silent_logger())
    start = time.perf_counter()
    model.learn(total_timesteps=settings.sb3_steps)
    wall = time.perf_counter() - start
    (out / "run").mkdir(parents=True, exist_ok=True)
    model.save(out / "run" / "model.zip")
    x0 = held_out_starts(env.system, settings.eval_episodes, settings.eval_seed)
    act = lambda x: model.predict(x.numpy(), deterministic=True)[0]   # noqa: E731
    metrics = rollout_metrics(env.system, swingup_alone(env.system, act, period), x0, TASKS[system_name].horizon)
    facts = {"interactions": int(model.num_timesteps), "train_wall_time_s": wall, "best_training_return": None,
             "which": "deterministic policy",
             "config": {"algorithm": f"stable_baselines3.{SB3_ALGORITHMS[method]}", "policy": "MlpPolicy",
                        "hyperparameters": "SB3 defaults", "sb3_version": sb3.__version__,
                        "total_timesteps": settings.sb3_steps, "seed": seed, "decision_period": period}}
    return metrics, facts


TRAINERS: dict[str, Callable[[str, int, StudySettings, Path], tuple[dict, dict]]] = {
    **{m: functools.partial(_train_apg, m) for m in ("ce-apg", "papg", "cem", "apg", "shapg")},
    "sac": _train_sac,
    **{m: functools.partial(_train_sb3, m) for m in SB3_ALGORITHMS},
}
"""Study method -> ``trainer(system_name, seed, settings, out) -> (metrics, facts)`` (one per STUDY_METHODS)."""


def run_one(method: str, system_name: str, seed: int, out: str | Path, settings: StudySettings | None = None,
            command: str | None = None) -> dict:
    """Train and score one (method, system, seed); writes ``out/record.json`` (atomically) and returns it.
    An existing record is returned as it is (the study resumes)."""
    settings = settings or StudySettings()
    if method not in STUDY_METHODS:
        raise ValueError(f"unknown method {method!r}; known: {', '.join(STUDY_METHODS)}")
    out = Path(out)
    if (out / "record.json").exists():
        return io.read_json(out / "record.json")
    torch.set_num_threads(1)
    start = time.perf_counter()
    metrics, facts = TRAINERS[method](system_name, seed, settings, out)
    record = {"method": method, "system": system_name, "seed": seed, "task": dataclasses.asdict(TASKS[system_name]),
              "eval": {**metrics, "seed": settings.eval_seed}, **facts,
              "wall_time_s": time.perf_counter() - start, "machine": machine(), "command": command}
    io.write_json(out / "record.json", record)
    return record


def run_study(out: str | Path, systems=("cartpole",), methods=STUDY_METHODS, seeds=(0, 1, 2, 3),
              settings: StudySettings | None = None, command: str | None = None,
              report: Callable[[str], None] | None = print) -> list[dict]:
    """:func:`run_one` over systems x methods x seeds into ``out/SYSTEM/METHOD-sSEED``; the records."""
    records = []
    for system_name in systems:
        for seed in seeds:
            for method in methods:
                record = run_one(method, system_name, seed, Path(out) / system_name / f"{method}-s{seed}", settings,
                                 command)
                records.append(record)
                if report:
                    e = record["eval"]
                    report(f"{system_name} {method} seed {seed}: return {e['mean_return']:.1f}, stabilised "
                           f"{e['stabilised']:.0%}, upright {e['upright']:.0%}, {record['interactions']:.2e} "
                           f"interactions, {record['wall_time_s']:.0f} s")
    return records


def zero_policy_baseline(system_name: str, settings: StudySettings | None = None) -> dict:
    """:func:`rollout_metrics` of u = 0 (the system left hanging) on the study's held-out starts: the
    return every learner must beat."""
    settings = settings or StudySettings()
    system = task_system(system_name)
    x0 = held_out_starts(system, settings.eval_episodes, settings.eval_seed)
    return rollout_metrics(system, swingup_alone(system, ZeroSwingup(), system.swingup_period), x0,
                           settings.horizon or TASKS[system_name].horizon)


def summarize(records: list[dict]) -> list[dict]:
    """One row per (system, method): mean and std over seeds of the held-out return, the stabilisation
    and upright rates, the best training return, interactions, wall time of the last process and
    training wall time over every session of a resumed run."""
    rows = []
    keys = sorted({(r["system"], r["method"]) for r in records},
                  key=lambda k: (k[0], STUDY_METHODS.index(k[1])))
    for system_name, method in keys:
        group = [r for r in records if r["system"] == system_name and r["method"] == method]
        ret = np.array([r["eval"]["mean_return"] for r in group])
        best = [r["best_training_return"] for r in group if r.get("best_training_return") is not None]
        rows.append({"system": system_name, "method": method, "seeds": len(group),
                     "return_mean": float(ret.mean()), "return_std": float(ret.std()),
                     "stabilised": float(np.mean([r["eval"]["stabilised"] for r in group])),
                     "upright": float(np.mean([r["eval"]["upright"] for r in group])),
                     "best_training_return": float(np.mean(best)) if best else None,
                     "interactions": int(np.mean([r["interactions"] for r in group])),
                     "wall_time_s": float(np.mean([r["wall_time_s"] for r in group])),
                     # training alone, summed over a run's resumed sessions (wall_time_s is the last
                     # process's, evaluation included)
                     "train_wall_time_s": float(np.mean([r.get("train_wall_time_s") or r["wall_time_s"]
                                                         for r in group]))})
    return rows
