"""The reachable-state mesh report of a rimless wheel on rough terrain (thesis Ch. 5; what
``hybridctl mesh`` does): mesh, transition matrix, mean first passage time, Monte Carlo check,
mesh sizes and the figures.

>>> from hybridctl.experiments import mesh_report
>>> report = mesh_report("rimless-wheel", "runs/mesh", box_size=0.01, monte_carlo=500)
>>> report["mfpt"]["from_seed"]
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Sequence

import scipy.sparse as sp

from .. import io, viz
from ..analysis import (DEFAULT_REFINE_RTOL, GaussianDisturbance, RimlessWheel, mesh_sizes, monte_carlo_mfpt,
                        reachable_dimension, refined_mesh, shared_backend)
from ..limits import MAX_REFINED_DISTURBANCES
from ..drake import DrakeCompassGaitMap, DrakeRimlessWheelMap
from .training import MESH_MARKERS, open_run_folder

MESH_MAPS = {"rimless-wheel": "analytic rimless wheel on rough terrain (Byl & Tedrake 2009)",
             "drake-rimless-wheel": "Drake's RimlessWheel, apex found by a witness function",
             "compass-gait": "Drake's passive CompassGait, mid-stance to mid-stance, guarded steps"}
"""The section maps :func:`mesh_report` knows, by name."""

MESH_DEFAULTS = {"rimless-wheel": {"slope_mean": 0.15, "slope_std": 0.06, "box_size": 1e-3, "disturbances": 25},
                 "drake-rimless-wheel": {"slope_mean": 0.15, "slope_std": 0.06, "box_size": 1e-3, "disturbances": 25},
                 "compass-gait": {"slope_mean": 0.0525, "slope_std": 0.005, "box_size": 0.1, "disturbances": 5}}
"""Per map: the mean slope and slope std (rad), the box side and the first slope grid's points that ``mesh``
uses when not given (the compass gait's: Drake's default slope, and a mesh of 393 states whose slope grid
settles at 9 points, built in 72 s by ``--backend processes --workers 2`` on a loaded 2-core machine; each
step is a Drake simulation of ~15 ms. A box of 0.15 is too coarse: its MFPT jumps and the grid refines
past 33 points)."""


def section_map_by_name(name: str, **options):
    """The Poincare section map called ``name`` (a key of ``MESH_MAPS``); ``options`` go to the
    compass gait (:class:`~hybridctl.drake.DrakeCompassGaitMap`: parameters, ``hip_pd``)."""
    if name == "compass-gait":
        return DrakeCompassGaitMap(**options)
    if options:
        raise ValueError(f"map {name!r} takes no options, got {', '.join(sorted(options))}")
    if name == "rimless-wheel":
        return RimlessWheel()
    if name == "drake-rimless-wheel":
        return DrakeRimlessWheelMap()
    raise ValueError(f"unknown map {name!r}; known: {', '.join(sorted(MESH_MAPS))}")


def mesh_seed(section_map, slope_mean: float) -> list[float]:
    """The seed state of a mesh: the map's gait on the constant slope ``slope_mean`` (ValueError: none)."""
    if isinstance(section_map, DrakeCompassGaitMap):
        try:
            return [float(v) for v in section_map.gait(slope_mean)]
        except ValueError as err:
            raise ValueError(f"--slope-mean {slope_mean} has no compass gait to seed the mesh from ({err})") from None
    seed = RimlessWheel().fixed_point(slope_mean)
    if not math.isfinite(seed):
        raise ValueError(f"--slope-mean {slope_mean} has no rolling gait to seed the mesh from")
    return [seed]


def guard_record(section_map) -> dict | None:
    """A guarded Drake map's guard trips (in this process) for the report, or None for other maps."""
    trips = getattr(section_map, "guard_trips", None)
    if trips is None:
        return None
    return {"trips": dict(trips), "note": "steps stopped by a guard count as falls; counted in this process only "
                                          "(steps in worker processes are not included)"}


