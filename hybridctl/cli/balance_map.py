"""``hybridctl balance-map SYSTEM``: the balanced fraction over a grid of rest states (thesis Fig. 3.6)."""

from __future__ import annotations

import argparse

from ..experiments import balance_map
from ..experiments.balance_map import ENGINES, check_balance_map, near_hanging_down, output_folder
from ..systems import load
from ._common import (add_backend_flags, add_debug_flag, add_force_flag, add_quiet_flag, add_system_argument,
                      check_backend_flags, cli_errors, limits_epilog, positive, ray_options_for)
from .simulate import controller_help


def add_parser(sub) -> None:
    """Register ``balance-map`` on the top-level sub-parsers."""
    p = sub.add_parser("balance-map", help="balanced fraction over a grid of rest states (thesis Fig. 3.6)",
                       epilog=limits_epilog("grid", "duration", "workers"))
    add_system_argument(p)
    p.add_argument("--controller", default="energy", help=controller_help())
    p.add_argument("--grid", type=positive(int), default=41, help="grid points per axis (default 41, thesis)")
    p.add_argument("--duration", type=positive(float), help="seconds per run (default: the spec's episode)")
    p.add_argument("--near", type=positive(float), metavar="HALF_WIDTH",
                   help="starts near hanging down: the map's two axes within +-HALF_WIDTH of the spec's nominal "
                        "state, in (0, pi] (default: the spec's start ranges; the acrobot's span every angle)")
    # the default backend depends on --engine: None here, chosen in run_balance_map (the text is the help's)
    add_backend_flags(p, "processes for --engine drake, serial for --engine torch", "the grid's simulation")
    p.set_defaults(backend=None)
    p.add_argument("--engine", choices=ENGINES, default="drake",
                   help="drake: the Drake diagram, one run per start (default); torch: batched rollouts of the "
                        "switched controller in torch, every start as one batch (seconds), or with --backend "
                        "processes/ray one chunk of the grid per worker, each chunk one batch (the same map)")
    p.add_argument("--device", help="torch device of the torch engine's rollouts (cpu, cuda, cuda:0; default cpu); "
                                    "refused for --engine drake")
    p.add_argument("--out", default="runs/balance_map", help="output folder")
    add_force_flag(p, also="and load a KIND:PATH checkpoint trained on other spec values (another plant) anyway, "
                           "with a warning naming what differs")
    add_quiet_flag(p)
    add_debug_flag(p)
    p.set_defaults(func=run_balance_map)


@cli_errors
def run_balance_map(args: argparse.Namespace) -> int:
    """Simulate every grid start, write balance_map.png and balance_map.json, print the fraction."""
    system = load(args.system)
    if args.backend is None:     # the engine's default: Drake runs in worker processes, torch as one batch here
        args.backend = "serial" if args.engine == "torch" else "processes"
    check_backend_flags(args)
    check_balance_map(system, args.grid, args.duration, args.engine, args.workers if args.backend != "ray" else None,
                      args.force, args.device)  # before --out is made
    axes, ranges = near_hanging_down(system, args.near) if args.near is not None else (None, None)
    # --out is checked and locked before the simulations: a folder holding an input, or another run's, fails here
    with output_folder(args.out), ray_options_for(args):  # ray: --task-cpus/-gpus/-memory, --runtime-env
        result = balance_map(system, args.controller, grid=args.grid, duration=args.duration, axes=axes,
                             ranges=ranges, workers=args.workers, progress=not args.quiet, engine=args.engine,
                             force=args.force, backend=args.backend, address=args.address, device=args.device)
        result.meta["command"] = args.command_line
        summary = result.save(args.out)
    print(f"balanced_fraction: {summary['balanced_fraction']:.4f} "
          f"({summary['balanced_count']}/{args.grid * args.grid}), wall {result.wall_time:.1f} s ({args.engine}, {args.backend})")
    print(f"wrote {args.out}/balance_map.png, balance_map.json")
    return 0
