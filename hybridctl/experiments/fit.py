"""``hybridctl fit MODEL_FILE --out DIR``: a complete spec and a learned switched controller from a model file alone.

The stages, in order; each measures what it chooses and records why (``report.json``):

- ``model``: the actuators and their effort limit (none: one line asking for ``--action-limit``); the
  equilibria over the revolute coordinates (every combination of 0 and pi, refined by
  :func:`hybridctl.systems.nearest_equilibrium`, prismatic coordinates at 0); ``goal="auto"`` keeps the one
  of highest potential energy, the rest state the lowest.
- ``lqr``: the control hold, the largest multiple of the integration step at which the saturated LQR still
  balances at least ``hold_keep`` of the samples it balances at the finest hold; then Q and R, screened
  over ``qr_family`` at that hold, the pair with the largest balanced fraction kept.
- ``integrator``: the cheapest integrator (Euler or Heun, a step dividing the hold) that keeps the positions
  within ``step_tolerance`` of a 4x finer Heun reference and the LQR's balanced share.
- ``gate``: the cost-to-go gate's scale V* / ln(1 / gate.on) from the LQR's basin level V*
  (:func:`hybridctl.learn.gate.measure_basin`).
- ``reward``: the tip height of the body that rises most from rest to goal (thesis eq. 3.1).
- ``swingup``, ``learned_gate``, ``learner``, ``verify``: :mod:`hybridctl.experiments.fit_learn` (the collocation
  swing-up, tracked by TVLQR, sets the learner's periods; the learned gate's sampling comes from the measured
  basin; SSAC in the budget; balance maps in torch and Drake keep a checkpoint and a gate).
- ``clone``: :mod:`hybridctl.experiments.fit_clone` (the tracked swing-up cloned into SSAC's actor, DART and
  DAgger; SSAC starts from it, and the verification may keep the clone itself).

Each stage's result is cached as ``DIR/stages/NAME.json`` (atomic) with the inputs it was computed from (the
model file's sha256, the options, the settings, the earlier stages' results); ``resume=True`` reuses a stage
whose inputs match, and the learner continues its own newest checkpoint (a learner or clone folder made on other
inputs, or found by a fit that is not a resume, moves to ``DIR/stale/``, kept). ``DIR/report.json`` lists every stage
(what was tried, what was kept and why, seconds) and is written after each stage, so a run stopped by bad input
keeps what it had. ``DIR/system.toml`` is the complete spec; ``fitted:DIR`` names the controller.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import io, limits
from ..systems import System, load
from . import fit_clone, fit_learn
from .fitted import CHECKPOINT, CLONE, GATES, fitted_controller
from .fit_stages import (FitError, FitSettings, build_system, settings_dict, stage_gate, stage_integrator, stage_lqr,
                         stage_model, stage_reward)

__all__ = ["fit", "FitResult", "FitError", "FitSettings", "STAGES", "OUTPUTS", "NOT_YET_BUILT", "LEARNERS",
           "fitted_controller"]

STAGES = ("model", "lqr", "integrator", "gate", "reward", "swingup", "learned_gate", "clone", "learner", "verify")
"""The stages, in order."""
CLASSICAL = STAGES[:5]
"""What ``learner=None`` runs: a spec and the classical controller (LQR, cost-to-go gate) only."""
NOT_YET_BUILT = ("learners other than ssac",)
"""What ``fit`` does not do yet; report.json and ``hybridctl fit --help`` say so."""
LEARNERS = ("auto", "ssac")
"""``learner``: "auto" is SSAC (thesis Ch. 3), the learner whose gate is learned."""
OUTPUTS = ("system.toml", "report.json", "stages", "trajopt", "clone", "learner", "stale", "maps", "replay.html",
           "replay.json")
"""What ``fit`` writes into its folder."""


@dataclass
class FitResult:
    """What :func:`fit` made: the folder, the spec file, the report, each stage's record, which stages ran now."""
    out: Path
    system_file: Path
    report: dict
    stages: dict[str, dict]
    computed: list[str] = field(default_factory=list)
    system: System | None = None

    @property
    def controller(self) -> str | None:
        """The fitted controller's name (``fitted:DIR``), None before the verification."""
        return f"fitted:{self.out}" if "verify" in self.stages else None


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _digest(data: Any) -> str:
    return hashlib.sha256(json.dumps(io.to_jsonable(data), sort_keys=True).encode()).hexdigest()[:20]


