"""Runs that cannot be destroyed (issue 12 item 3, and the load_controller check of item 2).

* kill -9 of a real ``hybridctl train ssac``, ``hybridctl train ars`` and ``hybridctl mesh``
  subprocess mid-run, then ``--resume``: the run continues from the checkpoint's counter, its
  log keeps every row up to the checkpoint, and it reaches the target;
* every refusal: another algorithm, another plant, missing or damaged files, a changed math
  setting on resume, a folder that holds a run, ``--out`` a file; and the ``--force`` /
  ``--overwrite`` paths;
* checkpoints by wall time (``checkpoint_minutes``) in the skeleton and the mesh builder.
"""

import csv
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hybridctl import systems
from hybridctl.cli import main
from hybridctl.experiments import PRETRAINED_ACROBOT, RunFolderError, make_config, mesh_report, prepare_run_folder
from hybridctl.learn import ARS, SAC, SSAC, CheckpointError, load_controller
from hybridctl.learn.checkpoint import spec_hash, system_record
from hybridctl.learn.gate import GateNet
from hybridctl.systems.switched import CostToGoGate, LearnedGate

ROOT = Path(__file__).resolve().parents[1]
SAC_TINY = dict(num_envs=8, exploration_steps=400, steps_per_update=200, updates_per_round=1,
                replay_batch_size=128, minibatch_size=64, buffer_size=20_000, needle_buffer_size=5_000,
                log_every=400, checkpoint_every=400, tensorboard=False)
SSAC_TINY = dict(SAC_TINY, gate_refit_every=800, gate_refit_steps=20, gate_batch_size=256)
SSAC_FLAGS = ["--num-envs", "8", "--exploration-steps", "400", "--steps-per-update", "200", "--updates-per-round", "1",
              "--replay-batch-size", "128", "--minibatch-size", "64", "--buffer-size", "20000",
              "--needle-buffer-size", "5000", "--log-every", "400", "--no-tensorboard", "--gate-refit-every", "800",
              "--gate-refit-steps", "20", "--gate-batch-size", "256", "--gate-warm-samples", "500",
              "--gate-warm-fit-steps", "50", "--gate-relabel-per-refit", "50", "--eval-episodes", "2", "--quiet"]
ARS_FLAGS = ["--set", "n_directions=2", "--set", "top_directions=1", "--set", "episode_steps=200",
             "--set", "transient_steps=5", "--backend", "serial", "--eval-episodes", "1", "--quiet"]
SAC_FLAGS = [f for f in SSAC_FLAGS[:SSAC_FLAGS.index("--gate-refit-every")]] + ["--eval-episodes", "2", "--quiet"]


def env_with_path():
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    return env


