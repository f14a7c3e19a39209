"""The command line as a user runs it: files written, JSON fields, clear errors."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hybridctl.cli import main

ROOT = Path(__file__).resolve().parents[1]


def run(*args, check=True):
    proc = subprocess.run([sys.executable, "-m", "hybridctl.cli", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    if check and proc.returncode != 0:
        raise AssertionError(f"hybridctl {' '.join(args)} failed:\n{proc.stdout}\n{proc.stderr}")
    return proc


def run_in_process(capsys, *args) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of ``hybridctl ARGS`` called in this process (no interpreter start, seconds
    each: torch and Drake are imported already). ``python -m hybridctl.cli`` itself: test_debug_flag_shows_the_traceback
    and test_output_into_a_closed_pipe_is_not_an_error here, the installed console script in test_install.py."""
    try:
        code = main(list(args))
    except SystemExit as stop:
        code = stop.code
    out = capsys.readouterr()
    return code, out.out, out.err


def test_simulate_writes_all_outputs(tmp_path, capsys):
    out = tmp_path / "sim"
    code, _, err = run_in_process(capsys, "simulate", "pendulum", "--x0", "0.05,0", "--duration", "6", "--out", str(out))
    assert code == 0, err
    data = np.load(out / "trajectory.npz")
    assert set(data.files) >= {"t", "x", "u", "gate"}
    assert data["x"].shape == (601, 2) and data["u"].shape == (601, 1)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["balanced"] is True and summary["diverged"] is False
    assert isinstance(summary["return"], float)
    assert (out / "plot.png").stat().st_size > 10_000
    assert "<html" in (out / "replay.html").read_text()[:2000].lower()


def test_simulate_force_loads_a_checkpoint_trained_on_other_spec_values_from_a_spec_file(tmp_path, capsys):
    """SYSTEM may be a spec file's path; --force loads a checkpoint trained on other spec values (as the
    refusal says), with a warning naming what differs."""
    text = (ROOT / "systems" / "acrobot.toml").read_text()
    spec = tmp_path / "acrobot_g97.toml"
    spec.write_text(text.replace("gravity      = { value = 9.8,", "gravity = { value = 9.7,"))
    args = ("simulate", str(spec), "--controller", f"ssac:{ROOT / 'models/policies/ssac-acrobot'}", "--duration", "0.05",
            "--no-html")
    code, _, err = run_in_process(capsys, *args, "--out", str(tmp_path / "refused"))
    assert code == 2 and "params.gravity=9.8; this system has 9.7" in err and "--force" in err
    with pytest.warns(UserWarning, match="force: loading anyway: .*params.gravity=9.8; this system has 9.7"):
        code, out, _ = run_in_process(capsys, *args, "--force", "--out", str(tmp_path / "forced"))
    assert code == 0 and json.loads((tmp_path / "forced" / "summary.json").read_text())["system"] == "acrobot"


def test_balance_map_writes_png_and_json(tmp_path, capsys):
    out = tmp_path / "map"
    code, stdout, err = run_in_process(capsys, "balance-map", "pendulum", "--grid", "3", "--workers", "1", "--quiet",
                                       "--out", str(out))
    assert code == 0, err
    result = json.loads((out / "balance_map.json").read_text())
    assert 0.0 <= result["balanced_fraction"] <= 1.0
    assert np.array(result["balanced"]).shape == (3, 3)
    assert result["balanced_fraction"] == pytest.approx(np.mean(result["balanced"]))
    assert (out / "balance_map.png").exists()
    assert "balanced_fraction" in stdout


