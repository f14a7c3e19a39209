"""``hybridctl fit MODEL_FILE --out DIR``: a complete spec and the classical controller from a URDF/SDF.

Built so far: the model stage (actuators, effort limit, goal and rest equilibria), the LQR stage (control hold,
Q and R) and the gate stage (the cost-to-go gate's scale), each measured, cached in DIR/stages and resumable.
Not built yet: the learned swing-up (--learner), the learned gate, the Drake balance-map verification and the
parallel-work flags; until they land, the swing-up is ``hybridctl simulate DIR/system.toml --controller trajopt``.
"""

from __future__ import annotations

import argparse

from ..experiments.fit import NOT_YET_BUILT, fit
from ._common import add_debug_flag, cli_errors, positive

EPILOG = ("Writes DIR/system.toml (a complete spec, every chosen value with the measurement that chose it as its "
          "source), DIR/report.json (each stage: tried, kept, why, seconds) and DIR/stages/*.json (the cache "
          "--resume reads). Then: hybridctl simulate DIR/system.toml --controller lqr | trajopt. "
          "Not built yet: " + "; ".join(NOT_YET_BUILT) + ".")


def add_parser(sub) -> None:
    """Register ``fit`` on the top-level sub-parsers."""
    p = sub.add_parser("fit", help="fit a spec and the classical controller (goal, LQR hold, Q/R, gate) to a URDF/SDF",
                       description=__doc__, epilog=EPILOG)
    p.add_argument("model_file", metavar="MODEL_FILE", help="a URDF or SDF file")
    p.add_argument("--out", required=True, help="output folder (made by fit; never one holding a spec or a model)")
    p.add_argument("--goal", default="auto", help="auto (the highest-potential equilibrium over the revolute "
                   "coordinates) or a state, comma-separated; write --goal=-1,0,0,0 when it starts with a minus")
    p.add_argument("--action-limit", type=positive(float), help="the largest command (default: the model's effort limit)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sampled starts (default 0)")
    p.add_argument("--resume", action="store_true", help="reuse the stages in --out whose inputs match")
    p.add_argument("--budget", type=positive(float), default=20.0, help="minutes; no stage starts past it (default 20)")
    add_debug_flag(p)
    p.set_defaults(func=run_fit)


@cli_errors
def run_fit(args: argparse.Namespace) -> int:
    """Run the stages, print where each came from and what to run next."""
    result = fit(args.model_file, args.out, goal=args.goal, action_limit=args.action_limit, seed=args.seed,
                 resume=args.resume, budget_minutes=args.budget, command=args.command_line)
    for stage in result.report["stages"]:
        took = "cached" if stage["cached"] else f"{stage['seconds']:.1f} s"
        print(f"{stage['name']}: {took}")
    print(f"wrote {result.system_file} and {result.out / 'report.json'}")
    for line in result.report["next"]:
        print(f"next: {line}")
    return 0
