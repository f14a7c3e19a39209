"""Hopper mesh MFPT with several samples per box (Ulam's method with arrival samples).

``hopper_error.json`` located the mesh's error: the representative of a box fails about as often
as the states the true process visits there, but the chain built from one representative per box
goes elsewhere (the same push lands in the visited state's next box in only 17-36 % of
transitions), so it spends twice as many steps in boxes that can fail. Here each box keeps the
first ``k`` states that reach it and its row is the mean of their rows
(``build_mesh(..., samples_per_box=k)``), so a box's transitions spread over where states in it
go. ``k = 1`` is the thesis' mesh (the rows of ``hopper_error.json``).

Same policy, section map, seeds and pushes as ``hopper.py`` / ``hopper_error.py`` (the shipped ARS
hopper, 25 pushes in [-100, 100] N along x at the apex). Monte Carlo references: ``hopper.json``
(seed 1, 300 runs) and ``hopper_error.json`` (seed 2, 200 runs).

```text
usage: python -m hybridctl.reproduce.hopper_ulam --runs 1:4 0.7:4 1:16 0.7:8 [--time-budget-s 3600]
Runs are BOX:K pairs, done in order; mesh checkpoints go to ``--work`` (runs/ch5/ulam) and resume.
Writes ``results/ch5/hopper_ulam.json`` and ``.png`` (``--out``) after each run; reads ``hopper.json`` and
``hopper_error.json`` beside it. The meshes run on --backend/--workers/--address (default: serial).
```
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from hybridctl.io import atomic_write_text
from hybridctl.analysis import build_mesh
from hybridctl.envs.sections import HopperApexMap, x_pushes
from hybridctl.learn.ars import ARS
from hybridctl.reproduce.common import (RESULTS, add_backend_flags, backend_options, check_backend_flags, command_line,
                                       machine_info, recorded_path, shipped_policy)



def parse_run(text: str) -> tuple[float, int]:
    """``BOX:K`` -> (box size > 0, samples per box >= 1)."""
    try:
        box, k = text.split(":")
        box, k = float(box), int(k)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a run is BOX:K, e.g. 0.7:4, got {text!r}") from None
    if not (box > 0 and k >= 1):
        raise argparse.ArgumentTypeError(f"BOX must be > 0 and K >= 1, got {text!r}")
    return box, k


def references(folder: Path) -> dict:
    """The Monte Carlo runs and the k = 1 mesh rows already recorded in ``folder`` (``hopper.json``,
    ``hopper_error.json``)."""
    mc1 = json.loads((folder / "hopper.json").read_text())["monte_carlo"]
    error = json.loads((folder / "hopper_error.json").read_text())
    single = {f"{r['box_size']:g}": {"states": r["mesh_states"], "mfpt": r.get("mesh_mfpt_seeds")}
              for r in error["rows"]}
    return {"monte_carlo_seed1": mc1, "monte_carlo_seed2": error["monte_carlo_seed2"], "one_sample_per_box": single}


def plot(record: dict, path: Path) -> None:
    """Mesh MFPT against samples per box, one line per box size, over the Monte Carlo intervals."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for key, label, color in (("monte_carlo_seed1", "Monte Carlo seed 1 (300 runs)", "0.85"),
                              ("monte_carlo_seed2", "Monte Carlo seed 2 (200 runs)", "0.7")):
        mc = record[key]
        lo, hi = mc.get("interval95") or [mc["lo95"], mc["hi95"]]
        ax.axhspan(lo, hi, color=color, alpha=0.6, label=label)
    boxes = sorted({r["box_size"] for r in record["rows"]}, reverse=True)
    for d in boxes:
        pts = [(1, record["one_sample_per_box"][f"{d:g}"]["mfpt"])] if f"{d:g}" in record["one_sample_per_box"] else []
        pts += [(r["samples_per_box"], r["mfpt_seeds"]) for r in record["rows"] if r["box_size"] == d and r["complete"]]
        pts.sort()
        ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=f"box {d:g}")
    ax.set(xscale="log", yscale="log", xlabel="samples per box k (k = 1: the thesis' mesh)",
           ylabel="mesh MFPT from the seeds (apexes)", title="Hopper mesh MFPT against Monte Carlo")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=parse_run, nargs="+", required=True, metavar="BOX:K")
    parser.add_argument("--policy", default=str(shipped_policy("ars-hopper")))
    parser.add_argument("--max-states", type=int, default=40000, help="cap on boxes per mesh")
    parser.add_argument("--time-budget-s", type=float, default=None,
                        help="start no new run after this many seconds (a run in progress checkpoints and resumes)")
    parser.add_argument("--work", default="runs/ch5/ulam")
    parser.add_argument("--out", default=str(RESULTS / "ch5" / "hopper_ulam.json"))
    add_backend_flags(parser, "serial", "the meshes")
    args = parser.parse_args(argv)
    check_backend_flags(args, parser)
    torch.set_num_threads(1)
    start = time.perf_counter()
    out, work = Path(args.out), Path(args.work)
    agent = ARS.load(args.policy, backend="serial")
    section = HopperApexMap(agent.frozen_policy())
    seeds = section.apex_states(steps=2000, skip=3, seed=0)       # as hopper.py
    pushes = x_pushes(100.0, 25)
    record = json.loads(out.read_text()) if out.is_file() else {"rows": []}
    record.update({"command": command_line("hybridctl.reproduce.hopper_ulam", argv),
                   "machine": machine_info(), "policy": recorded_path(args.policy),
                   "pushes": "25 along x in [-100, 100] N at the apex", "seed_apexes": int(len(seeds)),
                   **references(Path(args.out).parent)})
    for d, k in args.runs:
        if args.time_budget_s is not None and time.perf_counter() - start > args.time_budget_s:
            print(f"time budget reached: box {d:g} k {k} not started", flush=True)
            break
        t0 = time.perf_counter()
        mesh = build_mesh(section, seeds, pushes, d, mean=agent.stats.mean, std=agent.stats.std,
                          max_states=args.max_states, batch_size=256, samples_per_box=k, **backend_options(args),
                          checkpoint=work / f"mesh-d{d:g}-k{k}.npz", resume=True, checkpoint_minutes=2)
        row = {"box_size": d, "samples_per_box": k, "states": mesh.size, "complete": mesh.complete,
               "samples": int(mesh.states.shape[0]), "transitions": int(mesh.successors.size),
               "wall_time_s": mesh.wall_time, "this_call_s": time.perf_counter() - t0}
        if mesh.complete:
            result = mesh.mfpt()
            row.update({"mfpt_seeds": float(result.mean(mesh.seed_distribution())),
                        "mfpt_quasi_stationary": float(result.mean()), "mfpt_eigen": float(result.eigen_estimate),
                        "one_step_failure_mean": float(mesh.failure_probability().mean())})
        record["rows"] = [r for r in record["rows"] if (r["box_size"], r["samples_per_box"]) != (d, k)] + [row]
        record["rows"].sort(key=lambda r: (-r["box_size"], r["samples_per_box"]))
        record["wall_time_s"] = record.get("wall_time_s", 0.0) + time.perf_counter() - t0
        atomic_write_text(out, json.dumps(record, indent=1) + "\n")
        plot(record, out.with_suffix(".png"))
        print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
