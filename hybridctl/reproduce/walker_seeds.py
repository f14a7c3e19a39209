"""Walker2d-v5 ARS seeds for Table 4.4 (the table needs >= 4 seeds that move): train them,
and record which walk. Serves :mod:`hybridctl.reproduce.table44` (``--env Walker2d-v5``).

At Chapter 4's reduced scale (N 8 / b 4, 100 epochs; ``hybridctl.reproduce.table41 --train``) no seed walked, so these use
Mania et al. 2018's Walker2d-v1 settings for ARS V2-t (their Table 9: step 0.03, noise 0.025, N 40,
b 30, reward shift 1; ``table51.ARS_SETTINGS``). The thesis' own (N 50 / b 20, 750 epochs) are ~3x the
env steps of 150 epochs here per seed and do not fit a session.

``--train EPOCHS --seeds S ...`` trains (or resumes, or extends to more epochs) each seed's identity
run ``WORK/sSEED/pretrain-plain``, the pretrain ``hybridctl.reproduce.table44 --env Walker2d-v5`` continues. Then
``walker_seeds.json`` gets, per seed, the epochs, env steps and wall time of training (the run's own
clock, kept across resumes) and the 5-episode evaluation of ``eval.json``. A seed **walks** if no
evaluation episode ends early (1,000 steps) and the mean return reaches ``--min-return`` (2,000, the
bar of ``table44``; standing still earns about 1,000). The training runs run on
``--backend``/``--workers``/``--address`` (default: serial, one process per seed; the runs do not depend on it).

```text
usage: python -m hybridctl.reproduce.walker_seeds [--train 150 --seeds 1 2 3]
       [--work results/ch4/walker_runs] [--out results/ch4/walker_seeds.json] [--backend serial]
```
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from hybridctl.io import atomic_write_text
from hybridctl.reproduce.common import (RESULTS, add_backend_flags, backend_cli_args, check_backend_flags, command_line,
                                       machine_info)
from hybridctl.reproduce import table51

ENV = "Walker2d-v5"


def seed_row(run: Path, min_return: float) -> dict:
    """One seed's training totals and evaluation."""
    evaluation = json.loads((run / "eval.json").read_text())
    progress = json.loads((run / "final" / "progress.json").read_text())
    config = json.loads((run / "final" / "config.json").read_text())["config"]
    walks = not any(evaluation["terminated"]) and evaluation["mean_return"] >= min_return
    return {"epochs": progress["epoch"], "env_steps": progress["env_steps"], "train_wall_time_s": progress["wall_time"],
            "return": evaluation["mean_return"], "episode_steps": evaluation["steps"], "walks": bool(walks),
            "settings": {k: config.get(k) for k in ("n_directions", "top_directions", "step_size", "noise",
                                                    "reward_shift")}}


def previous_commands(out: Path) -> list[str]:
    """The commands of the record at ``out`` (its ``commands``, or its one ``command``): seeds trained by
    parallel processes or in earlier sessions stay on the record's history."""
    if not out.is_file():
        return []
    old = json.loads(out.read_text())
    return old.get("commands", [old["command"]] if "command" in old else [])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", default=str(RESULTS / "ch4" / "walker_runs"))
    parser.add_argument("--min-return", type=float, default=2000.0)
    parser.add_argument("--out", default=str(RESULTS / "ch4" / "walker_seeds.json"))
    parser.add_argument("--train", type=int, metavar="EPOCHS", help="train each of --seeds to this many epochs first")
    parser.add_argument("--seeds", type=int, nargs="+", default=[])
    add_backend_flags(parser, "serial", "the training runs")
    args = parser.parse_args(argv)
    check_backend_flags(args, parser)
    if (args.train is None) != (not args.seeds):
        parser.error("--train EPOCHS and --seeds go together")
    if args.train is not None and args.train < 1:
        parser.error(f"--train must be an integer >= 1, got {args.train}")
    hc = str(Path(sys.executable).with_name("hybridctl"))
    for seed in args.seeds:
        table51.train_pretrain(hc, seed, Path(args.work), "plain", args.train, ENV, backend_cli_args(args))
    runs = sorted(Path(args.work).glob("s*/pretrain-plain/eval.json"), key=lambda p: int(p.parts[-3][1:]))
    if not runs:
        parser.error(f"no finished runs under {args.work}: train some first with --train 150 --seeds 1 2 3")
    seeds = {p.parts[-3][1:]: seed_row(p.parent, args.min_return) for p in runs}
    command = command_line("hybridctl.reproduce.walker_seeds", argv)
    record = {"command": command, "commands": previous_commands(Path(args.out)) + [command],
              "ars": {"env": ENV, "settings": table51.ARS_SETTINGS[ENV]},
              "machine": machine_info(), "min_return": args.min_return, "seeds": seeds,
              "walking": [s for s, r in seeds.items() if r["walks"]]}
    atomic_write_text(Path(args.out), json.dumps(record, indent=1) + "\n")
    for s, r in seeds.items():
        print(f"seed {s}: {r['epochs']} epochs, {r['env_steps']:.2e} steps, {r['train_wall_time_s']:.0f} s, "
              f"return {r['return']:.0f}, episode steps {r['episode_steps']}, walks: {r['walks']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
