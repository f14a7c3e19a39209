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