def mesh_report(map_name: str = "rimless-wheel", out: str | Path = "runs/mesh", box_size: float | None = None,
                slope_mean: float | None = None, slope_std: float | None = None, disturbances: int | None = None,
                max_states: int = 1_000_000, monte_carlo: int = 0, sizes: Sequence[float] | None = None,
                backend: str = "serial", workers: int | None = None, resume: bool = False,
                progress: bool = True, command: str | None = None, overwrite: bool = False,
                checkpoint_every: int = 20, checkpoint_minutes: float = 5.0, address: str | None = None,
                monte_carlo_chunks: int = 1, disturbance_rule: str = "grid", refine_rtol: float = DEFAULT_REFINE_RTOL,
                max_disturbances: int = MAX_REFINED_DISTURBANCES, tails: float = 6.0,
                map_options: dict | None = None) -> dict:
    """Mesh the states a map reaches from its rolling gait under Gaussian slopes; write the report.

    Seeds the mesh with the map's gait at ``slope_mean`` (:func:`mesh_seed`); ``box_size``,
    ``slope_mean``, ``slope_std``, ``disturbances`` default to the map's :data:`MESH_DEFAULTS`; ``map_options`` go to
    :func:`section_map_by_name`. The slopes: with
    ``disturbance_rule="grid"`` (default) a weighted grid of ``disturbances`` points over
    ``slope_mean`` +- ``tails`` std, doubled (:func:`~hybridctl.analysis.refined_mesh`) until the MFPT
    from the seed changes by at most ``refine_rtol`` (or the grid would pass ``max_disturbances``),
    the steps recorded under ``disturbance.refinement``; with ``"quantiles"``, the thesis'
    ``disturbances`` equal-probability quantiles (25: +-2.05 std, the tails cut off). Writes into ``out``: ``mfpt.json`` (the returned report),
    and for a complete mesh ``transition_matrix.npz``, ``mesh.npz`` (``ReachableMesh.load``) and
    ``sparsity.png``, ``cumulative_mass.png``, ``states.png`` (plus ``mesh_sizes.png`` with
    ``sizes``). ``out/mesh_checkpoint.npz`` lets ``resume`` continue an interrupted mesh.

    Args:
        monte_carlo: episodes of a Monte Carlo MFPT estimate on the true map (0: none), with
            continuous slopes and with the mesh's slope set.
        monte_carlo_chunks: groups the Monte Carlo episodes are split into, each a task on
            ``backend`` with its own random stream: the estimate depends on it (not on the backend),
            so it is a setting of its own; at least the worker count fills the workers (default 1).
        disturbances: points of the first grid (``"grid"``) or the quantiles (``"quantiles"``; 25 is
            the thesis' set).
        disturbance_rule, refine_rtol, max_disturbances, tails: the slope set's rule, the relative
            change of the MFPT from the seed at which its refinement stops (1 %), the most grid points
            it may reach, and the grid's half-width in std (6).
        sizes: further box sizes to mesh at (thesis Table 5.1); two complete ones give
            ``reachable_dimension``.
        resume: continue the mesh from ``out/mesh_checkpoint.npz``.
        overwrite: replace the run ``out`` holds. Without it (or ``resume``) a folder that
            already holds a run (``mesh.npz``, ``mfpt.json``, a mesh checkpoint, a training
            run) raises :class:`~hybridctl.experiments.RunFolderError`, as does a folder that
            another run holds locked (naming its pid).
        checkpoint_every, checkpoint_minutes: the mesh checkpoint's cadence in batches and in
            minutes of wall time (at least every 5 minutes by default; 0: by batches only).
        backend, workers, address: where the mesh's batches, the Monte Carlo chunks and the meshes of
            ``sizes`` run
            (:func:`hybridctl.parallel.make_backend`; ``address``: a Ray cluster, default ``RAY_ADDRESS``).

    Returns:
        The report: ``mesh``, ``mfpt`` (with ``from_seed``), ``monte_carlo``, ``mesh_sizes``,
        ``reachable_dimension``; for a mesh cut off at ``max_states``, ``error`` instead of results.

    Raises:
        ValueError: an unknown map, a bad disturbance, or no rolling gait at ``slope_mean``.
    """
    section_map = section_map_by_name(map_name, **(map_options or {}))
    defaults = MESH_DEFAULTS[map_name]
    box_size = defaults["box_size"] if box_size is None else box_size
    slope_mean = defaults["slope_mean"] if slope_mean is None else slope_mean
    slope_std = defaults["slope_std"] if slope_std is None else slope_std
    disturbances = defaults["disturbances"] if disturbances is None else disturbances
    slopes = GaussianDisturbance(slope_mean, slope_std, disturbances, rule=disturbance_rule, tails=tails)
    refine = {"rtol": refine_rtol, "max_count": max_disturbances}
    seed = mesh_seed(section_map, slope_mean)
    with open_run_folder(out, resume, overwrite, markers=MESH_MARKERS) as folder:
        folder.clear()   # --overwrite: the mesh reads no input files
        with shared_backend(backend, workers, address):   # every stage's meshes and chunks on the same workers
            return _mesh_report_in(folder.path, map_name, section_map, slopes, seed, box_size, slope_mean, slope_std,
                                   disturbances, max_states, monte_carlo, sizes, backend, workers, resume,
                                   progress, command, checkpoint_every, checkpoint_minutes, address,
                                   monte_carlo_chunks, refine)


