"""``hybridctl fit MODEL_FILE --out DIR``: a complete spec and a learned switched controller from a URDF/SDF.

The stages (each measured, cached in DIR/stages, resumable with --resume): model (actuators, effort limit, goal
and rest equilibria), lqr (control hold, Q and R), gate (the cost-to-go gate's scale), reward (the tip that
rises most), swingup (Drake's collocation swing-up, tracked by TVLQR, sets the learner's periods), learned_gate
(the thesis' gate from the measured basin), clone (the tracked swing-up cloned into SSAC's actor), learner (SSAC
from the clone in the budget left), verify (balance maps in torch and Drake keep a checkpoint and a gate).
``--learner none`` stops after the classical stages.
"""

from __future__ import annotations

import argparse
import sys

from ..experiments.fit import LEARNERS, NOT_YET_BUILT, fit
from ._common import add_backend_flags, add_debug_flag, check_ray_task_flags, cli_errors, positive, ray_options_for

EPILOG = ("Writes DIR/system.toml (a complete spec, every chosen value with the measurement that chose it as its "
          "source), DIR/report.json (each stage: tried, kept, why, seconds), DIR/stages/*.json (the cache --resume "
          "reads), DIR/clone (the cloned swing-up), DIR/learner (the SSAC run), DIR/maps (Drake balance maps) and "
          "DIR/replay.html. Then: hybridctl "
          "simulate DIR/system.toml --controller fitted:DIR. Not built yet: " + "; ".join(NOT_YET_BUILT) + ".")


def add_parser(sub) -> None:
    """Register ``fit`` on the top-level sub-parsers."""
    p = sub.add_parser("fit", help="fit a spec and a learned switched controller (swing-up, gate, LQR) to a URDF/SDF",
                       description=__doc__, epilog=EPILOG)
    p.add_argument("model_file", metavar="MODEL_FILE", help="a URDF or SDF file")
    p.add_argument("--out", required=True, help="output folder (made by fit; never one holding a spec or a model)")
    p.add_argument("--goal", default="auto", help="auto (the highest-potential equilibrium over the revolute "
                   "coordinates) or a state, comma-separated; write --goal=-1,0,0,0 when it starts with a minus")
    p.add_argument("--action-limit", type=positive(float), help="the largest command (default: the model's effort limit)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sampled starts (default 0)")
    p.add_argument("--resume", action="store_true", help="reuse the stages in --out whose inputs match")
    p.add_argument("--budget", type=positive(float), default=20.0,
                   help="minutes for all stages; the learner gets what the others leave (default 20)")
    p.add_argument("--learner", default="auto", choices=[*LEARNERS, "none"],
                   help="auto = ssac (the learner whose gate is learned); none: the classical stages only")
    add_backend_flags(p, "processes", "each Drake balance map of the verification")
    p.add_argument("--force", action="store_true", help="allow --workers above the cores this process may use")
    p.add_argument("--device", help="torch device of SSAC, its clone and the torch balance maps (cpu, cuda, cuda:0; "
                                    "default cpu)")
    add_debug_flag(p)
    p.set_defaults(func=run_fit)


@cli_errors
def run_fit(args: argparse.Namespace) -> int:
    """Run the stages, print where each came from and what to run next."""
    check_ray_task_flags(args, args.backend)
    with ray_options_for(args):   # --backend ray: --task-cpus/-gpus/-memory, --runtime-env
        result = fit(args.model_file, args.out, goal=args.goal, action_limit=args.action_limit, seed=args.seed,
                     resume=args.resume, budget_minutes=args.budget, command=args.command_line,
                     learner=None if args.learner == "none" else args.learner, backend=args.backend,
                     workers=args.workers, address=args.address, device=args.device, force=args.force)
    for stage in result.report["stages"]:
        took = "cached" if stage["cached"] else f"{stage['seconds']:.1f} s"
        print(f"{stage['name']}: {took}")
    print(f"wrote {result.system_file} and {result.out / 'report.json'}")
    controller = result.report.get("controller")
    if controller is not None:
        maps = ", ".join(f"{name} {m['balanced']}/{m['starts']}" for name, m in controller["drake_maps"].items())
        swingup = "the cloned swing-up" if controller.get("checkpoint") == "clone" else "SSAC's swing-up"
        print(f"kept: {swingup}, the {controller['gate']} gate, Drake's LQR; Drake balance maps: {maps}")
    for line in result.report["next"]:
        print(f"next: {line}")
    if result.report.get("swingup_found") is False:
        print(f"error: no swing-up found within the budget; {result.report['what_to_try']} "
              f"({result.out / 'report.json'} says what each stage reached)", file=sys.stderr)
        return 1
    return 0