@pytest.mark.parametrize("engine", ["drake", "torch"])
def test_balance_map_force_loads_a_checkpoint_trained_on_other_spec_values(engine, tmp_path, capsys):
    """As simulate --force: the refusal names what differs and --force; --force loads it anyway (warned), and the
    Drake engine's workers rebuild the controller by name with force too."""
    text = (ROOT / "systems" / "acrobot.toml").read_text()
    spec = tmp_path / "acrobot_g97.toml"
    spec.write_text(text.replace("gravity      = { value = 9.8,", "gravity = { value = 9.7,"))
    args = ("balance-map", str(spec), "--controller", f"ssac:{ROOT / 'models/policies/ssac-acrobot'}", "--grid", "2",
            "--duration", "0.2", "--engine", engine, "--backend", "serial", "--quiet")
    code, _, err = run_in_process(capsys, *args, "--out", str(tmp_path / "refused"))
    assert code == 2 and "params.gravity=9.8; this system has 9.7" in err and "--force" in err
    with pytest.warns(UserWarning, match="force: loading anyway: .*params.gravity=9.8; this system has 9.7"):
        code, out, err = run_in_process(capsys, *args, "--force", "--out", str(tmp_path / "forced"))
    assert code == 0, err
    result = json.loads((tmp_path / "forced" / "balance_map.json").read_text())
    assert np.array(result["balanced"]).shape == (2, 2)


def test_balance_map_near_hanging_down_spans_the_half_width_around_the_nominal_state(tmp_path, capsys):
    """--near 0.3: the acrobot's th1, th2 within +-0.3 of hanging down (not its default every angle)."""
    out = tmp_path / "near"
    code, stdout, err = run_in_process(capsys, "balance-map", "acrobot", "--grid", "3", "--near", "0.3",
                                       "--engine", "torch", "--duration", "1", "--quiet", "--out", str(out))
    assert code == 0, err
    result = json.loads((out / "balance_map.json").read_text())
    assert result["values1"] == pytest.approx([-np.pi / 2 - 0.3, -np.pi / 2, -np.pi / 2 + 0.3])
    assert result["values2"] == pytest.approx([-0.3, 0.0, 0.3])


def test_demo_balances_the_acrobot_and_the_cartpole(tmp_path, capsys, monkeypatch):
    # its two 2 x 2 maps in this process (a one-core machine's demo): two pools of 2 spawned workers, each
    # importing torch and Drake first, cost about 20 s here; the map is the same on every backend and the pool
    # with a checkpoint's controller is test_balance_engines.py's
    import importlib

    monkeypatch.setattr(importlib.import_module("hybridctl.experiments.balance_map"), "cpu_count", lambda: 1)
    code, stdout, err = run_in_process(capsys, "demo", "--grid", "2", "--quiet", "--out", str(tmp_path))
    assert code == 0, err
    proc = type("Proc", (), {"stdout": stdout})
    for name in ("acrobot", "cartpole"):
        summary = json.loads((tmp_path / name / "summary.json").read_text())
        assert summary["balanced"] and (tmp_path / name / "replay.html").exists()
    assert "papg:" in json.loads((tmp_path / "cartpole" / "summary.json").read_text())["controller"]
    for name in ("balance_map", "cartpole_balance_map"):
        assert (tmp_path / name / "balance_map.json").exists()
    assert proc.stdout.count("balanced=True") == 2


@pytest.mark.parametrize("args, message", [
    (["simulate", "acrobott"], "known systems: acrobot, acrobot_urdf, cartpole"),
    (["simulate", "acrobot", "--x0", "1,2"], "--x0 needs 4 values"),
    (["simulate", "acrobot", "--x0", "a,b,c,d"], "--x0 must be 4 comma-separated numbers"),
    (["simulate", "acrobot", "--controller", "nope"], "unknown controller 'nope'; known: energy"),
    (["simulate", "acrobot", "--duration", "-1"], "must be a finite number > 0"),
    (["balance-map", "acrobot", "--grid", "1", "--workers", "1"], "grid must be >= 2"),
    (["balance-map", "acrobot", "--grid", "2", "--near", "4"], "--near must be in (0, pi]"),
])
def test_bad_arguments_exit_nonzero_with_clear_message(args, message, tmp_path, capsys):
    code, out, err = run_in_process(capsys, *args, "--out", str(tmp_path))
    assert code == 2
    assert message in err + out and "Traceback" not in err


