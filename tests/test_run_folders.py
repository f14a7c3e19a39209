"""The user's files are never lost (issue 29 item 3, Deliver 2).

* ``RUN_FOLDER_CASES``: every command line of the issue that destroyed data, wrote into the
  current folder or resumed the wrong thing is refused in one line (exit 2, no traceback), and
  what the user had is still there, byte for byte: an ``--out`` that is, holds or lies inside
  an input (``--policy``, ``--init``, a spec file), ``--resume`` inside a checkpoint, an empty
  ``--out``, progress counters a run cannot have reached;
* ``--overwrite`` removes nothing when the new run's inputs cannot be read;
* the run-folder lock (``hybridctl.io.locked_folder``): a second holder in another process is
  refused at once with the holder's pid, a kill -9 of the holder leaves no stale lock, the
  lock nests in one process, the learners' loop takes it too; and two real
  ``python -m hybridctl.cli train sac`` started together: one trains, the other is refused
  naming the first's pid, and the folder holds one consistent run.
"""

from __future__ import annotations

import csv
import hashlib
import json
import multiprocessing
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hybridctl import io
from hybridctl.experiments import RunFolderError, prepare_run_folder, train_and_evaluate
from hybridctl.learn import ARS, SAC

ROOT = Path(__file__).resolve().parents[1]
PPO_ZIP = ROOT / "models" / "policies" / "ppo-pendulum" / "model.zip"
ACROBOT_SPEC = ROOT / "hybridctl" / "data" / "systems" / "acrobot.toml"
SAC_TINY = dict(num_envs=8, exploration_steps=400, steps_per_update=200, updates_per_round=1,
                replay_batch_size=128, minibatch_size=64, buffer_size=20_000, needle_buffer_size=5_000,
                log_every=400, checkpoint_every=400, tensorboard=False)
SAC_FLAGS = ["--num-envs", "8", "--exploration-steps", "400", "--steps-per-update", "200", "--updates-per-round", "1",
             "--replay-batch-size", "128", "--minibatch-size", "64", "--buffer-size", "20000",
             "--needle-buffer-size", "5000", "--log-every", "400", "--no-tensorboard", "--eval-episodes", "1",
             "--quiet"]
ARS_TINY = dict(n_directions=2, top_directions=1, episode_steps=20, transient_steps=2, backend="serial")
ARS_FLAGS = ["--set", "n_directions=2", "--set", "top_directions=1", "--set", "episode_steps=20",
             "--set", "transient_steps=2", "--backend", "serial", "--eval-episodes", "1", "--quiet"]
FINETUNE_FLAGS = ["--updates", "1", "--directions", "2", "--eval-episodes", "1", "--backend", "serial", "--quiet"]


# ==================================================================== the user's files, made once

@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """Runs to copy into each case: ``ars`` (Pendulum-v1, 2 epochs), ``sac`` (acrobot, 8 env steps, with
    replay), ``zip`` (a folder with the shipped PPO zip), ``spec`` (a folder with an acrobot spec file)."""
    root = tmp_path_factory.mktemp("made")
    ARS("Pendulum-v1", **ARS_TINY).learn(total=2, out=root / "ars", progress=False)
    with pytest.warns(UserWarning, match="no gradient step"):
        SAC("acrobot", **SAC_TINY).learn(total=8, out=root / "sac", progress=False)
    (root / "zip").mkdir()
    shutil.copy(PPO_ZIP, root / "zip" / "model.zip")
    (root / "spec").mkdir()
    shutil.copy(ACROBOT_SPEC, root / "spec" / "mine.toml")
    return root


