"""Throughput of the batched torch dynamics against gymnasium's Acrobot-v1, and the
real-time factor of the Drake hybrid diagram. Prints one JSON document.

    .venv/bin/python benchmarks/dynamics.py [--quick] [--out FILE] [--threads N]

Every number is the median of several timed repeats (wall clock, after a
warm-up), measured in this one run, so ratios compare like with like on the
same machine under the same load. See benchmarks/README.md for what is and is
not comparable.
"""

from __future__ import annotations

import argparse
import ast
import datetime as _dt
import statistics
import sys
import time
from pathlib import Path

# Benchmark this checkout, whether or not the package is installed.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from common import command_line, emit, machine_info  # noqa: E402
from hybridctl import systems  # noqa: E402

ACROBOT_BATCHES = (1, 64, 4096)
OTHER_BATCH = 4096
DRAKE_DURATION = 10.0   # simulated seconds per Drake run
DRAKE_REPEATS = 3


def _settings(quick: bool) -> dict:
    """Repeats and seconds per repeat: --quick is for tests (whole run well under 20 s)."""
    return {"repeats": 3, "seconds_per_repeat": 0.02, "gym_steps": 2000} if quick else \
        {"repeats": 7, "seconds_per_repeat": 0.25, "gym_steps": 20000}


def time_calls(fn, seconds: float, repeats: int) -> dict:
    """Median seconds per call of ``fn()``: warm up, size a repeat to ``seconds``, time ``repeats``."""
    for _ in range(3):
        fn()
    calls, start = 0, time.perf_counter()
    while True:                       # estimate the cost of one call
        fn()
        calls += 1
        elapsed = time.perf_counter() - start
        if elapsed >= seconds / 5 or calls >= 10000:
            break
    number = max(1, round(seconds / (elapsed / calls)))
    per_call, cpu_per_call = [], []
    for _ in range(repeats):
        start, cpu_start = time.perf_counter(), time.thread_time()
        for _ in range(number):
            fn()
        per_call.append((time.perf_counter() - start) / number)
        cpu_per_call.append((time.thread_time() - cpu_start) / number)
    return {"median": statistics.median(per_call), "min": min(per_call), "max": max(per_call),
            "cpu_median": statistics.median(cpu_per_call), "calls_per_repeat": number}


def bench_gym_acrobot(settings: dict) -> dict:
    """gymnasium Acrobot-v1 ``env.step`` rate (unwrapped, random actions, reset on termination)."""
    import gymnasium as gym

    env = gym.make("Acrobot-v1").unwrapped
    env.reset(seed=0)
    n = settings["gym_steps"]
    actions = [int(a) for a in np.random.default_rng(0).integers(0, 3, size=n)]

    def run(count):
        for a in actions[:count]:
            _, _, terminated, _, _ = env.step(a)
            if terminated:
                env.reset()

    run(min(n, 500))                  # warm-up
    rates, cpu_rates = [], []
    for _ in range(settings["repeats"]):
        start, cpu_start = time.perf_counter(), time.thread_time()
        run(n)
        rates.append(n / (time.perf_counter() - start))
        cpu_rates.append(n / (time.thread_time() - cpu_start))
    env.close()
    return {"env": "Acrobot-v1 (unwrapped)", "steps_per_s": statistics.median(rates),
            "min": min(rates), "max": max(rates), "steps_per_cpu_s": statistics.median(cpu_rates),
            "steps_per_repeat": n, "repeats": settings["repeats"]}