def test_train_ars_resume_and_init(tmp_path, capsys):
    """hybridctl train ars: a run, its resume, and the thesis' identity-then-post-processing protocol
    (in process: the console script itself is covered by the tests above)."""
    out = tmp_path / "ars"
    small = ["--set", "n_directions=2", "--set", "top_directions=1", "--set", "episode_steps=40",
             "--set", "transient_steps=5", "--backend", "serial", "--eval-episodes", "2", "--quiet"]

    def run(*args):
        code, stdout, err = run_in_process(capsys, *args)
        assert code == 0, err
        return type("Proc", (), {"stdout": stdout})

    run("train", "ars", "Pendulum-v1", "--epochs", "2", "--out", str(out), *small)
    result = json.loads((out / "eval.json").read_text())
    assert result["epochs"] == 2 and result["env_steps"] == 2 * 2 * 2 * 40
    assert set(result["mean_dimensions"]) == {"mesh_lower", "mesh_upper", "madogram", "variogram"}
    assert len((out / "progress.csv").read_text().splitlines()) == 3
    proc = run("train", "ars", "Pendulum-v1", "--epochs", "3", "--resume", "--out", str(out), *small)
    assert "resuming" in proc.stdout and json.loads((out / "eval.json").read_text())["epochs"] == 3
    post = tmp_path / "ars-mesh"
    run("train", "ars", "Pendulum-v1", "--init", str(out / "final"), "--postprocess", "madogram", "--epochs", "4",
        "--out", str(post), *small)
    config = json.loads((post / "final" / "config.json").read_text())["config"]
    assert config["postprocess"] == "madogram" and json.loads((post / "eval.json").read_text())["epochs"] == 4


@pytest.mark.parametrize("args, message", [
    (["train", "ars", "Pendulum-v1", "--postprocess", "fractal"], "postprocess"),
    (["train", "ars", "Pendulum-v1", "--steps", "10"], "--epochs"),
    (["train", "sac", "acrobot", "--postprocess", "madogram"], "ars only"),
    (["train", "ars", "Pendulum-v1", "--init", "/nonexistent/ck"], "no checkpoint"),
])
def test_train_ars_bad_arguments(args, message, tmp_path, capsys):
    code, out, err = run_in_process(capsys, *args, "--out", str(tmp_path / "x"), "--quiet")
    assert code == 2 and message in err and "Traceback" not in err, err


def test_mesh_writes_matrix_report_and_figures(tmp_path, capsys):
    import scipy.sparse as sp
    out = tmp_path / "mesh"
    code, stdout, err = run_in_process(capsys, "mesh", "rimless-wheel", "--box-size", "0.01", "--monte-carlo", "500",
                                       "--sizes", "0.1", "--out", str(out), "--quiet")
    assert code == 0 and "MFPT from the seed" in stdout, err
    report = json.loads((out / "mfpt.json").read_text())
    T = sp.load_npz(out / "transition_matrix.npz")
    assert T.shape[0] == report["mesh"]["states"] + 1 and np.allclose(T.sum(axis=1), 1.0)
    assert report["mfpt"]["from_seed"] > 1 and report["mfpt"]["infinite_states"] == 0
    mc = report["monte_carlo"]["mesh_disturbance_set"]
    assert mc["interval95"][0] < mc["mean_steps_to_failure"] < mc["interval95"][1]
    assert 0.5 < report["reachable_dimension"] < 1.5
    for name in ("sparsity.png", "cumulative_mass.png", "states.png", "mesh_sizes.png"):
        assert (out / name).stat().st_size > 5000, name


