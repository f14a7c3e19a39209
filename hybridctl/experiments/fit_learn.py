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

import dataclasses
import math
import time
from pathlib import Path

import numpy as np

from .fit_stages import FitError, FitSettings, bar
from .fitted import CHECKPOINT, CLONE, GATES

__all__ = ["stage_swingup", "stage_learned_gate", "stage_learner", "stage_verify", "write_replay", "LEARNER_SETTINGS"]

LEARNER_SETTINGS = {"gate_lqr_labels": "rollout", "checkpoint_minutes": 1.0}
"""SSAC's settings fit changes: its gate's LQR-active states labelled by LQR rollouts, not by the episode's
outcome (the episode labels of thesis Alg. 4 made the furuta's and the reaction wheel's gates hand back or never
hand over: results/your_robot/learned_gate/diagnosis.json); a checkpoint every minute (a killed fit loses little)."""


def stage_swingup(model_file: str, options: dict, earlier: dict, s: FitSettings, progress: bool, *,
                  system, folder: Path, **_) -> dict:
    """The collocation swing-up from rest; the learner's decision period (the longest at which the TVLQR-tracked
    swing-up still balances, measured), discount and episode from it; the kept tracking table for the clone."""
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
    tracked = {}
    if found:
        spacing = duration / (s.swingup_knots - 1)
        upper = min(max(spacing, s.decision_min), s.decision_max)
        episode = float(math.ceil(duration + s.horizon))
        tracked, tables = _screen_tracking(system, trajectory, _decision_periods(hold, s.decision_min, upper),
                                           episode, s, options["seed"], folder, progress)
        best = max(tracked.values())
        if best > 0:
            period = max(p for p, fraction in tracked.items() if fraction >= s.track_keep * best)
            period_why = (f"the longest decision period (multiples of the {hold:g} s hold that divide a second, from "
                          f"{s.decision_min:g} s to the collocation's knot spacing {spacing:.4g} s) at which the "
                          f"TVLQR-tracked swing-up balances at least {s.track_keep:g} of the best period's share of "
                          f"{s.track_samples} starts: " + ", ".join(f"{p:g} s {f:.2f}" for p, f in tracked.items()))
        else:
            period = _decision_period(upper, hold)
            period_why = (f"the tracked swing-up balanced no start at any period tried "
                          f"({', '.join(f'{p:g} s' for p in tracked)}): the collocation's knot spacing {spacing:.4g} s "
                          f"(a {duration:g} s swing-up over {s.swingup_knots} knots) within [{s.decision_min:g}, "
                          f"{s.decision_max:g}] s, rounded down to a multiple of the {hold:g} s hold that divides a "
                          f"second")
        gamma = min(max(1.0 - period / duration, s.gamma_range[0]), s.gamma_range[1])
        why = {"period": period_why,
               "gamma": (f"1 - period / T = 1 - {period:g} / {duration:g} (the discount looks one swing-up ahead), "
                         f"within {list(s.gamma_range)}"),
               "episode": (f"the {duration:g} s swing-up plus the {s.horizon:g} s LQR horizon of the gate labels, "
                           f"rounded up")}
        if best > 0:
            _save_tracking(tables[period], folder)
    else:
        period = _decision_period(0.05, hold)
        gamma, episode = 0.99, 10.0
        why = {k: f"no collocation swing-up ({summary['error']}): docs/your_robot.md's measured values"
               for k in ("period", "gamma", "episode")}
    return {"found": found, "duration_s": duration, "trajectory": summary, "swingup_period": period,
            "gamma": gamma, "episode_s": episode, "why": why,
            "tracked": {f"{p:g}": f for p, f in tracked.items()},
            "tracked_fraction": tracked.get(period, 0.0), "tracking_table": TRACKING_TABLE if tracked.get(period)
            else None}


TRACKING_TABLE = "trajopt/tracking-kept.npz"
"""The TVLQR table at the kept decision period, in the fit's folder: what the clone stage tracks."""


