"""``hybridctl fit MODEL_FILE --out DIR``: a complete spec and a controller from a URDF/SDF alone.

Built so far, the classical stages; each one measures what it chooses and records why:

- ``model``: the actuators and their effort limit (none: one line asking for ``--action-limit``); the
  equilibria over the revolute coordinates (every combination of 0 and pi, refined by
  :func:`hybridctl.systems.nearest_equilibrium`, prismatic coordinates at 0); ``goal="auto"`` keeps the one
  of highest potential energy (the generated model's energy at rest), the rest state the lowest.
- ``lqr``: the control hold, the largest multiple of the integration step at which the saturated LQR still
  balances at least :data:`HOLD_KEEP` of the samples it balances at the finest hold; then Q and R, screened
  over :data:`QR_FAMILY` at that hold, the pair with the largest balanced fraction kept.
- ``gate``: the cost-to-go gate's scale V* / ln(1 / gate.on) from the LQR's basin level V*
  (:func:`hybridctl.systems.control.lqr_basin_level`) at the kept hold, Q and R.

Each stage's result is cached as ``DIR/stages/NAME.json`` (atomic) with the inputs it was computed from (the
model file's sha256, the options, the earlier stages' results); ``resume=True`` reuses a stage whose inputs
match. ``DIR/report.json`` lists every stage (what was tried, what was kept and why, seconds) and is written
after each stage, so a run stopped by bad input keeps what it had. ``DIR/system.toml`` is the complete spec.

Not built yet (later stages ): the learned swing-up, the learned gate and the Drake balance-map
verification; until then the classical swing-up is ``hybridctl simulate DIR/system.toml --controller trajopt``.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import io, limits
from ..systems import EquilibriumError, System, control, from_drake, nearest_equilibrium

__all__ = ["fit", "FitResult", "FitError", "STAGES", "OUTPUTS", "NOT_YET_BUILT", "QR_FAMILY", "HOLD_STEPS",
           "HOLD_KEEP", "DT"]

STAGES = ("model", "lqr", "gate")
"""The stages built so far, in order."""
NOT_YET_BUILT = ("learned swing-up (--learner)", "learned gate", "Drake balance-map verification",
                 "--backend/--workers/--address/--device")
"""What ``fit`` will add; report.json and ``hybridctl fit --help`` say so."""
OUTPUTS = ("system.toml", "report.json", "stages")
"""What ``fit`` writes into its folder."""
DT = 0.001
"""The integration step (s) of the fitted spec: fine enough for the holds screened below."""
HOLD_STEPS = (1, 2, 5, 10, 20, 50)
"""Control holds screened, in integration steps (0.001 s to 0.05 s)."""
HOLD_KEEP = 0.9
"""A hold is kept while its balanced fraction is at least this share of the finest hold's."""
QR_FAMILY = ((10.0, 1.0, 1.0), (1.0, 1.0, 1.0), (100.0, 1.0, 1.0), (10.0, 10.0, 1.0), (100.0, 10.0, 1.0),
             (10.0, 1.0, 10.0))
"""(w_q, w_v, r): Q = diag(w_q on positions, w_v on velocities), R = r / U^2 I (U the action limit). The first
is the one the hold is screened with."""
SPREAD = (0.5, 2.0)
"""Samples around the goal: +-0.5 on each position (rad or m), +-2 on each velocity."""
SCREEN_SAMPLES = 1000
GATE_SAMPLES = 2000
HORIZON = 2.5
"""s: the LQR rollouts' length (the thesis' gate labels, from_drake's gate.label_horizon)."""
EQUILIBRIUM_SEARCH = 0.5
"""How far (rad) nearest_equilibrium may move a 0/pi combination."""


class FitError(ValueError):
    """Input ``fit`` cannot use (one line; the CLI exits with code 2, the finished stages kept)."""


@dataclass
class FitResult:
    """What :func:`fit` made: the folder, the spec file, the report, each stage's record, which stages ran now."""
    out: Path
    system_file: Path
    report: dict
    stages: dict[str, dict]
    computed: list[str] = field(default_factory=list)
    system: System | None = None


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _digest(data: Any) -> str:
    return hashlib.sha256(json.dumps(io.to_jsonable(data), sort_keys=True).encode()).hexdigest()[:20]


def _bar(total: int, desc: str, progress: bool):
    from tqdm import tqdm
    return tqdm(total=total, desc=f"fit {desc}", disable=not progress, file=sys.stderr, leave=True)


