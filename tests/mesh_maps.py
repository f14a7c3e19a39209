"""Picklable section maps for the reachable-mesh tests (importable by spawned workers)."""

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