def _decision_periods(hold: float, shortest: float, longest: float) -> list[float]:
    """Multiples of ``hold`` that divide one second, from ``shortest`` to ``longest`` (at least the longest such
    multiple up to ``longest``)."""
    periods = []
    for k in range(1, int(longest / hold + 1e-9) + 1):
        period = float(round(k * hold, 12))
        if period >= shortest - 1e-12 and abs(round(1.0 / period) * period - 1.0) < 1e-9:
            periods.append(period)
    return periods or [_decision_period(longest, hold)]


def _screen_tracking(system, trajectory, periods: list[float], duration: float, s: FitSettings, seed: int,
                     folder: Path, progress: bool) -> tuple[dict[float, float], dict]:
    """The share of ``s.track_samples`` starts from the spec's start range that the TVLQR-tracked swing-up (held for
    each period, the cost-to-go gate and the LQR taking over) balances within ``duration``, and each period's
    TVLQR table (the periods whose solve failed have none)."""
    from ..drake.trajopt import TrajoptError, tracking_gains
    from ..learn.clone import TrackingSwingup, balanced_fraction
    from ..systems.switched import CostToGoGate, SwitchedController

    starts = system.sample_initial_states(s.track_samples, np.random.default_rng(seed))
    fractions, tables = {}, {}
    progress_bar = bar(len(periods), "swingup: tracked at each decision period", progress)
    for period in periods:
        try:
            gains = tracking_gains(system, trajectory, period, cache_dir=folder / "trajopt")
        except TrajoptError:
            fractions[period] = 0.0
        else:
            tables[period] = gains
            controller = SwitchedController.for_system(system, swingup=TrackingSwingup(gains, system),
                                                       gate=CostToGoGate(system), decision_period=period)
            fractions[period] = balanced_fraction(system, controller, starts, duration)["fraction"]
        progress_bar.update()
    progress_bar.close()
    return fractions, tables


def _save_tracking(gains, folder: Path) -> None:
    """Write the kept period's TVLQR table to :data:`TRACKING_TABLE` (numbers only; read without pickle)."""
    from .. import io

    period = gains.period
    arrays = {name: np.asarray(getattr(gains, name), dtype=float) for name in ("x0", "u0", "K", "k0")}
    path = folder / TRACKING_TABLE
    path.parent.mkdir(parents=True, exist_ok=True)
    io.atomic_write(path, lambda f: np.savez(f, period=np.float64(period), **arrays))


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
    from ..learn.gate import BASIN_GATE_CONFIG, learned_gate_from_basin

    progress_bar = bar(1, "learned gate: warm start from the basin", progress)
    kwargs = {} if s.learned_gate_samples is None else {"samples": s.learned_gate_samples}
    if s.learned_gate_fit_steps is not None:
        kwargs["config"] = dataclasses.replace(BASIN_GATE_CONFIG, warm_fit_steps=s.learned_gate_fit_steps)
    _, info = learned_gate_from_basin(system, seed=options["seed"], basin=earlier["gate"]["basin"], **kwargs)
    progress_bar.update()
    progress_bar.close()
    spread_why = (f"learned_gate_from_basin: the box around the LQR's measured basin V < {info['level']:.4g} "
                  f"(near) and 4 times it (far)")
    return {"works": bool(info["works"]), "info": info, "warm_near": info["near"], "warm_far": info["far"],
            "spread_why": spread_why,
            "why": (f"held-out: {info['criterion']}" + (": met" if info["works"] else
                    ": not met; the verification's maps decide between it and the cost-to-go gate"))}


