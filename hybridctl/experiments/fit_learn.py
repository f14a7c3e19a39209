"""The learned stages of ``hybridctl fit``: the swing-up plan, the learned gate, the learner and the verification.

- ``swingup``: Drake's direct-collocation swing-up from rest (:func:`hybridctl.drake.trajopt.swingup_trajectory`);
  its duration T sets the learner's decision period (the collocation's knot spacing T / (knots - 1), within
  [decision_min, decision_max], a multiple of the LQR hold), discount (1 - period / T: the discount's horizon
  is the swing-up) and episode length (T plus the gate labels' LQR horizon, rounded up to a second).
- ``learned_gate``: the thesis' learned gate, its warm-start sampling derived from the measured LQR basin
  (:func:`hybridctl.learn.gate.learned_gate_from_basin`); its held-out hand-overs decide whether the learner
  trains with it, and the spreads go into the spec (``gate.warm_near`` / ``gate.warm_far``).
- ``learner``: SSAC (thesis Ch. 3) on the fitted spec until the budget left is spent (resumable).
- ``verify``: balance maps of starts around rest and over the spec's start range for the learned and the
  cost-to-go gate in batched torch (the gate is kept by them), then the kept controller's maps in Drake.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from .fit_stages import FitError, FitSettings, bar
from .fitted import CHECKPOINT, GATES

__all__ = ["stage_swingup", "stage_learned_gate", "stage_learner", "stage_verify", "write_replay", "LEARNER_SETTINGS"]

LEARNER_SETTINGS = {"gate_lqr_labels": "rollout", "checkpoint_minutes": 1.0}
"""SSAC's settings fit changes: its gate's LQR-active states labelled by LQR rollouts, not by the episode's
outcome (the episode labels of thesis Alg. 4 made the furuta's and the reaction wheel's gates hand back or never
hand over: results/your_robot/learned_gate/diagnosis.json); a checkpoint every minute (a killed fit loses little)."""


def stage_swingup(model_file: str, options: dict, earlier: dict, s: FitSettings, progress: bool, *,
                  system, folder: Path, **_) -> dict:
    """The collocation swing-up from rest, and the learner's decision period, discount and episode from it."""
    from ..drake.trajopt import TrajoptError, swingup_trajectory

    hold = system.control_period
    progress_bar = bar(1, "swingup: direct collocation", progress)
    try:
        trajectory = swingup_trajectory(system, knots=s.swingup_knots, cache_dir=folder / "trajopt")
    except TrajoptError as exc:
        progress_bar.close()
        duration, found, summary = None, False, {"error": str(exc).splitlines()[0]}
    else:
        progress_bar.update()
        progress_bar.close()
        duration, found, summary = trajectory.duration, True, trajectory.summary()
    if found:
        spacing = duration / (s.swingup_knots - 1)
        period = _decision_period(min(max(spacing, s.decision_min), s.decision_max), hold)
        gamma = min(max(1.0 - period / duration, s.gamma_range[0]), s.gamma_range[1])
        episode = float(math.ceil(duration + s.horizon))
        why = {"period": (f"the collocation's knot spacing {spacing:.4g} s (a {duration:g} s swing-up over "
                          f"{s.swingup_knots} knots) within [{s.decision_min:g}, {s.decision_max:g}] s, rounded down "
                          f"to a multiple of the {hold:g} s hold that divides a second"),
               "gamma": (f"1 - period / T = 1 - {period:g} / {duration:g} (the discount looks one swing-up ahead), "
                         f"within {list(s.gamma_range)}"),
               "episode": (f"the {duration:g} s swing-up plus the {s.horizon:g} s LQR horizon of the gate labels, "
                           f"rounded up")}
    else:
        period = _decision_period(0.05, hold)
        gamma, episode = 0.99, 10.0
        why = {k: f"no collocation swing-up ({summary['error']}): docs/your_robot.md's measured values"
               for k in ("period", "gamma", "episode")}
    return {"found": found, "duration_s": duration, "trajectory": summary, "swingup_period": period,
            "gamma": gamma, "episode_s": episode, "why": why}


