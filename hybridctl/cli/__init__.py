"""The ``hybridctl`` command line.

    hybridctl systems
    hybridctl simulate acrobot --controller energy --x0=-1.5698,0,0,0 --duration 15 --out runs/sim
    hybridctl balance-map acrobot --controller energy --grid 41 --duration 15 --out runs/map
    hybridctl train ssac acrobot --seed 0 --out runs/train/ssac-acrobot-s0 [--resume] [--polyak 0.9]
    hybridctl mesh rimless-wheel --box-size 1e-3 --monte-carlo 2000 --out runs/mesh
    hybridctl finetune Pendulum-v1 --policy sb3:models/policies/ppo-pendulum/model.zip --updates 200
    hybridctl fit models/acrobot.urdf --out runs/fit-acrobot [--resume]
    hybridctl demo --out runs/demo

Add --debug to see the traceback of an error. Sizes, counts and durations have limits
(hybridctl.limits, listed in each command's --help), checked before any work; --force on
simulate, balance-map and mesh lifts the stated caps, never the memory limit.
"""

from __future__ import annotations

import argparse
import os
import sys

from . import balance_map, demo, finetune, fit, mesh, simulate, systems, train
from ._common import CommandParser, add_debug_flag, command_line
from .. import __version__
from ..experiments import PRETRAINED_ACROBOT

COMMANDS = (systems, simulate, balance_map, train, mesh, finetune, fit, demo)
"""The command modules, in the order ``hybridctl --help`` lists them; each has ``add_parser(sub)``."""

__all__ = ["main", "build_parser", "PRETRAINED_ACROBOT"]


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``hybridctl`` command."""
    parser = CommandParser(prog="hybridctl", description=__doc__)
    parser.add_argument("--version", action="version", version=f"hybridctl {__version__}")
    add_debug_flag(parser, top_level=True)
    sub = parser.add_subparsers(dest="command", required=True)
    for module in COMMANDS:
        module.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``hybridctl`` console script."""
    import torch

    torch.set_num_threads(1)  # small networks and single states: threads only add overhead
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    args.command_line = command_line(argv)
    try:
        return args.func(args)
    except BrokenPipeError:  # `hybridctl systems | head`: the reader left; not an error of ours
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # Python's exit flush would fail again
        return 0
