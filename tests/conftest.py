"""Shared test setup: deterministic torch and a small thread count (CI has 2 cores)."""

import os
import tempfile

import numpy as np
import pytest
import torch

os.environ.setdefault("MPLBACKEND", "Agg")
# SB3's default logger makes an empty SB3-<date> folder per learn call where SB3_LOGDIR does not name one
os.environ.setdefault("SB3_LOGDIR", os.path.join(tempfile.gettempdir(), "hybridctl-tests-sb3-log"))
torch.set_num_threads(1)


@pytest.fixture
def rng():
    """A seeded numpy generator."""
    return np.random.default_rng(12345)


@pytest.fixture
def one_torch_thread():
    """One torch thread for the test (as the learners' records were made), restored afterwards."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture
def cli_error(capsys):
    """Run ``hybridctl ARGV`` in-process and return its stderr, asserting the bad-input contract:
    exit code 2 and no traceback. Use: ``assert "--duration" in cli_error([...])``."""
    from hybridctl.cli import main

    def run(argv):
        with pytest.raises(SystemExit) as stop:
            main([str(a) for a in argv])
        err = capsys.readouterr().err
        assert stop.value.code == 2, err
        assert "Traceback" not in err, err
        return err
    return run


# `make test` sets HYBRIDCTL_REQUIRE_EXTRAS to the extras it installed: a missing one is then an error at the
# start of the session, so the tests of its paths cannot quietly skip in CI (a skipped test proves nothing).
EXTRA_MODULES = {
    "test": ("pytest_timeout", "xdist", "nbclient", "nbformat", "ipykernel"),
    "sb3": ("stable_baselines3", "sb3_contrib"),
    "mujoco": ("mujoco", "mujoco.batch"),
    "ray": ("ray",),
    "docs": ("mkdocs", "mkdocstrings", "mkdocs_jupyter", "material"),
}


def pytest_sessionstart(session):
    """Refuse to run when an extra that ``make test`` installed cannot be imported."""
    import importlib

    required = [name for name in os.environ.get("HYBRIDCTL_REQUIRE_EXTRAS", "").split(",") if name]
    unknown = sorted(set(required) - set(EXTRA_MODULES))
    if unknown:
        raise pytest.UsageError(f"HYBRIDCTL_REQUIRE_EXTRAS names unknown extras {unknown}; known: {sorted(EXTRA_MODULES)}")
    missing = []
    for extra in required:
        for module in EXTRA_MODULES[extra]:
            try:
                importlib.import_module(module)
            except ImportError as exc:
                missing.append(f"{module} (extra '{extra}': {exc})")
    if missing:
        raise pytest.UsageError("HYBRIDCTL_REQUIRE_EXTRAS: not importable, so their tests would skip: "
                                + "; ".join(missing))


@pytest.fixture(scope="session")
def local_ray():
    """One real local Ray instance (2 CPUs, bound to 127.0.0.1, no dashboard) for the whole test session.

    Tests that use it carry ``@pytest.mark.xdist_group("ray")`` so that ``make test`` (``--dist loadgroup``)
    runs them on one process, which starts the instance once. hybridctl's Ray backend joins a running
    instance (it passes no ``num_cpus``) and leaves it running. Skipped when Ray is not installed, which
    ``make test`` turns into an error (HYBRIDCTL_REQUIRE_EXTRAS)."""
    ray = pytest.importorskip("ray")
    import sys

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")     # nothing leaves the machine
    started = not ray.is_initialized()
    if started:
        # the workers import hybridctl and these test modules as this process does
        env = {"env_vars": {"PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}}
        ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False,
                 _node_ip_address="127.0.0.1", runtime_env=env)   # a new instance, never a head running here
    yield ray
    if started:
        ray.shutdown()
