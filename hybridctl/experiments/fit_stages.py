"""The classical stages of ``hybridctl fit``: the model, the LQR, the cost-to-go gate and the reward.

Each stage is a function ``(model_file, options, earlier, settings, progress) -> dict`` whose result is what
``DIR/stages/NAME.json`` keeps; every value it chooses comes with the measurement that chose it (``*_why``).
:class:`FitSettings` holds every number the stages use, each with its source (CleanRL style).
"""

from __future__ import annotations

import itertools
import math
import sys
import warnings
from dataclasses import asdict, dataclass, field, fields

import numpy as np

from .. import limits
from ..systems import EquilibriumError, System, control, from_drake, nearest_equilibrium

__all__ = ["FitSettings", "FitError", "stage_model", "stage_lqr", "stage_integrator", "stage_gate", "stage_reward",
           "build_system"]


class FitError(ValueError):
    """Input ``fit`` cannot use (one line; the CLI exits with code 2, the finished stages kept)."""


@dataclass(frozen=True)
class FitSettings:
    """Every number ``fit`` uses, with its source. Tests shrink the sample counts; the report records them all."""

    dt: float = 0.001                     # s, the fitted spec's integration step: fine enough for the holds screened
    hold_steps: tuple = (1, 2, 5, 10, 20, 50)   # control holds screened, in integration steps (0.001 s to 0.05 s)
    hold_keep: float = 0.9                # a hold is kept while its balanced fraction is >= this share of the finest's
    qr_family: tuple = ((10.0, 1.0, 1.0), (1.0, 1.0, 1.0), (100.0, 1.0, 1.0), (10.0, 10.0, 1.0),
                        (100.0, 10.0, 1.0), (10.0, 1.0, 10.0))
    # (w_q, w_v, r): Q = diag(w_q on positions, w_v on velocities), R = r / U^2 I; the first screens the holds
    spread: tuple = (0.5, 2.0)            # LQR screen starts: +-0.5 on each position (rad or m), +-2 on each velocity
    screen_samples: int = 1000            # starts per hold and per Q/R of the LQR screen
    gate_samples: int = 5000              # starts of the basin level that scales both gates (measure_basin)
    horizon: float = 2.5                  # s, LQR rollouts' length (the thesis' gate labels, implementation notes)
    equilibrium_search: float = 0.5       # rad, how far nearest_equilibrium may move a 0/pi combination
    step_tolerance: float = 0.02          # rad or m: an integrator's positions may differ this much from a 4x finer
    #                                       Heun reference after step_horizon (hybridctl choice: a tenth of the
    #                                       thesis' success eps 0.1 and of the gate labels' 0.2)
    step_horizon: float = 0.5             # s of random held inputs from random states: about a swing's quarter
    step_samples: int = 256               # trajectories per integrator candidate
    tip_rise_min: float = 0.01            # m, a body whose centre of mass rises less from rest to goal is no tip
    start_spread: float = 0.1             # rad or m, the spec's start range about rest on each position
    swingup_knots: int = 41               # collocation knots (TrajoptSettings' default, measured on every chain)
    decision_min: float = 0.02            # s, shortest swing-up decision (the thesis' acrobot period)
    decision_max: float = 0.1             # s, longest (from_drake's default)
    gamma_range: tuple = (0.95, 0.995)    # thesis 0.95 to the author's 0.99 and a little above (longer swing-ups)
    track_samples: int = 128              # starts from the spec's range on which the tracked swing-up is measured at
    #                                       each decision period (and the clone on as many others)
    track_keep: float = 0.9               # the longest period whose tracked share is >= this x the best's is kept
    clone_settings: dict = field(default_factory=dict)   # hybridctl.learn.clone.CloneConfig fields to change
    clone_start_min: float = 0.5          # SSAC starts from the clone only if it balances at least this share of the
    #                                       held-out starts (reaction wheel: a clone balancing 0.05 is no better a
    #                                       start than a new policy; SSAC from scratch balanced 121/121 there)
    learned_gate_samples: int | None = 10_000   # learned_gate_from_basin's samples (None: its 40,000; those took
    #                                             359 s of the made-up pendubot's 20-minute fit on the shared machine)
    learned_gate_fit_steps: int | None = None   # its warm fit's Adam steps (None: BASIN_GATE_CONFIG's 4000; tests: fewer)
    learner_max_steps: int = 3_000_000    # env steps at most (the Furuta's measured run, docs/your_robot.md)
    learner_stop_full: bool = True        # the learner stops at a checkpoint whose torch maps (verify's two, its
    #                                       learned gate) balance every start: the verification's best score
    eval_episodes: int = 20               # deterministic episodes in the learner's eval.json
    learner_settings: dict = field(default_factory=dict)   # SSACConfig fields to change (tests: a tiny run)
    verify_grid: int = 11                 # the Drake balance maps' grid (issue: 11 x 11)
    verify_near: float = 0.3              # rad, the rest map's half-width (the learner x system matrix's)
    verify_reserve: float = 1.5           # verify's measured-per-start estimate x this is kept from the learner
    verify_duration: float | None = None  # s per balance-map run (None: the fitted spec's episode)
    gate_tolerance: float = 0.05          # the learned gate is kept unless a torch map of it balances this share
    #                                       fewer starts than the cost-to-go gate's (6 of 121: beyond one start's noise)

    def to_dict(self) -> dict:
        """JSON-ready."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


def bar(total: int, desc: str, progress: bool):
    """A tqdm bar on stderr named ``fit DESC`` (disabled without ``progress``)."""
    from tqdm import tqdm
    return tqdm(total=total, desc=f"fit {desc}", disable=not progress, file=sys.stderr, leave=True)


def build_system(model_file: str, action_limit, goal, rest, Q=None, R=None, period=None, settings=None,
                 dt: float = FitSettings.dt, tip_body: str | None = None) -> System:
    """``from_drake`` with fit's step and hold (``settings``: more ``{"section.key": (value, source)}``)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if Q is None or R is None:
            from ..systems.symbolic import ModelRequest, load_model, resolve_source
            Q, R = np.eye(len(goal)), np.eye(load_model(ModelRequest(source=resolve_source(model_file))).n_u)
        chosen = {"integrator.dt": (dt, "fit: the integration step fit screens holds on"),
                  "control.period": (dt if period is None else period, "fit: the hold being screened")}
        return from_drake(model_file, goal=goal, Q=Q, R=R, action_limit=action_limit, nominal=rest,
                          tip_body=tip_body, settings={**chosen, **(settings or {})})