def _decision_period(at_most: float, hold: float) -> float:
    """The longest multiple of ``hold`` up to ``at_most`` that divides one second (so it divides the whole-second
    episodes), at least ``hold`` itself."""
    best = hold
    for k in range(1, int(at_most / hold + 1e-9) + 1):
        period = k * hold
        if abs(round(1.0 / period) * period - 1.0) < 1e-9:
            best = period
    return float(round(best, 12))


def stage_learned_gate(model_file: str, options: dict, earlier: dict, s: FitSettings, progress: bool, *,
                       system, **_) -> dict:
    """The learned gate from the measured basin: does it hand over on held-out in-basin states, safely?"""
    from ..learn.gate import learned_gate_from_basin

    progress_bar = bar(1, "learned gate: warm start from the basin", progress)
    kwargs = {} if s.learned_gate_samples is None else {"samples": s.learned_gate_samples}
    _, info = learned_gate_from_basin(system, seed=options["seed"], basin=earlier["gate"]["basin"], **kwargs)
    progress_bar.update()
    progress_bar.close()
    spread_why = (f"learned_gate_from_basin: the box around the LQR's measured basin V < {info['level']:.4g} "
                  f"(near) and 4 times it (far)")
    return {"works": bool(info["works"]), "info": info, "warm_near": info["near"], "warm_far": info["far"],
            "spread_why": spread_why,
            "why": (f"held-out: {info['criterion']}" + (": met" if info["works"] else
                    ": not met; the verification's maps decide between it and the cost-to-go gate"))}


def _verify_estimate(system, s: FitSettings) -> tuple[float, float]:
    """(seconds of one torch and one Drake balance map of the LQR here, verify's estimate from them): verify runs
    four torch maps and two Drake maps of the learned controller, whose network costs about as much again."""
    from .balance_map import balance_map

    duration = s.verify_duration or system.episode_duration
    seconds = []
    for engine in ("torch", "drake"):
        t0 = time.perf_counter()
        balance_map(system, "lqr", grid=s.verify_grid, duration=duration, engine=engine, progress=False)
        seconds.append(time.perf_counter() - t0)
    one = {"torch_map_s": seconds[0], "drake_map_s": seconds[1]}
    return one, s.verify_reserve * 2 * (4 * seconds[0] + 2 * seconds[1])


def stage_learner(model_file: str, options: dict, earlier: dict, s: FitSettings, progress: bool, *,
                  system, folder: Path, spec_file: Path, deadline: float, **_) -> dict:
    """SSAC on the fitted spec until the budget left (less verify's measured estimate) is spent or
    ``s.learner_max_steps`` are done; a stopped run writes ``final/`` and a resumed fit continues its newest
    checkpoint."""
    from ..learn.callbacks import Callback
    from .training import train_and_evaluate

    plan = earlier["swingup"]
    maps_s, reserve = _verify_estimate(system, s)
    run = folder / "learner"
    before = _steps_done(run)
    stop_at = deadline - reserve
    if time.monotonic() >= stop_at:
        raise FitError(f"the budget leaves {deadline - time.monotonic():.0f} s, not more than the {reserve:.0f} s the "
                       f"verification needs (an LQR map took {maps_s['torch_map_s']:.1f} s in torch, "
                       f"{maps_s['drake_map_s']:.1f} s in Drake); rerun with --resume and a larger --budget "
                       f"(learner stage: {before} steps reached)")

    class StopAtBudget(Callback):
        """Stop the run once the budget left for the learner is spent."""
        def on_step(self, learner):
            return False if time.monotonic() >= stop_at else None

    t0 = time.monotonic()
    settings = {"seed": options["seed"], "gamma": plan["gamma"], "total_steps": int(s.learner_max_steps),
                **LEARNER_SETTINGS, **s.learner_settings}
    record = train_and_evaluate("ssac", str(spec_file), out=run, settings=settings, resume=run.exists(),
                                eval_episodes=s.eval_episodes, progress=progress, report=None,
                                command=options.get("command"), callback=StopAtBudget()).evaluation
    steps = int(record.get("env_steps", 0))
    stopped = steps < s.learner_max_steps
    return {"algorithm": "ssac", "run": "learner", "checkpoint": CHECKPOINT, "steps": steps,
            "steps_before": before, "seconds": time.monotonic() - t0, "stopped_by_budget": stopped,
            "eval_success_rate": record.get("success_rate"), "eval_mean_return": record.get("mean_return"),
            "verify_reserve_s": reserve, "lqr_maps_s": maps_s,
            "why": (f"SSAC (thesis Ch. 3, its gate's LQR-active states labelled by LQR rollouts) on system.toml, "
                    f"{steps} env steps: " + (f"stopped when the budget left only the {reserve:.0f} s kept for the "
                                              f"verification" if stopped else
                                              f"all {s.learner_max_steps} (FitSettings.learner_max_steps)"))}