def _verify_estimate(system, s: FitSettings, resources: dict | None = None) -> tuple[dict, float]:
    """(seconds of one torch and one Drake balance map of the LQR here, verify's estimate from them): verify runs
    four torch maps and two Drake maps of the learned controller, whose network costs about as much again. Each
    map runs where verify's does (``resources``: the torch device; the Drake maps' backend, workers, address)."""
    from .balance_map import balance_map

    resources = resources or {}
    duration = s.verify_duration or system.episode_duration
    where = {"torch": {"device": resources.get("device")},
             "drake": {k: resources.get(k) for k in ("backend", "workers", "address")}}
    seconds = []
    for engine in ("torch", "drake"):
        t0 = time.perf_counter()
        balance_map(system, "lqr", grid=s.verify_grid, duration=duration, engine=engine, progress=False,
                    **where[engine])
        seconds.append(time.perf_counter() - t0)
    one = {"torch_map_s": seconds[0], "drake_map_s": seconds[1]}
    return one, s.verify_reserve * 2 * (4 * seconds[0] + 2 * seconds[1])


def stage_learner(model_file: str, options: dict, earlier: dict, s: FitSettings, progress: bool, *,
                  system, folder: Path, spec_file: Path, deadline: float, resources: dict | None = None, **_) -> dict:
    """SSAC on the fitted spec until the budget left (less verify's measured estimate) is spent or
    ``s.learner_max_steps`` are done; a stopped run writes ``final/`` and a resumed fit continues its newest
    checkpoint."""
    from ..learn.callbacks import Callback
    from .training import train_and_evaluate

    plan = earlier["swingup"]
    maps_s, reserve = _verify_estimate(system, s, resources)
    run = folder / "learner"
    before = _steps_done(run)
    stop_at = deadline - reserve
    if time.monotonic() >= stop_at:
        raise FitError(f"the budget leaves {deadline - time.monotonic():.0f} s, not more than the {reserve:.0f} s the "
                       f"verification needs (an LQR map took {maps_s['torch_map_s']:.1f} s in torch, "
                       f"{maps_s['drake_map_s']:.1f} s in Drake); rerun with --resume and a larger --budget "
                       f"(learner stage: {before} steps reached)")

    class StopAtBudget(Callback):
        """Stop the run once the budget left for the learner is spent, or (``s.learner_stop_full``) after a
        checkpoint whose torch maps balance every start."""
        checks: list[dict] = []
        full = False

        def on_step(self, learner):
            return False if self.full or time.monotonic() >= stop_at else None

        def on_training_start(self, learner):
            # a run from the clone: its maps first, before any policy step (the actor waits out actor_delay) could
            # move it off them (the cart-pole's SSAC fell from 1.00 to 0.00 training success by its first checkpoint)
            if s.learner_stop_full and init is not None:
                self._check(learner, folder / CLONE, CLONE)

        def on_checkpoint(self, learner, path):
            if s.learner_stop_full and path.name != "final":
                self._check(learner, path, path.name)

        def _check(self, learner, path, name):
            self.checks = [*self.checks, {"steps": int(learner.num_timesteps), "checkpoint": name,
                                          **checkpoint_maps(system, path, s, resources)}]
            self.full = self.checks[-1]["full"]

    stopper = StopAtBudget()
    t0 = time.monotonic()
    clone = earlier.get("clone") or {}
    from_clone = bool(clone.get("cloned") and clone.get("starts_ssac", True))
    init = folder / CLONE if from_clone and before == 0 else None   # a new run starts from a clone that balances
    record = train_and_evaluate("ssac", str(spec_file), out=run,
                                settings=learner_settings(options, plan, s, cloned=from_clone,
                                                          device=(resources or {}).get("device")),
                                resume=run.exists(), init=init, eval_episodes=s.eval_episodes, progress=progress,
                                report=None, command=options.get("command"), callback=stopper).evaluation
    steps = int(record.get("env_steps", 0))
    full, checks = stopper.full, stopper.checks
    stopped = steps < s.learner_max_steps and not full
    if full and checks[-1]["checkpoint"] == CLONE:
        ending = (f"stopped at its first step: the clone it started from balances every start of the torch maps "
                  f"(FitSettings.learner_stop_full), and no policy step came before the stop (actor_delay)")
    elif full:
        ending = (f"stopped after the checkpoint of {checks[-1]['steps']} steps, whose torch maps balance every "
                  f"start (FitSettings.learner_stop_full)")
    elif stopped:
        ending = f"stopped when the budget left only the {reserve:.0f} s kept for the verification"
    else:
        ending = f"all {s.learner_max_steps} (FitSettings.learner_max_steps)"
    return {"algorithm": "ssac", "run": "learner", "checkpoint": CHECKPOINT, "steps": steps,
            "steps_before": before, "seconds": time.monotonic() - t0, "stopped_by_budget": stopped,
            "stopped_full": full, "map_checks": checks,
            "eval_success_rate": record.get("success_rate"), "eval_mean_return": record.get("mean_return"),
            "verify_reserve_s": reserve, "lqr_maps_s": maps_s,
            "started_from": None if init is None else CLONE,
            "why": (f"SSAC (thesis Ch. 3, its gate's LQR-active states labelled by LQR rollouts) on system.toml"
                    + (" from the cloned swing-up, " if init is not None else ", ") +
                    f"{steps} env steps: " + ending)}


