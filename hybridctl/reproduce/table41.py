"""Thesis Table 4.1 (and the first Table 4.4) at a reduced scale: train the ARS runs, evaluate them,
write ``results/ch4/results.json``.

Training (``--train ENV SEED``; the scale fits a 2-core machine, see notebooks/03 section 7): ARS V2-t,
thesis alpha 0.02 and sigma 0.025, but N = 8 directions and b = 4 kept (thesis 50 / 20; Mania et al.
2018 Table 9 use 8 / 4 for Hopper), reward shift 1 for Hopper (Mania et al.; on Walker2d it taught
seed 0 to fall at once, so none there), ``P`` identity epochs, then ``C`` more epochs from that
checkpoint with identity, mesh-lower and mesh-upper (thesis: 750 + 250). One process per lane,
serial backend (``--backend``/``--workers``/``--address`` give the training runs another); a finished
run (its eval.json) is skipped, an interrupted one resumes. Runs go to
``RUNS/ENV-sSEED/{pretrain,identity,mesh-lower,mesh-upper}``.

Table 4.1 metrics (thesis Sec. 4.2.8): per seed, 5 deterministic rollouts of 10,000 steps
for the lower/upper mesh dimension (after the first 200 steps) and 5 of the normal 1,000
steps for the return. Table 4.4: failure rates (early termination) under the thesis'
action noise, observation noise and push settings, identity vs lower mesh dimension. The evaluations
and failure rates run on ``--backend``/``--workers``/``--address`` (default 2 local processes; the
failure rates of the MuJoCo envs step together on the batched stepper's ``--workers`` threads).

```text
usage: python -m hybridctl.reproduce.table41 --train ENV SEED [--epochs 100 40] [--runs runs/ch4]
       python -m hybridctl.reproduce.table41 [--runs runs/ch4] [--robust-episodes 20]
       [--robust-steps 2000] [--backend processes] [--workers 2] [--address HOST:PORT]
       [--out results/ch4/results.json]
```
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from hybridctl.io import atomic_write_text
from hybridctl.analysis import mesh_dimension
from hybridctl.analysis.postprocess import MIN_POINTS
from hybridctl.learn import failure_rates
from hybridctl.learn.ars import ARS
from hybridctl.parallel import make_backend
from hybridctl.reproduce.common import (RESULTS, add_backend_flags, backend_cli_args, backend_options,
                                       check_backend_flags, command_line, machine_info)

VARIANTS = ("pretrain", "identity", "mesh-lower", "mesh-upper")
# thesis Table 4.4: (action std, observation std, (push rate, magnitude N)) per env
TABLE44 = {"HalfCheetah-v5": (0.05, 0.005, (0.2, 3.0)), "Hopper-v5": (0.05, 0.02, (0.2, 1.0)),
           "Walker2d-v5": (0.15, 0.03, (0.2, 1.0))}


def evaluate_run(folder: Path, pool) -> dict:
    """Return (1,000 steps) and dimensions (10,000 steps) of one run's final policy."""
    agent = ARS.load(folder / "final", backend="serial")
    short = agent.evaluate(episodes=5, backend=pool)
    long = agent.evaluate(episodes=5, episode_steps=10_000, measure=True, keep_states=True, backend=pool)
    first = long.pop("states")[0][agent.config.transient_steps:]
    curve = mesh_dimension(first).as_dict() if len(first) >= MIN_POINTS else None   # thesis Fig. 4.6
    train = json.loads((folder / "eval.json").read_text())
    return {"epochs": agent.epoch, "env_steps": agent.env_steps, "train_wall_time_s": train["train_wall_time_s"],
            "command": train["command"], "return": short["mean_return"], "returns": short["returns"],
            "long_steps": long["steps"], "long_terminated": long["terminated"], **long["mean_dimensions"],
            "mesh_curve_first_episode": curve and {k: curve[k] for k in ("box_sizes", "sizes", "lower", "upper")}}


def train(env_id: str, seed: int, pretrain: int, more: int, runs: Path, backend: list[str] | None = None) -> Path:
    """Train (or resume) one seed's Table 4.1 runs under ``runs/ENV-sSEED``: the identity pretrain of
    ``pretrain`` epochs, then identity, mesh-lower and mesh-upper continuations to ``pretrain + more``.
    ``backend``: the training runs' ``--backend``/``--workers``/``--address`` (default serial)."""
    root = runs / f"{env_id}-s{seed}"
    hc = [sys.executable, "-m", "hybridctl.cli"]
    common = ["--seed", str(seed), *(backend or ["--backend", "serial"]), "--quiet", "--set", "n_directions=8",
              "--set", "top_directions=4", "--set", f"reward_shift={1 if env_id == 'Hopper-v5' else 0}"]
    if not (root / "pretrain" / "eval.json").is_file():
        subprocess.run([*hc, "train", "ars", env_id, *common, "--epochs", str(pretrain), "--out",
                        str(root / "pretrain"), "--resume"], check=True)
    for post in ("identity", "mesh-lower", "mesh-upper"):
        out = root / post
        if not (out / "eval.json").is_file():
            resumable = any(out.glob("checkpoint*")) or (out / "final").is_dir()   # final/ alone resumes
            start = ["--resume"] if resumable else ["--init", str(root / "pretrain" / "final")]
            subprocess.run([*hc, "train", "ars", env_id, *common, "--epochs", str(pretrain + more),
                            "--postprocess", post, "--out", str(out), *start], check=True)
    return root


