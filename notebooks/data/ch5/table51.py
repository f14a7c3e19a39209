"""Thesis Table 5.1: reachable-mesh sizes of hopper policies trained four ways, across box sizes.

Four training regimes per seed (thesis Sec. 5.3), at the reduced ARS scale of Chapter 4's
runs (``notebooks/data/ch4/run_table41.sh``: 8 directions, best 4, reward shift 1):

- **standard**: ``P`` identity epochs, then ``C`` more identity epochs;
- **fractal**: the same ``P`` epochs, then ``C`` epochs with the mesh-dimension reward
  (``--postprocess mesh-upper``, thesis eq. 4.4; the thesis continues 250 epochs);
- **standard noise** / **fractal noise**: as above with Gaussian noise in every training
  rollout, std 0.01 on actions and 0.001 on observations (thesis Ch. 5 appendix).

Each final policy gets reachable meshes (thesis Alg. 7) under the thesis' 25 pushes in
[-15, 15] N along x at the apex, in units of that policy's observation std, from the apexes of
one unpushed run, for each box size. A policy that does not hop (fewer than 4 apexes in 2000
steps) is recorded as such and gets no mesh. Training and meshes resume from their
checkpoints under ``--work``; the record (``table51.json`` here) is rewritten after each step.

usage: .venv/bin/python notebooks/data/ch5/table51.py --seeds 1 2 [--box-sizes 0.4 0.3 0.2]
       [--max-states 20000] [--epochs 100 40]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
from benchmarks.common import machine_info  # noqa: E402
from hybridctl.analysis import build_mesh  # noqa: E402
from hybridctl.envs.sections import HopperApexMap, x_pushes  # noqa: E402
from hybridctl.learn.ars import ARS  # noqa: E402

NOISE = ["--set", "train_action_noise=0.01", "--set", "train_obs_noise=0.001"]   # thesis Ch. 5 appendix
REGIMES = {"standard": ("plain", "identity"), "fractal": ("plain", "mesh-upper"),
           "standard noise": ("noise", "identity"), "fractal noise": ("noise", "mesh-upper")}


def ars_command(hc: str, seed: int) -> list[str]:
    """The ``hybridctl train ars`` prefix every run of a seed shares (Ch. 4's reduced scale)."""
    return [hc, "train", "ars", "Hopper-v5", "--seed", str(seed), "--backend", "serial", "--quiet",
            "--set", "n_directions=8", "--set", "top_directions=4", "--set", "reward_shift=1"]


def train_regime(hc: str, seed: int, work: Path, folder: str, kind: str, post: str, pretrain: int,
                 more: int) -> Path:
    """Train (or resume) one continuation ``work/sSEED/FOLDER`` of the ``kind`` pretrain
    (``plain`` or ``noise``) with post-processor ``post``; trains the pretrain first if missing.
    Returns the final checkpoint dir. Also used by ``notebooks/data/ch4/table44.py``."""
    extra = NOISE if kind == "noise" else []
    base = work / f"s{seed}" / f"pretrain-{kind}"
    if not (base / "eval.json").is_file():
        subprocess.run([*ars_command(hc, seed), *extra, "--epochs", str(pretrain), "--out", str(base), "--resume"],
                       check=True)
    out = work / f"s{seed}" / folder
    if not (out / "eval.json").is_file():
        start = ["--resume"] if any(out.glob("checkpoint*")) else ["--init", str(base / "final")]
        subprocess.run([*ars_command(hc, seed), *extra, "--epochs", str(pretrain + more), "--postprocess", post,
                        "--out", str(out), *start], check=True)
    return out / "final"


def train(hc: str, seed: int, work: Path, pretrain: int, more: int) -> dict:
    """Train (or resume) the four regimes of one seed; returns regime -> final checkpoint dir."""
    return {regime: train_regime(hc, seed, work, regime.replace(" ", "-"), kind, post, pretrain, more)
            for regime, (kind, post) in REGIMES.items()}


def meshes(policy_dir: Path, box_sizes, max_states: int, work: Path) -> dict:
    """Mesh sizes of one policy at each box size (thesis Table 5.1's pushes)."""
    agent = ARS.load(policy_dir, backend="serial")
    section = HopperApexMap(agent.frozen_policy())
    evaluation = json.loads((policy_dir.parent / "eval.json").read_text())
    row = {"policy": str(policy_dir), "return": evaluation.get("mean_return", evaluation.get("return")),
           "meshes": []}
    try:
        seeds = section.apex_states(steps=2000, skip=3, seed=0)
    except ValueError as err:        # it does not hop: no apexes to seed a mesh from
        row["hops"] = False
        row["note"] = str(err)
        return row
    row["hops"], row["seed_apexes"] = True, int(len(seeds))
    for d in box_sizes:
        mesh = build_mesh(section, seeds, x_pushes(15.0, 25), d, mean=agent.stats.mean, std=agent.stats.std,
                          max_states=max_states, backend="serial", batch_size=256, progress=False,
                          checkpoint=work / f"mesh-d{d:g}.npz", resume=True, checkpoint_minutes=2)
        row["meshes"].append({"box_size": d, "states": mesh.size, "complete": mesh.complete,
                              "transitions_to_failure": int((mesh.successors == 0).sum()),
                              "wall_time_s": mesh.wall_time})
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", required=True)
    parser.add_argument("--box-sizes", type=float, nargs="+", default=[0.4, 0.3, 0.2])
    parser.add_argument("--max-states", type=int, default=20000)
    parser.add_argument("--epochs", type=int, nargs=2, default=[100, 40], metavar=("P", "C"))
    parser.add_argument("--work", default="runs/ch5/table51")
    parser.add_argument("--out", default=str(Path(__file__).with_name("table51.json")))
    args = parser.parse_args()
    torch.set_num_threads(1)
    hc = str(Path(sys.executable).with_name("hybridctl"))
    work = Path(args.work)
    out = Path(args.out)
    record = json.loads(out.read_text()) if out.is_file() else {"runs": {}}
    record.update({"command": "python " + " ".join(sys.argv), "machine": machine_info(),
                   "pushes": "25 along x in [-15, 15] N (thesis Table 5.1)", "epochs": args.epochs,
                   "ars": "8 directions, best 4, reward shift 1, step 0.02, noise 0.025 (Ch. 4 reduced scale)",
                   "training_noise": "actions 0.01, observations 0.001 (thesis Ch. 5 appendix)"})
    for seed in args.seeds:
        finals = train(hc, seed, work, *args.epochs)
        for regime, final in finals.items():
            key = f"s{seed}/{regime}"
            row = meshes(final, args.box_sizes, args.max_states, work / f"s{seed}" / regime.replace(" ", "-"))
            progress = json.loads((final / "progress.json").read_text())
            # cumulative over the pretrain and the continuation (the run's own clock, kept across resumes)
            row.update({"epochs": progress["epoch"], "env_steps": progress["env_steps"],
                        "train_wall_time_s": progress["wall_time"]})
            record["runs"][key] = {"seed": seed, "regime": regime, **row}
            print(json.dumps(record["runs"][key]), flush=True)
            out.write_text(json.dumps(record, indent=1) + "\n")
    record["table"] = table(record)
    out.write_text(json.dumps(record, indent=1) + "\n")
    return 0


def table(record: dict) -> dict:
    """Mean mesh size per regime and box size over the seeds whose policy hops (complete meshes only)."""
    out = {}
    for regime in REGIMES:
        rows = [r for r in record["runs"].values() if r["regime"] == regime]
        sizes: dict[str, list] = {}
        for r in rows:
            for m in r.get("meshes", []):
                sizes.setdefault(f"{m['box_size']:g}", []).append(m["states"] if m["complete"] else None)
        out[regime] = {"seeds": len(rows), "hopping": sum(bool(r.get("hops")) for r in rows),
                       "mean_states": {d: (float(np.mean(v)) if v and None not in v else None)
                                       for d, v in sizes.items()},
                       "states": sizes}
    return out


if __name__ == "__main__":
    raise SystemExit(main())
