"""benchmarks/dynamics.py --quick runs and reports well-formed numbers (no speed thresholds)."""

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Each test runs a benchmark script end to end (~270 s of the default suite on 2 loaded cores):
# they check the JSON that `make bench` prints, so they run with `make test-all`, not `make test`.
pytestmark = pytest.mark.slow


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


def test_mfpt_benchmark_agrees_with_its_peers(tmp_path):
    """benchmarks/mfpt.py --quick: the auto MFPT equals spsolve's (and deeptime's, if installed) on a birth-death,
    a grid, a mesh-like and a uniform chain, picks the direct-first and the Krylov path, and reports ratios (no speed thresholds)."""
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "mfpt.py"), "--quick", "--repeats", "1"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(proc.stdout)
    assert report["benchmark"] == "mfpt"
    entries = {e["family"]: e for e in report["entries"]}
    assert set(entries) == {"birth-death", "grid-2d", "mesh-like", "uniform"}
    assert {f: e["auto_path"] for f, e in entries.items()} == {"birth-death": "direct-first", "grid-2d": "direct-first",
                                                               "mesh-like": "direct-first", "uniform": "krylov"}
    for entry in entries.values():
        assert 1_000 <= entry["states"] <= 1_100 and entry["infinite_states"] == 0
        assert entry["spsolve"]["max_rel_diff"] < 1e-9 and _positive_finite(entry["spsolve"]["ratio"])
        assert _positive_finite(entry["auto_s"]) and 10 < entry["mfpt_mean_over_states"] < 1e6
        assert "max_rel_diff" in entry["deeptime"] or entry["deeptime"] == {"skipped": "deeptime not installed"}
        if "max_rel_diff" in entry["deeptime"]:
            assert entry["deeptime"]["max_rel_diff"] < 1e-9


def test_training_benchmark_reports_rates_and_projection(tmp_path):
    """benchmarks/training.py --quick (eager only): our SAC and SSAC env rates, SB3's when installed."""
    out = tmp_path / "training.json"
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "training.py"), "--quick", "--no-compile",
                           "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(proc.stdout)
    assert json.loads(out.read_text()) == report
    assert _positive_finite(report["sac"]["off"]["env_steps_per_s"]["per_s"])
    assert _positive_finite(report["sac"]["off"]["gradient_steps_per_s"]["per_s"])
    assert _positive_finite(report["ssac_env"]["off"]["env_steps_per_s"]["per_s"])
    assert report["projected_ssac_2e6"]["gradient_steps"] == 499_200   # 3900 rounds x 4 updates x 32 minibatches
    assert _positive_finite(report["projected_ssac_2e6"]["hybridctl_off_s"])
    if "skipped" in report["sb3_sac"]:
        assert "stable-baselines3" in report["sb3_sac"]["skipped"]
    else:
        ratio = report["sac"]["off"]["gradient_steps_per_s"]["ratio_vs_sb3"]
        assert _positive_finite(ratio)


def test_step_limits_beside_the_measured_rate(report):
    limits = report["step_limits"]
    assert _positive_finite(limits["machine"]["float64_flops_per_s"])
    assert _positive_finite(limits["machine"]["sin_seconds_per_element"])
    assert set(limits["systems"]) == {"acrobot", "cartpole", "double_cartpole", "pendulum"}
    for name, entry in limits["systems"].items():
        assert isinstance(entry["arithmetic_flops"], int) and entry["arithmetic_flops"] > 0, name
        assert isinstance(entry["trig_calls"], int) and entry["trig_calls"] > 0, name
        for key in ("flop_limit_state_steps_per_s", "arithmetic_limit_state_steps_per_s",
                    "measured_state_steps_per_s", "fraction_of_flop_limit", "flop_limit_ratio_vs_gym_acrobot"):
            assert _positive_finite(entry[key]), (name, key)
        assert entry["flop_limit_state_steps_per_s"] < entry["arithmetic_limit_state_steps_per_s"]
    # the acrobot's Euler step: 4 sin/cos (phi1, phi2, th2 twice), as the formula needs
    assert limits["systems"]["acrobot"]["trig_calls"] == 4


