"""The training skeleton (hybridctl.learn.run): run log, declared checkpoints, resume, callbacks, guards."""

import json
import math

import numpy as np
import pytest
import torch

from hybridctl.learn import checkpoint as ckpt
from hybridctl.learn.base import Learner
from hybridctl.learn.callbacks import Callback, CallbackList, progress_bar
from hybridctl.learn.checkpoint import PROGRESS_FILE, Saved
from hybridctl.learn.run import EvalResult, check_finite, seeded, set_torch_threads
from hybridctl.learn.runlog import RunLog


class Counter(Learner):
    """A toy learner: theta += 1 per epoch, a linear module, an RNG, a bulky buffer."""

    algorithm_name = "COUNTER"
    budget_field, unit = "epochs", "epoch"
    log_key = "epoch"
    log_columns = ("epoch", "value")
    saved = (Saved("theta", "theta", "array"), Saved("net", "net", "state"), Saved("gen", "gen", "rng"),
             Saved("nested.scale", "scale", "param"), Saved("maybe", "maybe", "state", optional=True),
             Saved("epoch", "epoch", file=PROGRESS_FILE, load=int),
             Saved("seen", "seen", file=PROGRESS_FILE, optional=True, save=list, load=tuple),
             Saved("data", "data", "tensor", file="data.pt", bulky=True))

    def __init__(self, seed=0):
        import dataclasses

        @dataclasses.dataclass
        class Config:
            seed: int = 0
            epochs: int = 1
            torch_threads: int = 1

        self.config = Config(seed)
        with seeded(seed):
            self.net = torch.nn.Linear(2, 1)
        self.gen = torch.Generator().manual_seed(seed)
        self.theta, self.epoch, self.seen, self.maybe = np.zeros(3), 0, (), None
        self.scale = torch.ones(2, requires_grad=True)
        self.data = torch.zeros(0)
        self.log_rows = []
        self.restored_from = None

    @property
    def progress_count(self):
        return self.epoch

    def after_restore(self, found, meta, bulky):
        self.restored_from = (found.name, bulky)

    def system_record(self):
        return {"name": "toy"}

    def learn(self, total=None, **kwargs):
        return super().learn(total, **{"progress": False, **kwargs})

    def train(self, run, epochs, backend):
        while self.epoch < epochs and not run.stopped:
            self.epoch += 1
            self.theta = self.theta + 1
            self.seen = (*self.seen, float(torch.rand(1, generator=self.gen)))
            self.data = torch.cat([self.data, torch.tensor([float(self.epoch)])])
            run.log({"epoch": self.epoch, "value": float(self.theta[0])})
            run.advance(1)
            run.after_update()
            if self.epoch % 2 == 0:
                run.checkpoint()


def csv_epochs(path):
    import csv
    with open(path, newline="") as fh:
        return [int(r["epoch"]) for r in csv.DictReader(fh)]


# ------------------------------------------------------------------ checkpoints from the declared state
def test_declared_state_round_trips_with_nested_keys_and_bulky_files(tmp_path):
    a = Counter(seed=1).learn(3)
    a.save(tmp_path / "light")
    a.save(tmp_path / "full", include_replay=True)
    assert not (tmp_path / "light" / "data.pt").exists() and (tmp_path / "full" / "data.pt").is_file()
    model = torch.load(tmp_path / "full" / "model.pt", weights_only=True)
    assert set(model) == {"format", "theta", "net", "gen", "nested"} and "maybe" not in model   # None: skipped
    assert torch.equal(model["nested"]["scale"], a.scale.detach())
    progress = json.loads((tmp_path / "full" / "progress.json").read_text())
    assert progress["epoch"] == 3 and len(progress["seen"]) == 3
    meta = json.loads((tmp_path / "full" / "config.json").read_text())
    assert meta["algorithm"] == "COUNTER" and {"torch", "numpy"} <= set(meta["versions"])

    b = Counter(seed=2)
    scale_before = b.scale
    b.checkpointer.restore(tmp_path / "full", bulky=True)
    assert b.epoch == 3 and np.array_equal(b.theta, a.theta) and b.seen == a.seen and torch.equal(b.data, a.data)
    assert b.scale is scale_before                     # "param" entries are restored in place
    assert torch.equal(b.net.weight, a.net.weight)
    assert torch.equal(b.gen.get_state(), a.gen.get_state())
    assert b.restored_from == ("full", True)
    c = Counter(seed=2)
    c.checkpointer.restore(tmp_path / "full")         # without bulky: the data stays as it was
    assert c.data.numel() == 0 and c.restored_from == ("full", False)


