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


def contracting_plane_map(state, push):
    """A 2-D contraction with a push on x; fails outside the unit box."""
    x = np.array([0.8 * state[0] + push, 0.5 * state[1] + 0.3 * state[0]])
    return None if np.any(np.abs(x) > 1) else x