def checkpoint_maps(system, path: Path, s: FitSettings, resources: dict | None = None,
                    gate: str = "learned") -> dict:
    """The torch maps of verify's two grids (:func:`verify_maps`) for the checkpoint at ``path`` with ``gate`` (a
    key of :data:`GATES`): each map's balanced fraction, whether both balance every start (``full``) and the
    seconds they took. The learner's stop rule and the verification both measure through it."""
    from .balance_map import balance_map

    t0 = time.perf_counter()
    fractions = {name: balance_map(system, f"{GATES[gate]}:{path}", grid=s.verify_grid, axes=axes,
                                   ranges=ranges, engine="torch", progress=False, duration=s.verify_duration,
                                   device=(resources or {}).get("device")).fraction
                 for name, (axes, ranges) in verify_maps(system, s).items()}
    return {**fractions, "full": all(f == 1.0 for f in fractions.values()), "seconds": time.perf_counter() - t0}


def verify_maps(system, s: FitSettings) -> dict:
    """Name -> (axes, ranges) of the verification's two maps: starts about rest and over the spec's start range."""
    from .balance_map import grid_axes, near_hanging_down

    return {"rest": near_hanging_down(system, s.verify_near), "start_range": grid_axes(system)}


CLONED_START = {"exploration_steps": 0, "actor_delay": 50_000}
"""SSAC's settings when it starts from the clone: the clone explores (its stochastic actions, not uniform random
ones), and the critics learn its values for SAC's own warm-up length (50,000 steps) before the first policy step.
Measured on the long-pole cart (runs/fit-v2, 100,000 steps): without the delay the clone's training success fell
from 1.00 to 0.03 within 5,000 steps; with it, 1.00 for the 50,000 critic-only steps, then 0.86, 0.54, 0.26 within
15,000 more (the policy steps on critics fitted to the clone's narrow data). The verification keeps the clone
itself when SSAC does not improve it."""


def learner_settings(options: dict, plan: dict, s: FitSettings, cloned: bool = False, device: str | None = None) -> dict:
    """SSAC's settings in fit (the clone stage builds its learner with the same): the seed, the swing-up stage's
    discount, the step budget, :data:`LEARNER_SETTINGS`, :data:`CLONED_START` when it starts from the clone, and
    ``s.learner_settings`` (and the torch ``device``, where given)."""
    return {"seed": options["seed"], "gamma": plan["gamma"], "total_steps": int(s.learner_max_steps),
            **LEARNER_SETTINGS, **(CLONED_START if cloned else {}), **s.learner_settings,
            **({"device": device} if device is not None else {})}


def _steps_done(run: Path) -> int:
    """Env steps of the newest checkpoint in the learner's run folder (0: none yet)."""
    from .. import io
    from .training import newest_run_checkpoint

    found = newest_run_checkpoint(run) if run.is_dir() else None
    if found is None or not (found / "progress.json").is_file():
        return 0
    return int(io.read_json(found / "progress.json").get("env_steps", 0))


