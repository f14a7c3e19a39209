"""Shared test setup: deterministic torch and a small thread count (CI has 2 cores)."""

import os

import numpy as np
import pytest
import torch

os.environ.setdefault("MPLBACKEND", "Agg")
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
