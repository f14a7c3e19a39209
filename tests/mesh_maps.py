"""Picklable functions for tests that run in spawned workers (numpy only, so workers start fast)."""

import os
from pathlib import Path

import numpy as np


def walk_map(state, step):
    """Integer walk on 1..5: +-1 per step, reflecting at 5, failure at 0."""
    x = min(state[0] + step, 5.0)
    return None if x <= 0 else np.array([x])


def exploding_map(state, step):
    """Raises at state 3 (a broken simulator)."""
    if state[0] == 3.0:
        raise FloatingPointError("simulator blew up")
    return walk_map(state, step)


def contracting_plane_map(state, push):
    """A 2-D contraction with a push on x; fails outside the unit box."""
    x = np.array([0.8 * state[0] + push, 0.5 * state[1] + 0.3 * state[0]])
    return None if np.any(np.abs(x) > 1) else x


def die_once(marker: str) -> int:
    """Kill this worker the first time (a crashed simulator); succeed afterwards."""
    if not Path(marker).exists():
        Path(marker).write_text("died")
        os._exit(1)
    return 7
