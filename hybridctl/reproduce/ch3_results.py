"""Thesis Ch. 3 (Table 3.1's SSAC and SAC rows, Figs. 3.4-3.6): collect the Chapter 3 training runs into one
JSON record, ``results/ch3/results.json`` (read by notebooks/02_switched_sac.ipynb).

    python -m hybridctl.reproduce.ch3_results --runs runs/train --out results/ch3 \
        --balance-map ssac-acrobot-s0 ssac-acrobot-s1 --grid 41
    python -m hybridctl.reproduce.ch3_results --import-balance-map ssac-acrobot-s0=runs/balance_map/ssac-acrobot-s0

For every ``hybridctl train`` run folder under ``--runs`` (one with ``eval.json``):
the command, algorithm, system, seed, env steps, training wall time, the
deterministic evaluation and the training curve (from ``progress.csv``). With
``--balance-map RUN ...`` it also simulates those runs' final checkpoints in the
Drake diagram over a ``--grid`` x ``--grid`` grid of rest states (thesis Fig. 3.6)
and stores ``balance_map_RUN.json`` / ``.png`` next to the record (on ``--backend``/``--workers``/
``--address``, default local processes on every core); ``--import-balance-map
NAME=FOLDER`` takes one that ``hybridctl balance-map`` already wrote.

Runs already in the record whose folders are gone (trained in an earlier session) are
kept; a run folder present under ``--runs`` replaces its record.
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import numpy as np

from hybridctl.io import atomic_write_text
from hybridctl.reproduce.common import (RESULTS, add_backend_flags, backend_options, check_backend_flags, machine_info,
                                       recorded_path)


def evaluate_stopped(folder: Path, reason: str) -> None:
    """Write eval.json for a run stopped before its budget: its newest checkpoint, evaluated like
    ``hybridctl train`` does (100 deterministic episodes, numpy seed 12345)."""
    import torch

    from hybridctl.learn import SAC, SSAC
    from hybridctl.learn.checkpoint import newest_checkpoint, read_json, write_json

    torch.set_num_threads(1)
    found = newest_checkpoint([folder / "checkpoint", folder / "final"])
    if found is None:
        raise SystemExit(f"error: no checkpoint under {folder}")
    algo = {"SAC": SAC, "SSAC": SSAC}[read_json(found / "config.json")["algorithm"]]
    agent = algo.load(found)
    result = agent.evaluate(episodes=100)
    result.update({"command": f"stopped run; newest checkpoint {recorded_path(found)}", "env_steps": agent.num_timesteps,
                   "train_wall_time_s": agent.wall_time, "stopped": reason,
                   "train_mean_return_last100": agent.mean_return, "train_success_rate_last100": agent.success_rate})
    write_json(folder / "eval.json", result)
    print(f"{folder.name}: evaluated {found.name} at {agent.num_timesteps} steps: {result['mean_return']:.2f}")


def read_run(folder: Path) -> dict:
    """One run's record: config, evaluation, training curve."""
    meta_dir = folder / "final" if (folder / "final").is_dir() else folder / "checkpoint"
    meta = json.loads((meta_dir / "config.json").read_text())
    result = json.loads((folder / "eval.json").read_text())
    curve = []
    if (folder / "progress.csv").is_file():
        with open(folder / "progress.csv", newline="") as fh:
            for row in csv.DictReader(fh):
                curve.append({k: float(row[k]) if row.get(k) not in (None, "") else None
                              for k in ("env_steps", "mean_return", "success_rate", "wall_time", "lqr_share")
                              if k in row})
    cfg = meta["config"]
    return {"run": folder.name, "algorithm": meta["algorithm"], "system": meta["system"]["name"],
            "seed": cfg["seed"], "command": result.get("command"), "env_steps": result["env_steps"],
            "stopped": result.get("stopped"),
            "train_wall_time_s": result.get("train_wall_time_s"),
            "eval": {k: result[k] for k in ("episodes", "seed", "mean_return", "std_return", "min_return",
                                            "success_rate")},
            "train_last100": {"mean_return": result.get("train_mean_return_last100"),
                              "success_rate": result.get("train_success_rate_last100")},
            "config": {k: cfg[k] for k in ("polyak", "obs_transform", "needle_prob", "gamma", "total_steps")
                       if k in cfg},
            "gate": meta.get("gate", {}).get("info", {}), "curve": curve}