def bench_single_env(settings: dict) -> dict:
    """``SwingupEnv("acrobot").step`` rate (one decision: 0.2 s = 20 Euler steps of one state on
    plain floats, the reward, the checks), random actions, reset at the end of each episode;
    the same loop as :func:`bench_gym_acrobot`."""
    from hybridctl.envs import SwingupEnv

    env = SwingupEnv("acrobot")
    env.reset(seed=0)
    n = max(settings["gym_steps"] // 2, 500)
    limit = env.system.action_limit
    actions = [np.array([a], dtype=np.float32) for a in np.random.default_rng(0).uniform(-limit, limit, size=n)]

    def run(count):
        for a in actions[:count]:
            _, _, terminated, truncated, _ = env.step(a)
            if terminated or truncated:
                env.reset()

    run(min(n, 500))
    rates = []
    for _ in range(settings["repeats"]):
        start = time.perf_counter()
        run(n)
        rates.append(n / (time.perf_counter() - start))
    return {"env": "hybridctl SwingupEnv('acrobot')", "substeps_per_step": env.substeps,
            "steps_per_s": statistics.median(rates), "min": min(rates), "max": max(rates),
            "steps_per_repeat": n, "repeats": settings["repeats"]}


def bench_step(system, batch: int, dtype: torch.dtype, method: str, settings: dict) -> dict:
    """State-steps per second of ``System.step`` (or ``step_unchecked``) at one batch size and dtype.

    The same states and inputs are stepped every call (no feedback), so the
    timing does not depend on where a long rollout would drift.
    """
    rng = np.random.default_rng(0)
    x = torch.tensor(system.sample_initial_states(batch, rng), dtype=dtype)
    u = torch.tensor(rng.uniform(-1, 1, size=(batch, system.n_actions)) * system.action_limit, dtype=dtype)
    step = getattr(system, method)
    t = time_calls(lambda: step(x, u), settings["seconds_per_repeat"], settings["repeats"])
    return {"system": system.name, "method": method, "batch": batch, "dtype": str(dtype).replace("torch.", ""),
            "state_steps_per_s": batch / t["median"], "seconds_per_call": t["median"],
            "seconds_per_call_min": t["min"], "seconds_per_call_max": t["max"],
            "cpu_seconds_per_call": t["cpu_median"], "calls_per_repeat": t["calls_per_repeat"]}


def bench_columns(system, settings: dict, compiled: bool) -> dict:
    """``System.step_columns`` (states (n, 4096) column-major, float64), eager or through
    ``torch.compile`` (its build time reported; skipped under --quick, which must stay fast)."""
    method = "step_columns_compiled" if compiled else "step_columns"
    entry = {"system": system.name, "method": method, "batch": OTHER_BATCH, "dtype": "float64"}
    rng = np.random.default_rng(0)
    x = torch.tensor(system.sample_initial_states(OTHER_BATCH, rng).T.copy())
    u = torch.tensor(rng.uniform(-1, 1, size=(system.n_actions, OTHER_BATCH)) * system.action_limit)
    if compiled:
        if settings["repeats"] < 5:
            return {**entry, "skipped": "--quick (torch.compile takes ~15 s)"}
        start = time.perf_counter()
        try:
            system.step_columns(x, u, compiled=True)
        except Exception as exc:  # no C++ compiler, an inductor failure: report, don't crash
            return {**entry, "error": f"{type(exc).__name__}: {exc}"}
        entry["compile_s"] = time.perf_counter() - start
    t = time_calls(lambda: system.step_columns(x, u, compiled=compiled), settings["seconds_per_repeat"],
                   settings["repeats"])
    return {**entry, "state_steps_per_s": OTHER_BATCH / t["median"], "seconds_per_call": t["median"],
            "seconds_per_call_min": t["min"], "seconds_per_call_max": t["max"],
            "cpu_seconds_per_call": t["cpu_median"], "calls_per_repeat": t["calls_per_repeat"]}


GENERATED_BATCHES = (1, 4096)


def generated_twin(chain):
    """The multibody-family twin of a chain system: the same robot read by Drake from a model
    file (the thesis acrobot's URDF; the cart-poles' SDF templates filled with the spec's values), its
    torch step generated from Drake's symbolic plant. None for chains without a model file."""
    import tempfile
    from hybridctl.systems.plants import render_model

    common = {"Q": chain.Q, "R": chain.R, "gravity": float(chain.params["gravity"]), "action_limit": chain.action_limit,
              "integrator__method": chain.integrator, "dt": chain.dt}
    if chain.name == "acrobot":
        return systems.from_drake("acrobot.urdf", goal=chain.to_drake_state(chain.goal), **common)
    if str(chain.spec.get("model.drake", "")).startswith("multibody:"):
        folder = Path(tempfile.mkdtemp(prefix="hybridctl-bench-"))
        path = folder / f"{chain.name}.sdf"
        path.write_text(render_model(chain))
        return systems.from_drake(str(path), goal=chain.goal, **common)
    return None


def bench_generated(settings: dict) -> list:
    """The generated multibody step against the hand-folded chain step on the same robot, side by side
    (``step_unchecked``, float64, batch 1 and 4096): ratio = generated seconds per call / chain's."""
    out = []
    for name in ("acrobot", "cartpole", "double_cartpole"):
        chain = systems.load(name)
        twin = generated_twin(chain)
        for batch in GENERATED_BATCHES:
            pair = {kind: bench_step(system, batch, torch.float64, "step_unchecked", settings)
                    for kind, system in (("chain", chain), ("generated", twin))}
            out.append({"system": name, "batch": batch, "chain": pair["chain"], "generated": pair["generated"],
                        "generation_seconds": twin.model.info.get("generation_seconds"),
                        "cached": twin.model.info.get("cached"),
                        "ratio_generated_vs_chain_seconds": pair["generated"]["seconds_per_call"]
                        / pair["chain"]["seconds_per_call"]})
    return out


def formula_ops(system) -> dict:
    """Operations per state-step of the dynamics formula: the binary float operations (+ - * /)
    and sin/cos calls of one integrator step, counted in the straight-line one-state code
    (``ChainDynamics.scalar``: constants folded, terms with zero coefficients dropped,
    multiplications by +-1 not written), integrator update included."""
    source = system.dynamics.scalar(system.dt, system.integrator).source
    loop = next(node for node in ast.walk(ast.parse(source)) if isinstance(node, ast.For))
    arithmetic = sum(isinstance(node, ast.BinOp) for node in ast.walk(loop))
    trig = sum(isinstance(node, ast.Call) and getattr(node.func, "id", "") in ("_sin", "_cos")
               for node in ast.walk(loop))
    return {"arithmetic_flops": arithmetic, "trig_calls": trig}


def machine_flops(settings: dict) -> dict:
    """Measured float64 FLOP/s of one core (a dense 512 x 512 matmul, torch/MKL, torch's threads)
    and the cost of torch.sin per float64 element at batch 4096 (contiguous)."""
    n = 512
    a, b = torch.rand(n, n, dtype=torch.float64), torch.rand(n, n, dtype=torch.float64)
    mm = time_calls(lambda: a @ b, settings["seconds_per_repeat"], settings["repeats"])
    angles = torch.rand(OTHER_BATCH, dtype=torch.float64) * 6.0
    sin = time_calls(lambda: torch.sin(angles), settings["seconds_per_repeat"], settings["repeats"])
    flops = 2 * n ** 3 / mm["median"]
    return {"float64_flops_per_s": flops, "matmul": f"{n}x{n} @ {n}x{n} float64, median",
            "sin_seconds_per_element": sin["median"] / OTHER_BATCH,
            "sin_flop_equivalents": sin["median"] / OTHER_BATCH * flops}


def step_limits(systems_by_name: dict, steps: list, machine: dict) -> dict:
    """FLOP-based limits of the batched step, per system, beside the measured batch-4096 float64 rate.

    ``arithmetic_limit``: FLOP/s / arithmetic FLOPs per state-step (sin/cos free);
    ``flop_limit``: sin/cos counted at their measured cost (``sin_flop_equivalents`` FLOPs each),
    i.e. 1 / (arithmetic / FLOP/s + trig calls x seconds per sin). Both assume every
    operation runs at the matmul's rate, with no memory traffic or call overhead.
    """
    out = {}
    for name, system in systems_by_name.items():
        ops = formula_ops(system)
        seconds = ops["arithmetic_flops"] / machine["float64_flops_per_s"] \
            + ops["trig_calls"] * machine["sin_seconds_per_element"]
        measured = [e["state_steps_per_s"] for e in steps if e["system"] == name and e["batch"] == OTHER_BATCH
                    and e["dtype"] == "float64" and e["method"] == "step_unchecked"]
        entry = {**ops, "integrator": system.integrator,
                 "arithmetic_limit_state_steps_per_s": machine["float64_flops_per_s"] / ops["arithmetic_flops"],
                 "flop_limit_state_steps_per_s": 1.0 / seconds}
        if measured:
            entry["measured_state_steps_per_s"] = measured[0]
            entry["fraction_of_flop_limit"] = measured[0] / entry["flop_limit_state_steps_per_s"]
        fused = [e["state_steps_per_s"] for e in steps if e["system"] == name and e["method"] == "step_columns_compiled"]
        if fused:
            entry["measured_compiled_columns_state_steps_per_s"] = fused[0]
            entry["compiled_columns_fraction_of_flop_limit"] = fused[0] / entry["flop_limit_state_steps_per_s"]
        out[name] = entry
    return out


# The shipped learned controllers that run in Drake (ppo-pendulum and ars-hopper are gymnasium agents) and the
# hand-designed energy swing-ups, each timed on the default loop and on the pre-issue-15 Python loop.
DRAKE_CONTROLLERS = (("acrobot", "energy"), ("acrobot", "ssac:models/policies/ssac-acrobot"),
                     ("cartpole", "papg:models/policies/papg-cartpole"), ("cartpole", "energy"))
ROOT = Path(__file__).resolve().parents[1]


def _time_simulation(drake, diagram, x0, repeats: int, cpu: list | None = None) -> list[float]:
    """Wall seconds of ``repeats`` 10 s runs after one warm-up run (their CPU seconds appended to ``cpu``)."""
    drake.simulate(diagram, x0, DRAKE_DURATION)
    walls = []
    for _ in range(repeats):
        start, cpu_start = time.perf_counter(), time.thread_time()
        drake.simulate(diagram, x0, DRAKE_DURATION)
        walls.append(time.perf_counter() - start)
        if cpu is not None:
            cpu.append(time.thread_time() - cpu_start)
    return walls


def bench_drake_controller(drake, name: str, controller: str, repeats: int) -> dict:
    """Real-time factor of one named controller's diagram, on the default loop (C++ switch, LQR and saturation;
    Python only in periodic updates) and on ``switch="python"`` (the Python ModeSwitch evaluated at every
    derivative evaluation and the LQR in a Python block, the loop the C++ PortSwitch replaced), timed alternately
    in this run."""
    from hybridctl.experiments.controllers import build_named_diagram

    system = systems.load(name)
    x0 = system.nudged_nominal_state()
    diagrams = {"drake": build_named_diagram(system, controller),
                "python": build_named_diagram(system, controller, switch="python")}
    walls, cpus = {"drake": [], "python": []}, {"drake": [], "python": []}
    for _ in range(repeats):
        for key, diagram in diagrams.items():
            walls[key] += _time_simulation(drake, diagram, x0, 1, cpus[key])
    traj = drake.simulate(diagrams["drake"], x0, DRAKE_DURATION)
    fast, slow = statistics.median(walls["drake"]), statistics.median(walls["python"])
    return {"system": name, "controller": controller, "realtime_factor": DRAKE_DURATION / fast,
            "realtime_factor_python_switch": DRAKE_DURATION / slow, "speedup_vs_python_switch": slow / fast,
            "realtime_factor_cpu": DRAKE_DURATION / statistics.median(cpus["drake"]),
            "realtime_factor_python_switch_cpu": DRAKE_DURATION / statistics.median(cpus["python"]),
            "wall_s": fast, "wall_s_min": min(walls["drake"]), "wall_s_max": max(walls["drake"]),
            "wall_s_python_switch": slow, "repeats": repeats, "balanced": bool(traj.balanced)}


def bench_drake(quick: bool = False) -> dict:
    """Real-time factor (simulated s / wall s) of the default acrobot hybrid diagram, 10 s from hanging down,
    and of every shipped learned controller's diagram (``controllers``)."""
    try:
        from hybridctl import drake
    except Exception as exc:  # the module may not exist yet, or fail to import: report, don't crash
        return {"skipped": f"import hybridctl.drake failed: {type(exc).__name__}: {exc}"}
    repeats = 1 if quick else DRAKE_REPEATS
    try:
        system = systems.load("acrobot")
        # Hanging down, nudged 1e-3 rad as in `make demo`: the exact bottom is an
        # equilibrium where the swing-up outputs zero, which would time an idle loop.
        x0 = system.nudged_nominal_state()
        start = time.perf_counter()
        diagram = drake.build_hybrid_diagram(system)
        build = time.perf_counter() - start
        walls = _time_simulation(drake, diagram, x0, repeats)
        traj = drake.simulate(diagram, x0, DRAKE_DURATION)
        controllers = []
        for name, controller in DRAKE_CONTROLLERS:
            kind, _, path = controller.partition(":")
            if path and not (ROOT / path).exists():
                controllers.append({"system": name, "controller": controller, "skipped": "checkpoint not found"})
                continue
            controllers.append(bench_drake_controller(drake, name, controller, repeats))
    except Exception as exc:  # the API is still moving: make the failure visible in the JSON
        return {"error": f"{type(exc).__name__}: {exc}"}
    wall = statistics.median(walls)
    return {"system": "acrobot", "diagram": "build_hybrid_diagram defaults (energy swing-up, cost-to-go gate, LQR)",
            "x0": x0.tolist(), "duration_s": DRAKE_DURATION, "build_s": build, "wall_s": wall,
            "wall_s_min": min(walls), "wall_s_max": max(walls), "repeats": repeats,
            "realtime_factor": DRAKE_DURATION / wall,
            "steps_per_s": DRAKE_DURATION / system.dt / wall, "dt": system.dt,
            "balanced": bool(getattr(traj, "balanced", False)), "controllers": controllers}


def run(quick: bool = False, threads: int = 1) -> dict:
    torch.set_num_threads(threads)
    settings = _settings(quick)
    report = {
        "benchmark": "dynamics",
        "timestamp": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "command": command_line(),
        "quick": quick,
        "machine": machine_info(),
        "method": {"timer": "time.perf_counter (wall clock); cpu_* fields: time.thread_time of the "
                            "calling thread (complete only with --threads 1)",
                   "statistic": "median", **settings,
                   "unit": "state-steps/s = batch size x System.step calls per second"},
    }
    gym_result = bench_gym_acrobot(settings)
    single_env = bench_single_env(settings)
    steps = []
    acrobot = systems.load("acrobot")
    for method in ("step", "step_unchecked"):
        for batch in ACROBOT_BATCHES:
            for dtype in (torch.float32, torch.float64):
                steps.append(bench_step(acrobot, batch, dtype, method, settings))
    columns = [bench_columns(acrobot, settings, compiled) for compiled in (False, True)]
    steps += [c for c in columns if "state_steps_per_s" in c]
    for name in systems.known_systems():
        if name != "acrobot" and systems.load(name).family == "chain":
            for method in ("step", "step_unchecked"):
                steps.append(bench_step(systems.load(name), OTHER_BATCH, torch.float64, method, settings))
    loaded = {name: (acrobot if name == "acrobot" else systems.load(name)) for name in systems.known_systems()}
    loaded = {name: system for name, system in loaded.items() if system.family == "chain"}
    generated = bench_generated(settings)
    flops = machine_flops(settings)
    drake_result = bench_drake(quick)

    gym_rate = gym_result["steps_per_s"]
    for entry in steps:
        entry["ratio_vs_gym_acrobot"] = entry["state_steps_per_s"] / gym_rate
    if "steps_per_s" in drake_result:
        drake_result["ratio_vs_gym_acrobot"] = drake_result["steps_per_s"] / gym_rate
    single_env["ratio_vs_gym_acrobot"] = single_env["steps_per_s"] / gym_rate
    limits = {"machine": flops, "systems": step_limits(loaded, steps, flops)}
    for entry in limits["systems"].values():
        entry["flop_limit_ratio_vs_gym_acrobot"] = entry["flop_limit_state_steps_per_s"] / gym_rate
    report["step_columns_not_measured"] = [c for c in columns if "state_steps_per_s" not in c]
    report.update({"gym_acrobot": gym_result, "single_env": single_env, "step": steps, "step_limits": limits,
                   "generated_vs_chain": generated, "drake_hybrid": drake_result})
    return report


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer, shorter repeats (for tests)")
    parser.add_argument("--out", type=Path, help="also write the JSON to this file")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = parser.parse_args(argv)
    if args.threads < 1:
        parser.error("--threads must be >= 1")
    emit(run(quick=args.quick, threads=args.threads), args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