def stage_verify(model_file: str, options: dict, earlier: dict, s: FitSettings, progress: bool, *,
                 system, folder: Path, resources: dict | None = None, **_) -> dict:
    """Each candidate checkpoint's maps with both gates in torch (the learner's run and, where there is one, the
    clone it started from): a gate is kept per checkpoint by them, and the checkpoint whose kept gate balances most
    starts (ties: the learner's); then the kept controller's maps in Drake."""
    from .balance_map import balance_map

    resources = resources or {}
    maps = verify_maps(system, s)
    candidates = [CHECKPOINT] + ([CLONE] if (earlier.get("clone") or {}).get("cloned") else [])
    def key(candidate: str, gate: str, name: str) -> str:   # the learner's maps keep their names of old
        return f"{gate}/{name}" if candidate == CHECKPOINT else f"{candidate}/{gate}/{name}"

    torch_maps, kept_gates, whys = {}, {}, {}
    for candidate in candidates:
        for gate in GATES:
            measured = checkpoint_maps(system, folder / candidate, s, resources, gate=gate)
            for name in maps:
                torch_maps[key(candidate, gate, name)] = measured[name]
        score = {gate: tuple(torch_maps[key(candidate, gate, name)] for name in maps) for gate in GATES}
        kept_gates[candidate], whys[candidate] = _keep_gate(score, list(maps), s.gate_tolerance)
    totals = {c: sum(torch_maps[key(c, kept_gates[c], name)] for name in maps) for c in candidates}
    checkpoint = max(candidates, key=lambda c: (totals[c], c == CHECKPOINT))
    kept, why = kept_gates[checkpoint], whys[checkpoint]
    checkpoint_why = (f"{checkpoint} with its {kept} gate balances {totals[checkpoint]:.3f} of the two torch maps "
                      f"together" + ("" if len(candidates) == 1 else ", against " + ", ".join(
                          f"{c} {totals[c]:.3f}" for c in candidates if c != checkpoint) + " (ties: the learner's)"))
    drake_maps = {}
    progress_bar = bar(len(maps), "verify: Drake balance maps", progress)
    for name, (axes, ranges) in maps.items():
        result = balance_map(system, f"{GATES[kept]}:{folder / checkpoint}", grid=s.verify_grid, axes=axes,
                             ranges=ranges, engine="drake", progress=False, duration=s.verify_duration,
                             backend=resources.get("backend"), workers=resources.get("workers"),
                             address=resources.get("address"))
        result.save(folder / "maps" / name)
        drake_maps[name] = {"balanced_fraction": result.fraction, "balanced": int(result.balanced.sum()),
                            "starts": int(result.balanced.size), "axes": list(result.axes),
                            "ranges": [list(r) for r in ranges], "seconds": result.wall_time,
                            "plot": f"maps/{name}/balance_map.png"}
        progress_bar.update()
    progress_bar.close()
    return {"gate": kept, "gate_why": why, "checkpoint": checkpoint, "checkpoint_why": checkpoint_why,
            "candidates": candidates, "torch_maps": torch_maps, "drake_maps": drake_maps,
            "controller": f"{GATES[kept]}:{checkpoint}"}


def _keep_gate(score: dict, names: list[str], tolerance: float) -> tuple[str, str]:
    """The learned gate unless one of its torch maps balances ``tolerance`` fewer starts than the cost-to-go gate's."""
    worse = [f"{name} {score['learned'][i]:.3f} < {score['cost-to-go'][i]:.3f} - {tolerance:g}"
             for i, name in enumerate(names) if score["learned"][i] < score["cost-to-go"][i] - tolerance]
    if worse:
        return "cost-to-go", (f"the learned gate measurably fails: its torch maps balance fewer starts than the "
                              f"cost-to-go gate's ({'; '.join(worse)})")
    return "learned", (f"the learned gate's torch maps {score['learned']} (rest, start range) are within "
                       f"{tolerance:g} of the cost-to-go gate's {score['cost-to-go']} or above")


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