def test_single_env_entry(report):
    entry = report["single_env"]
    assert entry["env"].startswith("hybridctl SwingupEnv") and entry["substeps_per_step"] == 20
    assert _positive_finite(entry["steps_per_s"]) and _positive_finite(entry["ratio_vs_gym_acrobot"])


def test_mesh_scaling_benchmark_structure(tmp_path):
    """benchmarks/mesh_scaling.py --quick: the same mesh on 1 and 2 worker processes, a ratio
    between them, the 16-worker projection and the figure (no speed thresholds)."""
    out, png = tmp_path / "scaling.json", tmp_path / "scaling.png"
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "mesh_scaling.py"), "--quick", "--out", str(out),
                           "--figure", str(png)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(proc.stdout)
    assert json.loads(out.read_text()) == report and report["benchmark"] == "mesh_scaling"
    assert report["problem"]["backend"] == "processes"
    one, two = report["builds"]
    assert (one["workers"], two["workers"]) == (1, 2) and one["ratio_vs_1_worker"] == 1.0
    assert one["expanded_states"] == two["expanded_states"] > 0 and one["complete"] and two["complete"]
    assert one["same_mesh_as_first"] and two["same_mesh_as_first"]        # the wheel is deterministic
    for row in (one, two):
        assert _positive_finite(row["states_per_s"]) and _positive_finite(row["ratio_vs_1_worker"])
    projection = report["projection"]
    assert projection["states"] == 275_658 and projection["workers"] == 16
    for key in ("per_worker_states_per_s", "hours_at_measured_efficiency", "hours_at_linear_scaling",
                "driver_array_mib"):
        assert _positive_finite(projection[key]), key
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and report["figure"] == str(png)


def test_column_major_entries(report):
    """step_columns is timed (eager); its torch.compile build is skipped under --quick and says so."""
    eager = [e for e in report["step"] if e["method"] == "step_columns"]
    assert len(eager) == 1 and eager[0]["batch"] == 4096 and _positive_finite(eager[0]["ratio_vs_gym_acrobot"])
    (skipped,) = report["step_columns_not_measured"]
    assert skipped["method"] == "step_columns_compiled" and "--quick" in skipped["skipped"]

def test_mujoco_rollout_benchmark_structure(tmp_path):
    """benchmarks/mujoco_rollout.py --quick: gymnasium, mj_step and the batched stepper in one run (no thresholds)."""
    pytest.importorskip("mujoco")
    pytest.importorskip("mujoco.batch")
    out = tmp_path / "mujoco.json"
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "mujoco_rollout.py"), "--quick", "--out", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(proc.stdout)
    assert json.loads(out.read_text()) == report and report["benchmark"] == "mujoco_rollout" and report["quick"]
    assert report["env"] == "Hopper-v5" and report["frame_skip"] == 4
    assert _positive_finite(report["gym"]["env_steps_per_s"]) and _positive_finite(report["mj_step"]["seconds"])
    assert {r["nthread"] for r in report["batched"]} == {1, 2}
    for row in report["batched"] + report["rollout_open_loop_calls"]:
        for key in ("env_steps_per_s", "ratio_vs_gym", "limit_over_measured"):
            assert _positive_finite(row[key]), (key, row)
    assert _positive_finite(report["hopper_section_map"]["ratio_vs_gym"])
    assert report["hopper_section_map"]["gym"]["failures"] == report["hopper_section_map"]["batched_1_thread"]["failures"]
    assert _positive_finite(report["ars_epoch"]["ratio_vs_gym"])
    assert report["ars_epoch"]["gym_per_task"]["mean_return"] == report["ars_epoch"]["batched_1_thread"]["mean_return"]
    for row in report["batched"]:
        assert len(row["ratio_vs_gym_by_repeat"]) == len(row["limit_over_measured_by_repeat"]) == report["repeats"]
        assert row["physics_limit_steps_per_s"] == pytest.approx(
            row["nthread"] / (4 * report["mj_step"]["seconds"]))
