"""A reachable mesh whose disturbance set is refined until its MFPT settles.

A mesh is only as good as its disturbance set: the thesis' 25 equal-probability quantiles of a
Gaussian reach +-2.05 std, so the tail slopes that make a rimless wheel fall are cut off and its
MFPT comes out 1.6x (sigma 0.06 rad) to 57x (sigma 2.5 degrees) too long, or infinite. A weighted
grid keeps the tails (:func:`~hybridctl.analysis.poincare.weighted_grid`); :func:`refined_mesh`
meshes with ``count`` grid points, then ``2 count - 1`` (the same range, halved spacing), ... until
the MFPT from the seeds changes by at most ``rtol`` from one mesh to the next, and records every
step.

>>> mesh, result, record = refined_mesh(RimlessWheel(), [[1.29]], GaussianDisturbance(0.15, 0.06), 1e-3)
>>> record["mfpt_from_seed"][-1], record["counts"], record["converged"]
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import Callable

import numpy as np

from ..limits import MAX_REFINED_DISTURBANCES, LimitError
from .markov import MFPTResult, NearlyNeverFailsError
from .reachable import FAILURE, ReachableMesh, _load_checkpoint, build_mesh, check_disturbances

DEFAULT_REFINE_RTOL = 0.01
"""Relative change of the MFPT from the seeds between two successive grids at which refinement stops
(1 %). On the rimless wheel (mean slope 0.15 rad, sigma 0.06) 25 -> 49 -> 97 -> 193 points change it by
4.3 %, 1.1 %, 0.3 %; the grid's own error is about the last change."""


MAX_SETTLED_SPACING_STD = 0.5
"""The coarsest grid spacing, in the disturbance's std, at which the MFPT may count as settled. Two coarse grids
can agree by chance: the passive compass gait (slope sigma 0.005 rad, box 0.1) moved 0.2 % from 5 to 9 points
(spacing 3 and 1.5 std) and stopped at 16.4 steps against Monte Carlo's 27.5 [24.9, 30.1]; at box 0.05 the grids
of 5, 9 and 17 points gave 16.4, 18.3 and 25.1 steps. The thesis-sized grid (25 points over +-6 std) is 0.5 std.
A heavy-tailed ``ScipyDisturbance`` over its default 1e-9 tails (Student t with 3 degrees of freedom: about
+-870 of its central std) needs more points than ``max_count`` allows: its refinement stops unsettled and says
so; a larger ``tail`` narrows its grid."""


def _spacing_std(level) -> float:
    """Largest gap between neighbouring points of ``level``'s finite set, in the distribution's std (its
    ``central_std``: half its central 68.3 %, so heavy tails have a finite one)."""
    values = np.sort(np.asarray(level.finite_set().values, dtype=np.float64).reshape(-1))
    scale = level.central_std
    return float(np.diff(values).max() / scale) if values.size >= 2 and scale > 0 else math.inf


def _relative_change(new: float, old: float) -> float:
    if math.isinf(new) and math.isinf(old):
        return 0.0
    if not (math.isfinite(new) and math.isfinite(old)):
        return math.inf
    return abs(new - old) / abs(new)


def _saved_count(path: Path | None) -> int | None:
    """Disturbances of the mesh checkpoint at ``path`` (None: there is none)."""
    if path is None or not path.exists():
        return None
    return int(_load_checkpoint(path)["n_disturbances"])