def _build(model_file: str, action_limit, goal, rest, Q=None, R=None, period=DT, settings=None) -> System:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if Q is None or R is None:
            from ..systems.symbolic import ModelRequest, load_model, resolve_source
            Q, R = np.eye(len(goal)), np.eye(load_model(ModelRequest(source=resolve_source(model_file))).n_u)
        chosen = {"integrator.dt": (DT, "fit: the integration step fit screens holds on"),
                  "control.period": (period, "fit: the hold being screened")}
        return from_drake(model_file, goal=goal, Q=Q, R=R, action_limit=action_limit, nominal=rest,
                          settings={**chosen, **(settings or {})})


# ------------------------------------------------------------------------------------------- stages
def _stage_model(model_file: str, options: dict, earlier: dict, progress: bool) -> dict:
    from ..systems.spec import SpecError
    from ..systems.symbolic import ModelRequest, load_model, resolve_source

    model = load_model(ModelRequest(source=resolve_source(model_file)))    # ModelError: no actuator, a free base...
    try:
        probe = _build(model_file, options["action_limit"], np.zeros(2 * len(model.positions)), None)
    except SpecError as exc:
        if "action.limit" in str(exc):
            raise FitError(f"{model_file}: the model's actuators give no finite effort limit; pass --action-limit U "
                           f"(N m or N, the largest command)") from None
        raise
    n = probe.n_states
    angles = [i for i, revolute in enumerate(model.revolute) if revolute]
    if 2 ** len(angles) > limits.MAX_FIT_EQUILIBRIUM_CANDIDATES:
        raise FitError(f"{model_file}: {len(angles)} revolute coordinates give 2^{len(angles)} equilibrium candidates, "
                       f"above {limits.MAX_FIT_EQUILIBRIUM_CANDIDATES}; pass --goal")
    tried, found = [], []
    bar = _bar(2 ** len(angles), "model: equilibria", progress)
    for combo in itertools.product((0.0, math.pi), repeat=len(angles)):
        x = np.zeros(n)
        x[angles] = combo
        try:
            eq, _ = nearest_equilibrium(probe, x, tolerance=EQUILIBRIUM_SEARCH)
        except EquilibriumError:
            tried.append({"start": x[:n // 2], "equilibrium": None})
            bar.update()
            continue
        eq[angles] = math.pi - (math.pi - eq[angles]) % (2 * math.pi)     # one representative per angle, in (-pi, pi]
        snapped = np.round(eq / math.pi) * math.pi                        # 0 and pi exactly where they are equilibria
        eq = np.where(np.abs(eq - snapped) < 1e-9, snapped, eq)
        energy = float(np.asarray(probe.energy(eq[None]))[0])
        tried.append({"start": x[:n // 2], "equilibrium": eq[:n // 2], "potential_energy": energy})
        if not any(np.allclose(eq, f["x"], atol=1e-6) for f in found):
            found.append({"x": eq, "potential_energy": energy})
        bar.update()
    bar.close()
    if not found:
        raise FitError(f"{model_file}: no equilibrium with u = 0 near any 0/pi combination of the revolute coordinates; "
                       f"pass --goal")
    top = max(found, key=lambda f: f["potential_energy"])
    low = min(found, key=lambda f: f["potential_energy"])
    if options["goal"] is None:
        goal = top["x"]
        why = (f"highest-potential equilibrium over the revolute coordinates ({top['potential_energy']:.6g} J among "
               f"{len(found)} equilibria found from {len(tried)} 0/pi combinations)")
    else:
        given = np.asarray(options["goal"], dtype=float)
        if given.shape != (n,):
            raise FitError(f"--goal needs {n} values ({', '.join(probe.state_names)}), got {given.size}")
        try:
            goal, _ = nearest_equilibrium(probe, given)
        except EquilibriumError as exc:
            raise FitError(f"--goal: {exc}") from None
        why = "--goal, an equilibrium with u = 0 (hybridctl.systems.nearest_equilibrium)"
    return {"tried": tried, "equilibria": found, "goal": goal, "goal_why": why, "rest": low["x"],
            "rest_why": f"lowest-potential equilibrium ({low['potential_energy']:.6g} J among {len(found)})",
            "action_limit": probe.action_limit, "actuators": list(probe.action_names),
            "state_names": list(probe.state_names),
            "action_limit_why": ("--action-limit" if options["action_limit"] is not None
                                 else "the model's actuator effort limit")}


def _spread(n: int) -> np.ndarray:
    return np.array([SPREAD[0]] * (n // 2) + [SPREAD[1]] * (n // 2))


def _qr(weights, n: int, n_u: int, limit: float):
    wq, wv, r = weights
    return np.diag([wq] * (n // 2) + [wv] * (n // 2)), np.eye(n_u) * r / limit ** 2


def _stage_lqr(model_file: str, options: dict, earlier: dict, progress: bool) -> dict:
    m = earlier["model"]
    goal, rest, limit = np.asarray(m["goal"]), np.asarray(m["rest"]), options["action_limit"]
    n, n_u = len(goal), len(m["actuators"])
    system = _build(model_file, limit, goal, rest, *_qr(QR_FAMILY[0], n, n_u, m["action_limit"]))
    spread = _spread(n)
    holds = []
    bar = _bar(len(HOLD_STEPS) + len(QR_FAMILY), "lqr: holds, Q/R", progress)
    for k in HOLD_STEPS:
        r = control.lqr_basin_level(system, n_samples=SCREEN_SAMPLES, horizon=HORIZON, spread=spread,
                                    seed=options["seed"], hold=k)
        holds.append({"hold_s": k * DT, "steps": k, "balanced": r["success_rate"], "level": r["level"]})
        bar.update()
    finest = holds[0]["balanced"]
    if finest <= 0:
        bar.close()
        raise FitError(f"{model_file}: the saturated LQR about the goal balances none of {SCREEN_SAMPLES} starts within "
                       f"+-{SPREAD[0]} / +-{SPREAD[1]} of it even at a {DT:g} s hold; a larger --action-limit may help")
    kept_hold = max((h for h in holds if h["balanced"] >= HOLD_KEEP * finest), key=lambda h: h["steps"])
    screened = []
    for weights in QR_FAMILY:
        Q, R = _qr(weights, n, n_u, m["action_limit"])
        try:
            K, S = system.lqr(Q, R)
        except ValueError as exc:
            screened.append({"w_q": weights[0], "w_v": weights[1], "r": weights[2], "error": str(exc)})
            bar.update()
            continue
        r = control.lqr_basin_level(system, n_samples=SCREEN_SAMPLES, horizon=HORIZON, spread=spread,
                                    seed=options["seed"], K=K, S=S, hold=kept_hold["steps"])
        screened.append({"w_q": weights[0], "w_v": weights[1], "r": weights[2], "Q": Q, "R": R,
                         "balanced": r["success_rate"], "level": r["level"]})
        bar.update()
    bar.close()
    good = [s for s in screened if "error" not in s]
    if not good:
        raise FitError(f"{model_file}: no LQR about the goal for any Q/R tried ({screened[0]['error']})")
    best = max(good, key=lambda s: (s["balanced"], s["level"]))
    return {"holds": holds, "hold_s": kept_hold["hold_s"], "hold_steps": kept_hold["steps"],
            "hold_why": (f"the largest hold whose balanced fraction {kept_hold['balanced']:.3g} stays >= {HOLD_KEEP:g} x "
                         f"the finest ({finest:.3g} at {DT:g} s) among {len(holds)} tried, {SCREEN_SAMPLES} starts"),
            "qr": screened, "Q": best["Q"], "R": best["R"],
            "qr_why": (f"Q/R with the largest balanced fraction {best['balanced']:.3g} (basin level {best['level']:.4g}) "
                       f"among {len(screened)} tried at the {kept_hold['hold_s']:g} s hold")}


def _stage_gate(model_file: str, options: dict, earlier: dict, progress: bool) -> dict:
    m, q = earlier["model"], earlier["lqr"]
    system = _build(model_file, options["action_limit"], np.asarray(m["goal"]), np.asarray(m["rest"]),
                    np.asarray(q["Q"]), np.asarray(q["R"]), period=q["hold_s"])
    bar = _bar(1, "gate: basin level", progress)
    r = control.lqr_basin_level(system, n_samples=GATE_SAMPLES, horizon=HORIZON, spread=_spread(system.n_states),
                                seed=options["seed"] + 1, hold=q["hold_steps"])
    bar.update()
    bar.close()
    return {"basin": r, "cost_scale": r["gate_scale"],
            "why": (f"V*/ln(1/{system.gate.on:g}) with V* = {r['level']:.4g}, the saturated LQR's basin level from "
                    f"{GATE_SAMPLES} starts (every start below it balanced; {r['success_rate']:.3g} of all)")}


_RUN = {"model": _stage_model, "lqr": _stage_lqr, "gate": _stage_gate}


# ------------------------------------------------------------------------------------------- fit
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


def fit(model_file, out, *, goal="auto", action_limit: float | None = None, seed: int = 0, resume: bool = False,
        budget_minutes: float = 20, progress: bool = True, command: str | None = None) -> FitResult:
    """Fit a spec and the classical controller to ``model_file`` in the folder ``out`` (see the module text).

    ``goal``: "auto" or a state (list or "x1,x2,..."); ``action_limit``: the largest command (default the
    model's effort limit); ``seed``: the sampled starts; ``resume``: reuse the stages cached in ``out`` whose
    inputs match; ``budget_minutes``: a stage is not started past it (rerun with ``resume``).
    Raises :class:`FitError` (one line) on input fit cannot use, with the finished stages kept.
    """
    start = time.monotonic()
    model_path = Path(model_file).expanduser()
    if not model_path.is_file():
        raise FitError(f"{model_file}: no such model file")
    limits.check_at_most("--budget", budget_minutes, limits.MAX_FIT_BUDGET_MINUTES)
    if not budget_minutes > 0:
        raise FitError(f"--budget must be > 0 minutes, got {budget_minutes}")
    if action_limit is not None and not (math.isfinite(action_limit) and action_limit > 0):
        raise FitError(f"--action-limit must be a finite number > 0, got {action_limit}")
    options = {"goal": _parse_goal(goal), "action_limit": None if action_limit is None else float(action_limit),
               "seed": int(seed)}
    model_ref = str(model_path.resolve())
    sha = _sha256(model_path)
    with io.command_folder(out, "fit", OUTPUTS) as folder:
        (folder / "stages").mkdir(exist_ok=True)
        report = {"command": command, "model_file": model_ref, "model_sha256": sha, "options": options,
                  "stages": [], "not_yet_built": list(NOT_YET_BUILT)}
        records: dict[str, dict] = {}
        computed: list[str] = []
        for name in STAGES:
            inputs = {"model_sha256": sha, "options": options, "earlier": _digest(records), "stage": name}
            path = folder / "stages" / f"{name}.json"
            cached = io.read_json(path) if resume and path.is_file() else None
            if cached is not None and cached.get("inputs") == io.to_jsonable(inputs):
                records[name] = cached["result"]
                report["stages"].append({**cached["summary"], "cached": True})
                continue
            if time.monotonic() - start > budget_minutes * 60:
                raise FitError(f"the budget of {budget_minutes:g} minutes is spent before the {name} stage; rerun with "
                               f"--resume (and a larger --budget)")
            t0 = time.monotonic()
            try:
                result = io.to_jsonable(_RUN[name](model_ref, options, records, progress))
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
        system = _final_system(model_ref, options, records)
        spec_file = system.save_spec(folder / "system.toml", overwrite=True)
        report["system"] = "system.toml"
        report["seconds"] = time.monotonic() - start
        report["next"] = [f"hybridctl simulate {spec_file} --controller lqr", f"hybridctl simulate {spec_file} --controller trajopt"]
        io.write_json(folder / "report.json", report)
        return FitResult(out=folder, system_file=spec_file, report=report, stages=records, computed=computed,
                         system=system)


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
                          "qr": [{k: v for k, v in s.items() if k not in ("Q", "R")} for s in result["qr"]]},
                "kept": {"hold_s": result["hold_s"], "Q": result["Q"], "R": result["R"]},
                "why": {"hold": result["hold_why"], "qr": result["qr_why"]}}
    return {"tried": f"lqr_basin_level, {GATE_SAMPLES} starts", "kept": {"cost_scale": result["cost_scale"]},
            "why": result["why"]}


def _final_system(model_ref: str, options: dict, records: dict) -> System:
    m, q, g = records["model"], records["lqr"], records["gate"]
    settings = {
        "state.goal": (m["goal"], f"fit: model stage, {m['goal_why']}"),
        "initial_state.nominal": (m["rest"], f"fit: model stage, {m['rest_why']}"),
        "integrator.dt": (DT, "fit: the integration step fit screens holds on"),
        "control.period": (q["hold_s"], f"fit: lqr stage, {q['hold_why']}"),
        "lqr.Q": (q["Q"], f"fit: lqr stage, {q['qr_why']}"),
        "lqr.R": (q["R"], f"fit: lqr stage, {q['qr_why']}"),
        "gate.cost_scale": (g["cost_scale"], f"fit: gate stage, {g['why']}"),
    }
    if options["action_limit"] is not None:
        settings["action.limit"] = (options["action_limit"], "fit: --action-limit")
    return _build(model_ref, options["action_limit"], np.asarray(m["goal"]), np.asarray(m["rest"]),
                  np.asarray(q["Q"]), np.asarray(q["R"]), period=q["hold_s"], settings=settings)
