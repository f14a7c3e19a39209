"""``hybridctl systems``: the benchmark systems with their states, integrator and description."""

from __future__ import annotations

import argparse

from ..systems import known_systems, load
from ._common import cli_errors


def add_parser(sub) -> None:
    """Register ``systems`` on the top-level sub-parsers."""
    p = sub.add_parser("systems", help="list the benchmark systems")
    p.set_defaults(func=run_systems)


@cli_errors
def run_systems(args: argparse.Namespace) -> int:
    """List the benchmark systems with their state names and integrator."""
    for name in known_systems():
        system = load(name)
        print(f"{name:16s} states={','.join(system.state_names):28s} {system.integrator} dt={system.dt} "
              f"limit={system.action_limit:g}  {system.description}")
    return 0
