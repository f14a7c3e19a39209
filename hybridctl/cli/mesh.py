"""``hybridctl mesh MAP``: reachable-state mesh and mean first passage time (thesis Ch. 5)."""

from __future__ import annotations

import argparse
import math

from ..experiments import MESH_MAPS, mesh_report
from ..experiments.mesh_report import MESH_DEFAULTS
from ..experiments.mfpt_sweep import mfpt_vs_roughness, sweep_line
from ..analysis import DEFAULT_REFINE_RTOL, DISTURBANCE_RULES
from ..analysis.reachable import check_disturbances
from ..limits import MAX_MONTE_CARLO, MAX_REFINED_DISTURBANCES, MAX_SWEEP_MONTE_CARLO_STEPS, check_at_most
from ._common import (non_negative, USAGE_ERROR, add_backend_flags, add_debug_flag, ray_options_for, check_backend_flags, add_force_flag, add_quiet_flag, cli_errors, finite,
                      limits_epilog, positive)


def add_parser(sub) -> None:
    """Register ``mesh`` on the top-level sub-parsers."""
    p = sub.add_parser("mesh", help="reachable-state mesh and mean first passage time (thesis Ch. 5)",
                       epilog=limits_epilog("disturbances", "monte-carlo", "workers"))
    p.add_argument("map", choices=sorted(MESH_MAPS), help="; ".join(f"{k}: {v}" for k, v in MESH_MAPS.items()))
    p.add_argument("--box-size", type=positive(float), default=None,
                   help="box side (default 1e-3; compass-gait 0.1)")
    p.add_argument("--slope-mean", type=finite(float), default=None,
                   help="mean terrain slope, rad (default 0.15; compass-gait 0.0525)")
    p.add_argument("--slope-std", type=slope_std, nargs="+", default=None, metavar="SIGMA",
                   help="slope std, rad, or degrees as '2deg' (default 0.06; compass-gait 0.005); several values: "
                        "the MFPT-vs-roughness "
                        "sweep (mfpt_vs_roughness.json and .png: refined mesh per sigma, Monte Carlo where affordable)")
    p.add_argument("--monte-carlo-budget", type=positive(float), default=MAX_SWEEP_MONTE_CARLO_STEPS, metavar="STEPS",
                   help="sweep: run a sigma's Monte Carlo only if --monte-carlo x the mesh's MFPT is at most STEPS "
                        f"expected steps, else skip it with the reason (default and limit {MAX_SWEEP_MONTE_CARLO_STEPS:.0e})")
    p.add_argument("--disturbances", type=positive(int), default=None,
                   help="slope points of the first grid, doubled until the MFPT settles (--disturbance-rule grid), "
                        "or the slope quantiles (quantiles); default 25 (compass-gait 5)")
    p.add_argument("--disturbance-rule", choices=DISTURBANCE_RULES, default="grid",
                   help="grid (default): a weighted grid over mean +- --tails std that keeps the tails, refined; "
                        "quantiles: the thesis' equal-probability quantiles (25 reach only +-2.05 std)")
    p.add_argument("--refine-rtol", type=positive(float), default=DEFAULT_REFINE_RTOL, metavar="RTOL",
                   help=f"stop refining the grid when the MFPT from the seed changes by at most RTOL (default "
                        f"{DEFAULT_REFINE_RTOL:g})")
    p.add_argument("--max-disturbances", type=positive(int), default=MAX_REFINED_DISTURBANCES, metavar="N",
                   help=f"the most points the grid may be refined to (default and limit {MAX_REFINED_DISTURBANCES})")
    p.add_argument("--tails", type=positive(float), default=6.0, metavar="STD",
                   help="half-width of the grid in slope std (default 6)")
    p.add_argument("--max-states", type=positive(int), default=1_000_000, help="cap on mesh states")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="compass-gait only: a CompassGaitParams value (mass_hip, mass_leg, length_leg, "
                        "center_of_mass_leg, gravity), repeatable")
    p.add_argument("--hip-pd", type=finite(float), nargs=3, metavar=("KP", "KD", "TARGET"),
                   help="compass-gait only: hip torque KP (TARGET - inter-leg angle) - KD (its rate); default: passive")
    p.add_argument("--monte-carlo", type=non_negative(int), default=0, metavar="EPISODES",
                   help="also estimate the MFPT by Monte Carlo on the true map")
    p.add_argument("--monte-carlo-chunks", type=positive(int), default=1, metavar="N",
                   help="groups the Monte Carlo episodes run in, one task each with its own random stream (the "
                        "estimate depends on N, not on the backend; N >= --workers fills the workers; default 1)")
    p.add_argument("--sizes", type=positive(float), nargs="*", help="also mesh at these box sizes (Table 5.1)")
    add_backend_flags(p, "serial", "section-map steps of the mesh")
    p.add_argument("--resume", action="store_true", help="continue from out/mesh_checkpoint.npz; a sweep of several --slope-std values keeps the rows its record holds when made on the same settings")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the run the --out folder holds (without it, or --resume, such a folder is refused)")
    p.add_argument("--checkpoint-every", type=positive(int), default=20, metavar="BATCHES",
                   help="write out/mesh_checkpoint.npz every this many batches (default 20)")
    p.add_argument("--checkpoint-minutes", type=float, default=5.0, metavar="MINUTES",
                   help="and at least every this many minutes of wall time, so a kill loses minutes at most "
                        "(0: by batches only; default 5)")
    p.add_argument("--out", default="runs/mesh", help="output folder")
    add_force_flag(p)
    add_quiet_flag(p)
    add_debug_flag(p)
    p.set_defaults(func=run_mesh)


