"""Bounded by default (issue 29, item 4 and Deliver 3): every duration, grid, count, thread and size is
checked against ``hybridctl.limits`` before any work, with one line naming the flag and its limit;
``--force`` lifts the stated caps, never the memory limit; no flag abbreviations.

Each bad-input row must fail fast: a short timeout per row (the unbounded runs of the issue ran for
minutes, or for ever) and nothing written into ``--out``.
"""

from __future__ import annotations

import math
import re

import pytest

from hybridctl import limits
from hybridctl.limits import LimitError

CLI_CASES = [
    # item 4: unbounded work, and the tracebacks and silent acceptances of the same flags
    (["simulate", "acrobot", "--controller", "zero", "--duration", "1e9"],
     r"--duration is 1e\+09, above its limit of 100000 \(seconds of one run: 10,000,000 steps of dt = 0.01 s\); "
     r"pass --force"),
    (["simulate", "acrobot", "--duration", "1e308"], r"--duration is 1e\+308, above its limit of 100000"),
    (["simulate", "acrobot", "--duration", "1e12", "--force"], r"--duration needs .* GiB for the recorded run"),
    (["simulate", "acrobot", "--duration", "1e-9"], r"--duration 1e-09 s is shorter than one time step of acrobot"),
    (["simulate", "acrobot", "--x0=1,,0,0,0,"], r"--x0 has an empty field at position 2: it needs 4"),
    (["simulate", "acrobot", "--x0=1,0,0,0,"], r"--x0 has an empty field at position 5"),
    (["balance-map", "acrobot", "--engine", "torch", "--duration", "1e9"], r"--duration is 1e\+09, above its limit"),
    (["balance-map", "acrobot", "--grid", "100000"], r"--grid is 100,000, above its limit of 1,001 \(points per axis\)"),
    (["balance-map", "acrobot", "--grid", "1001", "--duration", "100"],
     r"--grid 1001 x 1001 runs of --duration 100 s is 10,020,010,000, above its limit of 10,000,000,000"),
    (["balance-map", "acrobot", "--grid", "5000", "--engine", "torch", "--force"],
     r"--grid and --duration needs .* GiB for the torch engine's batched states"),
    (["balance-map", "acrobot", "--grid", "2", "--workers", "1000000"],
     r"--workers is 1,000,000, above its limit of \d+ \(cores this process may use\); pass --force"),
    (["mesh", "rimless-wheel", "--disturbances", "100000000"],
     r"disturbances \(--disturbances\) is 100,000,000, above its limit of 100,000"),
    (["mesh", "rimless-wheel", "--disturbances", "200000", "--force"],
     r"disturbances \(--disturbances\) x max_states \(--max-states\) needs .* GiB for the mesh's successor table"),
    (["mesh", "rimless-wheel", "--max-states", "1000000000000"],
     r"disturbances \(--disturbances\) x max_states \(--max-states\) needs .* GiB"),
    (["mesh", "rimless-wheel", "--monte-carlo", "1000000000"], r"--monte-carlo is 1,000,000,000, above its limit"),
    (["mesh", "rimless-wheel", "--workers", "1000000"], r"--workers is 1,000,000, above its limit of \d+"),
    (["mesh", "rimless-wheel", "--slope-mean", "inf"], r"argument --slope-mean: must be a finite number, got inf"),
    (["mesh", "rimless-wheel", "--slope-mean", "nan"], r"argument --slope-mean: must be a finite number, got nan"),
    (["train", "ce-apg", "acrobot", "--torch-threads", "100000"],
     r"argument --torch-threads: must be an integer at most \d+ \(cores this process may use\), got 100000"),
    (["train", "sac", "acrobot", "--torch-threads", "100000"], r"argument --torch-threads: must be an integer at most \d+ .*got 100000"),
    (["train", "sac", "acrobot", "--hidden-size", "10000000"],
     r"argument --hidden-size: must be an integer at most 65,536 .*got 10000000"),
    (["train", "sac", "acrobot", "--hidden-size", "60000"],
     r"SACConfig.hidden_size \(--hidden-size\) x SACConfig.hidden_layers \(--hidden-layers\) needs .* GiB"),
    (["train", "sac", "acrobot", "--num-envs", "1000000000000"],
     r"argument --num-envs: must be an integer at most 1,000,000 .*got 1000000000000"),
    (["train", "ssac", "acrobot", "--seed", "1e23"], r"argument --seed: must be an integer at most "
                                                     r"9,223,372,036,854,775,807 .*got 1e23"),
    (["demo", "--grid", "1"], r"--grid must be >= 2 \(an integer\), got 1"),
    (["demo", "--grid", "5000"], r"--grid is 5,000, above its limit of 1,001"),
    # items 5-6: a Ray address with a local backend, flag abbreviations
    (["train", "ars", "Pendulum-v1", "--address", "auto"],
     r"ARSConfig.address \(--address\) applies to backend 'ray' only, not 'processes'"),
    (["train", "ce-apg", "acrobot", "--init-s", "0.5"], r"unrecognized arguments: --init-s 0.5"),
    (["train", "ce-apg", "acrobot", "--over"], r"unrecognized arguments: --over"),
    (["simulate", "acrobot", "--dur", "5"], r"unrecognized arguments: --dur 5"),
    (["balance-map", "acrobot", "--eng", "torch"], r"unrecognized arguments: --eng torch"),
    (["mesh", "rimless-wheel", "--monte", "5"], r"unrecognized arguments: --monte 5"),
]