def refined_mesh(section_map, seeds, disturbance, box_size: float, rtol: float = DEFAULT_REFINE_RTOL,
                 max_count: int = MAX_REFINED_DISTURBANCES, method: str = "auto",
                 checkpoint: str | os.PathLike | None = None, resume: bool = False,
                 report: Callable[[str], None] | None = None,
                 **build_kwargs) -> tuple[ReachableMesh, MFPTResult | None, dict]:
    """Mesh ``section_map`` from ``seeds`` under ``disturbance``, refining its grid until the MFPT settles.

    ``disturbance``: a :class:`~hybridctl.analysis.GaussianDisturbance` or
    :class:`~hybridctl.analysis.ScipyDisturbance`; with ``rule="grid"`` its ``count`` is the first
    grid's, doubled (``2 count - 1``: every point kept, one added between each two) until the MFPT
    from the seeds changes by at most ``rtol`` relative on a grid whose points are at most
    :data:`MAX_SETTLED_SPACING_STD` std apart, or the next grid would pass ``max_count``
    (at most :data:`~hybridctl.limits.MAX_REFINED_DISTURBANCES`) or the memory that ``build_mesh``
    checks for ``max_states``. With ``rule="quantiles"`` (the thesis' set) one mesh, no refinement.
    A chain that almost never fails counts as MFPT infinity (two in a row: settled).

    ``checkpoint`` / ``resume``: the current grid's mesh checkpoint (:func:`build_mesh`); on resume
    the grids before it are meshed again (deterministic, and together about as costly as the last).
    ``report``: called with one line per grid meshed (its points, states, the MFPT from the seeds and its change
    from the grid before), so a long refinement says where it stands. Other keyword arguments go to
    :func:`build_mesh`.

    Returns the finest mesh, its :class:`MFPTResult` (None where the chain almost never fails or the
    mesh is incomplete) and the record: rule, counts, states, MFPT from the seeds per grid, the
    relative change reached, ``rtol``, ``converged`` and, when it stopped early, ``stopped``.
    """
    if not (isinstance(rtol, (int, float)) and math.isfinite(rtol) and rtol > 0):
        raise ValueError(f"rtol must be a finite number > 0, got {rtol!r}")
    if not (isinstance(max_count, (int, np.integer)) and max_count >= 1):
        raise ValueError(f"max_count must be an integer >= 1, got {max_count!r}")
    rule = getattr(disturbance, "rule", None)
    if rule not in ("grid", "quantiles"):
        raise ValueError(f"refined_mesh needs a GaussianDisturbance or ScipyDisturbance, got {type(disturbance).__name__}")
    max_count = min(int(max_count), MAX_REFINED_DISTURBANCES)
    path = Path(checkpoint) if checkpoint is not None else None
    record = {"rule": rule, **disturbance.describe(), "rtol": rtol if rule == "grid" else None,
              "counts": [], "states": [], "mfpt_from_seed": [], "relative_change": None, "converged": None}
    if rule == "grid":
        record.update(spacing_std=[], max_settled_spacing_std=MAX_SETTLED_SPACING_STD)
    count = int(disturbance.count)
    while True:
        level = dataclasses.replace(disturbance, count=count)
        saved = _saved_count(path) if resume else None
        level_checkpoint = None if saved is not None and saved > count else path   # keep a later grid's progress
        mesh = build_mesh(section_map, seeds, level, box_size, checkpoint=level_checkpoint,
                          resume=resume and saved == count, **build_kwargs)
        record["counts"].append(count)
        record["states"].append(mesh.size)
        record["count"] = count
        spacing = _spacing_std(level) if rule == "grid" else None
        if spacing is not None:
            record["spacing_std"].append(spacing)
        if not mesh.complete:
            record["stopped"] = "the mesh reached max_states"
            return mesh, None, record
        try:
            if not np.any(mesh.successors == FAILURE):
                raise NearlyNeverFailsError(f"no disturbance of the {count} in the set makes any mesh state fail: "
                                            f"the MFPT is infinite")
            result = mesh.mfpt(method=method)
            value = result.mean(mesh.seed_distribution())
        except NearlyNeverFailsError as exc:
            result, value = None, math.inf
            record["never_fails_note"] = str(exc)
        record["mfpt_from_seed"].append(value)
        change = _relative_change(value, record["mfpt_from_seed"][-2]) if len(record["mfpt_from_seed"]) >= 2 else None
        if report is not None:
            report(f"disturbance grid of {count} points" + ("" if spacing is None else f" ({spacing:.3g} std apart)")
                   + f": {mesh.size} states, MFPT from the seed {value:.6g} steps"
                   + ("" if change is None else f", {change:.2%} from the grid before (stops at {rtol:.2%}"
                      f" once the points are at most {MAX_SETTLED_SPACING_STD:g} std apart)"))
        if rule == "quantiles":
            return mesh, result, record
        if change is not None:
            record["relative_change"] = change
            if change <= rtol and spacing <= MAX_SETTLED_SPACING_STD:
                record["converged"] = True
                return mesh, result, record
        following = 2 * count - 1
        stop = None
        if following > max_count or following == count:
            stop = f"the next grid ({following} points) would pass max_count {max_count}"
        else:
            try:
                check_disturbances(following, build_kwargs.get("max_states", 1_000_000),
                                   build_kwargs.get("samples_per_box", 1), force=build_kwargs.get("force", False))
            except LimitError as exc:
                stop = f"the next grid ({following} points) is too large: {exc}"
        if stop is not None:
            record["converged"] = False
            record["stopped"] = stop
            return mesh, result, record
        count = following