def digests(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (relative name -> sha256), the lock file aside."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name != io.LOCK_FILE}


def edit_json(path: Path, **values) -> None:
    """Set keys of the JSON file ``path`` (as a hand edit or a damaged disk would)."""
    doc = json.loads(path.read_text())
    doc.update(values)
    path.write_text(json.dumps(doc))


# (case, argv with {ars} {sac} {zip} {spec} {tmp} folders, edits: (file, {key: value}), message regex)
RUN_FOLDER_CASES = [
    ("finetune --out holding its own source zip",
     ["finetune", "Pendulum-v1", "--policy", "sb3:{zip}/model.zip", "--out", "{zip}", *FINETUNE_FLAGS], None,
     r"--out \S+zip holds the --policy input \S+zip/model.zip: the run would overwrite what it reads"),
    ("finetune --out the run of its ssac policy, --overwrite",
     ["finetune", "acrobot", "--policy", "ssac:{sac}/final", "--out", "{sac}", "--overwrite", *FINETUNE_FLAGS],
     None, r"--out \S+sac holds the --policy input \S+sac/final"),
    ("finetune --out inside its policy checkpoint",
     ["finetune", "acrobot", "--policy", "ssac:{sac}/final", "--out", "{sac}/final/tuned", *FINETUNE_FLAGS], None,
     r"--out \S+sac/final/tuned lies inside the --policy input \S+sac/final"),
    ("finetune --out the --normalizer file's folder",
     ["finetune", "Pendulum-v1", "--policy", f"sb3:{PPO_ZIP}", "--normalizer", "{ars}/progress.csv", "--out", "{ars}",
      *FINETUNE_FLAGS], None, r"--out \S+ars holds the --normalizer input"),
    ("train ars --init from the run it overwrites",
     ["train", "ars", "Pendulum-v1", "--init", "{ars}/final", "--epochs", "3", "--out", "{ars}", "--overwrite",
      *ARS_FLAGS], None, r"--out \S+ars holds the --init input \S+ars/final"),
    ("train ars --out the --init checkpoint itself",
     ["train", "ars", "Pendulum-v1", "--init", "{ars}/final", "--epochs", "3", "--out", "{ars}/final", *ARS_FLAGS],
     None, r"--out \S+ars/final is the --init input"),
    ("train sac with a spec file inside --out",
     ["train", "sac", "{spec}/mine.toml", "--steps", "8", "--out", "{spec}", *SAC_FLAGS], None,
     r"--out \S+spec holds the SYSTEM spec input \S+spec/mine.toml"),
    ("train ars --resume --out RUN/final",
     ["train", "ars", "Pendulum-v1", "--resume", "--epochs", "3", "--out", "{ars}/final", *ARS_FLAGS], None,
     r"--out \S+ars/final holds model.pt: it is a checkpoint, not a run folder; --resume continues the run folder "
     r"that holds it \(e.g. --out \S+ars\)"),
    ("train sac --resume --out RUN/checkpoint-like folder with config.json only",
     ["train", "sac", "acrobot", "--resume", "--steps", "16", "--out", "{tmp}/ckpt", *SAC_FLAGS],
     ("ckpt/config.json", {}), r"--out \S+ckpt holds config.json: it is a checkpoint"),
    ("train sac a new run in RUN/final",
     ["train", "sac", "acrobot", "--steps", "8", "--out", "{sac}/final", *SAC_FLAGS], None,
     r"--out \S+sac/final holds model.pt: it is a checkpoint, not a run folder; a run goes into a folder of its own"),
    ("train sac --out ''", ["train", "sac", "acrobot", "--steps", "8", "--out", "", *SAC_FLAGS], None,
     r"--out is empty: give the folder for the outputs"),
    ("train ars --out ''", ["train", "ars", "Pendulum-v1", "--epochs", "1", "--out", "", *ARS_FLAGS], None,
     r"--out is empty"),
    ("finetune --out ''", ["finetune", "Pendulum-v1", "--policy", f"sb3:{PPO_ZIP}", "--out", "", *FINETUNE_FLAGS],
     None, r"--out is empty"),
    ("mesh --out ''", ["mesh", "rimless-wheel", "--box-size", "0.01", "--quiet", "--out", ""], None,
     r"--out is empty"),
    ("simulate --out ''", ["simulate", "acrobot", "--controller", "zero", "--duration", "0.1", "--out", ""], None,
     r"--out is empty"),
    ("resume with env_steps 1e300",
     ["train", "sac", "acrobot", "--resume", "--steps", "16", "--out", "{sac}", *SAC_FLAGS],
     ("sac/final/progress.json", {"env_steps": 1e300}), r"\S+sac/final/progress.json: 'env_steps' must be an integer"),
    ("resume with epoch 1e300",
     ["train", "ars", "Pendulum-v1", "--resume", "--epochs", "3", "--out", "{ars}", *ARS_FLAGS],
     ("ars/final/progress.json", {"epoch": 1e300}), r"\S+ars/final/progress.json: 'epoch' must be an integer"),
    ("resume with epoch -1",
     ["train", "ars", "Pendulum-v1", "--resume", "--epochs", "3", "--out", "{ars}", *ARS_FLAGS],
     ("ars/final/progress.json", {"epoch": -1}), r"\S+ars/final/progress.json: 'epoch' must be an integer"),
    ("resume with epoch 2.5",
     ["train", "ars", "Pendulum-v1", "--resume", "--epochs", "3", "--out", "{ars}", *ARS_FLAGS],
     ("ars/final/progress.json", {"epoch": 2.5}), r"\S+ars/final/progress.json: 'epoch' must be an integer"),
    ("resume with more epochs than the run's budget",
     ["train", "ars", "Pendulum-v1", "--resume", "--epochs", "3", "--out", "{ars}", *ARS_FLAGS],
     ("ars/final/progress.json", {"epoch": 50}),
     r"\S+ars/final/progress.json: 'epoch' is 50, beyond this run's budget of 3 epochs"),
    ("resume with more env steps than the run's budget",
     ["train", "sac", "acrobot", "--resume", "--steps", "16", "--out", "{sac}", *SAC_FLAGS],
     ("sac/final/progress.json", {"env_steps": 10 ** 9}),
     r"\S+sac/final/progress.json: 'env_steps' is 1,000,000,000, beyond this run's budget of 16 steps"),
]


@pytest.mark.parametrize("case, argv, edit, message", RUN_FOLDER_CASES, ids=[c[0] for c in RUN_FOLDER_CASES])
def test_a_command_that_would_lose_files_is_refused_in_one_line(case, argv, edit, message, made, tmp_path,
                                                                cli_error, monkeypatch):
    for name in ("ars", "sac", "zip", "spec"):
        shutil.copytree(made / name, tmp_path / name)
    if edit is not None:
        path = tmp_path / edit[0]
        path.parent.mkdir(parents=True, exist_ok=True)
        if not path.exists():
            path.write_text("{}")
        edit_json(path, **edit[1])
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")   # an empty --out would write here
    before = digests(tmp_path)
    folders = {name: str(tmp_path / name) for name in ("ars", "sac", "zip", "spec")}
    err = cli_error([a.format(tmp=tmp_path, **folders) for a in argv])
    assert len(err.strip().splitlines()) == 1, err
    assert __import__("re").search(message, err), err
    assert digests(tmp_path) == before                     # nothing removed, replaced or added
    assert not any((tmp_path / "cwd").iterdir())


# ==================================================================== --overwrite removes only after the inputs are read

@pytest.mark.parametrize("argv", [
    ["train", "ars", "Pendulum-v1", "--init", "{tmp}/no-such-run/final", "--epochs", "3", "--overwrite", *ARS_FLAGS],
    ["finetune", "acrobot", "--policy", "ssac:{tmp}/no-such-run/final", "--overwrite", *FINETUNE_FLAGS],
    ["train", "sac", "acrobot", "--steps", "8", "--overwrite", "--lr", "nan", *SAC_FLAGS],
], ids=["train-ars-init", "finetune-policy", "train-sac-bad-setting"])
def test_overwrite_keeps_the_old_run_when_the_new_one_cannot_start(argv, made, tmp_path, cli_error):
    run = tmp_path / "run"
    shutil.copytree(made / "ars", run)
    before = digests(run)
    err = cli_error([*(a.format(tmp=tmp_path) for a in argv), "--out", str(run)])
    assert "no-such-run" in err or "lr" in err
    assert digests(run) == before


def test_overwrite_replaces_the_run_once_the_init_is_read(made, tmp_path):
    init = tmp_path / "init"
    shutil.copytree(made / "ars", init)
    run = tmp_path / "run"
    shutil.copytree(made / "sac", run)
    (run / "notes.txt").write_text("mine")
    result = train_and_evaluate("ars", "Pendulum-v1", out=run, settings={**ARS_TINY, "epochs": 3},
                                init=init / "final", overwrite=True, progress=False, report=None, eval_episodes=1)
    assert result.agent.epoch == 3
    assert json.loads((run / "final" / "config.json").read_text())["algorithm"] == "ARS"
    assert (run / "notes.txt").read_text() == "mine" and (init / "final" / "model.pt").is_file()
    assert not (run / "training_curves.png").exists()     # the SAC run's outputs went


def test_the_api_refuses_an_empty_folder(tmp_path):
    with pytest.raises(RunFolderError, match="--out is empty"):
        prepare_run_folder("")
    with pytest.raises(RunFolderError, match="--out is empty"):
        io.output_folder("")
    with pytest.raises(RunFolderError, match="--grid-out is empty"):
        io.output_folder(" ", "--grid-out")


# ==================================================================== the lock

def _hold(folder: str, ready) -> None:
    """A lock holder in another process: lock ``folder``, say so, hold it until killed."""
    with io.locked_folder(folder):
        ready.set()
        time.sleep(120)


@pytest.fixture
def holder(tmp_path):
    """A process (forked: it starts in milliseconds) that holds ``tmp_path/run`` locked until killed.

    It is ended by a kill, never told through an Event: a multiprocessing Event's ``set`` waits for
    every waiter to wake, and a waiter killed with SIGKILL never does (that hung the suite)."""
    context = multiprocessing.get_context("fork")
    ready = context.Event()
    process = context.Process(target=_hold, args=(str(tmp_path / "run"), ready), daemon=True)
    process.start()
    assert ready.wait(30), "the holder did not lock the folder"
    yield process
    if process.is_alive():
        process.kill()
    process.join(10)


def test_a_second_holder_is_refused_with_the_pid_and_a_kill_leaves_no_stale_lock(tmp_path, holder):
    run = tmp_path / "run"
    with pytest.raises(RunFolderError, match=f"--out {run} is locked by pid {holder.pid}: another run is writing it"):
        with io.locked_folder(run):
            pass
    assert (run / io.LOCK_FILE).read_text().strip() == str(holder.pid)
    os.kill(holder.pid, signal.SIGKILL)
    holder.join(10)
    with io.locked_folder(run):                            # at once: the OS dropped the lock with its process
        assert (run / io.LOCK_FILE).read_text().strip() == str(os.getpid())


def test_the_cli_and_the_learners_loop_refuse_a_locked_folder(tmp_path, holder, cli_error):
    run = tmp_path / "run"
    err = cli_error(["train", "ars", "Pendulum-v1", "--epochs", "1", "--out", str(run), *ARS_FLAGS])
    assert f"--out {run} is locked by pid {holder.pid}" in err
    err = cli_error(["mesh", "rimless-wheel", "--box-size", "0.01", "--quiet", "--out", str(run)])
    assert f"is locked by pid {holder.pid}" in err
    with pytest.raises(RunFolderError, match=f"out {run} is locked by pid {holder.pid}"):
        ARS("Pendulum-v1", **ARS_TINY).learn(total=1, out=run, progress=False)
    assert sorted(p.name for p in run.iterdir()) == [io.LOCK_FILE]     # nothing was written


def test_the_lock_nests_in_one_process_and_is_released(tmp_path):
    with io.locked_folder(tmp_path / "run") as run:
        with io.locked_folder(run):
            pass
        with io.locked_folder(run):                        # still held after the inner block: no error
            pass
    fd = os.open(run / io.LOCK_FILE, os.O_RDWR)
    try:
        import fcntl
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)      # released: anyone may take it
    finally:
        os.close(fd)


