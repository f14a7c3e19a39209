"""The ``hybridctl`` command line.

    hybridctl systems
    hybridctl simulate acrobot --controller energy --x0 -1.5698,0,0,0 --duration 15 --out runs/sim
    hybridctl balance-map acrobot --controller energy --grid 41 --duration 15 --out runs/map
    hybridctl train ssac acrobot --seed 0 --out runs/ssac-acrobot-s0 [--resume] [--set polyak=0.9]
    hybridctl mesh rimless-wheel --box-size 1e-3 --monte-carlo 2000 --out runs/mesh
    hybridctl demo --out runs/demo
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

DEMO_X0 = "-1.5698,0,0,0"  # hanging down, nudged 1e-3 rad: the exact bottom is an equilibrium


def _parse_x0(text: str | None, system) -> np.ndarray:
    if text is None:
        x0 = np.array(system.spec.get("initial_state.nominal"), dtype=float)
        x0[system.angle_indices[0]] += 1e-3
        return x0
    try:
        values = [float(v) for v in text.replace(" ", "").split(",") if v]
    except ValueError:
        raise SystemExit(f"error: --x0 must be {system.n_states} comma-separated numbers "
                         f"({', '.join(system.state_names)}), got {text!r}")
    if len(values) != system.n_states:
        raise SystemExit(f"error: --x0 needs {system.n_states} values ({', '.join(system.state_names)}), "
                         f"got {len(values)}")
    return np.array(values)


def _load_system(name: str):
    from ..systems import SpecError, load
    try:
        return load(name)
    except KeyError as exc:
        raise SystemExit(f"error: {exc.args[0]}")
    except SpecError as exc:
        raise SystemExit(f"error: {exc}")


def _positive(kind):
    def parse(text):
        value = kind(text)
        if value <= 0:
            raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
        return value
    return parse


def cmd_systems(args) -> int:
    """List the benchmark systems with their state names and integrator."""
    from ..systems import known_systems, load
    for name in known_systems():
        system = load(name)
        print(f"{name:16s} states={','.join(system.state_names):28s} {system.integrator} dt={system.dt} "
              f"limit={system.action_limit:g}  {system.spec.get('system.description')}")
    return 0


def run_simulation(system_name: str, controller: str, x0: str | None, duration: float | None,
                   out: Path, html: bool = True, meshcat: bool = False) -> dict:
    """Simulate, then write trajectory.npz, summary.json, plot.png and replay.html into ``out``."""
    import matplotlib.pyplot as plt

    from ..drake import simulate
    from ..experiments import build_named_diagram
    from ..learn.checkpoint import CheckpointError
    from ..viz import plot_trajectory, replay_html

    system = _load_system(system_name)
    start = _parse_x0(x0, system)
    live = None
    if meshcat:
        from ..viz import start_meshcat
        live = start_meshcat()
        print(f"meshcat: open {live.web_url()} (live view while simulating at real time)")
    try:
        diagram = build_named_diagram(system, controller, meshcat=live)
    except (ValueError, CheckpointError) as exc:
        raise SystemExit(f"error: {exc}")
    traj = simulate(diagram, start, duration, realtime_rate=1.0 if live is not None else 0.0)
    traj.meta.update({"controller": controller, "command": "hybridctl " + " ".join(sys.argv[1:])})
    summary = traj.save(out)
    fig = plot_trajectory(traj.t, traj.x, traj.u, traj.gate, system, path=out / "plot.png",
                          title=f"{system.name}, {controller}: balanced={summary['balanced']}")
    plt.close(fig)
    if html and len(traj.t) > 1:
        replay_html(system, traj.t, traj.x, path=out / "replay.html")
    return summary


def cmd_simulate(args) -> int:
    """`hybridctl simulate SYSTEM ...`"""
    out = Path(args.out)
    summary = run_simulation(args.system, args.controller, args.x0, args.duration, out,
                             html=not args.no_html, meshcat=args.meshcat)
    print(json.dumps({k: summary[k] for k in ("system", "balanced", "return", "diverged",
                                                 "first_balance_time", "wall_time_s")}, indent=1))
    print(f"wrote {out}/trajectory.npz, summary.json, plot.png" + ("" if args.no_html else ", replay.html"))
    return 0


def cmd_balance_map(args) -> int:
    """`hybridctl balance-map SYSTEM ...`"""
    from ..experiments import balance_map
    from ..learn.checkpoint import CheckpointError
    system = _load_system(args.system)
    try:
        result = balance_map(system, args.controller, grid=args.grid, duration=args.duration,
                             workers=args.workers, progress=not args.quiet)
    except (ValueError, CheckpointError) as exc:
        raise SystemExit(f"error: {exc}")
    result.meta["command"] = args.command_line
    summary = result.save(args.out)
    print(f"balanced_fraction: {summary['balanced_fraction']:.4f} "
          f"({summary['balanced_count']}/{args.grid * args.grid}), wall {result.wall_time:.1f} s")
    print(f"wrote {args.out}/balance_map.png, balance_map.json")
    return 0


PRETRAINED_ACROBOT = Path(__file__).resolve().parents[2] / "models" / "policies" / "ssac-acrobot"


def cmd_demo(args) -> int:
    """`hybridctl demo`: the pretrained SSAC acrobot in Drake from hanging down, replay and balance map."""
    out = Path(args.out)
    start = time.perf_counter()
    controller = f"ssac:{PRETRAINED_ACROBOT}"
    print("hybridctl demo: acrobot (thesis Ch. 3) in Drake: learned SSAC swing-up (TorchPolicy) + learned gate "
          "(Gate, hysteresis) + Drake LQR")
    print(f"  checkpoint: {PRETRAINED_ACROBOT} (how it was trained: README.md there)")
    summary = run_simulation("acrobot", controller, DEMO_X0, 10.0, out / "acrobot", meshcat=args.meshcat)
    print(f"  simulate 10 s from hanging down: balanced={summary['balanced']} return={summary['return']:.1f} "
          f"(thesis max 100), LQR from t={summary['first_balance_time']} s, "
          f"{summary['realtime_factor']:.0f}x real time")
    print(f"  open {out / 'acrobot' / 'replay.html'} in a browser to watch it")
    from ..experiments import balance_map
    result = balance_map("acrobot", controller, grid=args.grid, progress=not args.quiet)
    result.meta["command"] = args.command_line
    bm = result.save(out / "balance_map")
    print(f"  balance map {args.grid}x{args.grid} of rest states, 10 s each: {bm['balanced_fraction']:.1%} balanced "
          f"(thesis: every start of a 41 x 41 grid)")
    print(f"demo done in {time.perf_counter() - start:.0f} s; outputs under {out}/")
    return 0 if summary["balanced"] else 1


def _parse_settings(pairs: list[str], config_class) -> dict:
    """--set key=value pairs -> config overrides (values parsed as JSON, else kept as text)."""
    import dataclasses

    fields = {f.name for f in dataclasses.fields(config_class)}
    out = {}
    for pair in pairs or []:
        key, sep, text = pair.partition("=")
        key = key.strip().replace("-", "_")
        if not sep or not key:
            raise SystemExit(f"error: --set expects key=value, got {pair!r}")
        if key not in fields:
            raise SystemExit(f"error: --set {key}: not a {config_class.__name__} field; fields: "
                             + ", ".join(sorted(fields)))
        try:
            out[key] = json.loads(text)
        except json.JSONDecodeError:
            out[key] = text
    return out


def cmd_train(args) -> int:
    """`hybridctl train ALGO SYSTEM ...`: train, checkpoint, evaluate, plot."""
    from ..learn import SAC, SSAC, SSACConfig
    from ..learn.checkpoint import CheckpointError

    if args.algorithm == "ars":
        return _train_ars(args)
    for flag in ("epochs", "postprocess", "init", "backend", "workers", "address"):
        if getattr(args, flag) is not None:
            raise SystemExit(f"error: --{flag} applies to ars only")
    args.eval_episodes = args.eval_episodes or 100
    algo = {"sac": SAC, "ssac": SSAC}[args.algorithm]
    settings = _parse_settings(args.set, algo.config_class)
    if args.seed is not None:
        settings["seed"] = args.seed
    if args.steps is not None:
        settings["total_steps"] = args.steps
    out = Path(args.out or f"runs/train/{args.algorithm}-{args.system}-s{settings.get('seed', 0)}")
    _load_system(args.system)  # clear error for an unknown system name
    try:
        if args.algorithm == "ssac":
            config = SSACConfig.variant(args.variant, **settings)
        else:
            if args.variant != "hybridctl":
                raise SystemExit("error: --variant applies to ssac only")
            config = SAC.config_class(**settings)
        config.validate()
    except (TypeError, ValueError) as exc:
        raise SystemExit(f"error: {exc}")
    start = time.perf_counter()
    try:
        if args.resume and (out / "checkpoint").exists() or args.resume and (out / "final").exists():
            from ..learn.checkpoint import newest_checkpoint
            found = newest_checkpoint([out / "checkpoint", out / "final"])
            agent = algo.load(found, **{k: v for k, v in settings.items() if k == "total_steps"})
            print(f"resuming {found} at {agent.num_timesteps} env steps")
        else:
            if args.resume:
                print(f"--resume: no checkpoint under {out}; starting a new run")
            print(f"{algo.algorithm_name} on {args.system}: {config.total_steps} env steps, seed {config.seed}"
                  + (" (warm-starting the gate first)" if args.algorithm == "ssac" else ""))
            agent = algo(args.system, config=config)
        agent.learn(progress=not args.quiet, log_dir=out, resume=args.resume)
    except CheckpointError as exc:
        raise SystemExit(f"error: {exc}")
    except FloatingPointError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    result = agent.evaluate(episodes=args.eval_episodes)
    result.update({"command": args.command_line, "env_steps": agent.num_timesteps,
                   "train_wall_time_s": agent.wall_time, "session_wall_time_s": time.perf_counter() - start,
                   "train_mean_return_last100": agent.mean_return, "train_success_rate_last100": agent.success_rate})
    from ..learn.checkpoint import write_json
    write_json(out / "eval.json", result)
    print(f"deterministic return over {result['episodes']} episodes: {result['mean_return']:.2f} "
          f"+- {result['std_return']:.2f} (min {result['min_return']:.2f}), success {result['success_rate']:.0%}")
    print(f"wrote {out}/final (checkpoint), progress.csv, training_curves.png, eval.json")
    return 0


def _train_ars(args) -> int:
    """`hybridctl train ars ENV ...`: ARS V2-t with optional dimension post-processing (thesis Ch. 4)."""
    from ..learn.ars import ARS, ARSConfig
    from ..learn.checkpoint import CheckpointError, newest_checkpoint, write_json

    if args.steps is not None or args.variant != "hybridctl":
        raise SystemExit("error: ars takes --epochs (not --steps) and no --variant")
    settings = _parse_settings(args.set, ARSConfig)
    for key in ("seed", "postprocess", "backend", "workers", "address"):
        if getattr(args, key) is not None:
            settings[key] = getattr(args, key)
    if args.epochs is not None:
        settings["epochs"] = args.epochs
    out = Path(args.out or f"runs/train/ars-{args.system.replace('/', '_')}-s{settings.get('seed', 0)}")
    try:
        ARSConfig(**settings).validate()
        found = newest_checkpoint([out / "checkpoint", out / "final"]) if args.resume else None
        if found is not None:
            agent = ARS.load(found, **settings)
            print(f"resuming {found} at epoch {agent.epoch}")
        elif args.init is not None:
            agent = ARS.load(args.init, env=args.system, **settings)
            print(f"starting from {args.init} (epoch {agent.epoch}); training to epoch {agent.config.epochs}")
        else:
            agent = ARS(args.system, ARSConfig(**settings))
            print(f"ARS on {args.system}: {agent.config.epochs} epochs, seed {agent.config.seed}, "
                  f"post-processor {agent.config.postprocess}, backend {agent.config.backend}")
        agent.learn(log_dir=out, progress=not args.quiet)
    except (TypeError, ValueError) as exc:
        raise SystemExit(f"error: {exc}")
    except CheckpointError as exc:
        raise SystemExit(f"error: {exc}")
    except FloatingPointError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    result = agent.evaluate(episodes=args.eval_episodes or agent.config.eval_episodes, measure=True)
    result.update({"command": args.command_line, "epochs": agent.epoch, "env_steps": agent.env_steps,
                   "train_wall_time_s": agent.wall_time})
    write_json(out / "eval.json", result)
    dims = result["mean_dimensions"]
    print(f"return over {result['episodes']} episodes: {result['mean_return']:.1f} +- {result['std_return']:.1f}; "
          f"mesh dimension lower {dims['mesh_lower']}, upper {dims['mesh_upper']}; "
          f"wrote {out}/final, progress.csv, eval.json")
    return 0


MESH_MAPS = {"rimless-wheel": "analytic rimless wheel on rough terrain (Byl & Tedrake 2009)",
             "drake-rimless-wheel": "Drake's RimlessWheel, apex found by a witness function"}


def cmd_mesh(args) -> int:
    """`hybridctl mesh MAP ...`: reachable-state mesh, transition matrix, MFPT report, Monte Carlo, figures."""
    import scipy.sparse as sp

    from ..analysis import (GaussianDisturbance, RimlessWheel, build_mesh, mesh_sizes, monte_carlo_mfpt,
                            reachable_dimension)
    from ..learn.checkpoint import write_json
    from .. import viz

    if args.map == "rimless-wheel":
        section_map = RimlessWheel()
    else:
        from ..drake import DrakeRimlessWheelMap
        section_map = DrakeRimlessWheelMap()
    try:
        slopes = GaussianDisturbance(args.slope_mean, args.slope_std, args.disturbances)
    except ValueError as exc:
        raise SystemExit(f"error: {exc}")
    seed = RimlessWheel().fixed_point(args.slope_mean)
    if not math.isfinite(seed):
        raise SystemExit(f"error: --slope-mean {args.slope_mean} has no rolling gait to seed the mesh from")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    mesh = build_mesh(section_map, [[seed]], slopes, args.box_size, max_states=args.max_states,
                      backend=args.backend, workers=args.workers, checkpoint=out / "mesh_checkpoint.npz",
                      resume=args.resume, progress=not args.quiet)
    report = {"command": args.command_line, "map": args.map, "seed_state": [seed], "mesh": mesh.summary(),
              "disturbance": {"slope_mean": args.slope_mean, "slope_std": args.slope_std, "count": args.disturbances}}
    if not mesh.complete:
        report["error"] = f"mesh incomplete at --max-states {args.max_states}: no transition matrix"
        write_json(out / "mfpt.json", report)
        print(report["error"])
        return 2
    T = mesh.transition_matrix()
    sp.save_npz(out / "transition_matrix.npz", T)
    mesh.save(out / "mesh.npz")
    result = mesh.mfpt()
    report["mfpt"] = {**result.report(), "from_seed": result.mean(mesh.seed_distribution())}
    if args.monte_carlo:
        mc = monte_carlo_mfpt(section_map, [[seed]], slopes, episodes=args.monte_carlo, seed=0)
        same = monte_carlo_mfpt(section_map, [[seed]], slopes.finite_set(), episodes=args.monte_carlo, seed=0)
        report["monte_carlo"] = {"continuous_disturbance": mc.summary(), "mesh_disturbance_set": same.summary()}
    viz.plot_transition_sparsity(T, path=out / "sparsity.png")
    viz.plot_cumulative_mass(T, path=out / "cumulative_mass.png")
    viz.plot_mesh_states(mesh, path=out / "states.png")
    if args.sizes:
        rows = mesh_sizes(section_map, [[seed]], slopes, sorted(set(args.sizes) | {args.box_size}),
                          max_states=args.max_states)
        report["mesh_sizes"] = rows
        if sum(r["complete"] for r in rows) >= 2:
            report["reachable_dimension"] = reachable_dimension(rows)
            viz.plot_mesh_sizes(rows, path=out / "mesh_sizes.png")
    write_json(out / "mfpt.json", report)
    line = f"{mesh.size} states; MFPT from the seed {report['mfpt']['from_seed']:.1f} steps, eigen estimate " \
           f"{report['mfpt']['eigen_estimate']:.1f}"
    if args.monte_carlo:
        lo, hi = report["monte_carlo"]["mesh_disturbance_set"]["interval95"]
        line += f"; Monte Carlo (same disturbances) {report['monte_carlo']['mesh_disturbance_set']['mean_steps_to_failure']:.1f} [{lo:.1f}, {hi:.1f}]"
    print(line)
    print(f"wrote {out}/mfpt.json, transition_matrix.npz, mesh.npz (ReachableMesh.load) and figures")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``hybridctl`` command."""
    from ..experiments import CONTROLLERS

    parser = argparse.ArgumentParser(prog="hybridctl", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("systems", help="list the benchmark systems")
    p.set_defaults(func=cmd_systems)

    controller_help = "controller: " + "; ".join(f"{k} = {v}" for k, v in CONTROLLERS.items())
    p = sub.add_parser("simulate", help="simulate one run of a system under a controller")
    p.add_argument("system")
    p.add_argument("--controller", default="energy", help=controller_help)
    p.add_argument("--x0", help="initial state, comma-separated; write --x0=-1.57,0,0,0 when it starts "
                   "with a minus (default: hanging down + 1e-3 rad)")
    p.add_argument("--duration", type=_positive(float), help="seconds (default: the spec's episode)")
    p.add_argument("--out", default="runs/simulate", help="output folder (default: runs/simulate)")
    p.add_argument("--no-html", action="store_true", help="skip the replay.html")
    p.add_argument("--meshcat", action="store_true", help="also show it live in meshcat (localhost)")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("balance-map", help="balanced fraction over a grid of rest states (thesis Fig. 3.6)")
    p.add_argument("system")
    p.add_argument("--controller", default="energy", help=controller_help)
    p.add_argument("--grid", type=_positive(int), default=41, help="grid points per axis (default 41, thesis)")
    p.add_argument("--duration", type=_positive(float), help="seconds per run (default: the spec's episode)")
    p.add_argument("--workers", type=_positive(int), help="processes (default: all cores)")
    p.add_argument("--out", default="runs/balance_map", help="output folder")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_balance_map)

    p = sub.add_parser("train", help="train SAC / Switched SAC (thesis Ch. 3) on a system, or ARS (Ch. 4) on an env")
    p.add_argument("algorithm", choices=["ssac", "sac", "ars"])
    p.add_argument("system", help="system name (ssac, sac); gymnasium env id or system name (ars)")
    p.add_argument("--steps", type=_positive(int), help="total env steps (default 2e6, thesis)")
    p.add_argument("--epochs", type=_positive(int), help="ars: total epochs (default 1000, thesis)")
    p.add_argument("--postprocess", help="ars: reward post-processor: identity, mesh-lower, mesh-upper, "
                   "mesh-mean, madogram, variogram (thesis Sec. 4.2.5)")
    p.add_argument("--init", help="ars: start from this checkpoint's policy and normalisation (the thesis "
                   "trains 750 identity epochs, then 250 with post-processing)")
    p.add_argument("--backend", choices=["serial", "processes", "ray"], help="ars: rollout backend (default processes)")
    p.add_argument("--workers", type=_positive(int), help="ars: rollout workers (default: all cores)")
    p.add_argument("--address", help="ars: Ray cluster address for --backend ray (default: a local instance)")
    p.add_argument("--seed", type=int, help="seed (default 0)")
    p.add_argument("--variant", choices=["hybridctl", "paper", "author"], default="hybridctl",
                   help="SSAC settings: hybridctl's defaults, the thesis' throughout, or the author's code")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a config field, e.g. --set polyak=0.9 (repeatable)")
    p.add_argument("--out", help="run folder (default runs/train/ALGO-SYSTEM-sSEED)")
    p.add_argument("--resume", action="store_true", help="continue from the run folder's newest checkpoint")
    p.add_argument("--eval-episodes", type=_positive(int), help="episodes in eval.json (default 100; ars 5)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("mesh", help="reachable-state mesh and mean first passage time (thesis Ch. 5)")
    p.add_argument("map", choices=sorted(MESH_MAPS), help="; ".join(f"{k}: {v}" for k, v in MESH_MAPS.items()))
    p.add_argument("--box-size", type=_positive(float), default=1e-3, help="box side (default 1e-3)")
    p.add_argument("--slope-mean", type=float, default=0.15, help="mean terrain slope, rad (default 0.15)")
    p.add_argument("--slope-std", type=_positive(float), default=0.06, help="slope std, rad (default 0.06)")
    p.add_argument("--disturbances", type=_positive(int), default=25, help="slope quantiles in the mesh (default 25)")
    p.add_argument("--max-states", type=_positive(int), default=1_000_000, help="cap on mesh states")
    p.add_argument("--monte-carlo", type=int, default=0, metavar="EPISODES",
                   help="also estimate the MFPT by Monte Carlo on the true map")
    p.add_argument("--sizes", type=_positive(float), nargs="*", help="also mesh at these box sizes (Table 5.1)")
    p.add_argument("--backend", choices=["serial", "processes", "ray"], default="serial")
    p.add_argument("--workers", type=_positive(int))
    p.add_argument("--resume", action="store_true", help="continue from out/mesh_checkpoint.npz")
    p.add_argument("--out", default="runs/mesh", help="output folder")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_mesh)

    p = sub.add_parser("demo", help="what `make demo` runs")
    p.add_argument("--out", default="runs/demo")
    p.add_argument("--grid", type=_positive(int), default=11, help="balance-map grid (default 11)")
    p.add_argument("--meshcat", action="store_true", help="also show the run live in meshcat")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``hybridctl`` console script."""
    import torch

    torch.set_num_threads(1)  # small networks and single states: threads only add overhead
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    args.command_line = "hybridctl " + " ".join(argv)
    return args.func(args)

