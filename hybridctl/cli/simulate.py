"""``hybridctl simulate SYSTEM``: one run of a system under a named controller, written to a folder."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from ..drake.simulate import check_duration
from ..experiments import CONTROLLERS, simulate_and_write
from ..experiments.simulation import OUTPUTS, OWN
from ..io import check_output_folder
from ..systems import System, load
from ._common import add_system_argument, add_debug_flag, add_force_flag, cli_errors, limits_epilog, positive

SUMMARY_KEYS = ("system", "balanced", "return", "diverged", "first_balance_time", "wall_time_s")
"""The summary fields ``simulate`` prints."""


def controller_help() -> str:
    """The ``--controller`` help: every named controller with what it is."""
    return "controller: " + "; ".join(f"{k} = {v}" for k, v in CONTROLLERS.items())


def parse_state(text: str | None, system: System) -> np.ndarray | None:
    """``--x0`` text ("-1.57,0,0,0") -> a state of ``system``; None stays None (the default start)."""
    if text is None:
        return None
    fields = text.replace(" ", "").split(",") if text.strip() else []  # "--x0=": no values at all
    if "" in fields:  # "1,,0" is a typo, not the two numbers 1 and 0
        raise ValueError(f"--x0 has an empty field at position {fields.index('') + 1}: it needs {system.n_states} "
                         f"comma-separated numbers ({', '.join(system.state_names)}), got {text!r}")
    try:
        values = [float(v) for v in fields]
    except ValueError:
        raise ValueError(f"--x0 must be {system.n_states} comma-separated numbers "
                         f"({', '.join(system.state_names)}), got {text!r}") from None
    if len(values) != system.n_states:
        raise ValueError(f"--x0 needs {system.n_states} values ({', '.join(system.state_names)}), "
                         f"got {len(values)}")
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"--x0 must be finite numbers ({', '.join(system.state_names)}), got {text!r}")
    return np.array(values)


def add_parser(sub) -> None:
    """Register ``simulate`` on the top-level sub-parsers."""
    p = sub.add_parser("simulate", help="simulate one run of a system under a controller",
                       epilog=limits_epilog("duration"))
    add_system_argument(p)
    p.add_argument("--controller", default="energy", help=controller_help())
    p.add_argument("--x0", help="initial state, comma-separated; write --x0=-1.57,0,0,0 when it starts "
                   "with a minus (default: the spec's nominal start, first angle + 1e-3 rad)")
    p.add_argument("--duration", type=positive(float), help="seconds (default: the spec's episode)")
    p.add_argument("--out", default="runs/simulate", help="output folder (default: runs/simulate)")
    p.add_argument("--no-html", action="store_true", help="skip the replay.html")
    p.add_argument("--meshcat", action="store_true", help="also show it live in meshcat (localhost)")
    add_force_flag(p, also="and load a KIND:PATH checkpoint trained on other spec values (another plant) anyway, "
                           "with a warning naming what differs")
    add_debug_flag(p)
    p.set_defaults(func=run_simulate)


def start_live_view():
    """Start meshcat and say where to look (the ``--meshcat`` flag)."""
    from ..viz import start_meshcat

    live = start_meshcat()
    print(f"meshcat: open {live.web_url()} (live view while simulating at real time)")
    return live


@cli_errors
def run_simulate(args: argparse.Namespace) -> int:
    """Simulate, write trajectory.npz, summary.json, plot.png (and replay.html), print the summary."""
    system = load(args.system)
    x0 = parse_state(args.x0, system)
    check_duration(system, args.duration, args.force)  # before meshcat starts or anything is built
    check_output_folder(args.out, "simulate", OUTPUTS, OWN)  # and --out (checked again under its lock)
    live = start_live_view() if args.meshcat else None
    summary = simulate_and_write(system, args.controller, args.out, x0=x0, duration=args.duration,
                                 html=not args.no_html, meshcat=live, command=args.command_line, force=args.force)
    print(json.dumps({k: summary[k] for k in SUMMARY_KEYS}, indent=1))
    print(f"wrote {args.out}/" + ", ".join(summary["written"]))
    if "plot.png" not in summary["written"]:
        print("no plot.png or replay.html: the run diverged within its first step")
    return 0