@pytest.mark.timeout(60)
@pytest.mark.parametrize("argv, message", CLI_CASES, ids=[" ".join(a) for a, _ in CLI_CASES])
def test_cli_refuses_before_any_work(argv, message, tmp_path, cli_error):
    out = tmp_path / "out"
    err = cli_error([*argv, "--out", out])
    errors = [line for line in err.splitlines() if "error:" in line]  # argparse prints its usage above
    assert len(errors) == 1 and re.search(message, errors[0]), err
    assert not out.exists(), "the command started work before refusing"


def _acrobot():
    from hybridctl.systems import load

    return load("acrobot")


def _simulate_huge():
    from hybridctl.drake.simulate import check_duration

    check_duration(_acrobot(), 1e9)


def _balance_map(**kw):
    from hybridctl.experiments import balance_map

    balance_map("pendulum", "energy", progress=False, **kw)


def _mesh(count, **kw):
    from hybridctl.analysis import GaussianDisturbance, RimlessWheel, build_mesh

    wheel = RimlessWheel()
    build_mesh(wheel, [[wheel.fixed_point(0.15)]], GaussianDisturbance(0.15, 0.06, count), 1e-3, progress=False, **kw)


def _monte_carlo(episodes, **kw):
    from hybridctl.analysis import GaussianDisturbance, RimlessWheel, monte_carlo_mfpt

    monte_carlo_mfpt(RimlessWheel(), [[1.29]], GaussianDisturbance(0.15, 0.06), episodes=episodes, **kw)


def _config(module, cls, **kw):
    import importlib

    getattr(importlib.import_module(f"hybridctl.learn.{module}"), cls)(**kw).validate()


def _backend(name, **kw):
    from hybridctl.parallel import make_backend

    make_backend(name, **kw)


def _env(num_envs):
    from hybridctl.envs import TorchVectorEnv

    TorchVectorEnv("acrobot", num_envs)


API_CASES = [
    ("simulate duration", _simulate_huge, LimitError, r"--duration is 1e\+09"),
    ("balance_map grid", lambda: _balance_map(grid=100_000), LimitError, r"--grid is 100,000"),
    ("balance_map grid 1", lambda: _balance_map(grid=1), ValueError, r"--grid must be >= 2 \(an integer\)"),
    ("balance_map steps", lambda: _balance_map(grid=1001, duration=1000.0), LimitError,
     r"time steps of all runs together"),
    ("balance_map workers", lambda: _balance_map(grid=2, workers=10**6), LimitError, r"--workers is 1,000,000"),
    ("build_mesh disturbances", lambda: _mesh(10**8), LimitError, r"disturbances \(--disturbances\) is 100,000,000"),
    ("build_mesh memory", lambda: _mesh(10**8, force=True), LimitError, r"needs .* GiB for the mesh's successor"),
    ("monte_carlo_mfpt episodes", lambda: _monte_carlo(10**9), LimitError, r"episodes \(--monte-carlo\) is 1,000,0"),
    ("monte_carlo_mfpt memory", lambda: _monte_carlo(10**13, force=True), LimitError, r"needs .* GiB"),
    ("serial backend address", lambda: _backend("serial", address="auto"), ValueError,
     r"address 'auto' \(--address\) applies to backend 'ray' only, not 'serial'"),
    ("processes backend address", lambda: _backend("processes", address="auto"), ValueError, r"not 'processes'"),
    ("TorchVectorEnv num_envs", lambda: _env(10**12), LimitError, r"num_envs \(--num-envs\) needs .* GiB"),
    ("SACConfig torch_threads", lambda: _config("sac", "SACConfig", torch_threads=10**5), LimitError,
     r"SACConfig.torch_threads \(--torch-threads\)"),
    ("SACConfig seed", lambda: _config("sac", "SACConfig", seed=2**63), LimitError, r"SACConfig.seed \(--seed\)"),
    ("ARSConfig torch_threads", lambda: _config("ars", "ARSConfig", torch_threads=10**5), LimitError,
     r"ARSConfig.torch_threads"),
    ("FineTuneConfig seed", lambda: _config("finetune", "FineTuneConfig", seed=10**23), LimitError,
     r"FineTuneConfig.seed"),
    ("APGConfig address", lambda: _config("apg", "APGConfig", address="auto"), ValueError,
     r"APGConfig.address \(--address\) applies to backend 'ray' only, not 'serial'"),
    ("GateConfig hidden", lambda: _config("gate", "GateConfig", hidden=(32, 10**6)), LimitError,
     r"GateConfig.hidden \(--hidden\) is 1,000,000, above its limit of 65,536"),
    ("GateConfig hidden memory", lambda: _config("gate", "GateConfig", hidden=(65_536,) * 100), LimitError,
     r"GateConfig.hidden \(--hidden\) needs .* GiB"),
]


