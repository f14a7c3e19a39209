"""Seeds of the shipped cart-pole recipe (PAPG through the LQR takeover): each run's torch evaluation
and its 11 x 11 Drake balance map, into results/ch7/papg-takeover-cartpole.json (``--out``).

    # each seed (about 200 s on one core; seed 0 is models/policies/papg-cartpole, its README):
    hybridctl train papg cartpole --takeover lqr --policy mlp:32,32 --horizon 60 --batch 16 \\
        --start-noise none --reward-kind angle_cosine --position-weight 0.1 --velocity-penalty 0.01 \\
        --clip 10 --lr-start 3e-3 --lr-end 1e-4 --apg-iterations 100 --epochs 40 --population 8 \\
        --elites 3 --compile on --seed S --out runs/ch7/papg-takeover-cartpole-sS
    python -m hybridctl.reproduce.papg_takeover_seeds runs/explore/I2 runs/ch7/papg-takeover-cartpole-s1 ...

The balance maps run on ``--backend``/``--workers``/``--address`` (default: serial, in this process).
"""

import argparse
from pathlib import Path

from hybridctl import io
from hybridctl.experiments.balance_map import balance_map
from hybridctl.reproduce.common import RESULTS, add_backend_flags, backend_options, check_backend_flags, recorded_path
from hybridctl.systems import load

RECORD = RESULTS / "ch7" / "papg-takeover-cartpole.json"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", help="hybridctl train papg run folders (eval.json, final/)")
    parser.add_argument("--out", type=Path, default=RECORD, help=f"the record (default {RECORD})")
    add_backend_flags(parser, "serial", "the balance maps' Drake runs")
    args = parser.parse_args(argv)
    check_backend_flags(args, parser)
    runs = []
    for folder in map(Path, args.folders):
        evaluation = io.read_json(folder / "eval.json")
        result = balance_map(load("cartpole"), f"papg:{folder / 'final'}", grid=11, progress=False, force=args.force,
                             **backend_options(args))
        runs.append({"run": recorded_path(folder), "seed": io.read_json(folder / "final" / "config.json")["config"]["seed"],
                     "command": evaluation.get("command"), "interactions": evaluation.get("env_steps"),
                     "train_wall_time_s": evaluation.get("train_wall_time_s"), "eval": evaluation,
                     "balance_map": {"grid": 11, "balanced_fraction": result.fraction,
                                     "balanced_count": int(result.balanced.sum())}})
        print(f"{folder}: {result.fraction:.1%} of the 11 x 11 map balanced")
    io.write_json(args.out, {"recipe": "models/policies/papg-cartpole/README.md", "machine": "2-core x86_64, "
                           "torch 2.13.0+cpu, one thread per run, two runs at a time", "runs": runs})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