def test_restore_names_missing_entries_and_foreign_algorithms(tmp_path):
    Counter().save(tmp_path / "ck")
    model = torch.load(tmp_path / "ck" / "model.pt", weights_only=True)
    del model["theta"]
    torch.save(model, tmp_path / "ck" / "model.pt")
    with pytest.raises(ckpt.CheckpointError, match="lacks 'theta'"):
        Counter().checkpointer.restore(tmp_path / "ck")
    Counter().save(tmp_path / "other")
    meta = json.loads((tmp_path / "other" / "config.json").read_text())
    ckpt.write_json(tmp_path / "other" / "config.json", {**meta, "algorithm": "SAC"})
    with pytest.raises(ckpt.CheckpointError, match="written by SAC, not COUNTER"):
        Counter().checkpointer.restore(tmp_path / "other")


def test_config_json_is_written_once_per_checkpoint(tmp_path, monkeypatch):
    from hybridctl.learn import run as run_module
    writes = []
    original = run_module.ckpt.write_json
    monkeypatch.setattr(run_module.ckpt, "write_json", lambda path, data: (writes.append(path.name), original(path, data)))
    Counter().save(tmp_path / "ck")
    assert writes.count("config.json") == 1 and writes.count("progress.json") == 1


def test_a_failed_write_leaves_the_old_checkpoint(tmp_path):
    good = Counter().learn(2)
    good.save(tmp_path / "ck")

    class Broken(Counter):
        def normalization(self):
            raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        Broken().learn(4).save(tmp_path / "ck")
    assert json.loads((tmp_path / "ck" / "progress.json").read_text())["epoch"] == 2


# ------------------------------------------------------------------ the run: log, resume, final checkpoint
def test_run_log_is_fresh_truncated_on_resume_and_keyed(tmp_path):
    Counter().learn(5, out=tmp_path)
    assert csv_epochs(tmp_path / "progress.csv") == [1, 2, 3, 4, 5]
    assert json.loads((tmp_path / "checkpoint" / "progress.json").read_text())["epoch"] == 4
    assert json.loads((tmp_path / "final" / "progress.json").read_text())["epoch"] == 5
    # resume: the newest checkpoint (final, epoch 5), rows up to it kept
    resumed = Counter().learn(7, out=tmp_path, resume=True)
    assert resumed.restored_from == ("final", True) and resumed.epoch == 7
    assert csv_epochs(tmp_path / "progress.csv") == [1, 2, 3, 4, 5, 6, 7]
    straight = Counter().learn(7)
    assert resumed.seen == straight.seen and torch.equal(resumed.data, straight.data)   # RNG and data restored
    # a fresh learner in the same folder starts a fresh log
    Counter().learn(1, out=tmp_path)
    assert csv_epochs(tmp_path / "progress.csv") == [1]
    # a loaded learner continuing without resume keeps the rows up to its counter
    Counter().learn(3, out=tmp_path / "b")           # checkpoint at epoch 2, final at 3
    at2 = Counter()
    at2.checkpointer.restore(tmp_path / "b" / "checkpoint")
    assert at2.epoch == 2
    at2.learn(3, out=tmp_path / "b")
    assert csv_epochs(tmp_path / "b" / "progress.csv") == [1, 2, 3]


def test_a_log_without_the_key_column_is_refused(tmp_path):
    (tmp_path / "progress.csv").write_text("a,b\n1,2\n")
    learner = Counter().learn(1)
    with pytest.raises(ValueError, match="no 'epoch' column"):
        learner.learn(2, out=tmp_path)
    with pytest.raises(ValueError, match="no 'epoch' column"):
        RunLog(tmp_path, ("epoch",), "epoch", upto=1)
    RunLog(tmp_path, ("epoch",), "epoch", upto=0).close()   # a fresh run replaces it
    assert (tmp_path / "progress.csv").read_text().splitlines() == ["epoch"]


def test_resume_without_a_checkpoint_warns_and_needs_a_log_dir(tmp_path):
    with pytest.warns(UserWarning, match="no checkpoint"):
        Counter().learn(1, out=tmp_path, resume=True)
    with pytest.raises(ValueError, match="needs out="):
        Counter().learn(1, resume=True)


