"""Angles as the plots draw them, without matplotlib: what the Drake simulation summary needs too (importing
``hybridctl.viz.plots`` loads pyplot, 0.45 s of every ``hybridctl.experiments`` import before this split)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..systems.control import wrap_angles

if TYPE_CHECKING:
    from ..systems import System

__all__ = ["wrap_about_goal"]


def wrap_about_goal(states, system: "System") -> np.ndarray:
    """States with each angle coordinate wrapped into [goal - pi, goal + pi) (a new array).

    The angle coordinates are ``system.angle_indices`` (the spec's ``state.angles``); rates
    and linear coordinates are returned unchanged. An elbow that made full turns on the way up
    (``th2`` ending at ``4 pi``) is drawn at the goal, where it is.
    """
    states = np.array(states, dtype=float)
    goal = np.asarray(system.goal, dtype=float)
    return goal + wrap_angles(states - goal, system.angle_indices)
