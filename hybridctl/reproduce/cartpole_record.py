"""Record of a shipped SSAC cart policy: Drake from hanging down, the 21 x 21 balance map of (x, theta)
starts at rest over the spec's start box (Drake engine), the same map by the torch engine, and a
wide map (x in +-1 m, the first angle over the whole circle, Drake). Writes ``OUT/drake_record.json`` and
the maps' folders (``results/ch3/cartpole``, ``results/ch3/double_cartpole``), the Drake trajectory to
``runs/ssac-SYSTEM-drake``.

    python -m hybridctl.reproduce.cartpole_record                       # the cart-pole, ~7 min shared
    python -m hybridctl.reproduce.cartpole_record --system double_cartpole \\
        --policy models/policies/ssac-double-cartpole --out results/ch3/double_cartpole

The three maps run on ``--backend``/``--workers``/``--address`` (default: each engine's, Drake in local
processes on every core, torch as one batch in this process); the maps do not depend on them.
"""
import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from hybridctl.io import atomic_write_text
from hybridctl import drake, experiments, systems
from hybridctl.experiments import balance_map
from hybridctl.reproduce.common import (RESULTS, add_backend_flags, backend_options, check_backend_flags, command_line,
                                       machine_info, recorded_path, shipped_policy)


def main(argv: list[str] | None = None):
    """Simulate, map and write drake_record.json into --out."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--system", default="cartpole")
    parser.add_argument("--policy", default="models/policies/ssac-cartpole",
                        help="a checkpoint folder; models/policies/NAME is also found in the installed package")
    parser.add_argument("--out", default=str(RESULTS / "ch3" / "cartpole"))
    parser.add_argument("--grid", type=int, default=21)
    add_backend_flags(parser, "processes for the drake maps, serial for the torch map", "each balance map")
    parser.set_defaults(backend=None)     # None: each engine's default (the text above is the help's)
    args = parser.parse_args(argv)
    check_backend_flags(args, parser)
    parallel = {**backend_options(args), "force": args.force}
    torch.set_num_threads(1)
    out = Path(args.out)
    policy = Path(args.policy)
    if not policy.exists() and policy.parent.as_posix() == "models/policies":
        policy = shipped_policy(policy.name)
    system = systems.load(args.system)
    named = recorded_path(policy)     # the balance maps record the controller: a relative path where it resolves
    controller = f"ssac:{named if Path(named).exists() else policy}"
    traj = drake.simulate(experiments.build_named_diagram(system, controller), system.initial_state.nominal,
                          duration=system.episode_duration)
    summary = traj.save(Path("runs") / f"ssac-{args.system}-drake")
    start = time.perf_counter()
    drake_map = balance_map(system, controller, grid=args.grid, progress=False, **parallel)
    drake_wall = time.perf_counter() - start
    drake_map.save(out / f"balance_map_{args.grid}")
    torch_map = balance_map(system, controller, grid=args.grid, engine="torch", progress=False, **parallel)
    # the whole circle of the first pole angle and +-1 m of cart
    start = time.perf_counter()
    wide_map = balance_map(system, controller, grid=args.grid, ranges=((-1.0, 1.0), (-np.pi, np.pi)),
                           progress=False, **parallel)
    wide_wall = time.perf_counter() - start
    wide_map.save(out / f"balance_map_{args.grid}_wide")
    low, high = system.initial_state.low, system.initial_state.high
    record = {
        "command": command_line("hybridctl.reproduce.cartpole_record", argv),
        "system": args.system,
        "policy": recorded_path(policy),
        "from_hanging_down_drake": {"balanced": bool(traj.balanced), "return": summary["return"],
                                    "first_balance_time": summary["first_balance_time"],
                                    "final_state": np.asarray(traj.x[-1]).round(4).tolist()},
        f"balance_map_{args.grid}_drake": {"balanced_fraction": drake_map.fraction, "wall_time_s": drake_wall,
                                           "x_range": [float(low[0]), float(high[0])],
                                           "theta_range": [float(low[1]), float(high[1])],
                                           "folder": recorded_path(out / f"balance_map_{args.grid}")},
        f"balance_map_{args.grid}_wide_drake": {"balanced_fraction": wide_map.fraction, "wall_time_s": wide_wall,
                                                "x_range": [-1.0, 1.0], "theta_range": [-np.pi, np.pi],
                                                "folder": recorded_path(out / f"balance_map_{args.grid}_wide")},
        f"balance_map_{args.grid}_torch": {"balanced_fraction": torch_map.fraction,
                                           "wall_time_s": torch_map.wall_time},
        "machine": machine_info(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S %z"),
    }
    atomic_write_text(out / "drake_record.json", json.dumps(record, indent=1))
    print(json.dumps(record, indent=1))


if __name__ == "__main__":
    raise SystemExit(main())