def slope_std(text: str) -> float:
    """An argparse type: a slope std in rad, or in degrees written ``2deg``; finite and > 0."""
    degrees = text.endswith("deg")
    value = positive(float)(text[:-3] if degrees else text)
    return math.radians(value) if degrees else value


slope_std.__name__ = "float"


def result_line(report: dict) -> str:
    """One line: mesh states, MFPT from the seed, eigen estimate and the Monte Carlo interval."""
    mfpt = report["mfpt"]
    refinement = report["disturbance"]["refinement"]
    if math.isinf(mfpt["from_seed"]):
        line = f"{report['mesh']['states']} states; the chain almost never fails (MFPT beyond float64's reach)"
    else:
        line = f"{report['mesh']['states']} states; MFPT from the seed {mfpt['from_seed']:.1f} steps, eigen estimate " \
               f"{mfpt['eigen_estimate']:.1f}"
    if refinement["rule"] == "grid":
        change = refinement["relative_change"]
        line += (f"; slopes: grid of {refinement['count']} over +-{refinement['tails_std']:g} std, "
                 f"{'settled' if refinement['converged'] else 'NOT settled'} (last change {change:.2%}, rtol "
                 f"{refinement['rtol']:g})" if change is not None else f"; slopes: grid of {refinement['count']}")
    else:
        line += f"; slopes: {refinement['count']} quantiles"
    if "monte_carlo" in report:
        for key, label in (("continuous_disturbance", "continuous slopes"), ("mesh_disturbance_set", "the mesh's slopes")):
            mc = report["monte_carlo"][key]
            lo, hi = mc["interval95"]
            line += f"; Monte Carlo ({label}) {mc['mean_steps_to_failure']:.1f} [{lo:.1f}, {hi:.1f}]"
    return line


COMPASS_GAIT_PARAMS = ("mass_hip", "mass_leg", "length_leg", "center_of_mass_leg", "gravity")


def map_options(args: argparse.Namespace) -> dict:
    """The compass gait's ``--param`` and ``--hip-pd`` as ``section_map_by_name`` options (refused for other maps)."""
    if args.map != "compass-gait":
        for flag, given in (("--param", args.param), ("--hip-pd", args.hip_pd)):
            if given:
                raise ValueError(f"{flag} applies to the compass-gait map only, not {args.map}")
        return {}
    options = {}
    for text in args.param:
        name, sep, value = text.partition("=")
        if not sep or name not in COMPASS_GAIT_PARAMS:
            raise ValueError(f"--param must be NAME=VALUE with NAME one of {', '.join(COMPASS_GAIT_PARAMS)}, got {text!r}")
        try:
            options[name] = float(value)
        except ValueError:
            raise ValueError(f"--param {name} must be a number, got {value!r}") from None
    if args.hip_pd:
        options["hip_pd"] = tuple(args.hip_pd)
    return options


def fill_map_defaults(args: argparse.Namespace) -> None:
    """Put the map's ``MESH_DEFAULTS`` into the flags not given (box size, slope mean and std, disturbances)."""
    defaults = MESH_DEFAULTS[args.map]
    args.box_size = defaults["box_size"] if args.box_size is None else args.box_size
    args.slope_mean = defaults["slope_mean"] if args.slope_mean is None else args.slope_mean
    args.slope_std = [defaults["slope_std"]] if args.slope_std is None else args.slope_std
    args.disturbances = defaults["disturbances"] if args.disturbances is None else args.disturbances


