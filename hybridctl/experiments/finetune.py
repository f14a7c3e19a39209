"""Fine-tune a trained agent and report before and after (thesis Ch. 6): the workflow behind
``hybridctl finetune`` and notebooks/06.

>>> report = finetune_and_report("Pendulum-v1", "sb3:runs/finetune-agents/Pendulum-v1-ppo/model.zip",
...                              "runs/finetune/pendulum-ppo", FineTuneConfig(updates=50))
>>> report["before"]["mean_return"], report["after"]["mean_return"]

Writes into ``out``: ``before.json`` (the pretrained agent; kept on ``resume``), the run log and
checkpoints of :class:`~hybridctl.learn.finetune.FineTune`, ``after.json``, ``report.json``
(command, seed, env steps, wall time, machine, both evaluations' statistics), ``finetune.png``
(return histograms, failure rates with 95 % intervals, the training curve) and, for an sb3
source, ``model.zip`` (+ ``vecnormalize.npz``) that SB3's own ``load`` reads.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path


from ..io import read_json, write_json
from ..learn.finetune import FineTune, FineTuneConfig
from ..learn.finetune_sources import parse_source
from ..learn.run import EVAL_SEED
from ..parallel import make_backend
from .controllers import display_name
from .training import machine, open_run_folder

FINETUNE_MARKERS = ("checkpoint", "final", "progress.csv", "before.json", "after.json", "report.json")
"""What makes a folder hold a fine-tuning run."""
FINETUNE_OUTPUTS = ("before.json", "after.json", "report.json", "finetune.png")
"""What ``overwrite`` removes besides the run outputs every run has (checkpoints, progress.csv)."""

SUMMARY_KEYS = ("episodes", "seed", "mean_return", "std_return", "min_return", "success_rate", "failures",
                "failure_rate", "failure_interval", "mean_dimension", "std_dimension", "nonfinite")


def summary(result: dict) -> dict:
    """The statistics of an evaluation without the per-episode lists (for report.json)."""
    return {k: result[k] for k in SUMMARY_KEYS if k in result}


def finetune_and_report(env: str, policy: str, out: str | Path, config: FineTuneConfig | None = None,
                        resume: bool = False, overwrite: bool = False, trust: bool = False,
                        normalizer: str | None = None, eval_episodes: int | None = None, eval_seed: int = EVAL_SEED,
                        progress: bool = True, command: str | None = None, figures: bool = True) -> dict:
    """Evaluate the pretrained ``policy`` on ``env``, fine-tune it, evaluate again, write the report.

    ``resume`` continues the run in ``out`` from its newest checkpoint (the "before" evaluation
    is kept); ``overwrite`` replaces the run ``out`` holds (removed once the policy is read). An
    ``out`` that is, holds or lies inside the policy or ``normalizer`` file is refused (the
    output ``model.zip`` would replace its own source), and the folder is locked while the
    run writes it (:func:`~hybridctl.experiments.training.open_run_folder`).
    ``eval_episodes``: deterministic episodes per evaluation (default ``config.eval_episodes``,
    the thesis' 100), the same initial conditions (``eval_seed``) before and after. Returns the
    report dict.
    """
    config = config or FineTuneConfig()
    config.validate()   # every setting is checked before --out is made or locked (FineTune checks it again)
    inputs = {"--policy": parse_source(policy)[1], "--normalizer": normalizer}
    with open_run_folder(out, resume=resume, overwrite=overwrite, markers=FINETUNE_MARKERS, inputs=inputs) as folder:
        tuner = FineTune(env, policy, config, trust=trust, normalizer=normalizer)
        folder.clear(FINETUNE_OUTPUTS)   # --overwrite: only now that the policy is read
        return _finetune_in(folder.path, env, policy, tuner, config, resume, eval_episodes, eval_seed, progress,
                            command, figures)


def _finetune_in(out: Path, env: str, policy: str, tuner: FineTune, config: FineTuneConfig, resume: bool,
                 eval_episodes: int | None, eval_seed: int, progress: bool, command: str | None,
                 figures: bool) -> dict:
    """The body of :func:`finetune_and_report` in its locked run folder ``out``."""
    episodes = int(eval_episodes or config.eval_episodes)
    start = time.perf_counter()
    with make_backend(config.backend, config.workers, config.address) as backend:
        before_file = out / "before.json"
        if resume and before_file.exists():
            before = read_json(before_file)
        else:
            before = tuner.evaluate(episodes, seed=eval_seed, theta=tuner.theta0, backend=backend).to_dict()
            write_json(before_file, before)
        tuner.learn(out=out, resume=resume, progress=progress, backend=backend)
        after = tuner.evaluate(episodes, seed=eval_seed, backend=backend).to_dict()
    write_json(out / "after.json", after)
    exported = None
    if tuner.tunable.sb3 is not None:
        exported = str(tuner.save_sb3(out / "model.zip"))
    report = {"env": env, "policy": policy, "command": command, "seed": config.seed, "updates": tuner.update,
              "n_params": tuner.n_params, "select": config.select, "reward": config.reward,
              "env_steps": tuner.env_steps, "interactions": {
                  "formula": "sum of episode lengths over 2 x n_directions rollouts x updates",
                  "n_directions": config.n_directions, "updates": tuner.update, "env_steps": tuner.env_steps},
              "train_wall_time_s": tuner.wall_time, "total_wall_time_s": time.perf_counter() - start,
              "machine": machine(), "before": summary(before), "after": summary(after),
              "final_checkpoint": str(out / "final"), "sb3_zip": exported,
              "config": dataclasses.asdict(config)}
    write_json(out / "report.json", report)
    if figures:
        from ..viz.finetune import plot_finetune_report
        plot_finetune_report(before, after, tuner.history, out / "finetune.png", title=f"{env}: {display_name(policy)}")
    return report
