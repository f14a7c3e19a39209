"""The MFPT of a rimless wheel against the roughness of its terrain (thesis Ch. 5, after Byl &
Tedrake 2009 Fig. 6): what ``hybridctl mesh MAP --slope-std A B C ...`` does.

For each slope std the refined mesh's MFPT (:func:`~hybridctl.analysis.refined_mesh`, with its
refinement record) and, where affordable, a Monte Carlo estimate on the true map with its 95 %
interval. Affordable is decided before any run from the mesh's own MFPT: ``monte_carlo`` runs times
that MFPT is the expected number of simulated steps, at most ``monte_carlo_budget`` (at most
:data:`~hybridctl.limits.MAX_SWEEP_MONTE_CARLO_STEPS` without ``force``); above it, or where the
chain never fails in float64, Monte Carlo is skipped and the reason recorded.

>>> from hybridctl.experiments.mfpt_sweep import mfpt_vs_roughness
>>> sweep = mfpt_vs_roughness("rimless-wheel", "runs/roughness", [0.035, 0.044, 0.06], monte_carlo=2000)
>>> [(row["slope_std_deg"], row["mesh_mfpt"], row["monte_carlo"]["status"]) for row in sweep["rows"]]
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Sequence

from .. import io
from ..analysis import DEFAULT_REFINE_RTOL, GaussianDisturbance, monte_carlo_mfpt, refined_mesh
from ..limits import MAX_REFINED_DISTURBANCES, MAX_SIMULATION_STEPS, MAX_SWEEP_MONTE_CARLO_STEPS, check_at_most
from ..viz.markov import plot_mfpt_vs_roughness
from .mesh_report import MESH_DEFAULTS, guard_record, mesh_seed, printed, section_map_by_name
from .training import MESH_MARKERS, open_run_folder

SWEEP_FILES = ("mfpt_vs_roughness.json", "mfpt_vs_roughness.png")
"""What :func:`mfpt_vs_roughness` writes into its folder."""

CENSOR_FACTOR = 30
"""A Monte Carlo run stops after this many times the mesh's MFPT (at least 1e5 steps): an exponential
first-passage time passes it with probability e^-30, so no run of a sweep is censored in practice."""


def mfpt_vs_roughness(map_name: str = "rimless-wheel", out: str | Path = "runs/roughness",
                      slope_stds: Sequence[float] = (0.06,), box_size: float | None = None,
                      slope_mean: float | None = None,
                      disturbances: int | None = None, max_states: int = 1_000_000, monte_carlo: int = 0,
                      monte_carlo_budget: float = MAX_SWEEP_MONTE_CARLO_STEPS, monte_carlo_chunks: int = 1,
                      disturbance_rule: str = "grid", refine_rtol: float = DEFAULT_REFINE_RTOL,
                      max_disturbances: int = MAX_REFINED_DISTURBANCES, tails: float = 6.0,
                      backend: str = "serial", workers: int | None = None, address: str | None = None,
                      progress: bool = False, command: str | None = None, overwrite: bool = False,
                      force: bool = False, map_options: dict | None = None, resume: bool = False) -> dict:
    """Refined mesh MFPT, and Monte Carlo where affordable, for each slope std in ``slope_stds`` (rad).

    ``box_size``, ``slope_mean`` and ``disturbances`` default to the map's ``MESH_DEFAULTS``; ``map_options`` go to
    ``section_map_by_name``. Writes ``out/mfpt_vs_roughness.json`` (the returned record) and ``out/mfpt_vs_roughness.png``
    (:func:`hybridctl.viz.markov.plot_mfpt_vs_roughness`). Each row: ``slope_std`` (rad and degrees), the
    mesh's states and MFPT from the seed (``inf``, in the JSON null, with ``never_fails`` true: the chain
    never fails in float64; None: the mesh is incomplete), its
    ``refinement`` record, the seconds it took, and ``monte_carlo``: ``status`` ``"run"`` (with the
    summary: mean, ``interval95``, censored runs, ``max_steps``, seconds), or ``"skipped"`` with the
    ``reason`` (not asked for, the chain never fails, or ``monte_carlo`` x MFPT above
    ``monte_carlo_budget`` simulated steps). Monte Carlo draws continuous slopes, seed 0, and stops a
    run after :data:`CENSOR_FACTOR` times the mesh's MFPT.

    Raises:
        LimitError: ``monte_carlo_budget`` above :data:`~hybridctl.limits.MAX_SWEEP_MONTE_CARLO_STEPS`
            (``force`` lifts it).
        ValueError: an unknown map, no slope std, or no rolling gait at ``slope_mean``.
    """
    stds = [float(s) for s in slope_stds]
    if not stds or not all(math.isfinite(s) and s > 0 for s in stds):
        raise ValueError(f"slope_stds must be one or more finite numbers > 0, got {list(slope_stds)!r}")
    check_at_most("monte_carlo_budget", monte_carlo_budget, MAX_SWEEP_MONTE_CARLO_STEPS, force,
                  why="expected simulated steps of one Monte Carlo estimate of a sweep")
    section_map = section_map_by_name(map_name, **(map_options or {}))
    box_size = MESH_DEFAULTS[map_name]["box_size"] if box_size is None else box_size
    slope_mean = MESH_DEFAULTS[map_name]["slope_mean"] if slope_mean is None else slope_mean
    disturbances = MESH_DEFAULTS[map_name]["disturbances"] if disturbances is None else disturbances
    seed = mesh_seed(section_map, slope_mean)
    where = {"backend": backend, "workers": workers, "address": address}
    record = {} if command is None else {"command": command}
    settings = {"map": map_name, "map_options": io.to_jsonable(map_options or {}), "seed_state": seed,
                "slope_mean": slope_mean, "box_size": box_size, "disturbance_rule": disturbance_rule,
                "first_count": disturbances, "refine_rtol": refine_rtol, "max_disturbances": max_disturbances,
                "tails": tails, "max_states": max_states, "monte_carlo_runs": monte_carlo,
                "monte_carlo_chunks": monte_carlo_chunks, "monte_carlo_budget_steps": monte_carlo_budget,
                "monte_carlo_disturbance": "continuous Gaussian slopes, seed 0"}
    record.update({**settings, "rows": [], "finished": False})
    with open_run_folder(out, resume, overwrite, markers=(*MESH_MARKERS, SWEEP_FILES[0])) as folder:
        done = _rows_to_resume(folder.path / SWEEP_FILES[0], settings) if resume else {}
        if not resume:
            folder.clear()
            for name in SWEEP_FILES:
                (folder.path / name).unlink(missing_ok=True)
        for std in sorted(stds):
            if std in done:      # measured by the run this one continues, on the same settings
                record["rows"].append(done[std])
                if progress:
                    print(_row_line(done[std]) + " (from the resumed run)", flush=True)
                continue
            slopes = GaussianDisturbance(slope_mean, std, disturbances, rule=disturbance_rule, tails=tails)
            started = time.perf_counter()
            mesh, _, refinement = refined_mesh(section_map, [seed], slopes, box_size, rtol=refine_rtol,
                                               max_count=max_disturbances, max_states=max_states,
                                               progress=progress, force=force,
                                               report=printed(f"sigma {std:g}: ") if progress else None, **where)
            row = {"slope_std": std, "slope_std_deg": math.degrees(std), "states": mesh.size,
                   "complete": mesh.complete, "refinement": refinement,
                   "mesh_seconds": round(time.perf_counter() - started, 3)}
            row["mesh_mfpt"] = refinement["mfpt_from_seed"][-1] if mesh.complete else None
            row["never_fails"] = row["mesh_mfpt"] is not None and math.isinf(row["mesh_mfpt"])   # JSON: null
            row["monte_carlo"] = _monte_carlo_row(section_map, seed, slopes, row["mesh_mfpt"], monte_carlo,
                                                  monte_carlo_budget, monte_carlo_chunks, where)
            record["rows"].append(row)
            io.write_json(folder.path / SWEEP_FILES[0], record)    # each sigma as it comes: a kill loses one row
            if progress:
                print(_row_line(row), flush=True)
        record["regimes"] = regimes(record["rows"])
        if guard_record(section_map) is not None:
            record["section_guard"] = guard_record(section_map)
        record["finished"] = True
        io.write_json(folder.path / SWEEP_FILES[0], record)
        plot_mfpt_vs_roughness(record, path=folder.path / SWEEP_FILES[1])
    return record


def _rows_to_resume(path: Path, settings: dict) -> dict[float, dict]:
    """The rows (by slope std) of the sweep record at ``path`` that a resumed sweep keeps: all of them, when the
    record was made on ``settings``; a ValueError naming the first setting that differs otherwise (a new sweep
    needs another --out or --overwrite)."""
    if not path.is_file():
        return {}
    old = io.read_json(path)
    if not isinstance(old, dict) or not isinstance(old.get("rows"), list):
        raise ValueError(f"{path} is not a sweep record (no rows); --overwrite starts a new sweep there")
    for key, value in io.to_jsonable(settings).items():
        if old.get(key) != value:
            raise ValueError(f"--resume: {path} was made with {key} = {old.get(key)!r}, this sweep asks for "
                             f"{value!r}; --overwrite starts a new sweep there")
    return {float(row["slope_std"]): row for row in old["rows"]}


def _monte_carlo_row(section_map, seed: list[float], slopes, mesh_mfpt: float | None, runs: int, budget: float,
                     chunks: int, where: dict) -> dict:
    """Run Monte Carlo at one slope std if asked and affordable, else say why not."""
    if not runs:
        return {"status": "skipped", "reason": "no Monte Carlo asked for (monte_carlo=0)"}
    if mesh_mfpt is None:
        return {"status": "skipped", "reason": "the mesh is incomplete (max_states): no MFPT to budget from"}
    if math.isinf(mesh_mfpt):
        return {"status": "skipped", "reason": "the chain never fails in float64 (MFPT beyond about 1e9 steps): "
                                               "no run would end"}
    expected = runs * mesh_mfpt
    if expected > budget:
        return {"status": "skipped", "expected_steps": expected,
                "reason": f"{runs} runs x mesh MFPT {mesh_mfpt:,.1f} = {expected:.3g} expected steps, above the "
                          f"budget of {budget:.3g}"}
    max_steps = int(min(MAX_SIMULATION_STEPS, max(100_000, math.ceil(CENSOR_FACTOR * mesh_mfpt))))
    started = time.perf_counter()
    result = monte_carlo_mfpt(section_map, [seed], slopes, episodes=runs, max_steps=max_steps, seed=0,
                              chunks=chunks, **where)
    return {"status": "run", "expected_steps": expected, **result.summary(),
            "simulated_steps": float(result.steps.sum()), "seconds": round(time.perf_counter() - started, 3)}


def regimes(rows: list[dict]) -> dict:
    """The slope stds (rad) where Monte Carlo ran, where the mesh is the only estimate, and where the
    chain never fails in float64."""
    out = {"monte_carlo": [], "mesh_only": [], "never_fails": []}
    for row in rows:
        if row["never_fails"]:
            out["never_fails"].append(row["slope_std"])
        elif row["monte_carlo"]["status"] == "run":
            out["monte_carlo"].append(row["slope_std"])
        elif row["mesh_mfpt"] is not None:
            out["mesh_only"].append(row["slope_std"])
    return out


def _row_line(row: dict) -> str:
    """One line of a sweep: sigma, mesh MFPT and Monte Carlo (or why it was skipped)."""
    mfpt = row["mesh_mfpt"]
    mesh = "never fails" if row["never_fails"] else "incomplete" if mfpt is None else f"{mfpt:,.1f}"
    line = f"sigma {row['slope_std']:.4g} rad ({row['slope_std_deg']:.2f} deg): mesh {mesh} ({row['states']} states, " \
           f"grid {row['refinement']['count']}, {row['mesh_seconds']:.1f} s)"
    mc = row["monte_carlo"]
    if mc["status"] == "run":
        lo, hi = mc["interval95"]
        return line + f"; Monte Carlo {mc['mean_steps_to_failure']:,.1f} [{lo:,.1f}, {hi:,.1f}] ({mc['seconds']:.1f} s)"
    return line + f"; Monte Carlo skipped: {mc['reason']}"


sweep_line = _row_line
"""The one-line summary of a sweep row the command prints."""