def test_mesh_sweep_of_slope_stds_writes_the_curve(tmp_path, capsys):
    """Several --slope-std values (rad, or degrees as 2deg): the MFPT-vs-roughness sweep, one line per sigma."""
    out = tmp_path / "sweep"
    code, stdout, err = run_in_process(capsys, "mesh", "rimless-wheel", "--slope-std", "0.06", "5deg", "2deg",
                                       "--box-size", "0.01", "--monte-carlo", "200", "--monte-carlo-budget", "1e5",
                                       "--out", str(out), "--quiet")
    assert code == 0, err
    record = json.loads((out / "mfpt_vs_roughness.json").read_text())
    assert [round(r["slope_std_deg"], 3) for r in record["rows"]] == [2.0, 3.438, 5.0]
    assert [r["monte_carlo"]["status"] for r in record["rows"]] == ["skipped", "run", "run"]
    assert "Monte Carlo skipped" in stdout and "above the budget" in stdout and record["command"].startswith("hybridctl")
    assert (out / "mfpt_vs_roughness.png").stat().st_size > 5000


@pytest.mark.parametrize("args, message", [
    (["mesh", "rimless-wheel", "--slope-mean", "-0.5"], "no rolling gait"),
    (["mesh", "rimless-wheel", "--box-size", "0"], "must be a finite number > 0"),
    (["mesh", "rimless-wheel", "--slope-std", "0.06", "0deg"], "must be a finite number > 0, got 0"),
    (["mesh", "rimless-wheel", "--slope-std", "0.06", "0.08", "--sizes", "0.1"], "does not apply to a sweep"),
    (["mesh", "rimless-wheel", "--slope-std", "0.06", "0.08", "--monte-carlo-budget", "1e9"],
     "--monte-carlo-budget is 1e+09, above its limit"),
    (["mesh", "hopper"], "invalid choice"),
    (["mesh", "rimless-wheel", "--hip-pd", "1", "1", "0.3"], "--hip-pd applies to the compass-gait map only"),
    (["mesh", "compass-gait", "--param", "mass_hip=-1"], "mass_hip must be in"),
    (["mesh", "compass-gait", "--param", "legs=2"], "--param must be NAME=VALUE"),
    (["mesh", "compass-gait", "--slope-mean", "0.4"], "no compass gait to seed the mesh from"),
])
def test_mesh_bad_arguments(args, message, tmp_path, capsys):
    code, out, err = run_in_process(capsys, *args, "--out", str(tmp_path / "m"), "--quiet")
    assert code == 2 and message in err and "Traceback" not in err, err


@pytest.mark.timeout(120)
def test_mesh_compass_gait_coarse(tmp_path, capsys):
    """The compass gait meshes from its passive gait (3 states per box key); guard trips are recorded."""
    out = tmp_path / "cg"
    code, stdout, err = run_in_process(capsys, "mesh", "compass-gait", "--box-size", "0.3", "--slope-std", "0.01",
                                       "--disturbances", "3", "--max-disturbances", "5", "--out", str(out), "--quiet")
    assert code == 0, err
    report = json.loads((out / "mfpt.json").read_text())
    assert report["map"] == "compass-gait" and len(report["seed_state"]) == 3
    assert report["mfpt"]["from_seed"] > 1 and set(report["section_guard"]["trips"]) >= {"wall-time guard"}


def test_mesh_cap_reports_incomplete(tmp_path, capsys):
    code, stdout, _ = run_in_process(capsys, "mesh", "rimless-wheel", "--max-states", "20", "--out", str(tmp_path / "m"),
                                     "--quiet")
    assert code == 2 and "incomplete" in stdout
    assert "incomplete" in json.loads((tmp_path / "m" / "mfpt.json").read_text())["error"]


# ---------------------------------------------------------------- the command package, in-process

def parse(*argv):
    from hybridctl.cli import build_parser
    return build_parser().parse_args(list(argv))