@pytest.mark.timeout(60)
@pytest.mark.parametrize("name, call, error, message", API_CASES, ids=[c[0] for c in API_CASES])
def test_python_api_refuses_before_any_work(name, call, error, message):
    with pytest.raises(error, match=message):
        call()


def test_the_limits_admit_what_they_state():
    """The boundaries are inclusive, --force lifts a cap, and valid settings pass (the checks can fail)."""
    from hybridctl.drake.simulate import check_duration
    from hybridctl.learn.config_check import MAX_SEED
    from hybridctl.learn.sac import SACConfig

    acrobot = _acrobot()
    longest = limits.MAX_SIMULATION_STEPS * acrobot.dt
    assert check_duration(acrobot, longest) == longest
    assert check_duration(acrobot, acrobot.dt) == acrobot.dt        # one step is enough to record a run
    assert check_duration(acrobot, None) == acrobot.episode_duration
    with pytest.raises(LimitError):
        check_duration(acrobot, 1.01 * longest)
    assert check_duration(acrobot, 1.01 * longest, force=True) == 1.01 * longest
    SACConfig(seed=MAX_SEED, torch_threads=limits.cpu_count(), num_envs=limits.MAX_NUM_ENVS).validate()


def test_help_lists_the_limits_from_hybridctl_limits(capsys):
    from hybridctl.cli import main

    for command, shown in (("simulate", [limits.MAX_SIMULATION_STEPS]),
                           ("balance-map", [limits.MAX_GRID, limits.MAX_TOTAL_STEPS, limits.MAX_SIMULATION_STEPS]),
                           ("mesh", [limits.MAX_DISTURBANCES, limits.MAX_MONTE_CARLO])):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert "--force" in text and "memory" in text, text
        for value in shown:
            assert f"{value:,}" in text, (command, value)


def test_every_parser_refuses_abbreviations():
    """allow_abbrev=False on every parser of the command, sub-commands and learners included."""
    import argparse

    from hybridctl.cli import build_parser
    from hybridctl.cli._common import CommandParser

    seen, todo = [], [build_parser()]
    while todo:
        parser = todo.pop()
        seen.append(parser)
        assert isinstance(parser, CommandParser) and parser.allow_abbrev is False, parser.prog
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                todo.extend(action.choices.values())
    assert len(seen) > 10  # the top level, every command and every learner of `train`


def test_balance_map_never_starts_more_workers_than_tasks(monkeypatch):
    """`balance-map --grid 2 --workers 64 --force` started 64 processes for 4 starts."""
    import importlib

    module = importlib.import_module("hybridctl.experiments.balance_map")  # the package exports a function of that name
    asked, real = [], module.make_backend

    def recording(name, workers=None, address=None, **kwargs):   # runs the tasks here, records what was asked
        asked.append((name, workers))
        backend = real("serial")
        backend.workers = workers or 1
        return backend

    monkeypatch.setattr(module, "make_backend", recording)
    result = module.balance_map("pendulum", "energy", grid=2, duration=0.2, workers=64, force=True, progress=False)
    assert asked == [("processes", 4)] and result.meta["workers"] == 4
    assert result.balanced.shape == (2, 2)


def test_simulate_says_what_it_wrote(tmp_path, capsys):
    """`--x0=1e6,...` printed "wrote ... plot.png" with no plot written."""
    from hybridctl.cli import main

    out = tmp_path / "sim"
    assert main(["simulate", "acrobot", "--x0=1e6,0,0,0", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"wrote {out}/trajectory.npz, summary.json\n" in printed
    assert "no plot.png or replay.html" in printed
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == ["summary.json", "trajectory.npz"]
    one_step = tmp_path / "step"
    assert main(["simulate", "acrobot", "--duration", "0.01", "--no-html", "--out", str(one_step)]) == 0
    assert f"wrote {one_step}/trajectory.npz, summary.json, plot.png\n" in capsys.readouterr().out
    assert (one_step / "plot.png").is_file()


def test_demo_checks_its_arguments_before_simulating(tmp_path):
    from hybridctl.experiments import run_demo

    with pytest.raises(ValueError, match="--grid must be >= 2 \\(an integer\\)"):
        run_demo(tmp_path / "demo", grid=1, report=None)
    with pytest.raises(Exception, match="no checkpoint directory"):
        run_demo(tmp_path / "demo", checkpoint=tmp_path / "missing", report=None)
    assert not (tmp_path / "demo").exists()
    assert math.isfinite(limits.memory_budget())