def printed(prefix: str = ""):
    """A ``report`` (of :func:`~hybridctl.analysis.refined_mesh`) that prints each line after ``prefix``, at once."""
    return lambda line: print(prefix + line, flush=True)


def _mesh_report_in(out: Path, map_name: str, section_map, slopes, seed: list[float], box_size: float, slope_mean: float,
                    slope_std: float, disturbances: int, max_states: int, monte_carlo: int,
                    sizes: Sequence[float] | None, backend: str, workers: int | None, resume: bool, progress: bool,
                    command: str | None, checkpoint_every: int, checkpoint_minutes: float,
                    address: str | None = None, monte_carlo_chunks: int = 1, refine: dict | None = None) -> dict:
    """The body of :func:`mesh_report` in its locked run folder ``out``."""
    mesh, result, refinement = refined_mesh(
        section_map, [seed], slopes, box_size, **(refine or {}), max_states=max_states, backend=backend,
        workers=workers, address=address, checkpoint=out / "mesh_checkpoint.npz", resume=resume, progress=progress,
        checkpoint_every=checkpoint_every, checkpoint_minutes=checkpoint_minutes,
        report=printed() if progress else None)
    slopes = dataclasses.replace(slopes, count=refinement["count"])     # the finest grid
    report = {} if command is None else {"command": command}
    report.update({"map": map_name, "seed_state": seed, "mesh": mesh.summary(),
                   "disturbance": {"slope_mean": slope_mean, "slope_std": slope_std, "rule": slopes.rule,
                                   "count": slopes.count, "refinement": refinement}})
    if not mesh.complete:
        report["error"] = f"mesh incomplete at --max-states {max_states}: no transition matrix"
        io.write_json(out / "mfpt.json", report)
        return report
    T = mesh.transition_matrix()
    io.atomic_write(out / "transition_matrix.npz", lambda f: sp.save_npz(f, T))
    mesh.save(out / "mesh.npz")
    if result is None:     # the chain almost never fails: no finite MFPT float64 can resolve
        report["mfpt"] = {"from_seed": math.inf, "eigen_estimate": None, "note": refinement["never_fails_note"]}
    else:
        report["mfpt"] = {**result.report(), "from_seed": result.mean(mesh.seed_distribution())}
    where = {"backend": backend, "workers": workers, "address": address}
    if monte_carlo:
        continuous = monte_carlo_mfpt(section_map, [seed], slopes, episodes=monte_carlo, seed=0,
                                      chunks=monte_carlo_chunks, **where)
        same = monte_carlo_mfpt(section_map, [seed], slopes.finite_set(), episodes=monte_carlo, seed=0,
                                chunks=monte_carlo_chunks, **where)
        report["monte_carlo"] = {"continuous_disturbance": continuous.summary(), "mesh_disturbance_set": same.summary()}
    if guard_record(section_map) is not None:
        report["section_guard"] = guard_record(section_map)
    viz.plot_transition_sparsity(T, path=out / "sparsity.png")
    viz.plot_cumulative_mass(T, path=out / "cumulative_mass.png")
    viz.plot_mesh_states(mesh, path=out / "states.png")
    if sizes:
        rows = mesh_sizes(section_map, [seed], slopes, sorted(set(sizes) | {box_size}), max_states=max_states,
                          **where)
        report["mesh_sizes"] = rows
        if sum(r["complete"] for r in rows) >= 2:
            report["reachable_dimension"] = reachable_dimension(rows)
            viz.plot_mesh_sizes(rows, path=out / "mesh_sizes.png")
    io.write_json(out / "mfpt.json", report)
    return report