@pytest.mark.parametrize("argv, hint", [
    # (" only" left off: a learner a test file registers, the toy of test_controller_registry, also counts epochs)
    (["train", "sac", "acrobot", "--epochs", "3"], "--epochs applies to ars, apg, shapg, papg, cem, ce-apg"),
    (["train", "ssac", "acrobot", "--postprocess", "madogram"], "--postprocess applies to ars only"),
    (["train", "ars", "Pendulum-v1", "--variant", "paper"], "--variant applies to ssac only"),
    (["train", "ars", "Pendulum-v1", "--polyak", "0.9"], "--polyak applies to sac, ssac only"),
    (["train", "sac", "acrobot", "--gate-lr", "0.1"], "--gate-lr applies to ssac only"),
])
def test_train_rejects_another_learners_flag_with_usage(argv, hint, capsys):
    with pytest.raises(SystemExit) as exc:
        parse(*argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2
    assert err.startswith(f"usage: hybridctl train {argv[1]} SYSTEM") and hint in err


def test_train_help_comes_from_the_config_fields(capsys):
    with pytest.raises(SystemExit) as exc:
        parse("train", "sac", "--help")
    text = " ".join(capsys.readouterr().out.split())
    assert exc.value.code == 0
    assert "--polyak X" in text and "default: 0.995" in text and 'appendix "Polyak constant"' in text
    assert "--steps N, --total-steps N" in text and "--save-replay, --no-save-replay" in text
    assert "--obs-transform {none,angle_sincos}" in text and "--epochs" not in text
    with pytest.raises(SystemExit):
        parse("train", "ssac", "--help")
    text = " ".join(capsys.readouterr().out.split())
    assert "--variant {hybridctl,paper,author}" in text
    assert "(default: 0.9; --variant paper: 0.995; --variant author: 0.995)" in text
    with pytest.raises(SystemExit):
        parse("train", "ars", "--help")
    text = " ".join(capsys.readouterr().out.split())
    assert "--postprocess {identity,mesh-lower,mesh-upper,mesh-mean,madogram,variogram}" in text
    assert "--init CHECKPOINT" in text and "--steps" not in text and "--variant" not in text


def test_every_config_field_has_a_flag_that_parses_its_default():
    import dataclasses

    from hybridctl.cli import train
    from hybridctl.experiments import training_algorithms

    for algorithm, learner in training_algorithms().items():
        argv, expected = [], {}
        for f in dataclasses.fields(learner.config_class):
            if f.name in train.NOT_FLAGS.get(algorithm, ()):
                continue
            flag = "--" + f.name.replace("_", "-")
            if isinstance(f.default, bool):
                argv.append(flag if f.default else "--no-" + flag[2:])
            else:
                argv.append(f"{flag}={'none' if f.default is None else f.default}")
            expected[f.name] = f.default
        assert train.config_settings(parse("train", algorithm, "x", *argv)) == expected, algorithm


def test_train_field_flags_parse_to_typed_settings():
    from hybridctl.cli.train import config_settings

    args = parse("train", "sac", "acrobot", "--set", "polyak=0.8", "--set", "obs_transform=angle_sincos",
                 "--polyak", "0.9", "--steps", "2e6", "--alpha", "auto", "--target-entropy", "none",
                 "--no-tensorboard", "--seed", "3")
    assert config_settings(args) == {"polyak": 0.9, "obs_transform": "angle_sincos", "total_steps": 2_000_000,
                                     "alpha": "auto", "target_entropy": None, "tensorboard": False, "seed": 3}
    assert config_settings(parse("train", "sac", "acrobot", "--alpha", "0.1")) == {"alpha": 0.1}
    assert config_settings(parse("train", "ssac", "acrobot")) == {}  # only what was given
    args = parse("train", "ars", "Hopper-v5", "--epochs", "4", "--backend", "serial", "--workers", "2",
                 "--postprocess", "mesh-lower", "--episode-steps", "none", "--eval-episodes", "2")
    assert config_settings(args) == {"epochs": 4, "backend": "serial", "workers": 2, "postprocess": "mesh-lower",
                                     "episode_steps": None}
    assert args.eval_episodes == 2 and args.init is None and not args.resume
    for bad in (["--steps", "0"], ["--steps", "1.5"], ["--obs-transform", "cos"], ["--polyak", "high"]):
        with pytest.raises(SystemExit):
            parse("train", "sac", "acrobot", *bad)


def test_cli_errors_one_line_exit_codes_and_debug(capsys):
    import argparse

    from hybridctl.cli._common import cli_errors
    from hybridctl.learn import CheckpointError
    from hybridctl.systems import load

    def command(exc):
        @cli_errors
        def fail(args):
            if callable(exc):
                exc()
            raise exc
        return fail

    plain, debug = argparse.Namespace(), argparse.Namespace(debug=True)
    for exc, message in [(ValueError("bad value"), "error: bad value"),
                         (lambda: load("acrobott"), "error: unknown system 'acrobott'; known systems: acrobot"),
                         (CheckpointError("no checkpoint at x"), "error: no checkpoint at x"),
                         (FileNotFoundError("missing.json"), "error: missing.json")]:
        with pytest.raises(SystemExit) as caught:
            command(exc)(plain)
        err = capsys.readouterr().err
        assert caught.value.code == 2 and err.startswith(message) and err.count("\n") == 1, err
        assert str(caught.value).startswith(message)
    assert command(FloatingPointError("loss became nan"))(plain) == 3
    assert capsys.readouterr().err == "error: loss became nan\n"
    with pytest.raises(ValueError, match="bad value"):
        command(ValueError("bad value"))(debug)
    with pytest.raises(FloatingPointError):
        command(FloatingPointError("nan"))(debug)
    with pytest.raises(ZeroDivisionError):  # a bug is not an expected error: its traceback shows
        command(ZeroDivisionError("bug"))(plain)


def test_debug_flag_shows_the_traceback(tmp_path, capsys):
    code, _, err = run_in_process(capsys, "simulate", "acrobot", "--x0", "1,2", "--out", str(tmp_path))
    assert code == 2 and err.startswith("error: --x0 needs 4 values") and "Traceback" not in err
    # in process, --debug lets the error propagate (wherever the flag stands) ...
    for argv in (["--debug", "simulate", "acrobot", "--x0", "1,2"], ["simulate", "acrobot", "--x0", "1,2", "--debug"]):
        with pytest.raises(ValueError, match="--x0 needs 4 values"):
            main([*argv, "--out", str(tmp_path)])
    # ... and the console prints it as a traceback (one interpreter start)
    loud = run("--debug", "simulate", "acrobot", "--x0", "1,2", "--out", str(tmp_path), check=False)
    assert loud.returncode != 0 and "Traceback" in loud.stderr and "--x0 needs 4 values" in loud.stderr


def test_train_sac_set_flags_resume_in_process(tmp_path, capsys):
    from hybridctl.cli import main

    out = tmp_path / "sac"
    tiny = ["--num-envs", "8", "--exploration-steps", "400", "--steps-per-update", "200", "--updates-per-round", "1",
            "--replay-batch-size", "128", "--minibatch-size", "64", "--buffer-size", "20000",
            "--needle-buffer-size", "5000", "--log-every", "400", "--checkpoint-every", "400", "--no-tensorboard",
            "--eval-episodes", "3", "--quiet", "--out", str(out)]
    assert main(["train", "sac", "acrobot", "--set", "polyak=0.9", "--set", "obs_transform=angle_sincos",
                 "--steps", "400", *tiny]) == 0
    assert "SAC on acrobot: 400 env steps, seed 0" in capsys.readouterr().out
    config = json.loads((out / "final" / "config.json").read_text())["config"]
    assert (config["polyak"], config["obs_transform"], config["tensorboard"]) == (0.9, "angle_sincos", False)
    assert main(["train", "sac", "acrobot", "--steps", "800", "--resume", *tiny]) == 0
    printed = capsys.readouterr().out
    assert "resuming" in printed and "deterministic return over 3 episodes" in printed
    result = json.loads((out / "eval.json").read_text())
    assert result["env_steps"] == 800 and result["episodes"] == 3 and "--resume" in result["command"]


def test_train_reward_flag_goes_with_spec_overrides(tmp_path):
    """SSAC's --reward with --spec: the reward is one more override of the plant the CLI loads (it used to fail
    after the run had started: "SACConfig.reward='quadratic', but system ... was loaded with ...")."""
    from hybridctl.cli import main

    out = tmp_path / "ssac"
    assert main(["train", "ssac", "acrobot", "--spec", "params.gravity=9.81", "--reward", "quadratic", "--steps", "400",
                 "--num-envs", "4", "--exploration-steps", "400", "--minibatch-size", "32", "--buffer-size", "2000",
                 "--gate-warm-samples", "200", "--gate-warm-fit-steps", "10", "--no-tensorboard", "--eval-episodes", "2",
                 "--quiet", "--out", str(out)]) == 0
    record = json.loads((out / "final" / "config.json").read_text())
    assert record["config"]["reward"] == "quadratic"
    assert record["system"]["overrides"] == {"params.gravity": 9.81, "reward.kind": "quadratic"}


def test_train_spec_overrides_are_recorded_and_checked_on_resume(tmp_path, capsys):
    """--spec KEY=VALUE trains on an overridden plant spec; the checkpoint loads with it, and a resume
    given other spec values refuses naming the key."""
    from hybridctl.cli import main

    out = tmp_path / "sac"
    tiny = ["--num-envs", "8", "--exploration-steps", "400", "--steps-per-update", "200", "--updates-per-round", "1",
            "--replay-batch-size", "128", "--minibatch-size", "64", "--buffer-size", "20000",
            "--needle-buffer-size", "5000", "--log-every", "400", "--checkpoint-every", "400", "--no-tensorboard",
            "--eval-episodes", "2", "--quiet", "--out", str(out)]
    spec = ["--spec", "reward.kind=upright_centered", "--spec", "initial_state.low=[-1, -3, 0, 0]"]
    assert main(["train", "sac", "cartpole", *spec, "--steps", "400", *tiny]) == 0
    system = json.loads((out / "final" / "config.json").read_text())["system"]
    assert system["overrides"] == {"reward.kind": "upright_centered", "initial_state.low": [-1, -3, 0, 0]}
    from hybridctl import systems
    from hybridctl.learn import CheckpointError, load_controller
    load_controller(out, systems.load("cartpole"))   # deployed: the reward and start distribution do not matter
    with pytest.raises(CheckpointError, match="cart_mass"):
        load_controller(out, systems.load("cartpole", cart_mass=5.0))   # the plant still does
    code, _, err = run_in_process(capsys, "train", "sac", "cartpole", "--spec", "reward.kind=tip_height", "--steps",
                                  "800", "--resume", *tiny)
    assert code == 2 and "reward.kind 'upright_centered' (given 'tip_height')" in err and "Traceback" not in err
    assert main(["train", "sac", "cartpole", "--steps", "800", "--resume", *tiny]) == 0   # the recorded spec
    assert json.loads((out / "eval.json").read_text())["env_steps"] == 800
    code, _, err = run_in_process(capsys, "train", "sac", "cartpole", "--spec", "reward.kind", "--out",
                                  str(tmp_path / "x"))
    assert code == 2 and "--spec expects section.key=value" in err


def test_workflows_run_from_python_as_from_the_cli(tmp_path):
    """The experiments functions behind simulate, demo and mesh, called as a notebook would."""
    from hybridctl import experiments, systems

    acrobot = systems.load("acrobot")
    start = acrobot.nudged_nominal_state()
    assert start == pytest.approx(acrobot.initial_state.nominal + np.array([1e-3, 0, 0, 0]))
    assert start[0] == pytest.approx(-1.5698, abs=1e-4)  # the demo's former --x0
    summary = experiments.simulate_and_write("pendulum", "energy", tmp_path / "sim", x0=[0.05, 0.0], duration=1.0,
                                             html=False)
    assert summary["samples"] == 101 and summary["controller"] == "energy" and "command" not in summary
    written = {p.name for p in (tmp_path / "sim").iterdir()}
    assert written - {".hybridctl.lock", ".hybridctl-output"} == {"trajectory.npz", "summary.json", "plot.png"}
    assert experiments.PRETRAINED_ACROBOT.is_dir()
    with pytest.raises(ValueError, match="no rolling gait"):
        experiments.mesh_report("rimless-wheel", tmp_path / "m", slope_mean=-0.5)
    with pytest.raises(ValueError, match="unknown map"):
        experiments.mesh_report("hopper", tmp_path / "m")
    with pytest.raises(ValueError, match="--variant applies to ssac only"):
        experiments.make_config("sac", variant="paper")
    assert experiments.make_config("ssac", variant="paper", seed=2).polyak == 0.995


def test_command_modules_read_typed_spec_sections():
    """cli and the workflows read ``system.initial_state`` / ``.description``, not ``spec.get("...")``."""
    package = ROOT / "hybridctl"
    files = [*sorted((package / "cli").glob("*.py"))]
    files += [package / "experiments" / f"{name}.py" for name in ("simulation", "demo", "mesh_report", "training")]
    for path in files:
        assert "spec.get(" not in path.read_text(), path


def test_version_and_help_examples_parse_as_printed(capsys):
    """--version prints the package version; every example line of `hybridctl --help` parses."""
    import shlex

    import hybridctl
    from hybridctl.cli import __doc__ as cli_doc, build_parser

    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0 and capsys.readouterr().out.strip() == f"hybridctl {hybridctl.__version__}"
    examples = [line.strip() for line in cli_doc.splitlines() if line.strip().startswith("hybridctl ")]
    assert len(examples) >= 5
    for example in examples:
        words = [w for w in shlex.split(example)[1:] if not (w.startswith("[") or w.endswith("]"))]
        build_parser().parse_args(words)  # a usage error would raise SystemExit


def test_help_lists_the_systems_and_every_default(capsys):
    import argparse

    from hybridctl import systems
    from hybridctl.cli import build_parser

    for command in (["simulate"], ["balance-map"], ["train", "ssac"], ["train", "sac"]):
        with pytest.raises(SystemExit):
            main([*command, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert all(name in text for name in systems.known_systems()), command

    def parsers(parser):
        yield parser
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for child in action.choices.values():
                    yield from parsers(child)

    checked = 0
    for parser in parsers(build_parser()):
        formatter = parser._get_formatter()
        for action in parser._actions:
            if (not action.option_strings or action.nargs == 0 or action.help == argparse.SUPPRESS
                    or action.default in (None, False, argparse.SUPPRESS)):
                continue
            assert "default" in formatter._get_help_string(action), (parser.prog, action.option_strings)
            checked += 1
    assert checked >= 10  # the walk reached the sub-commands (config-field flags state their defaults in their help)


def test_output_into_a_closed_pipe_is_not_an_error():
    """`hybridctl systems | head -1`: no 'Broken pipe' error, exit 0."""
    proc = subprocess.run(f"{sys.executable} -m hybridctl.cli systems | head -1", shell=True, cwd=ROOT,
                          capture_output=True, text=True, timeout=120, executable="/bin/bash")
    assert proc.stdout.startswith("acrobot")
    assert "Broken pipe" not in proc.stderr and "Traceback" not in proc.stderr


def test_top_level_help_lists_every_learner_of_train(capsys):
    """`hybridctl --help` names every learner `train` takes (the shipped eight, and one a test file registered),
    not only SAC / SSAC / ARS."""
    from hybridctl.cli import main
    from hybridctl.experiments.training import training_algorithms

    with pytest.raises(SystemExit):
        main(["--help"])
    shown = " ".join(capsys.readouterr().out.split())
    names = list(training_algorithms())
    assert names[:8] == ["sac", "ssac", "ars", "apg", "shapg", "papg", "cem", "ce-apg"] and "finetune" not in names
    assert f"({', '.join(names)})" in shown