# ------------------------------------------------------------------------------------------- model
def stage_model(model_file: str, options: dict, earlier: dict, s: FitSettings, progress: bool, **_) -> dict:
    """Actuators, effort limit; the equilibria over the revolute coordinates; the goal (highest) and rest (lowest)."""
    from ..systems.spec import SpecError
    from ..systems.symbolic import ModelRequest, load_model, resolve_source

    model = load_model(ModelRequest(source=resolve_source(model_file)))    # ModelError: no actuator, a free base...
    try:
        probe = build_system(model_file, options["action_limit"], np.zeros(2 * len(model.positions)), None, dt=s.dt)
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
    progress_bar = bar(2 ** len(angles), "model: equilibria", progress)
    for combo in itertools.product((0.0, math.pi), repeat=len(angles)):
        x = np.zeros(n)
        x[angles] = combo
        try:
            eq, _ = nearest_equilibrium(probe, x, tolerance=s.equilibrium_search)
        except EquilibriumError:
            tried.append({"start": x[:n // 2], "equilibrium": None})
            progress_bar.update()
            continue
        eq[angles] = math.pi - (math.pi - eq[angles]) % (2 * math.pi)     # one representative per angle, in (-pi, pi]
        snapped = np.round(eq / math.pi) * math.pi                        # 0 and pi exactly where they are equilibria
        eq = np.where(np.abs(eq - snapped) < 1e-9, snapped, eq)
        energy = float(np.asarray(probe.energy(eq[None]))[0])
        tried.append({"start": x[:n // 2], "equilibrium": eq[:n // 2], "potential_energy": energy})
        if not any(np.allclose(eq, f["x"], atol=1e-6) for f in found):
            found.append({"x": eq, "potential_energy": energy})
        progress_bar.update()
    progress_bar.close()
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
            "state_names": list(probe.state_names), "revolute": [bool(r) for r in model.revolute],
            "action_limit_why": ("--action-limit" if options["action_limit"] is not None
                                 else "the model's actuator effort limit")}


# ------------------------------------------------------------------------------------------- lqr
def screen_spread(n: int, s: FitSettings) -> np.ndarray:
    """The LQR screen's sampling half-widths: ``s.spread[0]`` on positions, ``s.spread[1]`` on velocities."""
    return np.array([s.spread[0]] * (n // 2) + [s.spread[1]] * (n // 2))


def _qr(weights, n: int, n_u: int, limit: float):
    wq, wv, r = weights
    return np.diag([wq] * (n // 2) + [wv] * (n // 2)), np.eye(n_u) * r / limit ** 2


def stage_lqr(model_file: str, options: dict, earlier: dict, s: FitSettings, progress: bool, **_) -> dict:
    """The largest control hold that keeps the saturated LQR's basin; then Q and R for the largest basin."""
    m = earlier["model"]
    goal, rest, limit = np.asarray(m["goal"]), np.asarray(m["rest"]), options["action_limit"]
    n, n_u = len(goal), len(m["actuators"])
    system = build_system(model_file, limit, goal, rest, *_qr(s.qr_family[0], n, n_u, m["action_limit"]), dt=s.dt)
    spread = screen_spread(n, s)
    holds = []
    progress_bar = bar(len(s.hold_steps) + len(s.qr_family), "lqr: holds, Q/R", progress)
    for k in s.hold_steps:
        r = control.lqr_basin_level(system, n_samples=s.screen_samples, horizon=s.horizon, spread=spread,
                                    seed=options["seed"], hold=k)
        holds.append({"hold_s": k * s.dt, "steps": k, "balanced": r["success_rate"], "level": r["level"]})
        progress_bar.update()
    finest = holds[0]["balanced"]
    if finest <= 0:
        progress_bar.close()
        raise FitError(f"{model_file}: the saturated LQR about the goal balances none of {s.screen_samples} starts "
                       f"within +-{s.spread[0]} / +-{s.spread[1]} of it even at a {s.dt:g} s hold; a larger "
                       f"--action-limit may help")
    kept_hold = max((h for h in holds if h["balanced"] >= s.hold_keep * finest), key=lambda h: h["steps"])
    screened = []
    for weights in s.qr_family:
        Q, R = _qr(weights, n, n_u, m["action_limit"])
        try:
            K, S = system.lqr(Q, R)
        except ValueError as exc:
            screened.append({"w_q": weights[0], "w_v": weights[1], "r": weights[2], "error": str(exc)})
            progress_bar.update()
            continue
        r = control.lqr_basin_level(system, n_samples=s.screen_samples, horizon=s.horizon, spread=spread,
                                    seed=options["seed"], K=K, S=S, hold=kept_hold["steps"])
        screened.append({"w_q": weights[0], "w_v": weights[1], "r": weights[2], "Q": Q, "R": R,
                         "balanced": r["success_rate"], "level": r["level"]})
        progress_bar.update()
    progress_bar.close()
    good = [x for x in screened if "error" not in x]
    if not good:
        raise FitError(f"{model_file}: no LQR about the goal for any Q/R tried ({screened[0]['error']})")
    best = max(good, key=lambda x: (x["balanced"], x["level"]))
    return {"holds": holds, "hold_s": kept_hold["hold_s"], "hold_steps": kept_hold["steps"],
            "hold_why": (f"the largest hold whose balanced fraction {kept_hold['balanced']:.3g} stays >= "
                         f"{s.hold_keep:g} x the finest ({finest:.3g} at {s.dt:g} s) among {len(holds)} tried, "
                         f"{s.screen_samples} starts"),
            "qr": screened, "Q": best["Q"], "R": best["R"],
            "qr_why": (f"Q/R with the largest balanced fraction {best['balanced']:.3g} (basin level {best['level']:.4g}) "
                       f"among {len(screened)} tried at the {kept_hold['hold_s']:g} s hold")}


# ------------------------------------------------------------------------------------------- integrator
def _held_input_run(system: System, x0, inputs, hold: float):
    """States after holding each row of ``inputs`` (steps, B, m) for ``hold`` seconds from ``x0`` (B, n)."""
    import torch

    x = torch.as_tensor(x0, dtype=torch.float64)
    substeps = int(round(hold / system.dt))
    for u in inputs:
        u = torch.as_tensor(u, dtype=torch.float64)
        for _ in range(substeps):
            x = system.step(x, u)
    return x


def stage_integrator(model_file: str, options: dict, earlier: dict, s: FitSettings, progress: bool, **_) -> dict:
    """The cheapest integrator (Euler or Heun, a step dividing the hold) whose positions stay within
    ``s.step_tolerance`` of a 4x finer Heun reference over ``s.step_horizon`` s of random held inputs from
    random states, and whose saturated LQR balances at least ``s.hold_keep`` of the lqr stage's share."""
    m, q = earlier["model"], earlier["lqr"]
    goal, rest, hold = np.asarray(m["goal"]), np.asarray(m["rest"]), q["hold_s"]
    n = len(goal)
    rng = np.random.default_rng(options["seed"] + 2)
    revolute = np.array(m["revolute"], dtype=bool)
    x0 = rest + np.concatenate([np.where(revolute, rng.uniform(-np.pi, np.pi, (s.step_samples, n // 2)),
                                         rng.uniform(-0.5, 0.5, (s.step_samples, n // 2))),
                                rng.uniform(-2.0, 2.0, (s.step_samples, n // 2))], axis=1)
    n_holds = max(1, int(round(s.step_horizon / hold)))
    limit = m["action_limit"]
    inputs = rng.uniform(-limit, limit, (n_holds, s.step_samples, len(m["actuators"])))

    def build(method, dt):
        return build_system(model_file, options["action_limit"], goal, rest, np.asarray(q["Q"]), np.asarray(q["R"]),
                            period=hold, dt=dt, settings={"integrator.method": (method, "fit: being screened")})

    reference_dt = s.dt / 4
    reference = _held_input_run(build("runge_kutta2", reference_dt), x0, inputs, hold).numpy()
    steps = [k for k in range(1, int(round(hold / s.dt)) + 1) if int(round(hold / s.dt)) % k == 0]
    candidates = sorted(((method, k * s.dt) for k in steps for method in ("euler", "runge_kutta2")),
                        key=lambda c: (1 if c[0] == "euler" else 2) / c[1])     # cheapest first: evaluations per s
    best = max((x for x in q["qr"] if "balanced" in x), key=lambda x: x["balanced"])
    tried, kept = [], None
    progress_bar = bar(len(candidates), "integrator: step and method", progress)
    for method, dt in candidates:
        system = build(method, dt)
        with np.errstate(all="ignore"):
            final = _held_input_run(system, x0, inputs, hold).numpy()
        error = system.state_error(final) - system.state_error(reference)
        position = float(np.nanmax(np.abs(np.asarray(error)[:, : n // 2]))) if np.isfinite(final).all() else math.inf
        entry = {"method": method, "dt": dt, "evaluations_per_s": (1 if method == "euler" else 2) / dt,
                 "max_position_error": position}
        if position <= s.step_tolerance:
            K, S = system.lqr()
            r = control.lqr_basin_level(system, n_samples=s.screen_samples, horizon=s.horizon,
                                        spread=screen_spread(n, s), seed=options["seed"], K=K, S=S,
                                        hold=int(round(hold / dt)))
            entry["balanced"] = r["success_rate"]
            if r["success_rate"] >= s.hold_keep * best["balanced"]:
                kept = entry
        tried.append(entry)
        progress_bar.update()
        if kept is not None:
            break
    progress_bar.close()
    if kept is None:    # the reference itself: the finest Heun step screened
        kept = {"method": "runge_kutta2", "dt": s.dt, "evaluations_per_s": 2 / s.dt}
    return {"tried": tried, "method": kept["method"], "dt": kept["dt"],
            "why": (f"the cheapest of {len(candidates)} (Euler or Heun, steps dividing the {hold:g} s hold) whose "
                    f"positions stay within {s.step_tolerance:g} of Heun at {reference_dt:g} s after {s.step_horizon:g} s "
                    f"of random held inputs from {s.step_samples} random states"
                    + (f" ({kept['max_position_error']:.2g})" if "max_position_error" in kept else "")
                    + f" and whose LQR balances >= {s.hold_keep:g} x the lqr stage's {best['balanced']:.3g}")}


# ------------------------------------------------------------------------------------------- gate
def stage_gate(model_file: str, options: dict, earlier: dict, s: FitSettings, progress: bool, **_) -> dict:
    """The cost-to-go gate's scale V* / ln(1 / gate.on) from the held LQR's basin level V*, measured on cost-to-go
    ellipsoids (:func:`hybridctl.learn.gate.measure_basin`: a box of starts narrower than the basin in some
    coordinate overstates V*, the furuta's 9 times)."""
    from ..learn.gate import measure_basin

    m, q, i = earlier["model"], earlier["lqr"], earlier["integrator"]
    system = build_system(model_file, options["action_limit"], np.asarray(m["goal"]), np.asarray(m["rest"]),
                          np.asarray(q["Q"]), np.asarray(q["R"]), period=q["hold_s"], dt=i["dt"],
                          settings={"integrator.method": (i["method"], "fit: integrator stage")})
    progress_bar = bar(1, "gate: basin level", progress)
    r = measure_basin(system, n_samples=s.gate_samples, seed=options["seed"] + 1)
    progress_bar.update()
    progress_bar.close()
    return {"basin": r, "cost_scale": r["gate_scale"],
            "why": (f"V*/ln(1/{system.gate.on:g}) with V* = {r['level']:.4g}, the held LQR's basin level from "
                    f"{s.gate_samples} starts on its cost-to-go ellipsoids (every start below it balanced within "
                    f"{r['horizon']:g} s; {r['success_rate']:.3g} of all)")}


# ------------------------------------------------------------------------------------------- reward
def _body_heights(system: System, x: np.ndarray) -> dict[str, tuple[float, np.ndarray, float]]:
    """{body: (centre-of-mass height in the world, centre of mass in the body frame, mass)} at state ``x``,
    from Drake's plant (the one the diagrams simulate)."""
    from pydrake.multibody.tree import BodyIndex
    from pydrake.systems.framework import DiagramBuilder

    from ..systems import plants

    builder = DiagramBuilder()
    handle, _ = plants.add_plant(system, builder)
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    plant = handle.plant
    plant_context = plant.GetMyMutableContextFromRoot(context)
    handle.apply_parameters(plant_context)
    plant.SetPositionsAndVelocities(plant_context, np.asarray(x, dtype=float))
    heights = {}
    for index in range(plant.num_bodies()):
        body = plant.get_body(BodyIndex(index))
        mass = body.get_mass(plant_context)
        if index == 0 or mass <= 0:
            continue
        com = np.asarray(body.CalcCenterOfMassInBodyFrame(plant_context)).reshape(3)
        pose = plant.EvalBodyPoseInWorld(plant_context, body)
        heights[body.name()] = (float((pose.rotation().matrix() @ com + pose.translation())[2]), com, float(mass))
    return heights


def stage_reward(model_file: str, options: dict, earlier: dict, s: FitSettings, progress: bool, **_) -> dict:
    """The learner's reward: the tip height (thesis eq. 3.1) of the body whose centre of mass rises most from
    rest to goal (a free-spinning wheel or a turning arm does not change it), ``tip_height_centered`` where a
    prismatic coordinate must also return; ``angle_cosine`` where no body rises by ``s.tip_rise_min``."""
    m = earlier["model"]
    system = build_system(model_file, options["action_limit"], np.asarray(m["goal"]), np.asarray(m["rest"]), dt=s.dt)
    at_goal, at_rest = _body_heights(system, np.asarray(m["goal"])), _body_heights(system, np.asarray(m["rest"]))
    rises = {name: at_goal[name][0] - at_rest[name][0] for name in at_goal}
    linear = [i for i, revolute in enumerate(m["revolute"]) if not revolute]
    if not rises or max(rises.values()) < s.tip_rise_min:
        return {"rises": rises, "kind": "angle_cosine", "tip_body": None, "tip_point": None,
                "why": (f"no body's centre of mass rises by {s.tip_rise_min:g} m from rest to goal "
                        f"({', '.join(f'{k} {v:.3g} m' for k, v in rises.items()) or 'no massive body'}): the "
                        f"angle cost of every coordinate")}
    tip = max(rises, key=rises.get)
    kind = "tip_height_centered" if linear else "tip_height"
    return {"rises": rises, "kind": kind, "tip_body": tip, "tip_point": at_goal[tip][1],
            "why": (f"{kind} of {tip}'s centre of mass, which rises most from rest to goal ({rises[tip]:.4g} m of "
                    + ", ".join(f"{k} {v:.3g} m" for k, v in rises.items()) + ")"
                    + (": the tip height charges no coordinate that does not lift it; minus 0.1 x^2 on the "
                       "prismatic coordinates, which must return" if linear else
                       ": the tip height charges no coordinate that does not lift it (a wheel's or an arm's angle)"))}


def settings_dict(s: FitSettings) -> dict:
    """``s`` as JSON-ready values (tuples as lists)."""
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(s).items()}
