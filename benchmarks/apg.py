"""Analytic policy gradients: APG iterations/s and state-steps/s through forward and backward for a
population x batch of 24 x 4 over T = 500 policy steps (thesis Sec. 7.3.7), against (a) a Python
loop over the 24 members and (b) a zeroth-order (ES) estimate of the same cost, in the same run.
Prints one JSON document.

    .venv/bin/python benchmarks/apg.py [--quick] [--horizon T] [--system NAME] [--dtype float32|float64] [--period S] [--compile]
                                       [--compile-steps S] [--repeats R] [--out FILE] [--threads N]
                                       [--learner-epochs E]

One APG iteration = the batched rollout of K members x N starts (the GRU policy of the thesis,
one action held over the spec's swing-up period, i.e. ``substeps`` integrator steps) and one
backward, giving every member its exact gradient. The member loop does the same work one member
at a time. The ES peer estimates ONE policy's gradient from K perturbations x N starts of the
same rollout, forward only (no graph), i.e. the same number of state steps: the ratio says what
an exact gradient costs over a zeroth-order estimate built from as many rollouts.

Every number is the median of ``repeats`` timed calls after a warm-up, measured in this one run,
so ratios compare like with like under the same machine load (which is recorded).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import torch  # noqa: E402

from common import command_line, emit, machine_info  # noqa: E402
from hybridctl import systems  # noqa: E402
from hybridctl.learn.apg import (compiled_policy_step, compiled_policy_steps, member_gradients,  # noqa: E402
                                 observation_size, population_returns)
from hybridctl.learn.policies import PolicyPopulation  # noqa: E402

POPULATION, BATCH, HORIZON = 24, 4, 500
PERIOD = 0.04   # s per policy step: the author's acrobot (dt 0.01 x 4 substeps, implementation notes Ch. 7)


def _time(fn, repeats: int, warm_up: bool = True) -> dict:
    """Median wall seconds of ``fn()`` over ``repeats`` calls after one warm-up call."""
    if warm_up:
        fn()
    walls = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        walls.append(time.perf_counter() - start)
    return {"median_s": statistics.median(walls), "min_s": min(walls), "max_s": max(walls), "repeats": repeats}


def run(system_name: str = "acrobot", horizon: int = HORIZON, dtype: str = "float32", repeats: int = 3,
        threads: int = 1, quick: bool = False, period: float = PERIOD, compile: bool = False,
        compile_steps: int = 10) -> dict:
    """Time the batched APG iteration, the member loop and the ES peer; the report as a dict."""
    torch.set_num_threads(threads)
    system = systems.load(system_name, reward__kind="angle_squared")
    torch_dtype = torch.float64 if dtype == "float64" else torch.float32
    substeps = max(1, int(round(period / system.dt)))
    obs = observation_size(system)
    pop = PolicyPopulation.gru(obs, system.n_actions, system.action_limit, members=POPULATION, dtype=torch_dtype,
                               generator=torch.Generator().manual_seed(0))
    x0 = torch.as_tensor(system.initial_state.nominal, dtype=torch_dtype).repeat(BATCH, 1)
    x0 = x0 + 0.01 * torch.rand(x0.shape, dtype=torch_dtype, generator=torch.Generator().manual_seed(1))
    members = [pop.resized(1, pop.to_flat()[k:k + 1]) for k in range(POPULATION)]

    def batched():
        returns, *_ = population_returns(system, pop, x0, horizon, substeps)
        return member_gradients(pop, -returns.mean(1))

    def fused():   # the same iteration with the per-step work through torch.compile
        returns, *_ = population_returns(system, pop, x0, horizon, substeps, step=compiled_policy_step())
        return member_gradients(pop, -returns.mean(1))

    def chunked():   # ``compile_steps`` policy steps per compiled call (APGConfig.compile_steps)
        returns, *_ = population_returns(system, pop, x0, horizon, substeps, steps=compiled_policy_steps(),
                                         steps_per_call=compile_steps)
        return member_gradients(pop, -returns.mean(1))

    def loop():
        return [member_gradients(m, -population_returns(system, m, x0, horizon, substeps)[0].mean(1))
                for m in members]

    es_pop = pop.resized(POPULATION, pop.to_flat()[:1].repeat(POPULATION, 1))
    noise = torch.randn((POPULATION // 2, pop.n_params), dtype=torch_dtype, generator=torch.Generator().manual_seed(2))
    theta = pop.to_flat()[0]

    def es():   # antithetic ES: 12 directions x (+, -) = 24 perturbed copies of ONE policy, forward only
        with torch.no_grad():
            es_pop.from_flat(torch.cat([theta + 0.02 * noise, theta - 0.02 * noise]))
            r = population_returns(system, es_pop, x0, horizon, substeps)[0].mean(1)
            return ((r[:POPULATION // 2] - r[POPULATION // 2:]) @ noise) / (2 * 0.02 * noise.shape[0])

    # the batched gradients are the member loop's (checked here, so a fast wrong answer shows)
    agree = max(float((a - b[0]).abs().max() / (b[0].abs().max() + 1e-30)) for a, b in zip(batched(), loop()))
    steps_per_iteration = POPULATION * BATCH * horizon
    results, checks = {}, {}
    runs = [("batched_population", batched), ("member_loop", loop), ("es_forward_only", es)]
    if compile:
        start = time.perf_counter()
        reference = batched()
        compiled = fused()
        checks["compile_s"] = time.perf_counter() - start
        checks["max_relative_difference_compiled_vs_eager"] = float((compiled - reference).abs().max()
                                                                    / reference.abs().max())
        start = time.perf_counter()
        several = chunked()
        checks["compile_steps_s"] = time.perf_counter() - start
        checks["max_relative_difference_compile_steps_vs_eager"] = float((several - reference).abs().max()
                                                                         / reference.abs().max())
        runs.insert(1, ("batched_population_compiled", fused))
        runs.insert(2, ("batched_population_compile_steps", chunked))
    for name, fn in runs:
        t = _time(fn, repeats, warm_up=name != "member_loop")   # the check above warmed the loop up
        t.update(iterations_per_s=1.0 / t["median_s"], state_steps_per_s=steps_per_iteration / t["median_s"],
                 physics_steps_per_s=steps_per_iteration * substeps / t["median_s"])
        results[name] = t
    b, l, e = (results[k]["median_s"] for k in ("batched_population", "member_loop", "es_forward_only"))
    ratios = {"batched_vs_member_loop": l / b, "apg_iteration_over_es_iteration": b / e,
              "es_iteration_over_apg_iteration": e / b}
    projection = {"ce_apg_epoch_s": 100 * b, "ce_apg_200_epochs_h": 200 * 100 * b / 3600}
    if compile:
        c = results["batched_population_compiled"]["median_s"]
        f = results["batched_population_compile_steps"]["median_s"]
        ratios.update(compiled_vs_eager=b / c, compiled_vs_member_loop=l / c, apg_compiled_over_es_iteration=c / e,
                      compile_steps_vs_compiled=c / f, compile_steps_vs_eager=b / f)
        projection.update(ce_apg_epoch_s_compiled=100 * c, ce_apg_200_epochs_h_compiled=200 * 100 * c / 3600,
                          ce_apg_epoch_s_compile_steps=100 * f, ce_apg_200_epochs_h_compile_steps=200 * 100 * f / 3600)
    return {
        "benchmark": "apg",
        "timestamp": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "command": command_line(),
        "quick": quick,
        "machine": machine_info(),
        "setting": {"system": system.name, "population": POPULATION, "batch": BATCH, "horizon": horizon,
                    "period_s": period, "substeps_per_policy_step": substeps, "integrator": system.integrator, "dt": system.dt,
                    "dtype": dtype, "policy": pop.describe(), "reward": "angle_squared",
                    "compile_steps": compile_steps if compile else None,
                    "state_steps_per_iteration": steps_per_iteration,
                    "unit": "state-steps = policy steps (K x N x T); physics steps = x substeps"},
        "results": results,
        "ratios": ratios,
        "projection": {**projection, "note": "100 APG iterations of the 24 x 4 population per CE epoch (thesis "
                                             "Sec. 7.3.7), scaled from the measured iteration at this horizon"},
        "check": {"max_relative_difference_batched_vs_loop": agree, **checks},
    }


def learner_epochs(system_name: str, period: float, horizon: int, epochs: int, settle: bool = True) -> dict:
    """Wall seconds of each epoch of the CE-APG learner itself (``hybridctl train ce-apg``: the thesis preset,
    K 24, N 4, 100 APG iterations an epoch, compiled) on ``system_name`` with ``period`` s policy steps; the
    first epoch includes compiling. ``settle`` False: without the training skeleton's freeze of what the
    compile left for the garbage collector (:class:`hybridctl.systems.compiled.CompileGarbage`), the peer."""
    import tempfile

    from hybridctl.learn import APG, APGConfig
    from hybridctl.systems import compiled

    original = compiled.CompileGarbage.settle
    if not settle:
        compiled.CompileGarbage.settle = lambda self: None
    try:
        config = APGConfig.preset("thesis", method="ce-apg", control_period=period, horizon=horizon, epochs=epochs,
                                  compile="on")
        agent = APG(system_name, config)
        with tempfile.TemporaryDirectory() as out:
            agent.learn(out=out, progress=False)
    finally:
        compiled.CompileGarbage.settle = original
    walls = [0.0] + [row["wall_time"] for row in agent.history]
    per_epoch = [b - a for a, b in zip(walls, walls[1:])]
    later = per_epoch[1:]
    return {"epoch_s": per_epoch, "settle": settle, "apg_iterations": config.apg_iterations,
            "median_epoch_s_after_the_first": statistics.median(later) if later else None}


def learner_epochs_in_a_process(system_name: str, period: float, horizon: int, epochs: int, settle: bool) -> dict:
    """:func:`learner_epochs` in a new interpreter (this script with ``--learner-run``), its JSON read back."""
    import json
    import subprocess

    out = subprocess.run([sys.executable, __file__, "--learner-run", "on" if settle else "off", "--system",
                          system_name, "--period", str(period), "--horizon", str(horizon), "--learner-epochs",
                          str(epochs)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def main(argv=None) -> int:
    """Parse flags, run, print the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="horizon 20, 2 repeats (for tests)")
    parser.add_argument("--horizon", type=int, default=None, help=f"policy steps per rollout (default {HORIZON})")
    parser.add_argument("--system", default="acrobot")
    parser.add_argument("--period", type=float, default=PERIOD,
                        help=f"seconds per policy step (default {PERIOD}: the author's acrobot)")
    parser.add_argument("--compile", action="store_true",
                        help="also time the iteration with the per-step work through torch.compile, one call "
                             "per policy step and --compile-steps steps per call")
    parser.add_argument("--compile-steps", type=int, default=10,
                        help="policy steps per compiled call for the second compiled timing (default 10)")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    parser.add_argument("--repeats", type=int, default=None, help="timed calls per measurement (default 3)")
    parser.add_argument("--out", type=Path, help="also write the JSON to this file")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--learner-epochs", type=int, default=0,
                        help="also time this many epochs of the CE-APG learner itself (thesis preset, compiled), with "
                             "and without the freeze of compile garbage (default 0: not timed; make bench: 3)")
    parser.add_argument("--learner-run", choices=("on", "off"), help=argparse.SUPPRESS)   # one learner_epochs run
    args = parser.parse_args(argv)
    horizon = args.horizon if args.horizon is not None else (20 if args.quick else HORIZON)
    repeats = args.repeats if args.repeats is not None else (2 if args.quick else 3)
    if horizon < 1 or repeats < 1 or args.threads < 1 or args.compile_steps < 1 or not args.period > 0:
        parser.error("--horizon, --repeats, --threads and --compile-steps must be >= 1, --period > 0")
    if args.learner_epochs < 0:
        parser.error("--learner-epochs must be >= 0")
    if args.learner_run:
        torch.set_num_threads(args.threads)
        print(json.dumps(learner_epochs(args.system, args.period, horizon, max(1, args.learner_epochs),
                                        args.learner_run == "on")))
        return 0
    report = run(args.system, horizon, args.dtype, repeats, args.threads, args.quick, args.period,
                 args.compile, args.compile_steps)
    if args.learner_epochs:
        eager_epoch = report["projection"]["ce_apg_epoch_s"]
        # each variant in a fresh interpreter: run one after the other in this process, the second found the
        # graphs compiled and the first one's garbage settled, and came out 2-11 % faster whichever it was
        timed = [learner_epochs_in_a_process(args.system, args.period, horizon, args.learner_epochs, settle)
                 for settle in (False, True)]
        report["learner"] = {"ce_apg_thesis_preset": timed, "eager_epoch_s_projected": eager_epoch,
                             "note": "epoch_s[0] includes compiling; the thesis' aim here is <= 20 s an epoch"}
        medians = [t["median_epoch_s_after_the_first"] for t in timed]
        if None not in medians:
            report["ratios"].update(learner_epoch_vs_eager=eager_epoch / medians[0],
                                    learner_epoch_settle_vs_without=medians[1] / medians[0])
    emit(report, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