def _steps_done(run: Path) -> int:
    """Env steps of the newest checkpoint in the learner's run folder (0: none yet)."""
    from .. import io
    from .training import newest_run_checkpoint

    found = newest_run_checkpoint(run) if run.is_dir() else None
    if found is None or not (found / "progress.json").is_file():
        return 0
    return int(io.read_json(found / "progress.json").get("env_steps", 0))


def stage_verify(model_file: str, options: dict, earlier: dict, s: FitSettings, progress: bool, *,
                 system, folder: Path, **_) -> dict:
    """Both gates' maps in torch (the gate is kept by them), then the kept controller's maps in Drake."""
    from .balance_map import balance_map, grid_axes, near_hanging_down

    checkpoint = str(folder / CHECKPOINT)
    maps = {"rest": near_hanging_down(system, s.verify_near), "start_range": grid_axes(system)}
    torch_maps = {}
    for gate in GATES:
        for name, (axes, ranges) in maps.items():
            result = balance_map(system, f"{GATES[gate]}:{checkpoint}", grid=s.verify_grid, axes=axes,
                                 ranges=ranges, engine="torch", progress=False, duration=s.verify_duration)
            torch_maps[f"{gate}/{name}"] = result.fraction
    score = {gate: (torch_maps[f"{gate}/rest"], torch_maps[f"{gate}/start_range"]) for gate in GATES}
    worse = [f"{name} {score['learned'][i]:.3f} < {score['cost-to-go'][i]:.3f} - {s.gate_tolerance:g}"
             for i, name in enumerate(maps) if score["learned"][i] < score["cost-to-go"][i] - s.gate_tolerance]
    kept = "cost-to-go" if worse else "learned"
    if worse:
        why = (f"the learned gate measurably fails: its torch maps balance fewer starts than the cost-to-go "
               f"gate's ({'; '.join(worse)})")
    else:
        why = (f"the learned gate's torch maps {score['learned']} (rest, start range) are within "
               f"{s.gate_tolerance:g} of the cost-to-go gate's {score['cost-to-go']} or above")
    drake_maps = {}
    progress_bar = bar(len(maps), "verify: Drake balance maps", progress)
    for name, (axes, ranges) in maps.items():
        result = balance_map(system, f"{GATES[kept]}:{checkpoint}", grid=s.verify_grid, axes=axes, ranges=ranges,
                             engine="drake", progress=False, duration=s.verify_duration)
        result.save(folder / "maps" / name)
        drake_maps[name] = {"balanced_fraction": result.fraction, "balanced": int(result.balanced.sum()),
                            "starts": int(result.balanced.size), "axes": list(result.axes),
                            "ranges": [list(r) for r in ranges], "seconds": result.wall_time,
                            "plot": f"maps/{name}/balance_map.png"}
        progress_bar.update()
    progress_bar.close()
    return {"gate": kept, "gate_why": why, "torch_maps": torch_maps, "drake_maps": drake_maps,
            "controller": f"{GATES[kept]}:{CHECKPOINT}"}


def write_replay(system, folder: Path, controller: str) -> dict:
    """``replay.html`` (and ``replay.json``'s summary) of the fitted controller in Drake from hanging down."""
    import json

    from .. import io
    from ..drake import build_hybrid_diagram, simulate
    from ..viz import replay_html
    from .controllers import controller_parts

    diagram = build_hybrid_diagram(system, controller_parts(system, controller))
    trajectory = simulate(diagram, system.nudged_nominal_state(), system.episode_duration)
    summary = trajectory.summary()
    if len(trajectory.t) >= 2:
        replay_html(system, trajectory.t, trajectory.x, path=folder / "replay.html")
    io.atomic_write_text(folder / "replay.json", json.dumps(io.to_jsonable(summary), indent=1))
    return summary
