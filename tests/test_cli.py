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


def test_mesh_writes_matrix_report_and_figures(tmp_path):
    import scipy.sparse as sp
    out = tmp_path / "mesh"
    proc = run("mesh", "rimless-wheel", "--box-size", "0.01", "--monte-carlo", "500", "--sizes", "0.1",
               "--out", str(out), "--quiet")
    assert "MFPT from the seed" in proc.stdout
    report = json.loads((out / "mfpt.json").read_text())
    T = sp.load_npz(out / "transition_matrix.npz")
    assert T.shape[0] == report["mesh"]["states"] + 1 and np.allclose(T.sum(axis=1), 1.0)
    assert report["mfpt"]["from_seed"] > 1 and report["mfpt"]["infinite_states"] == 0
    mc = report["monte_carlo"]["mesh_disturbance_set"]
    assert mc["interval95"][0] < mc["mean_steps_to_failure"] < mc["interval95"][1]
    assert 0.5 < report["reachable_dimension"] < 1.5
    for name in ("sparsity.png", "cumulative_mass.png", "states.png", "mesh_sizes.png"):
        assert (out / name).stat().st_size > 5000, name


@pytest.mark.parametrize("args, message", [
    (["mesh", "rimless-wheel", "--slope-mean", "-0.5"], "no rolling gait"),
    (["mesh", "rimless-wheel", "--box-size", "0"], "must be > 0"),
    (["mesh", "hopper"], "invalid choice"),
])
def test_mesh_bad_arguments(args, message, tmp_path):
    proc = run(*args, "--out", str(tmp_path / "m"), "--quiet", check=False)
    assert proc.returncode != 0 and message in proc.stderr, proc.stderr


def test_mesh_cap_reports_incomplete(tmp_path):
    proc = run("mesh", "rimless-wheel", "--max-states", "20", "--out", str(tmp_path / "m"), "--quiet", check=False)
    assert proc.returncode == 2 and "incomplete" in proc.stdout
    assert "incomplete" in json.loads((tmp_path / "m" / "mfpt.json").read_text())["error"]