def summarize(runs: list[dict]) -> dict:
    """Mean and spread over seeds per (algorithm, system)."""
    groups: dict[str, list[dict]] = {}
    for r in runs:
        groups.setdefault(f"{r['algorithm']} {r['system']}", []).append(r)
    return {key: {"seeds": [r["seed"] for r in rs],
                  "mean_return": float(np.mean([r["eval"]["mean_return"] for r in rs])),
                  "std_over_seeds": float(np.std([r["eval"]["mean_return"] for r in rs])),
                  "success_rate": float(np.mean([r["eval"]["success_rate"] for r in rs])),
                  "env_steps": [r["env_steps"] for r in rs],
                  "train_wall_time_s": [r["train_wall_time_s"] for r in rs]} for key, rs in groups.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", default="runs/train")
    parser.add_argument("--out", default=str(RESULTS / "ch3"))
    parser.add_argument("--balance-map", nargs="*", default=[], metavar="RUN")
    parser.add_argument("--grid", type=int, default=41)
    add_backend_flags(parser, "processes", "the balance maps' Drake runs")
    parser.add_argument("--evaluate-stopped", nargs="*", default=[], metavar="RUN",
                        help="evaluate the newest checkpoint of runs stopped before their budget")
    parser.add_argument("--stopped-reason", default="stopped before its budget (machine time)")
    parser.add_argument("--import-balance-map", nargs="*", default=[], metavar="NAME=FOLDER",
                        help="record a balance map written by `hybridctl balance-map --out FOLDER`")
    args = parser.parse_args(argv)
    check_backend_flags(args, parser)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name in args.evaluate_stopped:
        evaluate_stopped(Path(args.runs) / name, args.stopped_reason)
    folders = sorted(p.parent for p in Path(args.runs).glob("*/eval.json"))
    fresh = [{**read_run(f), "machine": machine_info()} for f in folders]
    old = out / "results.json"
    previous = json.loads(old.read_text()) if old.is_file() else {}
    names = {r["run"] for r in fresh}
    kept = [r for r in previous.get("runs", []) if r["run"] not in names]
    for r in kept:  # runs collected before runs carried their own machine record
        r.setdefault("machine", {**previous.get("machine", {}), "note": "collected in an earlier session"})
    runs = sorted(kept + fresh, key=lambda r: (r["algorithm"], r["system"], r["seed"]))
    record = {"machine": machine_info(), "collected": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
              "summary": summarize(runs), "runs": runs, "balance_maps": previous.get("balance_maps", {})}
    for spec in args.import_balance_map:
        name, sep, folder = spec.partition("=")
        if not sep:
            parser.error(f"--import-balance-map expects NAME=FOLDER, got {spec!r}")
        data = json.loads((Path(folder) / "balance_map.json").read_text())
        target = out / f"balance_map_{name}"
        target.mkdir(parents=True, exist_ok=True)
        for file in ("balance_map.json", "balance_map.png"):
            (target / file).write_bytes((Path(folder) / file).read_bytes())
        record["balance_maps"][name] = {"grid": data["grid"][0], "balanced_fraction": data["balanced_fraction"],
                                        "balanced_count": data["balanced_count"], "wall_time_s": data["wall_time_s"],
                                        "controller": data["controller"], "folder": target.name}
        print(f"{name}: {data['balanced_fraction']:.4f} balanced ({data['balanced_count']}/{data['grid'][0] ** 2})")
    from hybridctl.experiments import balance_map

    for name in args.balance_map:
        run = next(r for r in runs if r["run"] == name)
        kind = "ssac" if run["algorithm"] == "SSAC" else "sac"
        result = balance_map(run["system"], f"{kind}:{Path(args.runs) / name / 'final'}", grid=args.grid,
                             force=args.force, **backend_options(args))
        summary = result.save(out / f"balance_map_{name}")
        record["balance_maps"][name] = {"grid": args.grid, "balanced_fraction": summary["balanced_fraction"],
                                        "balanced_count": summary["balanced_count"],
                                        "wall_time_s": result.wall_time, "folder": f"balance_map_{name}"}
        print(f"{name}: {summary['balanced_fraction']:.4f} balanced ({summary['balanced_count']}/"
              f"{args.grid ** 2}) in {result.wall_time:.0f} s")
    atomic_write_text(out / "results.json", json.dumps(record, indent=1) + "\n")
    print(json.dumps(record["summary"], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
