"""benchmarks/dynamics.py --quick runs and reports well-formed numbers (no speed thresholds)."""

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench") / "nested" / "dynamics.json"
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "dynamics.py"), "--quick", "--out", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    printed = json.loads(proc.stdout)          # stdout is exactly one JSON document
    assert json.loads(out.read_text()) == printed
    return printed


def _positive_finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0


def _ratios(node):
    """Every value under a key named ratio_vs_gym_acrobot, anywhere in the document."""
    if isinstance(node, dict):
        for key, value in node.items():
            if key == "ratio_vs_gym_acrobot":
                yield value
            else:
                yield from _ratios(value)
    elif isinstance(node, list):
        for value in node:
            yield from _ratios(value)


def test_header(report):
    assert report["benchmark"] == "dynamics" and report["quick"] is True
    assert "benchmarks/dynamics.py" in " ".join(report["command"])
    assert isinstance(report["timestamp"], str) and report["timestamp"]
    machine = report["machine"]
    for key in ("platform", "cpu_count", "torch", "drake", "gymnasium", "torch_threads"):
        assert key in machine, key
    assert machine["torch_threads"] == 1          # the default


def test_gym_reference(report):
    gym = report["gym_acrobot"]
    assert gym["env"].startswith("Acrobot-v1") and _positive_finite(gym["steps_per_s"])


def test_step_entries(report):
    steps = report["step"]
    acrobot = {(e["method"], e["batch"], e["dtype"]) for e in steps if e["system"] == "acrobot"}
    assert {("step", b, d) for b in (1, 64, 4096) for d in ("float32", "float64")} <= acrobot
    others = {e["system"] for e in steps if e["system"] != "acrobot" and e["batch"] == 4096 and e["dtype"] == "float64"}
    assert others == {"cartpole", "double_cartpole", "pendulum"}
    for entry in steps:
        assert _positive_finite(entry["state_steps_per_s"]) and _positive_finite(entry["seconds_per_call"])
        assert _positive_finite(entry["ratio_vs_gym_acrobot"])


def test_every_ratio_is_positive_finite(report):
    ratios = list(_ratios(report))
    assert len(ratios) >= len(report["step"])
    assert all(_positive_finite(r) for r in ratios), ratios


def test_drake_entry_reports_or_skips(report):
    drake = report["drake_hybrid"]
    assert "error" not in drake, drake["error"]
    if "skipped" in drake:
        assert isinstance(drake["skipped"], str) and drake["skipped"]
    else:
        assert _positive_finite(drake["realtime_factor"]) and drake["duration_s"] == 10.0
        # every shipped Drake controller, on the default loop and the pre-issue-15 Python loop (issue 15)
        names = {entry["controller"] for entry in drake["controllers"]}
        assert {"energy", "ssac:models/policies/ssac-acrobot", "papg:models/policies/papg-cartpole"} <= names
        for entry in drake["controllers"]:
            if "skipped" not in entry:
                for key in ("realtime_factor", "realtime_factor_python_switch", "speedup_vs_python_switch"):
                    assert _positive_finite(entry[key]), (entry["controller"], key)


def test_ssac_baselines_script_runs_a_tiny_budget(tmp_path):
    """benchmarks/ssac_baselines.py trains SB3 SAC and A2C briefly and prints the Table 3.1 JSON."""
    pytest.importorskip("stable_baselines3")
    runs = tmp_path / "runs"
    (runs / "ssac-acrobot-s0").mkdir(parents=True)
    (runs / "ssac-acrobot-s0" / "eval.json").write_text(json.dumps({"mean_return": 90.0, "env_steps": 10}))
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "ssac_baselines.py"), "--steps", "200",
                           "--seeds", "0", "--algos", "sac", "a2c", "--eval-episodes", "2", "--runs", str(runs)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(proc.stdout)
    assert set(report["stable_baselines3"]) == {"SAC", "A2C"}
    assert report["stable_baselines3"]["SAC"]["thesis"] == [73.01, 11.41]
    assert math.isfinite(report["stable_baselines3"]["A2C"]["mean_return"])
    assert report["hybridctl"]["SSAC"]["mean_return"] == 90.0


def test_mesh_dimension_benchmark_reports_both_methods(tmp_path):
    """benchmarks/mesh_dimension.py --quick: both counts on the same curve, positive timings (no thresholds)."""
    out = tmp_path / "mesh.json"
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "mesh_dimension.py"), "--quick", "--out", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(proc.stdout)
    assert json.loads(out.read_text()) == report and report["benchmark"] == "mesh_dimension"
    assert {e["trajectory"] for e in report["entries"]} == {"gait", "random_walk"}
    for entry in report["entries"]:
        assert entry["n_dims"] == 17 and entry["n_states"] == 10_000
        assert _positive_finite(entry["vectorised_s"]) and _positive_finite(entry["dict_s"])
        assert _positive_finite(entry["speedup_vs_dict"]) and entry["meshes_on_curve"] >= 3
        assert 0 <= entry["lower"] <= entry["upper"]


def test_mfpt_benchmark_agrees_with_spsolve(tmp_path):
    """benchmarks/mfpt.py --quick: the Krylov MFPT equals spsolve's on a mesh-like chain (no speed thresholds)."""
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "mfpt.py"), "--quick"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(proc.stdout)
    (entry,) = report["entries"]
    assert report["benchmark"] == "mfpt" and entry["states"] == 12 ** 3 + 1
    assert entry["max_rel_diff_vs_spsolve"] < 1e-8 and entry["krylov_solver"]["converged"]
    assert _positive_finite(entry["krylov_s"]) and _positive_finite(entry["speedup_vs_spsolve"])
    assert 1 < entry["mfpt_mean_over_states"] < 1e6 and entry["infinite_states"] == 0