def check_mesh_arguments(args: argparse.Namespace) -> None:
    """Refuse, before any work, counts above their limits (``--force`` lifts them): disturbances (and
    their successor table's memory, which nothing lifts), Monte Carlo episodes, local worker
    processes above the cores. Fills the map's defaults and its options (``args.map_options``)."""
    fill_map_defaults(args)
    args.map_options = map_options(args)
    check_disturbances(args.disturbances, args.max_states, force=args.force)
    check_at_most("--max-disturbances", args.max_disturbances, MAX_REFINED_DISTURBANCES, force_flag=None,
                  why="points of a refined slope grid")
    check_at_most("--monte-carlo", args.monte_carlo, MAX_MONTE_CARLO, args.force, why="episodes")
    if args.monte_carlo and args.monte_carlo_chunks > args.monte_carlo:
        raise ValueError(f"--monte-carlo-chunks must be in [1, --monte-carlo={args.monte_carlo}], "
                         f"got {args.monte_carlo_chunks}")
    if len(args.slope_std) > 1:
        if args.sizes:
            raise ValueError("--sizes does not apply to a sweep of several --slope-std values")
        check_at_most("--monte-carlo-budget", args.monte_carlo_budget, MAX_SWEEP_MONTE_CARLO_STEPS, args.force,
                      why="expected simulated steps of one sigma's Monte Carlo")
    check_backend_flags(args)


@cli_errors
def run_mesh(args: argparse.Namespace) -> int:
    """Build the mesh and write the MFPT report and figures; exit 2 when the mesh hit --max-states."""
    check_mesh_arguments(args)
    if len(args.slope_std) > 1:
        with ray_options_for(args):
            sweep = _sweep(args)
        if args.quiet:      # else each row was printed as it came
            for row in sweep["rows"]:
                print(sweep_line(row))
        print(f"wrote {args.out}/mfpt_vs_roughness.json and mfpt_vs_roughness.png")
        return 0
    with ray_options_for(args):   # --task-cpus/--task-gpus/--task-memory/--runtime-env for the Ray tasks
        report = _mesh_report(args)
    if "error" in report:
        print(report["error"])
        return USAGE_ERROR
    print(result_line(report))
    print(f"wrote {args.out}/mfpt.json, transition_matrix.npz, mesh.npz (ReachableMesh.load) and figures")
    return 0


def _mesh_report(args: argparse.Namespace) -> dict:
    """:func:`mesh_report` with the command's flags."""
    return mesh_report(args.map, args.out, box_size=args.box_size, slope_mean=args.slope_mean,
                       slope_std=args.slope_std[0], disturbances=args.disturbances, max_states=args.max_states,
                       monte_carlo=args.monte_carlo, sizes=args.sizes, backend=args.backend,
                       workers=args.workers, resume=args.resume, progress=not args.quiet,
                       command=args.command_line, overwrite=args.overwrite,
                       checkpoint_every=args.checkpoint_every, checkpoint_minutes=args.checkpoint_minutes,
                       address=args.address, monte_carlo_chunks=args.monte_carlo_chunks,
                       disturbance_rule=args.disturbance_rule, refine_rtol=args.refine_rtol,
                       max_disturbances=args.max_disturbances, tails=args.tails, map_options=args.map_options)


def _sweep(args: argparse.Namespace) -> dict:
    """:func:`mfpt_vs_roughness` with the command's flags."""
    return mfpt_vs_roughness(args.map, args.out, args.slope_std, box_size=args.box_size, slope_mean=args.slope_mean,
                             disturbances=args.disturbances, max_states=args.max_states, monte_carlo=args.monte_carlo,
                             monte_carlo_budget=args.monte_carlo_budget, monte_carlo_chunks=args.monte_carlo_chunks,
                             disturbance_rule=args.disturbance_rule, refine_rtol=args.refine_rtol,
                             max_disturbances=args.max_disturbances, tails=args.tails, backend=args.backend,
                             workers=args.workers, address=args.address, progress=not args.quiet,
                             command=args.command_line, overwrite=args.overwrite, force=args.force,
                             map_options=args.map_options, resume=args.resume)
