"""The torch balance-map engine on a device and on every backend (issue 32).

On this CPU-only machine ``device="cpu"`` inside :func:`device_trap` stands in for a GPU: a tensor the
engine made without naming its device would be a meta tensor and fail the run, and :class:`HostSyncs`
counts the copies to the host, which must not grow with the number of decisions.
"""

import json

import numpy as np
import pytest
import torch

pytest.importorskip("pydrake")

from device_trap import HostSyncs, device_trap  # noqa: E402
from hybridctl import systems  # noqa: E402
from hybridctl.experiments.balance_map import balance_map, check_balance_map, torch_rollouts  # noqa: E402
from hybridctl.limits import LimitError, cpu_count  # noqa: E402

PAPG = "papg:models/policies/papg-cartpole"    # a loaded recurrent policy, float32, with the cost-to-go gate


@pytest.fixture(autouse=True)
def one_thread():
    torch.set_num_threads(1)


def same_map(a, b):
    """Equal verdicts, returns and divergences, cell for cell."""
    np.testing.assert_array_equal(a.balanced, b.balanced)
    np.testing.assert_array_equal(a.returns, b.returns)
    np.testing.assert_array_equal(a.diverged, b.diverged)


@pytest.mark.parametrize("name, controller, grid, duration", [
    ("pendulum", "energy", 3, None),          # energy swing-up + the spec's cost-to-go gate (a buffer S) + LQR
    ("cartpole", "lqr", 2, 1.0),              # the constant "always" gate
    ("acrobot", "swingup", 2, 1.0),           # the constant "never" gate
    ("cartpole", PAPG, 2, 1.0),               # a checkpoint's GRU, loaded on the CPU and moved to the device
])
def test_torch_engine_keeps_every_tensor_on_its_device(name, controller, grid, duration):
    """Inside the trap every tensor of the rollouts names the device: the map is the one made outside it."""
    expected = balance_map(name, controller, grid=grid, duration=duration, engine="torch", progress=False)
    with device_trap():
        bmap = balance_map(name, controller, grid=grid, duration=duration, engine="torch", device="cpu",
                           progress=False)
    same_map(bmap, expected)
    assert bmap.meta["device"] == "cpu" and bmap.meta["backend"] == "serial" and bmap.meta["chunks"] == 1


@pytest.mark.parametrize("name, controller", [("acrobot", "energy"), ("cartpole", PAPG)])
def test_torch_rollouts_copy_to_the_host_a_fixed_number_of_times(name, controller):
    """Twice the decisions, the same host copies: none inside the loop (the env's step made three each)."""
    system = systems.load(name)
    starts = np.repeat(system.nudged_nominal_state()[None], 4, axis=0)
    counts = {}
    for duration in (1.0, 2.0):
        with device_trap(), HostSyncs() as syncs:
            runs = torch_rollouts(system, controller, starts, duration, device="cpu")
        counts[duration] = syncs.count
        assert runs["states"].shape[1] == round(duration / (runs["times"][1] - runs["times"][0])) + 1
    assert counts[1.0] == counts[2.0], counts


@pytest.mark.xdist_group("ray")
def test_torch_engine_is_the_same_map_on_every_backend(local_ray):
    """Serial (one batch), local processes and Ray (one chunk per worker, 9 starts as 5 + 4): cell for cell."""
    kwargs = dict(grid=3, engine="torch", progress=False, device="cpu")
    maps = {backend: balance_map("pendulum", "energy", backend=backend, workers=2, **kwargs)
            for backend in ("serial", "processes", "ray")}
    assert 0 < maps["serial"].balanced.sum() < 9           # the map has both verdicts
    for backend, bmap in maps.items():
        assert bmap.meta["engine"] == "torch" and bmap.meta["backend"] == backend
        same_map(bmap, maps["serial"])
    assert maps["serial"].meta["chunks"] == 1
    assert maps["processes"].meta["chunks"] == maps["ray"].meta["chunks"] == 2
    same_map(maps["serial"], balance_map("pendulum", "energy", **kwargs))     # the default: serial


def test_torch_engine_checks_workers_and_devices():
    """Local workers above the cores are refused for the torch engine too; a device for drake, a bad name
    and a CUDA device this machine lacks are refused before any work."""
    system = systems.load("pendulum")
    with pytest.raises(LimitError, match="--workers"):
        check_balance_map(system, 3, None, "torch", workers=cpu_count() + 1)
    with pytest.raises(ValueError, match="applies to --engine torch only"):
        balance_map("pendulum", grid=2, device="cpu", progress=False)
    with pytest.raises(ValueError, match="must be a torch device hybridctl runs on"):
        balance_map("pendulum", grid=2, engine="torch", device="gpu0", progress=False)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available"):
            balance_map("pendulum", grid=2, engine="torch", device="cuda:0", progress=False)


def test_cli_device_flag(tmp_path, capsys):
    """``--device`` runs the torch engine there; with the drake engine it is a one-line error, no traceback."""
    from hybridctl.cli import main

    out = tmp_path / "map"
    assert main(["balance-map", "pendulum", "--grid", "3", "--engine", "torch", "--device", "cpu", "--quiet",
                 "--out", str(out)]) == 0
    summary = json.loads((out / "balance_map.json").read_text())
    assert summary["device"] == "cpu" and summary["backend"] == "serial"
    capsys.readouterr()
    with pytest.raises(SystemExit) as stop:      # cli_errors' CommandError: exit code 2
        main(["balance-map", "pendulum", "--grid", "3", "--device", "cpu", "--quiet", "--out", str(tmp_path / "drake")])
    assert stop.value.code != 0
    err = capsys.readouterr()
    text = err.out + err.err
    assert "--device cpu applies to --engine torch only" in text and "Traceback" not in text
    assert len(text.strip().splitlines()) == 1 and not (tmp_path / "drake").exists()


def test_cli_ray_task_flags_reach_the_balance_map(tmp_path, monkeypatch):
    """``--task-cpus`` (and the other Ray task flags of the shared backend flags) are in force while the map
    runs (``parallel.ray_options``), so every Ray task of the map asks for them; before, they were checked
    and then ignored."""
    import importlib

    from hybridctl import parallel
    from hybridctl.cli import main

    cli = importlib.import_module("hybridctl.cli.balance_map")
    real, seen = cli.balance_map, {}

    def spy(*args, **kwargs):
        seen.update(parallel._RAY_OPTIONS.get())
        return real(*args, **{**kwargs, "backend": "serial", "address": None})   # no Ray instance needed

    monkeypatch.setattr(cli, "balance_map", spy)
    assert main(["balance-map", "pendulum", "--grid", "2", "--engine", "torch", "--backend", "ray", "--task-cpus",
                 "1", "--quiet", "--out", str(tmp_path / "map")]) == 0
    assert seen == {"task_resources": {"num_cpus": 1.0}}
