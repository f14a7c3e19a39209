"""Training runs as ``hybridctl train`` does them: build (or resume, or warm-start) a learner, train
it with checkpoints and logs in a run folder, evaluate it and write ``eval.json``.

>>> from hybridctl.experiments import train_and_evaluate
>>> run = train_and_evaluate("ssac", "acrobot", out="runs/ssac", settings={"total_steps": 200_000})
>>> run.evaluation["mean_return"], run.agent
"""

from __future__ import annotations

import inspect
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, is_dataclass
from pathlib import Path
from typing import Any, Callable

from .. import io
from ..learn import APG, ARS, SAC, SSAC, ARSConfig, SACConfig, SSACConfig
from ..learn.apg import METHODS as APG_METHODS
from ..learn.apg import PRESETS as APG_PRESETS
from ..learn.apg import APGConfig
from ..learn.checkpoint import newest_checkpoint
from ..systems import load

ALGORITHMS = {"sac": SAC, "ssac": SSAC, "ars": ARS}
ALGORITHMS.update({method: APG for method in APG_METHODS})   # thesis Ch. 7: apg, shapg, papg, cem, ce-apg
"""Learner class by ``hybridctl train`` name; each has ``config_class``."""

SSAC_VARIANTS = ("hybridctl", "paper", "author")
"""Presets of :meth:`SSACConfig.variant`."""

DEFAULT_EVAL_EPISODES = {"sac": 100, "ssac": 100}
"""Episodes in ``eval.json`` when none are asked for (ARS: its config's ``eval_episodes``, 5)."""


@dataclass
class TrainingRun:
    """A finished :func:`train_and_evaluate`: the trained learner, its run folder and ``eval.json``."""

    agent: Any
    out: Path
    evaluation: dict = field(default_factory=dict)


def _silent(line: str) -> None:
    """A ``report`` that prints nothing."""


def learner_class(algorithm: str):
    """SAC, SSAC or ARS by name (``"sac"``, ``"ssac"``, ``"ars"``)."""
    try:
        return ALGORITHMS[algorithm]
    except KeyError:
        raise ValueError(f"unknown algorithm {algorithm!r}; known: {', '.join(ALGORITHMS)}") from None


def make_config(algorithm: str, variant: str = "hybridctl", **settings) -> SACConfig | SSACConfig | ARSConfig:
    """The validated config of ``algorithm`` with ``settings`` replacing its defaults.

    ``variant`` (SSAC only) picks the preset the settings start from: ``"hybridctl"``,
    ``"paper"`` or ``"author"`` (:meth:`SSACConfig.variant`). Unknown fields and invalid
    values raise ValueError naming them.
    """
    config_class = learner_class(algorithm).config_class
    if algorithm in APG_METHODS:   # variant: the preset ("thesis" or "reduced"; "hybridctl" means "thesis")
        return APGConfig.preset("thesis" if variant == "hybridctl" else variant, method=algorithm, **settings)
    if algorithm != "ssac" and variant != "hybridctl":
        raise ValueError("--variant applies to ssac only")
    try:
        config = SSACConfig.variant(variant, **settings) if algorithm == "ssac" else config_class(**settings)
    except TypeError as exc:  # an unknown field name
        raise ValueError(f"{config_class.__name__}: {exc}") from exc
    config.validate()
    return config


def default_run_dir(algorithm: str, system: str, seed: int = 0) -> Path:
    """``runs/train/ALGO-SYSTEM-sSEED`` (a gymnasium id's ``/`` becomes ``_``)."""
    return Path(f"runs/train/{algorithm}-{system.replace('/', '_')}-s{seed}")


def newest_run_checkpoint(out: str | Path) -> Path | None:
    """The newest checkpoint of a run folder (``checkpoint/`` or ``final/``), None if it has none."""
    out = Path(out)
    return newest_checkpoint([out / "checkpoint", out / "final"])


def _as_record(result) -> dict:
    """An evaluation result (a dict, a mapping or a dataclass) as a plain dict."""
    if isinstance(result, Mapping):
        return dict(result)
    if is_dataclass(result):
        return asdict(result)
    if hasattr(result, "keys"):
        return {key: result[key] for key in result.keys()}
    raise TypeError(f"cannot record an evaluation result of type {type(result).__name__}")


def _learn_accepts(agent, name: str) -> bool:
    """Whether ``agent.learn`` takes the keyword ``name``."""
    return name in inspect.signature(agent.learn).parameters


