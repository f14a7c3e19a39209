"""Thesis Ch. 5 on gymnasium's Hopper-v5: reachable apex meshes, MFPT (eigen vs exact) vs Monte Carlo.

The ARS hopper (``models/policies/ars-hopper`` by default) hops; at each apex of the torso
height one push along x, drawn from ``--pushes`` values evenly spaced in
[-magnitude, magnitude] N, acts on the torso for one env step (thesis Ch. 5: 25 values,
15 N). Meshes are built (thesis Alg. 7) from the apexes of an unpushed run, boxes in
units of the policy's observation std (the author's normalisation), for each box size;
per mesh: size, completeness, exact MFPT (Krylov solve) and the eigenvalue estimate
1/(1 - lambda_2), both averaged over the seed apexes. Monte Carlo runs the true map
from the same apexes with pushes drawn from the same set. Writes ``results/ch5/hopper.json``.
The meshes and the Monte Carlo run on ``--backend``/``--workers``/``--address`` (default 2 local
processes); neither depends on them.

```text
usage: python -m hybridctl.reproduce.hopper [--magnitude 15] [--box-sizes 2 1.5 1]
       [--max-states 3000] [--episodes 300] [--backend processes] [--workers 2] [--address HOST:PORT]
```
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from hybridctl.io import atomic_write_text
from hybridctl.analysis import build_mesh, monte_carlo_mfpt, reachable_dimension
from hybridctl.envs.sections import HopperApexMap, x_pushes
from hybridctl.learn.ars import ARS
from hybridctl.reproduce.common import (RESULTS, add_backend_flags, backend_options, check_backend_flags, command_line,
                                       machine_info, recorded_path, shipped_policy)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", default=str(shipped_policy("ars-hopper")))
    parser.add_argument("--magnitude", type=float, default=15.0)
    parser.add_argument("--pushes", type=int, default=25)
    parser.add_argument("--box-sizes", type=float, nargs="+", default=[2.0, 1.5, 1.0])
    parser.add_argument("--max-states", type=int, default=3000)
    parser.add_argument("--episodes", type=int, default=300)
    parser.add_argument("--max-hops", type=int, default=2000)
    add_backend_flags(parser, "processes", "the meshes and the Monte Carlo", workers=2)
    parser.add_argument("--out", default=str(RESULTS / "ch5" / "hopper.json"))
    parser.add_argument("--checkpoints", default="runs/ch5/hopper")
    parser.add_argument("--dimension-max-box", type=float, default=1.0,
                        help="fit the reachable-mesh dimension over box sizes up to this")
    parser.add_argument("--reuse-monte-carlo", action="store_true",
                        help="keep the Monte Carlo result of an earlier record with the same pushes")
    args = parser.parse_args(argv)
    check_backend_flags(args, parser)
    start = time.perf_counter()
    earlier = json.loads(Path(args.out).read_text()) if Path(args.out).is_file() else {}
    agent = ARS.load(args.policy, backend="serial")
    section = HopperApexMap(agent.frozen_policy())
    seeds = section.apex_states(steps=2000, skip=3, seed=0)
    pushes = x_pushes(args.magnitude, args.pushes)
    mean, std = agent.stats.mean, agent.stats.std
    record = {"command": command_line("hybridctl.reproduce.hopper", argv), "machine": machine_info(),
              "policy": recorded_path(args.policy),
              "push_magnitude_N": args.magnitude, "push_note": "thesis: 15 N; this policy did not fail in 20 x 300 apexes at 15 N, so the magnitude was raised until Monte Carlo could measure its MFPT", "pushes": args.pushes, "seed_apexes": int(len(seeds)),
              "normalisation": "the policy's observation mean/std", "meshes": []}
    Path(args.checkpoints).mkdir(parents=True, exist_ok=True)
    for d in args.box_sizes:
        mesh = build_mesh(section, seeds, pushes, d, mean=mean, std=std, max_states=args.max_states,
                          batch_size=16, **backend_options(args),
                          checkpoint=Path(args.checkpoints) / f"mesh-d{d:g}.npz", resume=True)
        row = {"box_size": d, "states": mesh.size, "complete": mesh.complete, "wall_time_s": mesh.wall_time,
               "transitions_to_failure": int((mesh.successors == 0).sum())}
        if mesh.complete:
            result = mesh.mfpt()     # exact (Krylov) per state, and the eigen estimate 1 / (1 - lambda_2)
            row.update({"mfpt_exact": result.mean(mesh.seed_distribution()), "mfpt_eigen": result.eigen_estimate,
                        "mfpt_exact_quasi_stationary": result.mean(), "lambda2": result.lambda2,
                        "lambda3_ratio": result.lambda3_ratio, "never_fail_states": int(result.infinite_states.size)})
        row = {k: ("inf" if isinstance(v, float) and np.isinf(v) else v) for k, v in row.items()}  # JSON has no inf
        record["meshes"].append(row)
        print(json.dumps(row), flush=True)
        atomic_write_text(Path(args.out), json.dumps(record, indent=1, allow_nan=False) + "\n")
    done = [r for r in record["meshes"] if r["complete"]]
    fine = [r for r in done if r["box_size"] <= args.dimension_max_box]
    if len(fine) >= 2:   # the coarsest meshes collapse onto a few boxes that never fail: not in the fit
        record["reachable_dimension"] = reachable_dimension(fine)
        record["reachable_dimension_boxes"] = [r["box_size"] for r in fine]
    if (args.reuse_monte_carlo and "monte_carlo" in earlier and earlier.get("push_magnitude_N") == args.magnitude
            and earlier.get("pushes") == args.pushes):
        record["monte_carlo"] = earlier["monte_carlo"]
        record["wall_time_s"] = time.perf_counter() - start
        atomic_write_text(Path(args.out), json.dumps(record, indent=1, allow_nan=False) + "\n")
        return 0
    t0 = time.perf_counter()
    mc = monte_carlo_mfpt(section, seeds, pushes, episodes=args.episodes, max_steps=args.max_hops, seed=1,
                          chunks=20, progress=True, **backend_options(args))
    record["monte_carlo"] = {**mc.summary(), "wall_time_s": time.perf_counter() - t0}
    print(json.dumps(record["monte_carlo"]), flush=True)
    record["wall_time_s"] = time.perf_counter() - start
    atomic_write_text(Path(args.out), json.dumps(record, indent=1, allow_nan=False) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