def test_two_training_runs_started_together_one_refused_one_consistent_run(tmp_path):
    """The issue's race: both passed the "folder holds a run" check; one died on progress.csv.tmp and
    the folder once held checkpoint/ of one seed and final/ of the other."""
    out = tmp_path / "X"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]))
    procs = {seed: subprocess.Popen([sys.executable, "-m", "hybridctl.cli", "train", "sac", "acrobot", "--steps",
                                     "4000", "--checkpoint-every", "800", "--seed", str(seed), *SAC_FLAGS,
                                     "--out", str(out)], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True)
             for seed in (1, 2)}
    results = {seed: (p.wait(120), *p.communicate()) for seed, p in procs.items()}
    codes = sorted(rc for rc, _, _ in results.values())
    assert codes == [0, 2], results
    winner = next(seed for seed, (rc, _, _) in results.items() if rc == 0)
    loser = 3 - winner
    assert f"is locked by pid {procs[winner].pid}" in results[loser][2], results[loser][2]
    assert "Traceback" not in results[loser][2]
    for name in ("final", "checkpoint"):                    # one run's checkpoints, one seed
        if (out / name).exists():
            assert json.loads((out / name / "config.json").read_text())["config"]["seed"] == winner
    final = json.loads((out / "final" / "progress.json").read_text())["env_steps"]
    with open(out / "progress.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert int(rows[-1]["env_steps"]) <= final and final >= 4000
    assert json.loads((out / "eval.json").read_text())["env_steps"] == final
    assert not list(out.glob("*.tmp*")) and not list(out.glob("*.bak-*"))


def test_training_commands_without_out_number_their_run_folders(tmp_path, monkeypatch, capsys):
    """Two training commands of the same settings without --out (the README's second command after its first)
    each get a run folder, as the RL Zoo numbers runs: runs/train/ars-Pendulum-v1-s0, then ...-s0-2; --resume
    without --out continues the newest."""
    from hybridctl.cli import main

    monkeypatch.chdir(tmp_path)
    base = Path("runs/train/ars-Pendulum-v1-s0")
    for _ in range(2):
        assert main(["train", "ars", "Pendulum-v1", "--epochs", "1", "--quiet", *ARS_FLAGS]) == 0
    assert (base / "final").is_dir() and (tmp_path / f"{base}-2" / "final").is_dir()
    assert f"wrote {base}-2/final" in capsys.readouterr().out
    assert main(["train", "ars", "Pendulum-v1", "--epochs", "2", "--resume", "--quiet", *ARS_FLAGS]) == 0
    assert json.loads((tmp_path / f"{base}-2" / "final" / "progress.json").read_text())["epoch"] == 2
    assert json.loads((base / "final" / "progress.json").read_text())["epoch"] == 1    # untouched
    assert not (tmp_path / f"{base}-3").exists()
