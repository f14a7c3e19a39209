"""Thesis Table 3.1 / Fig. 3.3: Stable-Baselines3 PPO, A2C, TRPO, SAC and TD3 on the acrobot swing-up.

Each algorithm trains on ``gymnasium.make("hybridctl/AcrobotSwingup-v0")`` (thesis dynamics and
reward, 0.2 s decisions, 50 per episode) with the RL Baselines3 Zoo's tuned hyperparameters, as the
thesis did: the zoo's ``Acrobot-v1`` entries for PPO, A2C and TRPO, its ``Pendulum-v1`` entries for
SAC and TD3 (the zoo has no continuous-action acrobot). They are written out in
:data:`hybridctl.experiments.sb3_runs.ZOO` (the workflow this driver runs), with the zoo file and key
of each; the zoo's ``n_timesteps`` is replaced by ``--steps``.

Training is resumable and runs in chunks of ``--chunk-steps`` environment steps. After every chunk
the run folder ``OUT/<algo>-s<seed>/`` receives, each written atomically (:func:`hybridctl.io.atomic_write`):

* ``model.zip``          SB3's own save of the model;
* ``replay_buffer.pkl``  SAC/TD3 only, ``model.save_replay_buffer``;
* ``vecnormalize.npz``   PPO/A2C/TRPO only (zoo ``normalize: true``): the running obs/return statistics
                         (:func:`hybridctl.learn.sb3_normalizer.save_vecnormalize`: ``load_sb3`` and fine-tuning read it);
* ``curve.csv``          one row per finished training episode: env_steps, return, length, success
                         (the raw return, before reward normalisation; Fig. 3.3 is drawn from it), packed
                         into ``curve.csv.xz`` (the same text) when the run reaches its budget;
* ``progress.json``      steps done, wall time of each chunk and the machine it ran on, the commands,
                         the seed and the hyperparameters (written last: it marks the checkpoint).

Rerunning the same command continues every run from its checkpoint; a run already at its budget is
skipped and only evaluated if its ``eval.json`` is missing, older than the model or made with another
``--eval-episodes``. ``--time-budget-s`` stops cleanly after the chunk that crosses the budget, so a
session of a few hours runs what fits and the next session resumes. When a run reaches its budget,
its deterministic policy is evaluated on ``--eval-episodes`` fresh episodes (seeds 10000 + seed + k),
with the observation normalisation frozen, into ``eval.json``.

``--report`` trains nothing: it gathers every run folder into one JSON (also written to
``--report-out``) with the thesis' numbers beside ours and per-run training curves binned per
``--curve-bin`` steps, and draws the reward curves (Fig. 3.3) to a PNG next to it.

    .venv/bin/pip install -c constraints.txt -e ".[sb3]"       # stable-baselines3 and sb3-contrib
    # the thesis budget for the on-policy algorithms, 4 seeds, resumable, 3 h per session:
    python -m hybridctl.reproduce.sb3_baselines --algos ppo a2c trpo --time-budget-s 10800
    # SAC and TD3 at the largest budget the machine allows (here: 3e5 steps per seed):
    python -m hybridctl.reproduce.sb3_baselines --algos sac td3 --steps 3e5 --time-budget-s 10800
    # the table, the curves and the figure:
    python -m hybridctl.reproduce.sb3_baselines --report --out results/ch3/sb3_baselines/runs \\
        --report-out results/ch3/sb3_baselines/results.json
    # a smoke run:
    python -m hybridctl.reproduce.sb3_baselines --algos a2c --seeds 0 --steps 2000 --out runs/sb3_smoke

Measured on one core of the 2-core development VM (torch 1 thread, smoke runs): PPO ~3,600, A2C
~5,000, TRPO ~1,900 env steps/s (2e6 steps: 6-18 min per seed); SAC ~51 and TD3 ~53 env steps/s once
learning (2e6 steps: ~11 h per seed), so SAC and TD3 get a smaller, explicit ``--steps``. Not run in
CI beyond tiny budgets (tests/test_sb3_baselines.py).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from hybridctl.experiments.sb3_runs import (ALGOS, ENV_ID, EVAL_SEED_BASE, ON_POLICY, THESIS_STEPS, THESIS_TABLE_3_1,
                                            Clock, UsageError, algorithm_class, check_run, collect_runs,
                                            hyperparameters, summarise, train_run, versions)
from hybridctl.reproduce import common


def command_line(argv) -> str:
    """The command as it would be typed again."""
    return common.command_line("hybridctl.reproduce.sb3_baselines", None if argv is None else list(map(str, argv)))


# -------------------------------------------------------------------------------------------- report


def hybridctl_runs(runs: Path) -> dict:
    """Per-algorithm summaries of ``hybridctl train`` eval.json files under ``runs`` (SSAC, SAC) of runs
    on the plain acrobot (the system and spec overrides their final/config.json records)."""
    found: dict[str, list[dict]] = {}
    for path in sorted(runs.glob("*/eval.json")) if runs.is_dir() else []:
        try:
            data = json.loads(path.read_text())
            mean = float(data["mean_return"])
            meta = json.loads((path.parent / "final" / "config.json").read_text())
        except (OSError, ValueError, KeyError, TypeError):
            continue
        system = meta.get("system") or {}
        if system.get("name") != "acrobot" or system.get("overrides"):
            continue  # another system (a cart-pole run), or the acrobot with another reward or starts
        algo = str(meta.get("algorithm", "SAC")).upper()
        found.setdefault(algo, []).append({"run": common.recorded_path(path.parent), "mean_return": mean,
                                           "env_steps": data.get("env_steps")})
    return {a: {"seeds": len(v), "mean_return": float(np.mean([r["mean_return"] for r in v])),
                "std_over_seeds": float(np.std([r["mean_return"] for r in v])), "runs": v}
            for a, v in found.items()}


def plot_curves(runs: list[dict], path: Path, curve_bin: int) -> None:
    """Fig. 3.3 style: mean training episode return per bin vs env steps, one line per seed, one colour per algo."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    colours = dict(zip(ALGOS, plt.get_cmap("tab10").colors))
    for algo in ALGOS:
        labelled = False
        for run in sorted((r for r in runs if r["algo"] == algo), key=lambda r: r["seed"]):
            curve = run["curve"]
            if not curve["env_steps"]:
                continue
            ax.plot(curve["env_steps"], curve["mean_return"], color=colours[algo], lw=1.0, alpha=0.8,
                    marker="o" if len(curve["env_steps"]) < 3 else None, ms=3,
                    label=None if labelled else algo.upper())
            labelled = True
    ax.set_xlabel("environment steps")
    ax.set_ylabel(f"mean training episode return (per {curve_bin:g} steps)")
    ax.set_title("Acrobot swing-up: Stable-Baselines3 baselines (one line per seed)")
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def report(args, command: str) -> dict:
    """The aggregated report of every run under ``--out``; written with its PNG next to ``--report-out``."""
    from hybridctl.reproduce.common import emit, machine_info

    runs = collect_runs(args.out, args.curve_bin)
    if not runs:
        raise UsageError(f"--out {args.out}: no run folders (<algo>-s<seed>/progress.json) to report on")
    out_path = args.report_out if args.report_out is not None else args.out / "results.json"
    png = out_path.with_suffix(".png")
    document = {"benchmark": "sb3_baselines", "env": ENV_ID, "command": command,
                "machine": machine_info(), "versions": versions(), "run_root": common.recorded_path(args.out),
                "eval": {"episodes_seeded_from": f"{EVAL_SEED_BASE} + seed + k", "deterministic": True},
                "stable_baselines3": summarise(runs), "hybridctl": hybridctl_runs(args.runs),
                "thesis_table_3_1": {k: {"mean": m, "std": s} for k, (m, s) in THESIS_TABLE_3_1.items()},
                "hyperparameters": {a: hyperparameters(a) for a in ALGOS},
                "figure": common.recorded_path(png), "curve_bin_steps": args.curve_bin, "runs": runs}
    plot_curves(runs, png, args.curve_bin)
    emit(document, out_path)
    return document