def start(*args) -> subprocess.Popen:
    """``python -m hybridctl.cli ARGS`` in a subprocess (this checkout's package)."""
    return subprocess.Popen([sys.executable, "-m", "hybridctl.cli", *args], cwd=ROOT, env=env_with_path(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def kill_when(proc: subprocess.Popen, ready, limit_s: float = 120.0) -> None:
    """Poll until ``ready()`` (or the process ends: the test then fails, it was not killed mid-run); SIGKILL."""
    deadline = time.monotonic() + limit_s
    while not ready():
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"the run ended (rc {proc.returncode}) before it could be killed mid-run:\n{out}\n{err}")
        if time.monotonic() > deadline:
            proc.kill()
            pytest.fail("no checkpoint appeared")
        time.sleep(0.01)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    proc.stdout.close()
    proc.stderr.close()


def progress_of(folder: Path, key: str):
    """The counter of the checkpoint in ``folder`` (None while there is none or it is being replaced)."""
    try:
        return json.loads((folder / "progress.json").read_text())[key]
    except (OSError, ValueError, KeyError):
        return None


def read_rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return [{k: float(v) if v not in ("", None) else math.nan for k, v in r.items()} for r in csv.DictReader(fh)]


def same_rows(a: list[dict], b: list[dict]) -> bool:
    return len(a) == len(b) and all(
        set(x) == set(y) and all((math.isnan(x[k]) and math.isnan(y[k])) or x[k] == y[k] for k in x)
        for x, y in zip(a, b))


# ==================================================================== kill -9, then --resume

@pytest.mark.slow   # trains SSAC in a subprocess and kills it (~60-75 s); the ARS kill -9 test below (~30 s idle) runs by default
def test_kill_9_ssac_then_resume_continues_from_the_checkpoint(tmp_path):
    """A real SSAC run checkpointing by wall time only (checkpoint_every 0), killed mid-run, resumed."""
    out = tmp_path / "ssac"
    flags = ["--steps", "2400", "--checkpoint-every", "0", "--checkpoint-minutes", "0.01", *SSAC_FLAGS,
             "--out", str(out)]
    proc = start("train", "ssac", "acrobot", *flags)
    kill_when(proc, lambda: (progress_of(out / "checkpoint", "env_steps") or 0) >= 800)
    at = progress_of(out / "checkpoint", "env_steps")
    assert 800 <= at < 2400 and not (out / "final").exists()
    before = [r for r in read_rows(out / "progress.csv") if r["env_steps"] <= at]
    assert [r["env_steps"] for r in before] == list(range(400, at + 1, 400))
    proc = subprocess.run([sys.executable, "-m", "hybridctl.cli", "train", "ssac", "acrobot", "--resume", *flags],
                          cwd=ROOT, env=env_with_path(), capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert f"resuming {out / 'checkpoint'} at {at} env steps" in proc.stdout
    rows = read_rows(out / "progress.csv")
    assert same_rows([r for r in rows if r["env_steps"] <= at], before)      # no row before the checkpoint lost
    assert [r["env_steps"] for r in rows] == list(range(400, 2401, 400))     # and none twice
    assert json.loads((out / "eval.json").read_text())["env_steps"] == 2400
    assert json.loads((out / "final" / "progress.json").read_text())["env_steps"] == 2400
    assert json.loads((out / "final" / "config.json").read_text())["algorithm"] == "SSAC"


def test_kill_9_ars_then_resume_continues_from_the_checkpoint(tmp_path):
    out = tmp_path / "ars"
    flags = ["--epochs", "100", "--checkpoint-every", "10", *ARS_FLAGS, "--out", str(out)]   # killed at >= 20
    proc = start("train", "ars", "Pendulum-v1", *flags)
    kill_when(proc, lambda: (progress_of(out / "checkpoint", "epoch") or 0) >= 20)
    at = progress_of(out / "checkpoint", "epoch")
    assert 20 <= at < 100 and at % 10 == 0 and not (out / "final").exists()
    before = [r for r in read_rows(out / "progress.csv") if r["epoch"] <= at]
    assert [r["epoch"] for r in before] == list(range(1, at + 1))
    proc = subprocess.run([sys.executable, "-m", "hybridctl.cli", "train", "ars", "Pendulum-v1", "--resume", *flags],
                          cwd=ROOT, env=env_with_path(), capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert f"resuming {out / 'checkpoint'} at epoch {at}" in proc.stdout
    rows = read_rows(out / "progress.csv")
    assert same_rows([r for r in rows if r["epoch"] <= at], before)
    assert [r["epoch"] for r in rows] == list(range(1, 101))
    assert json.loads((out / "eval.json").read_text())["epochs"] == 100


@pytest.mark.slow   # about 10 s; the ARS kill -9 test above covers the kill-resume path by default
def test_kill_9_mesh_then_resume_builds_the_same_mesh(tmp_path):
    from hybridctl.analysis import GaussianDisturbance, ReachableMesh, RimlessWheel, build_mesh

    out = tmp_path / "mesh"
    flags = ["mesh", "rimless-wheel", "--box-size", "5e-5", "--checkpoint-every", "5", "--quiet", "--out", str(out)]
    proc = start(*flags)
    kill_when(proc, lambda: (out / "mesh_checkpoint.npz").is_file())
    with np.load(out / "mesh_checkpoint.npz") as saved:
        done, known = len(saved["successors"]), len(saved["states"])
    assert 0 < done < known and not (out / "mfpt.json").exists()   # killed mid-build
    proc = subprocess.run([sys.executable, "-m", "hybridctl.cli", *flags, "--resume"], cwd=ROOT, env=env_with_path(),
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    resumed = ReachableMesh.load(out / "mesh.npz")
    seed = RimlessWheel().fixed_point(0.15)
    reference = build_mesh(RimlessWheel(), [[seed]], GaussianDisturbance(0.15, 0.06, 25), 5e-5, progress=False)
    assert resumed.complete and resumed.size == reference.size
    np.testing.assert_array_equal(resumed.states, reference.states)
    np.testing.assert_array_equal(resumed.successors, reference.successors)


# ==================================================================== what a checkpoint records

@pytest.fixture(scope="module")
def ssac_checkpoint(tmp_path_factory):
    """An SSAC checkpoint directory (no training: a gate without warm start)."""
    path = tmp_path_factory.mktemp("ssac") / "final"
    acrobot = systems.load("acrobot")
    SSAC(acrobot, gate=GateNet(acrobot), **SSAC_TINY).save(path, include_replay=True)
    return path


@pytest.fixture(scope="module")
def sac_checkpoint(tmp_path_factory):
    path = tmp_path_factory.mktemp("sac") / "final"
    SAC("acrobot", **SAC_TINY).save(path, include_replay=True)
    return path


def test_a_checkpoint_records_algorithm_system_spec_hash_and_values(sac_checkpoint):
    meta = json.loads((sac_checkpoint / "config.json").read_text())
    acrobot = systems.load("acrobot")
    assert meta["algorithm"] == "SAC" and meta["config"]["lr"] == 1e-3
    assert meta["system"]["name"] == "acrobot" and meta["system"]["overrides"] == {}
    assert meta["system"]["spec_values"]["params.link_mass"] == [1.0, 1.0]
    assert meta["system"]["spec_hash"] == spec_hash(acrobot.spec.values) == system_record(acrobot)["spec_hash"]
    # the hash is of the resolved values: the same plant spelled another way hashes the same
    assert spec_hash(systems.load("acrobot", link_mass=[1, 1]).spec.values) == meta["system"]["spec_hash"]
    assert spec_hash(systems.load("acrobot", link_mass=[2, 1]).spec.values) != meta["system"]["spec_hash"]


# ==================================================================== another algorithm

def test_sac_load_refuses_an_ssac_checkpoint_unless_forced(ssac_checkpoint):
    with pytest.raises(CheckpointError, match=r"was written by SSAC, not SAC .*force=True \(CLI: --force\)"):
        SAC.load(ssac_checkpoint)
    with pytest.warns(UserWarning, match="force: loading anyway"):
        agent = SAC.load(ssac_checkpoint, force=True)
    assert type(agent) is SAC


def test_ssac_load_refuses_a_sac_checkpoint(sac_checkpoint):
    with pytest.raises(CheckpointError, match="written by SAC, not SSAC"):
        SSAC.load(sac_checkpoint)


def test_cli_resume_of_an_ssac_run_as_sac_refuses_and_leaves_the_run(tmp_path, ssac_checkpoint, capsys):
    out = tmp_path / "run"
    shutil.copytree(ssac_checkpoint, out / "final")
    (out / "eval.json").write_text('{"mine": 1}')
    with pytest.raises(SystemExit) as exc:
        main(["train", "sac", "acrobot", "--out", str(out), "--resume", "--steps", "800", *SAC_FLAGS])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "was written by SSAC, not SAC" in err and "--force" in err
    assert json.loads((out / "final" / "config.json").read_text())["algorithm"] == "SSAC"   # final/ kept
    assert json.loads((out / "eval.json").read_text()) == {"mine": 1}


def test_cli_resume_on_another_system_refuses(tmp_path, sac_checkpoint, capsys):
    out = tmp_path / "run"
    shutil.copytree(sac_checkpoint, out / "checkpoint")
    with pytest.raises(SystemExit):
        main(["train", "sac", "pendulum", "--out", str(out), "--resume", "--steps", "800", *SAC_FLAGS])
    assert "was trained on system 'acrobot', not 'pendulum'" in capsys.readouterr().err


def test_ars_load_refuses_a_sac_checkpoint(sac_checkpoint):
    with pytest.raises(CheckpointError, match="written by SAC, not ARS"):
        ARS.load(sac_checkpoint)


# ==================================================================== another plant

def test_load_and_load_controller_refuse_another_plant_naming_the_value(sac_checkpoint, ssac_checkpoint):
    heavy = systems.load("acrobot", link_mass=[2, 1])
    expected = r"trained on acrobot with params.link_mass=\[1.0, 1.0\]; this system has \[2.0, 1.0\]"
    with pytest.raises(CheckpointError, match=expected):
        SAC.load(sac_checkpoint, system=heavy)
    with pytest.raises(CheckpointError, match=expected):
        load_controller(ssac_checkpoint, heavy)
    with pytest.warns(UserWarning, match="force: loading anyway.*link_mass"):
        agent = SAC.load(sac_checkpoint, system=heavy, force=True)
    assert agent.system.spec.values["params.link_mass"].tolist() == [2.0, 1.0]
    with pytest.warns(UserWarning, match="force"):
        controller = load_controller(ssac_checkpoint, heavy, force=True)
    assert isinstance(controller.gate, LearnedGate)
    with pytest.raises(CheckpointError, match="trained on system 'acrobot', but this system is 'pendulum'"):
        load_controller(ssac_checkpoint, systems.load("pendulum"))


def test_old_checkpoints_load_and_say_what_could_not_be_checked(tmp_path):
    """A checkpoint written before plant records (config.json system = name and overrides only)."""
    old = tmp_path / "old-ssac"
    shutil.copytree(PRETRAINED_ACROBOT, old)
    meta = json.loads((old / "config.json").read_text())
    meta["system"] = {"name": "acrobot", "overrides": {}}
    (old / "config.json").write_text(json.dumps(meta))
    with pytest.warns(UserWarning, match="records no spec hash.*nothing more can be checked"):
        controller = load_controller(old, systems.load("acrobot"))
    assert isinstance(controller.gate, LearnedGate)
    with pytest.raises(CheckpointError, match=r"params.link_mass=\[1.0, 1.0\]; this system has \[2.0, 1.0\] "
                                              r"\(an old checkpoint: only its spec overrides are recorded\)"):
        load_controller(old, systems.load("acrobot", link_mass=[2, 1]))


def test_the_shipped_ars_hopper_loads():
    pytest.importorskip("mujoco", reason="the ARS hopper's env is gymnasium's MuJoCo Hopper-v5 (mujoco extra)")
    ars = ARS.load(ROOT / "models" / "policies" / "ars-hopper")
    assert ars.epoch > 0


def test_the_shipped_ssac_acrobot_records_its_plant():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "records no spec hash" warning
        load_controller(PRETRAINED_ACROBOT, systems.load("acrobot"))
    assert json.loads((PRETRAINED_ACROBOT / "config.json").read_text())["system"]["spec_hash"]
    with pytest.raises(CheckpointError, match=r"params.link_mass=\[1.0, 1.0\]; this system has \[2.0, 1.0\] \(pass"):
        load_controller(PRETRAINED_ACROBOT, systems.load("acrobot", link_mass=[2, 1]))


def test_ars_refuses_a_checkpoint_of_another_env_unless_forced(tmp_path):
    folder = tmp_path / "ars"
    ARS("Pendulum-v1", n_directions=2, top_directions=1, episode_steps=10, transient_steps=2,
        backend="serial").learn(total=1, out=tmp_path / "run", progress=False)
    shutil.copytree(tmp_path / "run" / "final", folder)
    meta = json.loads((folder / "config.json").read_text())
    meta["system"]["name"] = "MountainCarContinuous-v0"
    (folder / "config.json").write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="trained on env 'MountainCarContinuous-v0'; this env is 'Pendulum-v1'"):
        ARS.load(folder, system="Pendulum-v1")
    with pytest.warns(UserWarning, match="force: loading anyway"):
        assert ARS.load(folder, system="Pendulum-v1", force=True).epoch > 0


def test_load_controller_reads_and_checks_normalization_and_model_keys(tmp_path, ssac_checkpoint):
    acrobot = systems.load("acrobot")
    broken = tmp_path / "norm"
    shutil.copytree(ssac_checkpoint, broken)
    (broken / "normalization.json").write_text('{"type": "none"}')
    with pytest.raises(CheckpointError, match="normalization .* differs from the agent's"):
        load_controller(broken, acrobot)
    (broken / "normalization.json").unlink()
    with pytest.raises(CheckpointError, match="missing file 'normalization.json'"):
        load_controller(broken, acrobot)
    keys = tmp_path / "keys"
    shutil.copytree(ssac_checkpoint, keys)
    import torch
    model = torch.load(keys / "model.pt", weights_only=True)
    del model["actor"]
    torch.save(model, keys / "model.pt")
    with pytest.raises(CheckpointError, match="model.pt lacks 'actor'"):   # the learner's own loader (SSAC.load)
        load_controller(keys, acrobot)


# ==================================================================== missing and damaged files on resume

@pytest.mark.parametrize("name, algorithm", [("replay.pt", "sac"), ("gate_data.pt", "ssac")])
def test_resume_refuses_a_missing_bulky_file_unless_forced(tmp_path, sac_checkpoint, ssac_checkpoint, name,
                                                           algorithm):
    source = sac_checkpoint if algorithm == "sac" else ssac_checkpoint
    agent_class = SAC if algorithm == "sac" else SSAC
    run = tmp_path / "run"
    shutil.copytree(source, run / "checkpoint")
    (run / "checkpoint" / name).unlink()
    agent = agent_class.load(run / "checkpoint")
    with pytest.raises(CheckpointError, match=f"missing file '{name}'.*--force"):
        agent.learn(total=8, out=run, resume=True, progress=False)
    (run / "checkpoint" / name).write_bytes(b"garbage")
    with pytest.raises(CheckpointError, match=f"{name}"):   # the damaged file is named (checkpoint.py words it)
        agent.learn(total=8, out=run, resume=True, progress=False)
    (run / "checkpoint" / name).unlink()
    with pytest.warns(UserWarning, match=f"force: .* has no {name}: the resumed run starts without"):
        agent.learn(total=8, out=run, resume=True, progress=False, force=True)
    assert (run / "final").is_dir()


def test_a_checkpoint_saved_without_replay_resumes_saying_so(tmp_path):
    SAC("acrobot", **SAC_TINY).save(tmp_path / "run" / "checkpoint")          # include_replay=False
    assert "replay.pt" not in json.loads((tmp_path / "run" / "checkpoint" / "config.json").read_text())["files"]
    agent = SAC.load(tmp_path / "run" / "checkpoint")
    with pytest.warns(UserWarning, match="was saved without replay.pt .*starts without replay, needle"):
        agent.learn(total=8, out=tmp_path / "run", resume=True, progress=False)


def test_cli_resume_without_gate_data_refuses_before_training_and_force_continues(tmp_path, ssac_checkpoint,
                                                                                   capsys):
    out = tmp_path / "run"
    shutil.copytree(ssac_checkpoint, out / "final")
    (out / "final" / "gate_data.pt").unlink()
    with pytest.raises(SystemExit):
        main(["train", "ssac", "acrobot", "--resume", "--steps", "16", "--quiet", "--eval-episodes", "2",
              "--out", str(out)])
    captured = capsys.readouterr()
    assert "missing file 'gate_data.pt' (gate_data, relabel_pool)" in captured.err and "resuming" not in captured.out
    with pytest.warns(UserWarning, match="force: .* has no gate_data.pt"):
        assert main(["train", "ssac", "acrobot", "--resume", "--force", "--steps", "16", "--quiet",
                     "--eval-episodes", "2", "--out", str(out)]) == 0


def test_resume_with_a_broken_checkpoint_is_an_error_naming_the_file(tmp_path, sac_checkpoint, capsys):
    """The user's case: final/ removed and checkpoint/model.pt deleted (was a TypeError)."""
    out = tmp_path / "run"
    shutil.copytree(sac_checkpoint, out / "checkpoint")
    (out / "checkpoint" / "model.pt").unlink()
    (out / "progress.csv").write_text("env_steps\n")
    with pytest.raises(SystemExit):
        main(["train", "sac", "acrobot", "--out", str(out), "--resume", "--steps", "8", *SAC_FLAGS])
    err = capsys.readouterr().err
    assert "cannot resume: checkpoint" in err and "missing file 'model.pt'" in err
    for damaged, text in (("normalization.json", "normalization.json"), ("progress.json", "progress.json"),
                          ("config.json", "config.json")):
        shutil.rmtree(out / "checkpoint")
        shutil.copytree(sac_checkpoint, out / "checkpoint")
        (out / "checkpoint" / damaged).write_text("{not json")
        with pytest.raises(SystemExit):
            main(["train", "sac", "acrobot", "--out", str(out), "--resume", "--steps", "8", *SAC_FLAGS])
        assert text in capsys.readouterr().err


# ==================================================================== changed settings on resume

def test_resume_applies_run_settings_and_refuses_changed_math_settings(tmp_path, capsys):
    out = tmp_path / "sac"
    assert main(["train", "sac", "acrobot", "--steps", "400", *SAC_FLAGS, "--checkpoint-every", "400",
                 "--out", str(out)]) == 0
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main(["train", "sac", "acrobot", "--resume", "--steps", "800", "--lr", "0.01", "--gamma", "0.9",
              *SAC_FLAGS, "--out", str(out)])
    err = capsys.readouterr().err
    assert "changed settings that change the algorithm: lr: recorded 0.001, given 0.01; gamma: recorded 0.95, " \
           "given 0.9" in err and "--force" in err
    assert json.loads((out / "final" / "progress.json").read_text())["env_steps"] == 400   # untouched
    # run settings are applied (steps, cadences); the math settings given as recorded pass
    assert main(["train", "sac", "acrobot", "--resume", "--steps", "800", *SAC_FLAGS, "--log-every", "200",
                 "--checkpoint-minutes", "0", "--lr", "0.001", "--out", str(out)]) == 0
    config = json.loads((out / "final" / "config.json").read_text())["config"]
    assert (config["total_steps"], config["log_every"], config["checkpoint_minutes"]) == (800, 200, 0)
    assert main(["train", "sac", "acrobot", "--resume", "--steps", "1200", "--lr", "0.01", "--force", *SAC_FLAGS,
                 "--out", str(out)]) == 0
    assert "--force: resuming with lr=0.01 (the checkpoint's run had 0.001)" in capsys.readouterr().out
    assert json.loads((out / "final" / "config.json").read_text())["config"]["lr"] == 0.01
    assert SAC.load(out / "final").actor_opt.param_groups[0]["lr"] == 0.01   # the optimizers use it


def test_ssac_resume_with_another_variant_refuses(tmp_path, ssac_checkpoint, capsys):
    out = tmp_path / "run"
    shutil.copytree(ssac_checkpoint, out / "final")
    with pytest.raises(SystemExit):
        main(["train", "ssac", "acrobot", "--resume", "--variant", "paper", *SSAC_FLAGS, "--out", str(out)])
    err = capsys.readouterr().err
    assert "variant_name: recorded 'hybridctl', given 'paper'" in err and "polyak: recorded 0.9, given 0.995" in err


def test_ars_resume_refuses_a_changed_step_size(tmp_path, capsys):
    out = tmp_path / "ars"
    small = [f.replace("episode_steps=200", "episode_steps=20") for f in ARS_FLAGS]
    assert main(["train", "ars", "Pendulum-v1", "--epochs", "2", *small, "--out", str(out)]) == 0
    with pytest.raises(SystemExit):
        main(["train", "ars", "Pendulum-v1", "--epochs", "3", "--step-size", "0.5", "--resume", *small,
              "--out", str(out)])
    assert "step_size: recorded 0.02, given 0.5" in capsys.readouterr().err
    assert main(["train", "ars", "Pendulum-v1", "--epochs", "3", "--checkpoint-every", "1", "--resume", *small,
                 "--out", str(out)]) == 0
    assert json.loads((out / "eval.json").read_text())["epochs"] == 3


# ==================================================================== run folders

def test_a_new_run_refuses_a_folder_that_holds_a_run(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "progress.csv").write_text("env_steps\n400\n")
    with pytest.raises(SystemExit):
        main(["train", "sac", "acrobot", "--steps", "8", *SAC_FLAGS, "--out", str(out)])
    err = capsys.readouterr().err
    assert f"{out} already holds a run (progress.csv); pass --resume to continue that run, or --overwrite to " \
           f"replace it" in err
    with pytest.raises(RunFolderError, match="already holds a run"):
        prepare_run_folder(out)
    (tmp_path / "file").write_text("x")
    with pytest.raises(SystemExit):
        main(["train", "sac", "acrobot", "--steps", "8", *SAC_FLAGS, "--out", str(tmp_path / "file")])
    assert "is a file, not a folder" in capsys.readouterr().err
    with pytest.raises(RunFolderError, match="exclude each other"):
        prepare_run_folder(out, resume=True, overwrite=True)


def test_overwrite_replaces_the_run_and_keeps_other_files(tmp_path, sac_checkpoint):
    out = tmp_path / "run"
    shutil.copytree(sac_checkpoint, out / "checkpoint")
    (out / "notes.txt").write_text("mine")
    (out / "eval.json").write_text("{}")
    prepare_run_folder(out, overwrite=True)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_mesh_refuses_a_folder_that_holds_a_run(tmp_path, capsys):
    out = tmp_path / "m"
    mesh_report("rimless-wheel", out, box_size=0.01, progress=False)
    with pytest.raises(RunFolderError, match="already holds a run .*mesh.npz.*--resume.*--overwrite"):
        mesh_report("rimless-wheel", out, box_size=0.01, progress=False)
    with pytest.raises(SystemExit):
        main(["mesh", "rimless-wheel", "--box-size", "0.01", "--quiet", "--out", str(out)])
    assert "already holds a run" in capsys.readouterr().err
    assert main(["mesh", "rimless-wheel", "--box-size", "0.01", "--quiet", "--overwrite", "--out", str(out)]) == 0
    assert main(["mesh", "rimless-wheel", "--box-size", "0.01", "--quiet", "--resume", "--out", str(out)]) == 0
    training = tmp_path / "t"
    (training / "final").mkdir(parents=True)
    with pytest.raises(RunFolderError, match="another kind of run"):
        mesh_report("rimless-wheel", training, box_size=0.01, progress=False, resume=True)


def test_a_progress_row_cut_short_by_a_kill_is_dropped_on_resume(tmp_path):
    from hybridctl.learn.run import RunLog

    (tmp_path / "progress.csv").write_text("epoch,x\n1,0.5\n2,0.25\n3")     # the kill cut "30,..." to "3"
    log = RunLog(tmp_path, ("epoch", "x"), "epoch", upto=10)
    log.close()
    assert [r["epoch"] for r in log.rows] == [1, 2]
    assert (tmp_path / "progress.csv").read_text().splitlines() == ["epoch,x", "1,0.5", "2,0.25"]


# ==================================================================== checkpoints by wall time

def test_checkpoints_by_time_in_the_skeleton(tmp_path):
    """ARS with an epoch cadence beyond the run: checkpoint/ comes from the time cadence alone."""
    small = dict(n_directions=2, top_directions=1, episode_steps=10, transient_steps=2, backend="serial",
                 checkpoint_every=1000)
    ARS("Pendulum-v1", checkpoint_minutes=1e-9, **small).learn(total=3, out=tmp_path / "by-time", progress=False)
    assert progress_of(tmp_path / "by-time" / "checkpoint", "epoch") == 2     # after epochs 1, 2; final/ at 3
    ARS("Pendulum-v1", checkpoint_minutes=0, **small).learn(total=3, out=tmp_path / "off", progress=False)
    assert not (tmp_path / "off" / "checkpoint").exists() and (tmp_path / "off" / "final").is_dir()
    with pytest.raises(ValueError, match="checkpoint_minutes must be a finite number >= 0"):
        ARS("Pendulum-v1", checkpoint_minutes=-1, **small).learn(total=1, out=tmp_path / "bad", progress=False)
    with pytest.raises(ValueError, match="checkpoint_minutes must be a finite number"):
        make_config("ssac", checkpoint_minutes=math.inf)      # before any work (the gate's warm start)
    agent = SAC("pendulum", **{**SAC_TINY, "checkpoint_every": 0}, checkpoint_minutes=1e-9)
    agent.learn(total=64, out=tmp_path / "sac", progress=False)
    assert progress_of(tmp_path / "sac" / "checkpoint", "env_steps") == 56   # the last step before the end


def test_mesh_checkpoints_by_time(tmp_path, monkeypatch):
    from hybridctl.analysis import GaussianDisturbance, RimlessWheel, build_mesh
    from hybridctl.analysis import reachable

    calls = []
    real = reachable._save_checkpoint
    monkeypatch.setattr(reachable, "_save_checkpoint", lambda *a, **k: (calls.append(len(a[2])), real(*a, **k)))
    seed = RimlessWheel().fixed_point(0.15)
    args = (RimlessWheel(), [[seed]], GaussianDisturbance(0.15, 0.06, 25), 2e-3)
    build_mesh(*args, checkpoint=tmp_path / "a.npz", checkpoint_every=10**6, checkpoint_minutes=1e-9, progress=False,
               batch_size=16)
    assert len(calls) > 2            # every batch by time, and the end
    calls.clear()
    build_mesh(*args, checkpoint=tmp_path / "b.npz", checkpoint_every=10**6, checkpoint_minutes=0, progress=False,
               batch_size=16)
    assert len(calls) == 1           # the end only
    (tmp_path / "c.npz").write_bytes(b"garbage")
    with pytest.raises(ValueError, match="mesh checkpoint .*c.npz is damaged"):
        build_mesh(*args, checkpoint=tmp_path / "c.npz", resume=True, progress=False)


def test_a_deployed_swingup_ignores_training_only_and_gate_sections(ssac_checkpoint):
    """The episode length never reaches a deployed policy; the gate section only a learned gate reads:
    ``gate="cost-to-go"`` (the ``ssac-costgate:`` controller) loads beside another gate scale."""
    longer = systems.load("acrobot", **{"episode.duration": 20.0})
    assert isinstance(load_controller(ssac_checkpoint, longer).gate, LearnedGate)
    rescaled = systems.load("acrobot", **{"gate.cost_scale": 7.0})
    with pytest.raises(CheckpointError, match=r"gate.cost_scale=.*this system has 7.0"):
        load_controller(ssac_checkpoint, rescaled)   # the learned gate's cost feature reads the scale
    controller = load_controller(ssac_checkpoint, rescaled, gate="cost-to-go")
    assert isinstance(controller.gate, CostToGoGate) and controller.swingup is not None
    with pytest.raises(CheckpointError, match=r"link_mass"):   # the plant is still checked
        load_controller(ssac_checkpoint, systems.load("acrobot", link_mass=[2, 1]), gate="cost-to-go")


@pytest.mark.parametrize("learner, shipped", [("SSAC", "ssac-acrobot"), ("APG", "papg-cartpole")])
def test_a_checkpoint_with_a_field_the_config_no_longer_has_loads_with_a_warning(learner, shipped, tmp_path):
    """A config field dropped since the checkpoint was written is ignored with a warning naming it, for the
    SAC family and the APG family alike (both read config.json through checkpoint.config_from_meta)."""
    import hybridctl.learn as learn

    old = tmp_path / shipped
    shutil.copytree(Path("models/policies") / shipped, old)
    meta = json.loads((old / "config.json").read_text())
    meta["config"]["a_field_dropped_since"] = 3
    (old / "config.json").write_text(json.dumps(meta))
    with pytest.warns(UserWarning, match=r"no longer has the recorded field\(s\) \['a_field_dropped_since'\]"):
        agent = getattr(learn, learner).load(old)
    assert not hasattr(agent.config, "a_field_dropped_since")


# ============================================== output folders of simulate, balance-map, demo (issue 47)

def _hold_lock(folder: str, ready) -> None:
    """A lock holder in another process: lock ``folder``, say so, hold it until killed."""
    from hybridctl import io
    with io.locked_folder(folder):
        ready.set()
        time.sleep(120)


@pytest.fixture
def locked_out(tmp_path):
    """``tmp_path/out`` held locked by another (forked) process, as a second run would find it."""
    import multiprocessing

    context = multiprocessing.get_context("fork")
    ready = context.Event()
    process = context.Process(target=_hold_lock, args=(str(tmp_path / "out"), ready), daemon=True)
    process.start()
    assert ready.wait(30), "the holder did not lock the folder"
    yield tmp_path / "out", process.pid
    process.kill()
    process.join(10)


SIMULATE = ["simulate", "acrobot", "--duration", "0.05", "--no-html"]
BALANCE_MAP = ["balance-map", "acrobot", "--grid", "2", "--duration", "0.05", "--engine", "torch", "--quiet"]


@pytest.mark.parametrize("argv", [SIMULATE, BALANCE_MAP, ["demo", "--grid", "2", "--quiet"]], ids=lambda a: a[0])
@pytest.mark.parametrize("held, what", [("acrobot.toml", "a spec acrobot.toml"),
                                        ("robot.urdf", "a model file robot.urdf"),
                                        ("config.json", "a checkpoint config.json"),
                                        ("model.pt", "a checkpoint model.pt")])
def test_outputs_never_go_into_a_folder_that_holds_an_input(tmp_path, cli_error, argv, held, what):
    out = tmp_path / "inputs"
    out.mkdir()
    (out / held).write_text("mine")
    (out / "summary.json").write_text('{"mine": 1}')
    err = cli_error([*argv, "--out", out])
    assert f"--out {out} holds {what}, which hybridctl {argv[0]} did not write" in err, err
    assert sorted(p.name for p in out.iterdir()) == sorted([held, "summary.json"])   # nothing written, no lock
    assert (out / "summary.json").read_text() == '{"mine": 1}'


def test_simulate_refuses_the_shipped_checkpoint_folder_and_a_summary_it_did_not_write(tmp_path, cli_error):
    before = sorted(p.name for p in Path(PRETRAINED_ACROBOT).iterdir())
    err = cli_error([*SIMULATE, "--out", PRETRAINED_ACROBOT])
    assert "holds a checkpoint config.json" in err
    assert sorted(p.name for p in Path(PRETRAINED_ACROBOT).iterdir()) == before
    other = tmp_path / "other"
    other.mkdir()
    (other / "summary.json").write_text("{}")
    assert "holds summary.json, which hybridctl simulate did not write: it would replace it" in \
        cli_error([*SIMULATE, "--out", other])


@pytest.mark.parametrize("argv", [SIMULATE, BALANCE_MAP], ids=lambda a: a[0])
def test_a_second_run_into_a_folder_is_refused_by_the_lock(cli_error, locked_out, argv):
    out, pid = locked_out
    err = cli_error([*argv, "--out", out])
    assert f"--out {out} is locked by pid {pid}: another run is writing it" in err, err
    assert sorted(p.name for p in out.iterdir()) == [".hybridctl.lock"]


@pytest.mark.parametrize("argv, written", [(SIMULATE, "summary.json"), (BALANCE_MAP, "balance_map.json")],
                         ids=lambda a: a[0] if isinstance(a, list) else a)
def test_a_folder_the_command_made_is_written_again(tmp_path, argv, written):
    out = tmp_path / "out"
    assert main([*argv, "--out", str(out)]) == 0
    first = (out / written).stat().st_mtime_ns
    assert main([*argv, "--out", str(out)]) == 0
    assert (out / written).stat().st_mtime_ns >= first
    legacy = tmp_path / "legacy"                                 # written before folders were marked
    shutil.copytree(out, legacy, ignore=shutil.ignore_patterns(".hybridctl*"))
    assert main([*argv, "--out", str(legacy)]) == 0


def test_train_refuses_a_spec_folder(tmp_path, cli_error):
    out = tmp_path / "specs"
    out.mkdir()
    (out / "acrobot.toml").write_text("mine")
    err = cli_error(["train", "sac", "acrobot", "--steps", "8", *SAC_FLAGS, "--out", out])
    assert f"--out {out} holds a spec acrobot.toml: a run never writes beside an input" in err
