"""The thesis drivers (python -m hybridctl.reproduce.NAME) that run parallel work take the commands'
--backend/--workers/--address and pass them to the workload; the others run nothing parallel."""

from __future__ import annotations

import argparse
import importlib
import json
from pathlib import Path

import numpy as np
import pytest

from hybridctl.reproduce import common

# driver -> the arguments before --help (a sub-command where the flags live)
PARALLEL = {"cartpole_record": [], "ch3_results": [], "ch6_finetune": ["finetune"], "hopper": [],
            "hopper_error": [], "hopper_ulam": [], "matrix": ["run"], "papg_takeover_seeds": [], "table41": [],
            "table44": [],
            "table51": [], "table71": ["run"], "walker_seeds": []}
# Stable-Baselines3 training and evaluation in this process (ch6_agents, sb3_baselines); Fig. 7.1's
# landscape and gradient norms of one population in this process (fig71)
NOTHING_PARALLEL = {"ch6_agents": [], "fig71": [], "sb3_baselines": [], "fit_robots": ["pendubot", "--out", "x"]}
REPRODUCE = Path(importlib.import_module("hybridctl.reproduce").__file__).parent


def help_text(name: str, before: list[str], capsys) -> str:
    module = importlib.import_module(f"hybridctl.reproduce.{name}")
    with pytest.raises(SystemExit) as stop:
        module.main([*before, "--help"])
    assert stop.value.code == 0
    return capsys.readouterr().out


def test_every_driver_is_classified():
    drivers = {p.stem for p in REPRODUCE.glob("*.py")} - {"__init__", "common"}
    assert drivers == set(PARALLEL) | set(NOTHING_PARALLEL)


@pytest.mark.parametrize("name", sorted(PARALLEL))
def test_parallel_drivers_list_the_backend_flags(name, capsys):
    text = help_text(name, PARALLEL[name], capsys)
    for flag in ("--backend {serial,processes,ray}", "--workers", "--address"):
        assert flag in text, f"{name}: {flag}"


@pytest.mark.parametrize("name", sorted(NOTHING_PARALLEL))
def test_the_other_drivers_have_no_backend_flags(name, capsys):
    assert "--backend" not in help_text(name, NOTHING_PARALLEL[name], capsys)


def test_the_flags_are_the_commands_flags():
    """Same names, choices, help, parsing and refusals as hybridctl.cli._common's: both are
    hybridctl.parallel.add_backend_arguments (reproduce may not import cli, ARCHITECTURE.md)."""
    from hybridctl.cli import _common

    ours, theirs = argparse.ArgumentParser(), argparse.ArgumentParser()
    common.add_backend_flags(ours, "processes", "work")
    _common.add_backend_flags(theirs, "processes", "work")
    actions = {parser: {a.dest: a for a in parser._actions} for parser in (ours, theirs)}
    for dest in ("backend", "workers", "address"):
        a, b = actions[ours][dest], actions[theirs][dest]
        assert (a.option_strings, a.choices, a.default, a.nargs, a.help) == (b.option_strings, b.choices, b.default,
                                                                             b.nargs, b.help)
    argv = ["--backend", "ray", "--workers", "3", "--address", "host:6379"]
    parsed, expected = ours.parse_args(argv), theirs.parse_args(argv)
    assert common.backend_options(parsed) == {key: getattr(expected, key) for key in ("backend", "workers", "address")}
    assert common.backend_options(parsed) == {"backend": "ray", "workers": 3, "address": "host:6379"}
    for bad in (["--workers", "0"], ["--workers", "two"], ["--backend", "mpi"]):
        with pytest.raises(SystemExit):
            ours.parse_args(bad)
        with pytest.raises(SystemExit):
            theirs.parse_args(bad)
    for args in (ours.parse_args(["--address", "host:6379"]), ours.parse_args(["--workers", "100000"])):
        with pytest.raises(ValueError, match="--address .* applies to --backend ray only|--workers is 100,000"):
            common.check_backend_flags(args)


def test_a_driver_passes_the_flags_to_its_workload(tmp_path, monkeypatch, capsys):
    """papg_takeover_seeds' balance maps get --backend/--workers/--address; without them, serial as before;
    --address without --backend ray is a usage error before any map."""
    driver = importlib.import_module("hybridctl.reproduce.papg_takeover_seeds")
    folder = tmp_path / "run"
    (folder / "final").mkdir(parents=True)
    (folder / "eval.json").write_text(json.dumps({"command": "x"}))
    (folder / "final" / "config.json").write_text(json.dumps({"config": {"seed": 3}}))
    calls = []

    class Map:
        fraction = 0.5
        balanced = np.array([[True, False]])

    def spy(system, controller, **kwargs):
        calls.append(kwargs)
        return Map()

    monkeypatch.setattr(driver, "balance_map", spy)
    out = tmp_path / "record.json"
    assert driver.main([str(folder), "--out", str(out)]) == 0
    assert driver.main([str(folder), "--out", str(out), "--backend", "processes", "--workers", "2"]) == 0
    assert [(c["backend"], c["workers"], c["address"]) for c in calls] == [("serial", None, None),
                                                                           ("processes", 2, None)]
    with pytest.raises(SystemExit) as stop:
        driver.main([str(folder), "--out", str(out), "--address", "host:6379"])
    assert stop.value.code == 2 and "applies to --backend ray only" in capsys.readouterr().err
    assert len(calls) == 2


def test_training_commands_keep_their_backend_unless_given():
    """The ARS training runs the drivers start: ``--backend serial`` as before, else the flags."""
    from hybridctl.reproduce import table51

    parser = argparse.ArgumentParser()
    common.add_backend_flags(parser, "serial", "work")
    default = common.backend_cli_args(parser.parse_args([]))
    assert table51.ars_command("hc", 1, backend=default) == table51.ars_command("hc", 1)
    assert "--backend serial" in " ".join(table51.ars_command("hc", 1))
    given = common.backend_cli_args(parser.parse_args(["--backend", "ray", "--workers", "4", "--address", "auto"]))
    assert given == ["--backend", "ray", "--workers", "4", "--address", "auto"]
    assert " ".join(given) in " ".join(table51.ars_command("hc", 1, backend=given))