def _parse_goal(goal) -> list[float] | None:
    if goal is None or (isinstance(goal, str) and goal.strip() == "auto"):
        return None
    if isinstance(goal, str):
        try:
            values = [float(v) for v in goal.replace(" ", "").split(",")]
        except ValueError:
            raise FitError(f"--goal must be 'auto' or comma-separated numbers, got {goal!r}") from None
    else:
        values = [float(v) for v in goal]
    if not all(math.isfinite(v) for v in values):
        raise FitError(f"--goal must be finite numbers, got {goal!r}")
    return values


def _check_options(model_path: Path, budget_minutes, action_limit, learner) -> None:
    if not model_path.is_file():
        raise FitError(f"{model_path}: no such model file")
    limits.check_at_most("--budget", budget_minutes, limits.MAX_FIT_BUDGET_MINUTES)
    if not budget_minutes > 0:
        raise FitError(f"--budget must be > 0 minutes, got {budget_minutes}")
    if action_limit is not None and not (math.isfinite(action_limit) and action_limit > 0):
        raise FitError(f"--action-limit must be a finite number > 0, got {action_limit}")
    if learner is not None and learner not in LEARNERS:
        raise FitError(f"--learner must be one of {', '.join(LEARNERS)}, got {learner!r}")


def _check_resources(backend, workers, address, device, force: bool = False) -> dict:
    """The resource options, checked (one-line ValueError naming the flag) before any work."""
    from ..parallel import BACKENDS, check_backend_arguments
    from .balance_map import check_device

    if backend is not None and backend not in BACKENDS:
        raise FitError(f"--backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    check_backend_arguments(backend, workers, address, force)
    if device is not None:
        check_device("torch", device)
    return {"backend": backend, "workers": workers, "address": address, "device": device}


_RUN = {"model": stage_model, "lqr": stage_lqr, "integrator": stage_integrator, "gate": stage_gate,
        "reward": stage_reward,
        "swingup": fit_learn.stage_swingup, "learned_gate": fit_learn.stage_learned_gate,
        "clone": fit_clone.stage_clone, "learner": fit_learn.stage_learner, "verify": fit_learn.stage_verify}


def fit(model_file, out, *, goal="auto", action_limit: float | None = None, seed: int = 0, resume: bool = False,
        budget_minutes: float = 20, learner: str | None = "auto", settings: FitSettings | None = None,
        progress: bool = True, command: str | None = None, backend: str | None = None, workers: int | None = None,
        address: str | None = None, device: str | None = None, force: bool = False) -> FitResult:
    """Fit a spec and a switched controller to ``model_file`` in the folder ``out`` (see the module text).

    ``goal``: "auto" or a state (list or "x1,x2,..."); ``action_limit``: the largest command (default the
    model's effort limit); ``seed``: every sampled start and the learner; ``resume``: reuse the stages cached in
    ``out`` whose inputs match (the learner continues its checkpoint); ``budget_minutes``: all stages together
    (the learner gets what the others leave; no stage starts past it); ``learner``: "auto" / "ssac", or None for
    the classical stages only (model, lqr, gate, reward); ``settings``: every number the stages use.
    ``backend`` / ``workers`` / ``address``: where the verification's Drake balance maps run
    (:func:`hybridctl.parallel.make_backend`; default local processes); ``device``: the torch device of SSAC (and
    its clone) and of the torch balance maps (default the CPU). They change where the work runs, not what it
    computes, so they are not among a stage's cached inputs. ``force``: local ``workers`` above the cores.
    Raises :class:`FitError` (one line) on input fit cannot use, with the finished stages kept.
    """
    start = time.monotonic()
    model_path = Path(model_file).expanduser()
    _check_options(model_path, budget_minutes, action_limit, learner)
    resources = _check_resources(backend, workers, address, device, force)
    deadline = start + budget_minutes * 60
    s = settings or FitSettings()
    options = {"goal": _parse_goal(goal), "action_limit": None if action_limit is None else float(action_limit),
               "seed": int(seed), "learner": None if learner is None else "ssac"}
    model_ref = str(model_path.resolve())
    sha = _sha256(model_path)
    stages = CLASSICAL if learner is None else STAGES
    with io.command_folder(out, "fit", OUTPUTS) as folder:
        (folder / "stages").mkdir(exist_ok=True)
        report = {"command": command, "model_file": model_ref, "model_sha256": sha, "options": options,
                  "settings": settings_dict(s), "budget_minutes": budget_minutes, "stages": [],
                  "not_yet_built": list(NOT_YET_BUILT)}
        records: dict[str, dict] = {}
        computed: list[str] = []
        spec_file = folder / "system.toml"
        for name in stages:
            inputs = {"model_sha256": sha, "options": options, "settings": _digest(settings_dict(s)),
                      "earlier": _digest(records), "stage": name}
            path = folder / "stages" / f"{name}.json"
            cached = io.read_json(path) if resume and path.is_file() else None
            if cached is not None and cached.get("inputs") == io.to_jsonable(inputs):
                records[name] = cached["result"]
                report["stages"].append({**cached["summary"], "cached": True})
                continue
            if time.monotonic() > deadline:
                raise FitError(f"the budget of {budget_minutes:g} minutes is spent before the {name} stage; rerun with "
                               f"--resume (and a larger --budget)")
            if name in RUN_FOLDERS:
                moved = _set_aside_stale_run(folder, name, inputs, resume)
                if moved:
                    report.setdefault("set_aside", []).append(moved)
            system = _system(model_ref, options, records, s) if name not in CLASSICAL else None
            if name in ("clone", "learner", "verify"):
                # the learner trains on the spec file fit wrote, and workers (balance maps) load it by its path
                system.save_spec(spec_file, overwrite=True)
                system = load(str(spec_file))
            t0 = time.monotonic()
            try:
                result = io.to_jsonable(_RUN[name](model_ref, {**options, "command": command}, records, s, progress,
                                                   system=system, folder=folder, spec_file=spec_file,
                                                   deadline=deadline, resources=resources))
            except Exception as exc:
                report["stages"].append({"name": name, "error": str(exc).splitlines()[0] if str(exc) else repr(exc),
                                         "seconds": time.monotonic() - t0})
                io.write_json(folder / "report.json", report)
                raise
            seconds = time.monotonic() - t0
            summary = {"name": name, "seconds": seconds, **_summary(name, result)}
            io.write_json(path, {"inputs": inputs, "result": result, "summary": summary, "finished_at": time.time()})
            records[name] = result
            computed.append(name)
            report["stages"].append({**summary, "cached": False})
            io.write_json(folder / "report.json", report)
        system = _system(model_ref, options, records, s)
        system.save_spec(spec_file, overwrite=True)
        report["system"] = "system.toml"
        if "verify" in records:
            verified = records["verify"]
            checkpoint = verified.get("checkpoint", CHECKPOINT)
            report["controller"] = {"name": f"fitted:{folder}", "checkpoint": checkpoint,
                                    "gate": verified["gate"], "why": verified["gate_why"],
                                    "checkpoint_why": verified.get("checkpoint_why"),
                                    "drake_maps": verified["drake_maps"]}
            report["replay"] = fit_learn.write_replay(system, folder, f"{GATES[verified['gate']]}:{folder / checkpoint}")
            rest_map = records["verify"]["drake_maps"]["rest"]
            found = bool(report["replay"].get("balanced")) or rest_map["balanced"] > 0
            report["swingup_found"] = found
            if not found:
                learner = records["learner"]
                report["what_to_try"] = (f"no start of the rest map balanced and the run from hanging down did not: "
                                         f"the learner reached {learner['steps']} steps; rerun with --resume and a "
                                         f"larger --budget (the learner continues its checkpoint)")
            report["next"] = [f"hybridctl simulate {spec_file} --controller fitted:{folder}",
                              f"hybridctl balance-map {spec_file} --controller fitted:{folder} --grid 11"]
        else:
            report["next"] = [f"hybridctl simulate {spec_file} --controller lqr",
                              f"hybridctl simulate {spec_file} --controller trajopt"]
        report["seconds"] = time.monotonic() - start
        io.write_json(folder / "report.json", report)
        return FitResult(out=folder, system_file=spec_file, report=report, stages=records, computed=computed,
                         system=system)


RUN_FOLDERS = {"clone": CLONE, "learner": "learner"}
"""Stages whose outputs are run folders, by the folder: a stage recomputed on other inputs does not continue them."""


def _set_aside_stale_run(folder: Path, name: str, inputs: dict, resume: bool) -> str | None:
    """Before ``name``'s stage runs: its run folder, if another start of the stage made it on other inputs (other
    earlier stages, options or settings) or the fit is not a resume, moves to ``stale/NAME-TIME`` (kept, never
    removed; with ``resume`` a learner killed mid-run on the same inputs is continued instead). Returns the moved
    folder's path in ``folder``, if any."""
    import os

    target = folder / RUN_FOLDERS[name]
    marker = folder / "stages" / f"{name}.started.json"
    started = io.read_json(marker) if marker.is_file() else None
    moved = None
    if target.exists() and (not resume or started != io.to_jsonable(inputs)):
        base = folder / "stale" / f"{RUN_FOLDERS[name]}-{time.strftime('%Y%m%dT%H%M%S')}"
        base.parent.mkdir(exist_ok=True)
        stale, count = base, 1
        while stale.exists():
            count += 1
            stale = base.with_name(f"{base.name}-{count}")
        os.replace(target, stale)
        moved = str(stale.relative_to(folder))
    io.write_json(marker, inputs)
    return moved


def _summary(name: str, result: dict) -> dict:
    """A stage's entry in report.json: what was tried, what was kept and why."""
    if name == "model":
        return {"tried": f"{len(result['tried'])} 0/pi combinations of the revolute coordinates, "
                         f"{len(result['equilibria'])} distinct equilibria",
                "kept": {"goal": result["goal"], "rest": result["rest"], "action_limit": result["action_limit"],
                         "actuators": result["actuators"]},
                "why": {"goal": result["goal_why"], "rest": result["rest_why"], "action_limit": result["action_limit_why"]}}
    if name == "lqr":
        return {"tried": {"holds": result["holds"],
                          "qr": [{k: v for k, v in x.items() if k not in ("Q", "R")} for x in result["qr"]]},
                "kept": {"hold_s": result["hold_s"], "Q": result["Q"], "R": result["R"]},
                "why": {"hold": result["hold_why"], "qr": result["qr_why"]}}
    if name == "integrator":
        return {"tried": result["tried"], "kept": {"method": result["method"], "dt": result["dt"]}, "why": result["why"]}
    if name == "gate":
        return {"tried": "measure_basin", "kept": {"cost_scale": result["cost_scale"]}, "why": result["why"]}
    if name == "reward":
        return {"tried": {"rises_m": result["rises"]},
                "kept": {"kind": result["kind"], "tip_body": result["tip_body"], "tip_point": result["tip_point"]},
                "why": result["why"]}
    if name == "swingup":
        return {"tried": result["trajectory"],
                "kept": {"duration_s": result["duration_s"], "swingup_period": result["swingup_period"],
                         "gamma": result["gamma"], "episode_s": result["episode_s"]}, "why": result["why"]}
    if name == "learned_gate":
        return {"tried": result["info"], "kept": {"works": result["works"]}, "why": result["why"]}
    if name == "clone":
        return {"tried": {k: result.get(k) for k in ("rounds", "tracker_fraction", "samples")},
                "kept": {"cloned": result["cloned"], "round": result.get("kept_round"),
                         "fraction": result.get("fraction")}, "why": result["why"]}
    if name == "learner":
        return {"tried": {k: result[k] for k in ("steps_before", "seconds", "stopped_by_budget", "eval_success_rate",
                                                 "eval_mean_return", "verify_reserve_s")},
                "kept": {"steps": result["steps"], "checkpoint": result["checkpoint"]},
                "why": result["why"]}
    return {"tried": result["torch_maps"],
            "kept": {"gate": result["gate"], "checkpoint": result.get("checkpoint", CHECKPOINT),
                     "drake_maps": result["drake_maps"]},
            "why": {"gate": result["gate_why"], "checkpoint": result.get("checkpoint_why")}}


def _system(model_ref: str, options: dict, records: dict, s: FitSettings) -> System:
    """The System of every stage finished so far, each chosen value with its stage's reason as the source."""
    m, q, g = records["model"], records["lqr"], records["gate"]
    n = len(m["goal"])
    spread = np.array([s.start_spread] * (n // 2) + [0.0] * (n // 2))
    chosen = {
        "state.goal": (m["goal"], f"fit: model stage, {m['goal_why']}"),
        "initial_state.nominal": (m["rest"], f"fit: model stage, {m['rest_why']}"),
        "initial_state.low": (-spread, f"fit: rest +- {s.start_spread:g} on each position, at rest (FitSettings)"),
        "initial_state.high": (spread, f"fit: rest +- {s.start_spread:g} on each position, at rest (FitSettings)"),
        "integrator.dt": (records["integrator"]["dt"], f"fit: integrator stage, {records['integrator']['why']}"),
        "integrator.method": (records["integrator"]["method"], f"fit: integrator stage, {records['integrator']['why']}"),
        "control.period": (q["hold_s"], f"fit: lqr stage, {q['hold_why']}"),
        "lqr.Q": (q["Q"], f"fit: lqr stage, {q['qr_why']}"),
        "lqr.R": (q["R"], f"fit: lqr stage, {q['qr_why']}"),
        "gate.cost_scale": (g["cost_scale"], f"fit: gate stage, {g['why']}"),
    }
    if options["action_limit"] is not None:
        chosen["action.limit"] = (options["action_limit"], "fit: --action-limit")
    r = records.get("reward")
    if r is not None:
        chosen["reward.kind"] = (r["kind"], f"fit: reward stage, {r['why']}")
        if r["tip_body"] is not None:
            chosen["model.tip_point"] = (r["tip_point"], f"fit: reward stage, {r['tip_body']}'s centre of mass")
    p = records.get("swingup")
    if p is not None:
        chosen["control.swingup_period"] = (p["swingup_period"], f"fit: swingup stage, {p['why']['period']}")
        chosen["episode.duration"] = (p["episode_s"], f"fit: swingup stage, {p['why']['episode']}")
    lg = records.get("learned_gate")
    if lg is not None:
        chosen["gate.warm_near"] = (lg["warm_near"], f"fit: learned_gate stage, {lg['spread_why']}")
        chosen["gate.warm_far"] = (lg["warm_far"], f"fit: learned_gate stage, {lg['spread_why']}")
    tip = r["tip_body"] if r is not None else None
    return build_system(model_ref, options["action_limit"], np.asarray(m["goal"]), np.asarray(m["rest"]),
                        np.asarray(q["Q"]), np.asarray(q["R"]), period=q["hold_s"], settings=chosen,
                        dt=records["integrator"]["dt"], tip_body=tip)