# ------------------------------------------------------------------------------------------------ CLI


def _count(name: str, minimum: int):
    """argparse type: an integer >= minimum, also written like 2e6."""
    def parse(text: str) -> int:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum:g}, got {text!r}") from None
        if not math.isfinite(value) or value != int(value) or value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum:g}, got {text!r}")
        return int(value)
    parse.__name__ = name
    return parse


def _seconds(text: str) -> float:
    """argparse type: a positive finite number of seconds."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds > 0, got {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected seconds > 0, got {text!r}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algos", nargs="+", choices=ALGOS, default=list(ON_POLICY),
                        help="algorithms to train (default: ppo a2c trpo)")
    parser.add_argument("--seeds", nargs="+", type=_count("seed", 0), default=[0, 1, 2, 3],
                        help="seeds, integers >= 0 (default: 0 1 2 3)")
    parser.add_argument("--steps", type=_count("steps", 1), default=None,
                        help=f"env steps per seed, >= 1 (e.g. 2e6). Default {THESIS_STEPS:,} (the thesis) for "
                             "ppo/a2c/trpo; sac and td3 need it given: they run at the largest budget the machine "
                             "allows (2e6 steps are many hours per seed on one core). A finished run given a larger "
                             "budget continues; one at or past it is skipped")
    parser.add_argument("--chunk-steps", type=_count("chunk-steps", 1), default=100_000,
                        help="env steps between checkpoints, >= 1 (default 1e5); on-policy algorithms finish "
                             "their last rollout, so a chunk can end a little past it")
    parser.add_argument("--time-budget-s", type=_seconds, default=None,
                        help="stop cleanly after the chunk that crosses this many seconds (> 0); rerun to resume")
    parser.add_argument("--out", type=Path, default=Path("runs/sb3_baselines"),
                        help="run root: one folder <algo>-s<seed> per run (default runs/sb3_baselines)")
    parser.add_argument("--resume", action="store_true",
                        help="resuming is automatic when a run folder has a checkpoint; with --resume a missing "
                             "checkpoint is an error instead of a fresh start")
    parser.add_argument("--eval-episodes", type=_count("eval-episodes", 1), default=100,
                        help="deterministic evaluation episodes per finished run, >= 1 (default 100)")
    parser.add_argument("--report", action="store_true",
                        help="train nothing: aggregate every run under --out into one JSON and a PNG")
    parser.add_argument("--report-out", type=Path, default=None,
                        help="report JSON path (default OUT/results.json); the figure goes next to it as .png")
    parser.add_argument("--curve-bin", type=_count("curve-bin", 1), default=None,
                        help="env steps per bin of the report's training curves, >= 1 (default 1e4)")
    parser.add_argument("--runs", type=Path, default=None,
                        help="report: hybridctl train runs (*/eval.json) to list beside (default runs/train)")
    return parser


def main(argv=None) -> int:
    """Train/resume the requested runs, or with ``--report`` aggregate them; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.out.exists() and not args.out.is_dir():
        parser.error(f"argument --out: {args.out} exists and is not a folder")
    if len(set(args.seeds)) != len(args.seeds):
        parser.error("argument --seeds: seeds must be distinct")
    if not args.report:
        for name in ("report_out", "curve_bin", "runs"):
            if getattr(args, name) is not None:
                parser.error(f"argument --{name.replace('_', '-')}: only with --report")
    args.curve_bin = 10_000 if args.curve_bin is None else args.curve_bin
    args.runs = Path("runs/train") if args.runs is None else args.runs
    if args.report_out is not None and args.report_out.suffix != ".json":
        parser.error("argument --report-out: expected a path ending in .json")
    missing_budget = [a for a in args.algos if a not in ON_POLICY]
    if not args.report and args.steps is None and missing_budget:
        parser.error(f"argument --steps: required for {' and '.join(missing_budget)} (choose the largest budget "
                     f"the machine allows; the thesis' {THESIS_STEPS:,} take many hours per seed on one core)")
    try:
        import stable_baselines3  # noqa: F401
        import torch
    except ImportError:
        print('error: stable-baselines3 is not installed: pip install -c constraints.txt -e ".[sb3]"', file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    command = command_line(argv)
    try:
        if args.report:
            report(args, command)
            return 0
        if "trpo" in args.algos:
            algorithm_class("trpo")      # fail before training anything when sb3-contrib is missing
        for algo in args.algos:           # every requested run checked before any training starts
            for seed in args.seeds:
                check_run(args.out / f"{algo}-s{seed}", algo, args.resume)
        clock = Clock(args.time_budget_s)
        results, stopped = [], False
        for algo in args.algos:
            budget = args.steps if args.steps is not None else THESIS_STEPS
            for seed in args.seeds:
                result = train_run(algo, seed, budget, out=args.out, chunk_steps=args.chunk_steps,
                                   eval_episodes=args.eval_episodes, resume=args.resume, clock=clock,
                                   command=command, machine=common.machine_info)
                results.append(result)
                if result["status"].endswith("(time budget)"):
                    stopped = True
                    break
                if clock.expired() and (algo, seed) != (args.algos[-1], args.seeds[-1]):
                    stopped = True
                    break
            if stopped:
                break
        print(json.dumps({"run_root": str(args.out), "complete": not stopped, "elapsed_s": round(clock.elapsed(), 1),
                          "runs": results}, indent=1))
        if stopped:
            print("time budget reached: rerun the same command to resume", file=sys.stderr)
        return 0
    except UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
