"""``hybridctl demo`` (what ``make demo`` runs): the pretrained SSAC acrobot, its replay and a balance map."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..experiments import run_demo
from ..experiments.demo import DEMO_GRID, PRETRAINED_ACROBOT, PRETRAINED_CARTPOLE, check_demo_arguments
from ..io import command_folder
from ..limits import MAX_GRID
from ._common import add_debug_flag, add_quiet_flag, cli_errors, positive
from .simulate import start_live_view

DEMO_PARTS = ("acrobot", "balance_map", "cartpole", "cartpole_balance_map")
"""The folders ``hybridctl demo`` writes into its --out (run_demo)."""


def add_parser(sub) -> None:
    """Register ``demo`` on the top-level sub-parsers."""
    p = sub.add_parser("demo", help="what `make demo` runs")
    p.add_argument("--out", default="runs/demo", help="output folder")
    p.add_argument("--grid", type=positive(int), default=DEMO_GRID,
                   help=f"balance-map grid points per axis, 2 to {MAX_GRID:,} (default {DEMO_GRID}); checked "
                        "before anything is simulated")
    p.add_argument("--meshcat", action="store_true", help="also show the run live in meshcat")
    add_quiet_flag(p)
    add_debug_flag(p)
    p.set_defaults(func=run_demo_command)


@cli_errors
def run_demo_command(args: argparse.Namespace) -> int:
    """Run the demo, printing its account as it goes; exit 1 when the acrobot or the cart-pole did not balance."""
    # every argument is checked before --out is made, so a refused run leaves nothing behind
    check_demo_arguments(Path(args.out), args.grid, PRETRAINED_ACROBOT, PRETRAINED_CARTPOLE)
    with command_folder(args.out, "demo", DEMO_PARTS, own=DEMO_PARTS[:1]):  # locked; never beside an input
        live = start_live_view() if args.meshcat else None
        result = run_demo(args.out, grid=args.grid, meshcat=live, progress=not args.quiet, command=args.command_line)
    cartpole = result["cartpole"]
    ok = result["simulation"]["balanced"] and (cartpole is None or cartpole["simulation"]["balanced"])
    return 0 if ok else 1