def test_an_error_in_the_loop_writes_no_final_checkpoint(tmp_path):
    def fail_at_3(learner):
        if learner.epoch == 3:
            raise FloatingPointError("boom")

    with pytest.raises(FloatingPointError):
        Counter().learn(6, out=tmp_path, callback=fail_at_3)
    assert not (tmp_path / "final").exists()
    assert json.loads((tmp_path / "checkpoint" / "progress.json").read_text())["epoch"] == 2


def test_threads_are_set_for_the_run_and_restored(tmp_path):
    previous = set_torch_threads(2)
    seen = []
    Counter().learn(1, callback=lambda learner: seen.append(torch.get_num_threads()))
    assert seen == [1] and torch.get_num_threads() == 2
    set_torch_threads(previous)


# ------------------------------------------------------------------ callbacks, guards, results
def test_callbacks_are_objects_and_any_false_stops():
    class Log(Callback):
        def __init__(self):
            self.events = []

        def on_training_start(self, learner):
            self.events.append("start")

        def on_update(self, learner):
            self.events.append(learner.epoch)

        def on_training_end(self, learner):
            self.events.append("end")

    log = Log()
    learner = Counter().learn(10, callback=[log, lambda learner: learner.epoch < 3])
    assert learner.epoch == 3 and log.events == ["start", 1, 2, 3, "end"]
    assert CallbackList.of(None).on_update(learner) is None


def test_check_finite_names_the_value_and_when():
    check_finite("loss", torch.tensor(1.0), "at step 1")
    check_finite("params", [torch.ones(3), torch.zeros(2)], "now")
    with pytest.raises(FloatingPointError, match=r"loss became nan at step 7; training stopped"):
        check_finite("loss", torch.tensor(math.nan), "at step 7")
    with pytest.raises(FloatingPointError, match="theta became non-finite"):
        check_finite("theta", np.array([0.0, math.inf]), "at epoch 2")
    with pytest.raises(FloatingPointError, match="params"):
        check_finite("params", [torch.ones(2), torch.tensor([math.nan])], "now")


def test_eval_result_is_a_dict_with_typed_fields():
    result = EvalResult.from_returns([1.0, 3.0], success_rate=0.5, first={"episodes": 2, "seed": 7})
    assert (result.mean_return, result.std_return, result.min_return, result.success_rate) == (2.0, 1.0, 1.0, 0.5)
    assert list(result)[:2] == ["episodes", "seed"] and result["returns"] == [1.0, 3.0]
    result.update({"command": "x"})
    assert json.loads(json.dumps(result))["command"] == "x" and result.to_dict()["mean_return"] == 2.0
    empty = EvalResult.from_returns([])
    assert empty.mean_return is None and empty.success_rate is None and empty.episodes == 0
    with pytest.raises(ValueError, match="mean_return"):
        EvalResult({"episodes": 1})


def test_seeded_leaves_the_global_rng_alone():
    state = torch.random.get_rng_state()
    with seeded(3):
        a = torch.rand(2)
    with seeded(3):
        b = torch.rand(2)
    assert torch.equal(a, b) and torch.equal(state, torch.random.get_rng_state())


def test_progress_bar_off_has_the_same_methods():
    bar = progress_bar(False, 10)
    bar.update(3)
    bar.set_postfix({"a": 1}, refresh=False)
    bar.close()


def test_training_curves_from_rows_or_a_progress_csv(tmp_path):
    from hybridctl.viz.training import plot_training_curves, read_progress_rows
    log = RunLog(tmp_path, ("env_steps", "mean_return", "q_loss", "pi_loss", "alpha", "success_rate"), "env_steps", 0)
    for step in (100, 200, 300):
        log.write({"env_steps": step, "mean_return": step / 10, "q_loss": 1.0, "pi_loss": -1.0, "alpha": 0.05})
    log.close()
    rows = read_progress_rows(tmp_path / "progress.csv")
    assert [r["env_steps"] for r in rows] == [100, 200, 300] and math.isnan(rows[0]["success_rate"])
    assert plot_training_curves(tmp_path / "progress.csv", tmp_path / "a.png").stat().st_size > 1000
    assert plot_training_curves(rows, tmp_path / "b.png", title="t").is_file()
    assert plot_training_curves([], tmp_path / "c.png") is None and not (tmp_path / "c.png").exists()