def train_and_evaluate(algorithm: str, system: str, out: str | Path | None = None, settings: dict | None = None,
                       variant: str = "hybridctl", resume: bool = False, init: str | Path | None = None,
                       eval_episodes: int | None = None, progress: bool = True, command: str | None = None,
                       report: Callable[[str], None] | None = print) -> TrainingRun:
    """Train ``algorithm`` on ``system``, checkpointing into ``out``; evaluate; write ``out/eval.json``.

    Args:
        algorithm: ``"sac"``, ``"ssac"`` (a system name) or ``"ars"`` (a gymnasium env id or a
            system name).
        out: the run folder (default :func:`default_run_dir`): ``progress.csv``, ``checkpoint/``,
            ``final/``, ``eval.json`` (and for SAC/SSAC ``training_curves.png``).
        settings: config fields to change (see :func:`make_config`); on ``resume`` SAC/SSAC take
            only ``total_steps`` from them (the rest comes from the checkpoint), ARS all of them.
        variant: SSAC's preset (``"hybridctl"``, ``"paper"``, ``"author"``).
        resume: continue from the run folder's newest checkpoint (a new run when it has none).
        init: ARS only: start from this checkpoint's policy and normalisation (the thesis trains
            750 identity epochs, then 250 with post-processing).
        eval_episodes: deterministic episodes in ``eval.json`` (default SAC/SSAC 100, ARS the
            config's ``eval_episodes``).
        command: the command line, recorded in ``eval.json``.
        report: called with each line of the run's account (default ``print``; None: silent).

    Raises:
        ValueError: a bad setting or an unknown system; CheckpointError: an unreadable
        checkpoint; FloatingPointError: training diverged (the last checkpoint stays intact).
    """
    report = report or _silent
    settings = dict(settings or {})
    algo = learner_class(algorithm)
    if algorithm in APG_METHODS:
        return _train_apg(algorithm, system, out, settings, variant, resume, eval_episodes, progress, command, report)
    if algorithm == "ars":
        return _train_ars(system, out, settings, variant, resume, init, eval_episodes, progress, command, report)
    if init is not None:
        raise ValueError("--init applies to ars only")
    load(system)  # a clear error for an unknown system name, before any work
    config = make_config(algorithm, variant, **settings)
    out = Path(out) if out is not None else default_run_dir(algorithm, system, settings.get("seed", 0))
    start = time.perf_counter()
    found = newest_run_checkpoint(out) if resume else None
    if found is not None:
        agent = algo.load(found, **{k: v for k, v in settings.items() if k == "total_steps"})
        report(f"resuming {found} at {agent.num_timesteps} env steps")
    else:
        if resume:
            report(f"--resume: no checkpoint under {out}; starting a new run")
        report(f"{algo.algorithm_name} on {system}: {config.total_steps} env steps, seed {config.seed}"
               + (" (warm-starting the gate first)" if algorithm == "ssac" else ""))
        agent = algo(system, config=config)
    agent.learn(progress=progress, log_dir=out, resume=resume)
    record = _as_record(agent.evaluate(episodes=eval_episodes or DEFAULT_EVAL_EPISODES[algorithm]))
    if command is not None:
        record["command"] = command
    record.update({"env_steps": agent.num_timesteps, "train_wall_time_s": agent.wall_time,
                   "session_wall_time_s": time.perf_counter() - start,
                   "train_mean_return_last100": agent.mean_return,
                   "train_success_rate_last100": agent.success_rate})
    io.write_json(out / "eval.json", record)
    return TrainingRun(agent, out, record)


def _train_ars(env: str, out, settings: dict, variant: str, resume: bool, init, eval_episodes, progress: bool,
               command: str | None, report: Callable[[str], None]) -> TrainingRun:
    """:func:`train_and_evaluate` for ARS V2-t with optional dimension post-processing (thesis Ch. 4)."""
    make_config("ars", variant, **settings)  # bad settings fail before any checkpoint is read
    out = Path(out) if out is not None else default_run_dir("ars", env, settings.get("seed", 0))
    found = newest_run_checkpoint(out) if resume else None
    if found is not None:
        agent = ARS.load(found, **settings)
        report(f"resuming {found} at epoch {agent.epoch}")
    elif init is not None:
        agent = ARS.load(init, env=env, **settings)
        report(f"starting from {init} (epoch {agent.epoch}); training to epoch {agent.config.epochs}")
    else:
        agent = ARS(env, ARSConfig(**settings))
        report(f"ARS on {env}: {agent.config.epochs} epochs, seed {agent.config.seed}, "
               f"post-processor {agent.config.postprocess}, backend {agent.config.backend}")
    if _learn_accepts(agent, "resume"):
        agent.learn(log_dir=out, progress=progress, resume=resume)
    else:
        agent.learn(log_dir=out, progress=progress)
    record = _as_record(agent.evaluate(episodes=eval_episodes or agent.config.eval_episodes, measure=True))
    if command is not None:
        record["command"] = command
    record.update({"epochs": agent.epoch, "env_steps": agent.env_steps, "train_wall_time_s": agent.wall_time})
    io.write_json(out / "eval.json", record)
    return TrainingRun(agent, out, record)


def _train_apg(method: str, system: str, out, settings: dict, preset: str, resume: bool, eval_episodes,
               progress: bool, command: str | None, report: Callable[[str], None]) -> TrainingRun:
    """:func:`train_and_evaluate` for the analytic-policy-gradient learners (thesis Ch. 7)."""
    if preset not in ("hybridctl", *APG_PRESETS):
        raise ValueError(f"unknown preset {preset!r} for {method}; known: {', '.join(APG_PRESETS)}")
    load(system)  # a clear error for an unknown system name, before any work
    config = make_config(method, preset, **settings)
    out = Path(out) if out is not None else default_run_dir(method, system, config.seed)
    found = newest_run_checkpoint(out) if resume else None
    if found is not None:
        agent = APG.load(found, **settings)
        report(f"resuming {found} at epoch {agent.epoch}")
    else:
        agent = APG(system, config)
        report(f"{method} on {system}: {config.epochs} epochs of {config.population if method != 'apg' else 1} x "
               f"{config.batch} x {config.horizon} steps, seed {config.seed}")
    agent.learn(log_dir=out, progress=progress)
    record = _as_record(agent.evaluate(episodes=eval_episodes or agent.config.eval_episodes))
    if command is not None:
        record["command"] = command
    record.update({"method": method, "epochs": agent.epoch, "iterations": agent.iterations,
                   "env_steps": agent.env_steps, "nan_grads": agent.nan_grads, "large_grads": agent.large_grads,
                   "train_wall_time_s": agent.wall_time})
    io.write_json(out / "eval.json", record)
    return TrainingRun(agent, out, record)