def summarise(values: list) -> dict | None:
    """Mean and std over seeds (None entries dropped)."""
    vals = [v for v in values if v is not None]
    return {"mean": float(np.mean(vals)), "std": float(np.std(vals)), "n": len(vals)} if vals else None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", default="runs/ch4")
    parser.add_argument("--robust-episodes", type=int, default=10)
    parser.add_argument("--robust-steps", type=int, default=2000)
    add_backend_flags(parser, "processes for the evaluations, serial for --train", "the work", workers=2)
    parser.set_defaults(backend=None)     # None: each part's default (the text above is the help's)
    parser.add_argument("--reuse-evaluations", action="store_true",
                        help="keep the runs' evaluations (and their wall time) of the existing record; redo Table 4.4")
    parser.add_argument("--out", default=str(RESULTS / "ch4" / "results.json"))
    parser.add_argument("--train", nargs=2, metavar=("ENV", "SEED"),
                        help="train (or resume) one seed's runs under --runs instead of evaluating")
    parser.add_argument("--epochs", type=int, nargs=2, default=[100, 40], metavar=("P", "C"),
                        help="with --train: identity epochs, then more epochs per post-processor")
    args = parser.parse_args(argv)
    check_backend_flags(args, parser)
    if args.train:
        train(args.train[0], int(args.train[1]), *args.epochs, Path(args.runs), backend_cli_args(args, "serial"))
        return 0
    parallel = backend_options(args, "processes")
    start = time.perf_counter()
    runs = sorted(p for p in Path(args.runs).glob("*-s*") if p.is_dir())
    record = {"command": command_line("hybridctl.reproduce.table41", argv), "machine": machine_info(), "runs": {}, "table41": {},
              "table44": {}, "protocol": {
                  "training": "python -m hybridctl.reproduce.table41 --train ENV SEED --epochs 100 40: ARS V2-t, alpha 0.02, sigma 0.025 "
                              "(thesis), N 8 / b 4 (thesis 50 / 20), reward shift 1 for Hopper (Mania et al. "
                              "2018; on Walker2d it taught seed 0 to fall at once, so none there); 100 identity epochs, then 40 more with identity or mesh-lower "
                              "from that checkpoint (thesis 750 + 250)",
                  "metrics": "5 rollouts of 1,000 steps for the return, 5 of 10,000 steps for the dimensions "
                             "(thesis Sec. 4.2.8), eval seed 12345",
                  "robustness": f"{args.robust_episodes} episodes of {args.robust_steps} steps per seed and "
                                f"condition (thesis: 10,000 steps); thesis Table 4.4 noise levels"}}
    earlier = json.loads(Path(args.out).read_text()) if args.reuse_evaluations and Path(args.out).is_file() else None
    if earlier is not None:
        record["runs"], record["evaluation_wall_time_s"] = earlier["runs"], earlier.get("evaluation_wall_time_s",
                                                                                          earlier.get("wall_time_s"))
        runs = []
    with make_backend(parallel["backend"], parallel["workers"], parallel["address"]) as pool:
        for run in runs:
            env_id, seed = run.name.rsplit("-s", 1)
            for variant in VARIANTS:
                if (run / variant / "final").exists() and (run / variant / "eval.json").exists():
                    print(f"{run.name}/{variant}", flush=True)
                    record["runs"][f"{run.name}/{variant}"] = {"env": env_id, "seed": int(seed), "variant": variant,
                                                                **evaluate_run(run / variant, pool)}
    record.setdefault("evaluation_wall_time_s", time.perf_counter() - start)
    for env_id in sorted({r["env"] for r in record["runs"].values()}):
        record["table41"][env_id] = {}
        for variant in VARIANTS:
            rows = [r for r in record["runs"].values() if r["env"] == env_id and r["variant"] == variant]
            if rows:
                record["table41"][env_id][variant] = {
                    "seeds": [r["seed"] for r in rows],
                    **{k: summarise([r[k] for r in rows]) for k in ("mesh_lower", "mesh_upper", "return",
                                                                    "madogram", "variogram")}}
        if env_id not in TABLE44 or env_id.startswith("HalfCheetah"):
            continue   # HalfCheetah never terminates in gymnasium: no failure to count
        action, obs, push = TABLE44[env_id]
        conditions = {f"action noise {action}": {"action_noise": action}, f"observation noise {obs}": {"obs_noise": obs},
                      f"push {push[1]} N at rate {push[0]}": {"push": push}}
        table, per_seed = {}, {}
        for variant in ("identity", "mesh-lower", "mesh-upper"):
            counts = {name: [0, 0] for name in conditions}
            for key, r in record["runs"].items():
                if r["env"] != env_id or r["variant"] != variant:
                    continue
                agent = ARS.load(Path(args.runs) / key / "final", backend="serial")
                rep = failure_rates(agent, conditions=conditions, episodes=args.robust_episodes,
                                    episode_steps=args.robust_steps, seed=r["seed"], **parallel)
                for name, c in rep.items():
                    counts[name][0] += c["failures"]
                    counts[name][1] += c["episodes"]
                    per_seed.setdefault(variant, {}).setdefault(name, {})[r["seed"]] = c["failures"]
            table[variant] = {name: {"failures": f, "episodes": n, "failure_rate": f / n if n else None,
                                     "failures_per_seed": per_seed.get(variant, {}).get(name, {})}
                              for name, (f, n) in counts.items()}
        record["table44"][env_id] = table
        print(env_id, json.dumps(table), flush=True)
    record["wall_time_s"] = time.perf_counter() - start
    atomic_write_text(Path(args.out), json.dumps(record, indent=1, allow_nan=False) + "\n")
    print(json.dumps(record["table41"], indent=1))
    print(f"wrote {args.out} in {record['wall_time_s']:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
