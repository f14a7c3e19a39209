"""The command line as a user runs it: files written, JSON fields, clear errors."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def run(*args, check=True):
    proc = subprocess.run([sys.executable, "-m", "hybridctl.cli", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    if check and proc.returncode != 0:
        raise AssertionError(f"hybridctl {' '.join(args)} failed:\n{proc.stdout}\n{proc.stderr}")
    return proc


def test_simulate_writes_all_outputs(tmp_path):
    out = tmp_path / "sim"
    run("simulate", "pendulum", "--x0", "0.05,0", "--duration", "6", "--out", str(out))
    data = np.load(out / "trajectory.npz")
    assert set(data.files) >= {"t", "x", "u", "gate"}
    assert data["x"].shape == (601, 2) and data["u"].shape == (601, 1)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["balanced"] is True and summary["diverged"] is False
    assert isinstance(summary["return"], float)
    assert (out / "plot.png").stat().st_size > 10_000
    assert "<html" in (out / "replay.html").read_text()[:2000].lower()


def test_balance_map_writes_png_and_json(tmp_path):
    out = tmp_path / "map"
    proc = run("balance-map", "pendulum", "--grid", "3", "--workers", "1", "--quiet", "--out", str(out))
    result = json.loads((out / "balance_map.json").read_text())
    assert 0.0 <= result["balanced_fraction"] <= 1.0
    assert np.array(result["balanced"]).shape == (3, 3)
    assert result["balanced_fraction"] == pytest.approx(np.mean(result["balanced"]))
    assert (out / "balance_map.png").exists()
    assert "balanced_fraction" in proc.stdout


def test_demo_balances_the_acrobot(tmp_path):
    proc = run("demo", "--grid", "2", "--quiet", "--out", str(tmp_path))
    summary = json.loads((tmp_path / "acrobot" / "summary.json").read_text())
    assert summary["balanced"] and (tmp_path / "acrobot" / "replay.html").exists()
    assert (tmp_path / "balance_map" / "balance_map.json").exists()
    assert "balanced=True" in proc.stdout


@pytest.mark.parametrize("args, message", [
    (["simulate", "acrobott"], "known systems: acrobot, cartpole"),
    (["simulate", "acrobot", "--x0", "1,2"], "--x0 needs 4 values"),
    (["simulate", "acrobot", "--x0", "a,b,c,d"], "--x0 must be 4 comma-separated numbers"),
    (["simulate", "acrobot", "--controller", "nope"], "unknown controller 'nope'; known: energy"),
    (["simulate", "acrobot", "--duration", "-1"], "must be > 0"),
    (["balance-map", "acrobot", "--grid", "1", "--workers", "1"], "grid must be >= 2"),
])
def test_bad_arguments_exit_nonzero_with_clear_message(args, message, tmp_path):
    proc = run(*args, "--out", str(tmp_path), check=False)
    assert proc.returncode != 0
    assert message in proc.stderr + proc.stdout


def test_train_ars_resume_and_init(tmp_path):
    """hybridctl train ars: a run, its resume, and the thesis' identity-then-post-processing protocol."""
    out = tmp_path / "ars"
    small = ["--set", "n_directions=2", "--set", "top_directions=1", "--set", "episode_steps=40",
             "--set", "transient_steps=5", "--backend", "serial", "--eval-episodes", "2", "--quiet"]
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
def test_train_ars_bad_arguments(args, message, tmp_path):
    proc = run(*args, "--out", str(tmp_path / "x"), "--quiet", check=False)
    assert proc.returncode != 0 and message in proc.stderr, proc.stderr
