"""The split APG phase (APGConfig.backend): chunks of members in workers give the serial run's result."""

from __future__ import annotations

import time

import pytest
import torch

from hybridctl.learn.apg import family as family_mod
from hybridctl.learn.apg import split as split_mod
from hybridctl.learn.apg import APG, APGConfig
from hybridctl.parallel import SerialBackend

# The chunks' rollouts are bitwise those of the whole population here, but the observation
# sums behind the normalisation are added up in another order (chunk by chunk), so from the
# second epoch on the runs differ by float rounding (~1e-13 measured): compare with 1e-9.
TOL = dict(rtol=1e-9, atol=1e-9)
COUNTERS = ("epoch", "iterations", "env_steps", "nan_grads", "large_grads")


pytestmark = pytest.mark.usefixtures("one_torch_thread")   # tests/conftest.py


def tiny(method: str, **overrides) -> APGConfig:
    values = dict(population=4, elites=2, apg_iterations=2, horizon=10, epochs=2, batch=2, dtype="float64")
    return APGConfig.preset("reduced", method=method, **{**values, **overrides})


def trained(method: str, system: str = "cartpole", **overrides) -> APG:
    agent = APG(system, tiny(method, **overrides))
    start = time.perf_counter()
    agent.learn(progress=False)
    agent.seconds = time.perf_counter() - start
    return agent


def assert_same_run(split: APG, serial: APG) -> None:
    for name in ("mean", "std", "members", "best", "stats"):
        assert torch.allclose(getattr(split, name), getattr(serial, name), **TOL), name
    for name in ("m", "v"):
        assert torch.allclose(getattr(split.adam, name), getattr(serial.adam, name), **TOL), name
    assert torch.equal(split.adam.t, serial.adam.t)
    assert len(split.history) == len(serial.history) == serial.config.epochs
    for a, b in zip(split.history, serial.history):
        for column in ("mean_return", "best_return", "elite_score", "grad_norm", "sigma"):
            assert a[column] == pytest.approx(b[column], **{"rel": 1e-9, "abs": 1e-9}), column


@pytest.fixture(scope="module")
def pair():
    """(PAPG split over 2 spawned processes, serial) after 2 epochs; spawning dominates (~4 s). One method on
    the pool: the split is the same code for every method, and CE-APG's split runs on Ray below."""
    return trained("papg", backend="processes", workers=2), trained("papg")


# one xdist worker runs both tests, so the module fixture spawns its pool once, not once per worker
@pytest.mark.xdist_group("apg_pair")
def test_processes_give_the_serial_result(pair):
    split, serial = pair
    assert_same_run(split, serial)
    assert split._backend is None  # learn closed its pool
    print(f"{serial.config.method}: serial {serial.seconds:.2f} s, processes {split.seconds:.2f} s")


def assert_same_counts(split: APG, serial: APG) -> None:
    for name in COUNTERS:
        assert getattr(split, name) == getattr(serial, name), name
    for a, b in zip(split.history, serial.history):
        assert {c: a[c] for c in COUNTERS + ("physics_steps",)} == {c: b[c] for c in COUNTERS + ("physics_steps",)}


@pytest.mark.xdist_group("apg_pair")
def test_processes_count_as_the_serial_run(pair):
    split, serial = pair
    assert_same_counts(split, serial)
    assert serial.env_steps == 2 * 2 * 4 * 2 * 10  # epochs x iterations x K x N x T


class RecordingBackend(SerialBackend):
    """The serial backend with a worker count, recording the chunks and whether it was closed."""

    def __init__(self, workers: int):
        self.workers, self.chunks, self.closed = workers, [], False

    def map(self, fn, tasks):
        self.chunks.append([len(t["theta"]) for t in tasks])
        return super().map(fn, tasks)

    def close(self):
        self.closed = True


@pytest.fixture
def recording(monkeypatch):
    made = []

    def make(name, workers=None, address=None):
        made.append(RecordingBackend(workers or 3))
        return made[-1]

    monkeypatch.setattr(family_mod, "make_backend", make)
    return made


def test_uneven_chunks_in_member_order_short_horizon(recording):
    split = trained("shapg", "pendulum", population=5, short_horizon=4, backend="processes", workers=2)
    serial = trained("shapg", "pendulum", population=5, short_horizon=4)
    assert len(recording) == 1 and recording[0].chunks == [[3, 2], [3, 2]]  # one pool for both epochs
    assert recording[0].closed and split._backend is None
    assert_same_run(split, serial)
    for name in COUNTERS:
        assert getattr(split, name) == getattr(serial, name), name


def test_more_workers_than_members_and_apg_stays_here(recording):
    trained("papg", population=2, elites=1, epochs=1, backend="processes", workers=4)
    assert recording[0].chunks == [[1, 1]]
    trained("apg", epochs=1, backend="processes", workers=2)  # one member: nothing to split
    assert len(recording) == 1


def test_the_pool_closes_when_training_fails(recording, monkeypatch):
    def broken(task):
        raise FloatingPointError("NaN in a worker")

    monkeypatch.setattr(split_mod, "apg_chunk", broken)
    agent = APG("cartpole", tiny("ce-apg", backend="processes", workers=2))
    with pytest.raises(FloatingPointError, match="NaN in a worker"):
        agent.learn(progress=False)
    assert recording[0].closed and agent._backend is None


@pytest.mark.parametrize("field, value, message", [
    ("backend", "threads", r"APGConfig.backend must be one of \('serial', 'processes', 'ray'\), got 'threads'"),
    ("workers", 0, "APGConfig.workers must be None .* or an integer >= 1, got 0"),
    ("workers", 1.5, "APGConfig.workers must be an integer or None, got 1.5"),
    ("address", "auto", r"APGConfig.address \(--address\) applies to backend 'ray' only, not 'serial'"),
])
def test_bad_parallel_settings_name_the_field(field, value, message):
    with pytest.raises(ValueError, match=message):
        tiny("ce-apg", **{field: value})


@pytest.mark.xdist_group("ray")
def test_ray_gives_the_serial_result(local_ray):
    split, serial = trained("ce-apg", backend="ray", workers=2), trained("ce-apg")
    assert_same_run(split, serial)
    assert_same_counts(split, serial)
    assert serial.env_steps == 2 * 2 * 4 * 2 * 10


@pytest.mark.parametrize("flags, message", [
    (["--backend", "bogus"], "argument --backend: invalid choice: 'bogus'"),
    (["--workers", "0"], "argument --workers: must be > 0, got 0"),
    (["--address", "auto"], "APGConfig.address (--address) applies to backend 'ray' only, not 'serial'"),
])
def test_cli_flags_and_one_line_errors(capsys, tmp_path, flags, message):
    from hybridctl.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["train", "ce-apg", "cartpole", "--help"])
    assert stop.value.code == 0
    shown = capsys.readouterr().out
    assert all(flag in shown for flag in ("--backend {serial,processes,ray}", "--workers N|none", "--address"))
    try:
        code = main(["train", "ce-apg", "cartpole", *flags, "--epochs", "1", "--out", str(tmp_path / "run")])
    except SystemExit as stop:
        code = stop.code
    err = capsys.readouterr().err
    assert code == 2
    assert [line for line in err.splitlines() if "error" in line] == [next(l for l in err.splitlines() if message in l)]
    assert not (tmp_path / "run").exists()


def test_split_with_the_lqr_takeover(recording):
    split = trained("papg", population=3, takeover="lqr", backend="processes", workers=2)
    serial = trained("papg", population=3, takeover="lqr")
    assert recording[0].chunks == [[2, 1], [2, 1]]
    assert_same_run(split, serial)
