"""Every public entry point rejects bad input before any work, naming the argument and the accepted range.

One table: (entry point, bad input) -> the message it must give. Cases cover empty, NaN, inf,
wrong type, wrong shape and out-of-range values for the command line, spec overrides, the
dynamics, the post-processors, the section maps and mesh builder, the Drake simulation, the
envs and every learner config. The command-line cases also check the exit code (2) and that
no traceback is printed.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import typing
import warnings

import numpy as np
import pytest
import torch

from hybridctl import systems
from hybridctl.cli import main
from hybridctl.systems import SpecError

NAN, INF = float("nan"), float("inf")

# ------------------------------------------------------------------------------------- CLI
CLI_CASES = [
    (["simulate", "acrobot", "--x0=nan,0,0,0"], "--x0 must be finite numbers"),
    (["simulate", "acrobot", "--x0=inf,0,0,0"], "--x0 must be finite numbers"),
    (["simulate", "acrobot", "--x0=1e300,0,0,0"], r"x0 entries must lie in \[-1e\+06, 1e\+06\]"),
    (["simulate", "acrobot", "--x0=1,2"], "--x0 needs 4 values"),
    (["simulate", "acrobot", "--x0=a,b,c,d"], "--x0 must be 4 comma-separated numbers"),
    (["simulate", "acrobot", "--x0="], "--x0 needs 4 values"),
    (["simulate", "acrobot", "--duration", "nan"], "--duration: must be a finite number > 0"),
    (["simulate", "acrobot", "--duration", "inf"], "--duration: must be a finite number > 0"),
    (["simulate", "acrobot", "--duration", "-1"], "--duration: must be a finite number > 0"),
    (["simulate", "acrobot", "--duration", "ten"], "--duration: invalid float value"),
    (["simulate", "nosuch"], "unknown system 'nosuch'; known systems: acrobot"),
    (["simulate", "acrobot", "--controller", "nope"], "unknown controller 'nope'"),
    (["simulate", "acrobot", "--controller", "ssac:"], "needs a checkpoint path"),
    (["simulate", "acrobot", "--out", "{file}"], "is a file; outputs go into a folder"),
    (["balance-map", "acrobot", "--grid", "2.5"], "--grid: invalid int value"),
    (["balance-map", "acrobot", "--grid", "1"], "grid must be >= 2"),
    (["balance-map", "acrobot", "--grid", "0"], "--grid: must be a finite number > 0"),
    (["balance-map", "acrobot", "--workers", "0"], "--workers: must be a finite number > 0"),
    (["balance-map", "acrobot", "--grid", "2", "--out", "{file}"], "is a file; outputs go into a folder"),
    (["mesh", "rimless-wheel", "--box-size", "nan"], "--box-size: must be a finite number > 0"),
    (["mesh", "rimless-wheel", "--box-size", "0"], "--box-size: must be a finite number > 0"),
    (["mesh", "rimless-wheel", "--monte-carlo", "-5"], "--monte-carlo: must be a finite number >= 0"),
    (["mesh", "rimless-wheel", "--slope-std", "-1"], "--slope-std: must be a finite number > 0"),
    (["mesh", "no-such-map"], "invalid choice: 'no-such-map'"),
    (["train", "sac", "acrobot", "--epochs", "3"], "--epochs applies to ars, apg, shapg, papg, cem, ce-apg"),   # a test-registered toy may follow
    (["train", "sac", "acrobot", "--lr", "nan"], "SACConfig.lr must be a finite number"),
    (["train", "sac", "acrobot", "--polyak", "2"], r"SACConfig.polyak must be in \[0, 1\]"),
    (["train", "sac", "acrobot", "--obs-transform", "cubes"], "--obs-transform: invalid choice"),
    (["train", "sac", "acrobot", "--set", "lr"], "--set expects key=value"),
    (["train", "sac", "acrobot", "--set", "nope=1"], "not a SACConfig field"),
    (["train", "sac", "nosuch"], "unknown system 'nosuch'"),
    (["train", "ssac", "acrobot", "--variant", "mine"], "--variant: invalid choice"),
    (["train", "ssac", "pendulum", "--steps", "100"], "gate learning needs 'gate.warm_near'"),
    (["train", "ars", "NoSuchEnv-v0", "--epochs", "1"], "NoSuchEnv"),
    (["train", "ars", "Pendulum-v1", "--step-size", "-0.1"], "ARSConfig.step_size must be a finite number > 0"),
    (["finetune", "Pendulum-v1", "--policy", "pickle:model.pkl"], "--policy must be KIND:PATH"),
    (["finetune", "Pendulum-v1", "--policy", "sb3:/no/such/model.zip"], "/no/such/model.zip"),
    (["finetune", "Pendulum-v1", "--policy", "sb3:{file}"], "a_file"),
    (["finetune", "Pendulum-v1", "--policy", "ssac:models/policies/ssac-acrobot"], "env must be one of"),
    (["finetune", "acrobot", "--policy", "ssac:models/policies/ssac-acrobot", "--updates", "0"],
     "--updates: must be a finite number > 0"),
    (["finetune", "acrobot", "--policy", "ssac:models/policies/ssac-acrobot", "--select", "critic"],
     "--select: invalid choice"),
    # issue 47: only cpu and cuda[:N] reach torch; counts are integral, finite and bounded (hybridctl.limits)
    *[(["balance-map", "acrobot", "--grid", "2", "--engine", "torch", "--device", device],
       rf"--device must be a torch device hybridctl runs on \(cpu, cuda or cuda:N\), got '{device}'")
      for device in ("meta", "mps", "xla", "cpu:3")],
    (["train", "sac", "acrobot", "--device", "meta", "--steps", "16"], r"SACConfig.device must be a torch device "
     r"hybridctl runs on \(cpu, cuda or cuda:N\)"),
    (["train", "ce-apg", "cartpole", "--device", "mps", "--epochs", "1"], r"APGConfig.device must be a torch device "
     r"hybridctl runs on \(cpu, cuda or cuda:N\)"),
    (["finetune", "acrobot", "--policy", "ssac:models/policies/ssac-acrobot", "--device", "xla"],
     "FineTuneConfig.device must be a torch device hybridctl runs on \\(cpu, cuda or cuda:N\\), got 'xla'"),
    (["train", "sac", "acrobot", "--steps", "1e30"],
     r"--steps/--total-steps: must be an integer in \[1, 10,000,000,000\] \(env steps of one training run\)"),
    (["train", "ssac", "acrobot", "--total-steps", "99999999999999999999"],
     r"must be an integer in \[1, 10,000,000,000\]"),
    (["train", "sac", "acrobot", "--set", "total_steps=100000000000000000000000000000"],
     r"SACConfig.total_steps \(--total-steps\) is .* above its limit of 10,000,000,000"),
    (["train", "sac", "acrobot", "--steps", "inf"], "--steps/--total-steps: invalid int value"),
    (["train", "ars", "Pendulum-v1", "--epochs", "1e9"], r"--epochs: must be an integer in \[1, 10,000,000\]"),
    (["train", "sac", "acrobot", "--exploration-steps", "1e20"],
     r"--exploration-steps: must be an integer at most 10,000,000,000"),
    (["train", "sac", "acrobot", "--buffer-size", "1e30"],
     r"SACConfig.buffer_size \(--buffer-size\) is .* above its limit"),
    (["finetune", "acrobot", "--policy", "ssac:models/policies/ssac-acrobot", "--updates", "100000000000"],
     r"FineTuneConfig.updates \(--updates\) is 100,000,000,000, above its limit of 10,000,000"),
    (["finetune", "acrobot", "--policy", "ssac:models/policies/ssac-acrobot", "--eval-episodes", "100000000000"],
     r"FineTuneConfig.eval_episodes \(--eval-episodes\) is .* above its limit of 1,000,000"),
]


@pytest.mark.parametrize("argv, message", CLI_CASES, ids=[" ".join(a) for a, _ in CLI_CASES])
def test_cli_rejects_bad_input_in_one_line(argv, message, tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("not a folder")
    argv = [a.replace("{file}", str(a_file)) for a in argv]
    if "--out" not in argv and argv[0] in ("simulate", "balance-map", "mesh", "train"):
        argv += ["--out", str(tmp_path / "out")]
    with pytest.raises(SystemExit) as stop:
        main(argv)
    err = capsys.readouterr().err
    assert stop.value.code == 2, err
    assert "Traceback" not in err
    assert any(__import__("re").search(message, line) for line in err.splitlines()), err


# ------------------------------------------------------------------------------ spec overrides
OVERRIDE_CASES = [
    ({"k_energy": NAN}, "override k_energy=nan .*must be a finite number"),
    ({"k_p": -50}, "override k_p=-50 .*must be finite and >= 0"),
    ({"k_energy": 0.0}, "override k_energy=0.0 .*must be finite and > 0"),
    ({"label_horizon": -2.5}, "override label_horizon=-2.5 .*> 0"),
    ({"warm_near": [NAN] * 4}, "override warm_near=.*must be a finite number"),
    ({"warm_near": [0.5, 1.0, 5.0]}, "override warm_near=.*shape \\(4,\\)"),
    ({"angle_offset": INF}, "override angle_offset=inf .*must be a finite number"),
    ({"lookback": 2.5}, "override lookback=2.5 .*must be an integer"),
    ({"lookback": 0}, "override lookback=0 .*must be >= 1"),
    ({"link_mass": -1.0}, "override link_mass=-1.0 .*shape \\(2,\\)"),
    ({"link_mass": [-1.0, 1.0]}, "override link_mass=.*must be finite and > 0"),
    ({"link_mass": []}, "override link_mass=\\[\\] .*shape \\(2,\\)"),
    ({"link_mass": "heavy"}, "override link_mass='heavy' .*expected a number"),
    ({"dt": "x"}, "override dt='x' .*expected a number"),
    ({"dt": 0.0}, "override dt=0.0 .*must be finite and > 0"),
    ({"dt": [0.01]}, "override dt=\\[0.01\\] .*single number"),
    ({"dt": True}, "override dt=True .*expected a number"),
    ({"control__period": 0.015}, "override control__period=0.015 .*whole multiple"),
    ({"gate__on": 0.4}, "override gate__on=0.4 .*0 < gate.off < gate.on < 1"),
    ({"method": "rk4"}, "override method='rk4' .*must be one of"),
    ({"kind": "fun"}, "override kind='fun' .*must be one of"),
    ({"kind": 3}, "override kind=3 .*must be a string"),
    ({"R": [[0.0]]}, "override R=.*positive definite"),
    ({"Q": [[1, 0, 0, 0]] * 4}, "override Q=.*symmetric positive semidefinite"),
    ({"limit": -25.0}, "override limit=-25.0 .*> 0"),
    ({"names": ["a"]}, "override 'names' is ambiguous"),
    ({"nope": 1}, "override 'nope' is not a key of this spec"),
    ({"angles": [0.5, 1]}, "override angles=.*list of integers"),
    # issue 29: expressions, physical ranges, the smallest time step, a name that is a path
    ({"angle_offset": "pi/0"}, "override angle_offset='pi/0' .*divides by zero"),
    ({"gravity": 1e300}, r"override gravity=1e\+300 .*must lie in \[0, 300\]"),
    ({"gravity": 1e30}, r"override gravity=1e\+30 .*must lie in \[0, 300\]"),
    ({"link_mass": [1e-300, 1e-300]}, r"override link_mass=.*must lie in \[0.001, 10000\]"),
    ({"link_inertia": [0.2, 1e9]}, r"override link_inertia=.*must lie in \[0, 1e\+06\]"),
    ({"joint_damping": [0.0, 1e9]}, r"override joint_damping=.*must lie in \[0, 10000\]"),
    ({"link_length": [1.0, 1e9]}, r"override link_length=.*must lie in \[0.001, 100\]"),
    ({"dt": 1e-300}, "override dt=1e-300 .*must be at least 1e-06 s"),
    ({"system__name": "../../evil"}, "override system__name='../../evil' .*must be a plain name"),
    ({"Q": [[1], [1, 2]]}, "override Q=.*nested lists must all have the same length"),
]


@pytest.mark.parametrize("override, message", OVERRIDE_CASES, ids=[str(o) for o, _ in OVERRIDE_CASES])
def test_spec_overrides_are_checked_like_the_file(override, message):
    with pytest.raises(SpecError, match=message) as info:
        systems.load("acrobot", **override)
    assert "acrobot.toml" not in str(info.value)  # the file is fine; the override is named


def _acrobot_spec(old: str = "", new: str = "") -> bytes:
    return (systems.spec.SPEC_DIR / "acrobot.toml").read_text().replace(old, new).encode()


SPEC_FILE_CASES = [  # issue 29: (name, file content, message naming the file)
    ("pi/0", _acrobot_spec('"pi/2"', '"pi/0"'), r"'model.angle_offset': divides by zero in 'pi/0'"),
    ("100k nested [", b"a = " + b"[" * 100_000, "not valid TOML: arrays or tables nested too deeply"),
    ("binary", b"\xff\xfe\x00\x01 binary", r"not a text file \(not UTF-8 at byte 0\)"),
    ("over MAX_SPEC_BYTES", b"#" * ((1 << 20) + 1), "a spec file is at most 1,048,576 bytes"),
    ("gravity 1e30", _acrobot_spec("value = 9.8,", "value = 1e30,"), r"'params.gravity' must lie in \[0, 300\]"),
    ("dt 1e-300", _acrobot_spec("value = 0.01, units = \"s\", source = \"thesis Sec. 3.2: time step",
                                "value = 1e-300, units = \"s\", source = \"thesis Sec. 3.2: time step"),
     "'integrator.dt' must be at least 1e-06 s"),
    ("name a path", _acrobot_spec('name = "acrobot"', 'name = "../../evil"'), "'system.name' must be a plain name"),
]


@pytest.mark.parametrize("name, content, message", SPEC_FILE_CASES, ids=[c[0] for c in SPEC_FILE_CASES])
def test_a_bad_spec_file_is_one_line_naming_the_file(tmp_path, name, content, message):
    path = tmp_path / "bad.toml"
    path.write_bytes(content)
    with pytest.raises(SpecError, match=message) as info:
        systems.load(str(path))
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_a_spec_file_whose_name_is_no_system_name_is_skipped_with_a_warning(tmp_path, monkeypatch, cli_error):
    """Issue 47: ``a b;rm -rf.toml`` in $HYBRIDCTL_SYSTEMS breaks no command; asked for by name it is unknown."""
    folder = tmp_path / "specs"
    folder.mkdir()
    (folder / "a b;rm -rf.toml").write_bytes(_acrobot_spec())
    monkeypatch.setenv("HYBRIDCTL_SYSTEMS", str(folder))
    with pytest.warns(UserWarning, match=r"skipped spec file .*a b;rm -rf\.toml: 'a b;rm -rf' is not a system name"):
        assert "a b;rm -rf" not in systems.known_systems()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["simulate", "acrobot", "--duration", "0.05", "--no-html", "--out", str(tmp_path / "out")]) == 0
        assert main(["systems"]) == 0
        assert "unknown system 'a b;rm -rf'" in cli_error(["simulate", "a b;rm -rf", "--out", tmp_path / "o2"])


SPEC_CLI_CASES = [  # issue 29: the same through the command line (exit 2, one line, no traceback)
    (["train", "sac", "acrobot", "--spec", "angle_offset=pi/0"], "divides by zero"),
    (["train", "sac", "acrobot", "--spec", "params.gravity=1e300"], r"must lie in [0, 300]"),
    (["train", "sac", "acrobot", "--spec", "params.link_mass=[1e-300,1e-300]"], "must lie in [0.001, 10000]"),
    (["train", "sac", "acrobot", "--spec", "system.name=../../evil"], "must be a plain name"),
    (["train", "sac", "acrobot", "--spec", "integrator.dt=1e-300"], "must be at least 1e-06 s"),
    (["train", "sac", "acrobot", "--buffer-size", "10", "--minibatch-size", "64"],
     "buffer_size (10) must be >= minibatch_size (64)"),
    (["train", "sac", "acrobot", "--device", "cuda:99"], "CUDA"),
    (["train", "shapg", "cartpole", "--short-horizon", "100000"], "short_horizon (100000) must be <= horizon"),
]


@pytest.mark.parametrize("argv, message", SPEC_CLI_CASES, ids=[" ".join(a) for a, _ in SPEC_CLI_CASES])
def test_bad_specs_and_config_rules_on_the_command_line(tmp_path, cli_error, argv, message):
    err = cli_error([*argv, "--quiet", "--out", str(tmp_path / "out")])
    assert message in err and len(err.strip().splitlines()) == 1, err


ENTRY_LQR_CASES = [  # issue 29: an LQR Drake cannot solve is a ValueError naming the system and what to change
    ("no gravity", {"gravity": 0.0}, r"acrobot \(acrobot.toml, gravity=0.0\): no LQR about the goal"),
    ("Q zero", {"Q": [[0.0] * 4] * 4}, "check the spec's params .* and lqr.Q / lqr.R"),
]


@pytest.mark.parametrize("name, overrides, message", ENTRY_LQR_CASES, ids=[c[0] for c in ENTRY_LQR_CASES])
def test_an_lqr_that_cannot_be_solved_names_the_system(name, overrides, message):
    with pytest.raises(ValueError, match=message):
        systems.load("acrobot", **overrides).lqr()


# ---------------------------------------------------------------------- dynamics and engines
ACROBOT = systems.load("acrobot")
T = torch.float64


def _tensor(*shape, fill=0.0):
    return torch.full(shape, fill, dtype=T)


def _rollout_nan_at_5():
    controls = _tensor(2, 10, 1)
    controls[1, 5, 0] = NAN
    ACROBOT.rollout(_tensor(2, 4), controls)


def _simulate(x0=(-1.5698, 0, 0, 0), duration=1.0):
    from hybridctl import drake
    drake.simulate(drake.build_hybrid_diagram(ACROBOT), x0, duration)


def _env(**kwargs):
    from hybridctl.envs import TorchVectorEnv
    TorchVectorEnv("acrobot", **kwargs)


def _postprocess(kind="mesh-lower", states=None, ret=1.0, **kwargs):
    from hybridctl.analysis import PostProcessor
    states = np.random.default_rng(0).normal(size=(400, 3)) if states is None else states
    PostProcessor(kind, **kwargs)(states, ret)


def _mesh(seeds=((1.29,),), box_size=1e-3, **kwargs):
    from hybridctl.analysis import GaussianDisturbance, RimlessWheel, build_mesh
    build_mesh(RimlessWheel(), seeds, GaussianDisturbance(0.15, 0.06, 5), box_size, progress=False, **kwargs)


def _wheel_step(states, slopes):
    from hybridctl.analysis import RimlessWheel
    RimlessWheel().step_many(states, slopes)


ENTRY_CASES = [
    ("step: wrong width", lambda: ACROBOT.step(_tensor(3), _tensor(1)), r"x must have shape \(4,\)"),
    ("step: NaN state", lambda: ACROBOT.step(_tensor(4, fill=NAN), _tensor(1)), "x contains NaN or Inf"),
    ("step: inf input", lambda: ACROBOT.step(_tensor(4), _tensor(1, fill=INF)), "u contains NaN or Inf"),
    ("step: broadcasting", lambda: ACROBOT.step(_tensor(4), _tensor(3, 1)), "must both be single"),
    ("step: batch mismatch", lambda: ACROBOT.step(_tensor(2, 4), _tensor(3, 1)), "batch sizes differ: 2 vs 3"),
    ("step: empty batch", lambda: ACROBOT.step(_tensor(0, 4), _tensor(0, 1)), "empty batch"),
    ("step: numpy", lambda: ACROBOT.step(np.zeros(4), np.zeros(1)), "must be torch tensors"),
    ("derivatives: 3-D", lambda: ACROBOT.derivatives(_tensor(2, 2, 4), _tensor(2, 2, 1)), "must have shape"),
    ("rollout: NaN at t=5", _rollout_nan_at_5, "controls contains NaN or Inf"),
    ("rollout: 2-D controls", lambda: ACROBOT.rollout(_tensor(2, 4), _tensor(2, 1)), r"controls \(B, T >= 1, 1\)"),
    ("rollout: zero steps", lambda: ACROBOT.rollout(_tensor(2, 4), _tensor(2, 0, 1)), r"T >= 1"),
    ("rollout: batch mismatch", lambda: ACROBOT.rollout(_tensor(2, 4), _tensor(3, 5, 1)), "x0 must be"),
    ("initial states: n = 0", lambda: ACROBOT.sample_initial_states(0), "n must be >= 1"),
    ("success test: wrong shape", lambda: systems.success.is_balanced(np.zeros((5, 3)), ACROBOT), "states must have shape"),
    ("lqr: wrong Q", lambda: ACROBOT.lqr(Q=np.eye(3)), "Q must be 4x4"),
    ("basin level: n_samples", lambda: systems.control.lqr_basin_level(ACROBOT, n_samples=5), "n_samples must be >= 10"),
    ("lqr rollouts: horizon", lambda: systems.control.lqr_rollouts_balanced(ACROBOT, np.zeros((2, 4)), 0.01),
     "horizon must be >="),
    ("cost-to-go gate: scale", lambda: systems.control.CostToGoGate(ACROBOT, scale=-1.0), "scale must be > 0"),
    ("simulate: NaN x0", lambda: _simulate(x0=(NAN, 0, 0, 0)), "x0 contains NaN or Inf"),
    ("simulate: x0 shape", lambda: _simulate(x0=(0, 0)), r"x0 must have shape \(4,\)"),
    ("simulate: x0 beyond bound", lambda: _simulate(x0=(1e300, 0, 0, 0)), "x0 entries must lie in"),
    ("simulate: NaN duration", lambda: _simulate(duration=NAN), "duration must be a finite number > 0"),
    ("simulate: zero duration", lambda: _simulate(duration=0.0), "duration must be a finite number > 0"),
    ("gate block: off > on", lambda: __import__("hybridctl.drake", fromlist=["Gate"]).Gate(
        lambda x: [0.0], 1, 0.01, on=0.5, off=0.9), "0 < off < on < 1"),
    ("diagram: swing-up name", lambda: __import__("hybridctl.drake", fromlist=["x"]).build_hybrid_diagram(
        ACROBOT, swingup="nope"), "swingup must be"),
    ("env: num_envs 0", lambda: _env(num_envs=0), "num_envs must be an integer >= 1"),
    ("env: decision period", lambda: _env(num_envs=2, decision_period=0.013), "decision_period must be"),
    ("env: unknown system", lambda: __import__("hybridctl.envs", fromlist=["x"]).TorchVectorEnv("nosuch", 2),
     "unknown system 'nosuch'"),
    ("postprocess: kind", lambda: _postprocess(kind="fractal"), "kind must be one of"),
    ("postprocess: form", lambda: _postprocess(form="square"), "form must be one of"),
    ("postprocess: transient", lambda: _postprocess(transient_steps=-1), "transient_steps must be an integer >= 0"),
    ("postprocess: min_points", lambda: _postprocess(min_points=2), "min_points must be an integer >= 3"),
    ("postprocess: NaN return", lambda: _postprocess(ret=NAN), "episode_return must be a finite number"),
    ("postprocess: inf return", lambda: _postprocess(ret=INF), "episode_return must be a finite number"),
    ("postprocess: text return", lambda: _postprocess(ret="high"), "episode_return must be a finite number"),
    ("postprocess: NaN states", lambda: _postprocess(states=np.full((300, 3), NAN)), "states contain NaN"),
    ("postprocess: 1-D states", lambda: _postprocess(states=np.zeros(300)), "states must have shape"),
    ("section: NaN state", lambda: _wheel_step([[NAN]], [0.1]), "states must be finite"),
    ("section: two columns", lambda: _wheel_step(np.ones((2, 2)), [0.1, 0.1]), r"states must have shape \(N, 1\)"),
    ("section: disturbance count", lambda: _wheel_step([[1.0], [1.2]], [0.1]), "one entry per state"),
    ("section: NaN slope", lambda: _wheel_step([[1.0]], [NAN]), "finite slopes"),
    ("section: empty", lambda: _wheel_step(np.zeros((0, 1)), []), "N >= 1"),
    ("mesh: NaN box", lambda: _mesh(box_size=NAN), "box_size must be a finite number > 0"),
    ("mesh: negative box", lambda: _mesh(box_size=-1.0), "box_size must be a finite number > 0"),
    ("mesh: NaN seed", lambda: _mesh(seeds=[[NAN]]), "seeds must be a non-empty array of finite states"),
    ("mesh: no seeds", lambda: _mesh(seeds=np.zeros((0, 1))), "seeds must be a non-empty array"),
    ("mesh: max_states", lambda: _mesh(max_states=0), "max_states must be an integer >= 1"),
    ("disturbance: std", lambda: __import__("hybridctl.analysis", fromlist=["x"]).GaussianDisturbance(0.1, -1, 5),
     "std > 0"),
    ("disturbance: empty set", lambda: __import__("hybridctl.analysis", fromlist=["x"]).FiniteDisturbances([]),
     "empty"),
    ("learner: unknown system", lambda: __import__("hybridctl.learn", fromlist=["x"]).SAC("nosuch"),
     "unknown system 'nosuch'"),
]


@pytest.mark.parametrize("name, call, message", ENTRY_CASES, ids=[c[0] for c in ENTRY_CASES])
def test_entry_points_reject_bad_input(name, call, message):
    with pytest.raises((ValueError, KeyError), match=message):
        call()


# --------------------------------------------------------------------------- learner configs
def _config_classes():
    from hybridctl.learn import ARSConfig, FineTuneConfig, GateConfig, SACConfig, SSACConfig
    return (SACConfig, SSACConfig, ARSConfig, GateConfig, FineTuneConfig)


def _bad_values(hint, default):
    """Values no field of this annotation accepts: the wrong type, NaN and inf for numbers."""
    args = typing.get_args(hint)
    optional = type(None) in args
    base = [a for a in args if a is not type(None)] or [hint]
    bad = []
    if all(b in (int, float) for b in base):
        bad += [NAN, INF, "junk", [1.0]]
        if int in base and float not in base:
            bad.append(1.5)
    elif base == [bool]:
        bad += ["yes", 2]
    elif base == [str]:
        bad += [3, 1.0]
    if not optional and default is not None and base != [str]:
        bad.append(None)
    return bad


def _config_cases():
    cases = []
    for cls in _config_classes():
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            default = f.default if f.default is not dataclasses.MISSING else None
            for bad in _bad_values(hints[f.name], default):
                cases.append((cls, f.name, bad))
    return cases


CONFIG_CASES = _config_cases()


@pytest.mark.parametrize("cls, field, bad", CONFIG_CASES,
                         ids=[f"{c.__name__}.{f}={b!r}" for c, f, b in CONFIG_CASES])
def test_learner_configs_reject_wrong_types_and_non_finite_numbers(cls, field, bad):
    try:
        config = cls(**{field: bad})
    except (ValueError, TypeError) as exc:  # __post_init__ may refuse it already
        assert field in str(exc) or "must" in str(exc)
        return
    with pytest.raises(ValueError, match=rf"{cls.__name__}\.{field} must"):
        config.validate()


RANGE_CASES = [
    ("SACConfig", {"gamma": 1.5}, r"gamma must be in \[0, 1\]"),
    ("SACConfig", {"minibatch_size": 0}, "minibatch_size must be an integer >= 1"),
    ("SACConfig", {"alpha": "sometimes"}, "alpha must be a number >= 0 or 'auto'"),
    ("SACConfig", {"log_std_min": 3.0}, "log_std_min < log_std_max"),
    ("SACConfig", {"device": "gpu-please"}, "device must be a torch device"),
    ("SSACConfig", {"gate_class_weight_from": "none"}, "gate_class_weight_from must be"),
    ("SSACConfig", {"reward": "fun"}, "reward must be None"),
    ("SSACConfig", {"gate_warm_samples": 1}, "gate_warm_samples must be"),
    ("ARSConfig", {"top_directions": 99}, "top_directions .* must be <= n_directions"),
    ("ARSConfig", {"postprocess": "fractal"}, "postprocess must be one of"),
    ("ARSConfig", {"backend": "cloud"}, "backend must be one of"),
    ("ARSConfig", {"workers": 0}, "workers must be None"),
    ("ARSConfig", {"policy": "mlp:"}, "policy"),
    ("FineTuneConfig", {"select": "value_net"}, "select must be one of"),
    ("FineTuneConfig", {"reward": "fractal"}, "reward must be one of"),
    ("FineTuneConfig", {"dimension_settings": "mine"}, "dimension_settings must be one of"),
    ("FineTuneConfig", {"n_directions": 0}, "n_directions must be an integer >= 1"),
    ("FineTuneConfig", {"noise_end": 0.0}, "noise_end must be a finite number > 0"),
    ("FineTuneConfig", {"workers": 0}, "workers must be None"),
    ("GateConfig", {"hidden": ()}, "hidden must be a non-empty tuple"),
    ("GateConfig", {"hidden": (32, 0)}, "hidden must be a non-empty tuple"),
    ("GateConfig", {"warm_samples": 1}, "warm_samples must be an integer >= 2"),
    ("GateConfig", {"label_horizon": -1.0}, "label_horizon must be None"),
]


@pytest.mark.parametrize("name, overrides, message", RANGE_CASES, ids=[f"{n}{o}" for n, o, _ in RANGE_CASES])
def test_learner_configs_reject_out_of_range_values(name, overrides, message):
    cls = {c.__name__: c for c in _config_classes()}[name]
    with pytest.raises(ValueError, match=message):
        cls(**overrides).validate()


def test_the_table_is_large():
    """The closing note of issue 12 reports this count; issue 29 added the spec file, spec CLI and LQR
    rows here and the checkpoint tables of tests/test_bad_checkpoints.py."""
    total = (len(CLI_CASES) + len(OVERRIDE_CASES) + len(ENTRY_CASES) + len(CONFIG_CASES) + len(RANGE_CASES)
             + len(SPEC_FILE_CASES) + len(SPEC_CLI_CASES) + len(ENTRY_LQR_CASES))
    assert total > 200


def test_cli_names_a_missing_optional_extra(tmp_path, capsys, monkeypatch):
    """`--backend ray` without Ray (hidden here, so the test runs whether or not it is installed): one line that
    says how to install it."""
    monkeypatch.setitem(sys.modules, "ray", None)      # `import ray` now raises ImportError
    with pytest.raises(SystemExit) as stop:
        main(["train", "ars", "Pendulum-v1", "--backend", "ray", "--epochs", "1", "--quiet",
              "--out", str(tmp_path / "ars")])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "Traceback" not in err
    assert "backend 'ray' needs Ray: pip install 'hybridctl[ray]' (in a checkout: pip install -c constraints.txt -e '.[ray]')" in err
