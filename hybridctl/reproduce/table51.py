"""Thesis Table 5.1: reachable-mesh sizes of hopper policies trained four ways, across box sizes.

Four training regimes per seed (thesis Sec. 5.3), at the reduced ARS scale of Chapter 4's
runs (``hybridctl.reproduce.table41``: 8 directions, best 4, reward shift 1):

- **standard**: ``P`` identity epochs, then ``C`` more identity epochs;
- **fractal**: the same ``P`` epochs, then ``C`` epochs with the mesh-dimension reward
  (``--postprocess mesh-upper``, thesis eq. 4.4; the thesis continues 250 epochs);
- **standard noise** / **fractal noise**: as above with Gaussian noise in every training
  rollout, std 0.01 on actions and 0.001 on observations (thesis Ch. 5 appendix).

Each final policy gets reachable meshes (thesis Alg. 7) under the thesis' 25 pushes in
[-15, 15] N along x at the apex, in units of that policy's observation std, from the apexes of
one unpushed run, for each box size. A policy that does not hop (fewer than 4 apexes in 2000
steps) is recorded as such and gets no mesh. Training and meshes resume from their
checkpoints under ``--work``; the record (``results/ch5/table51.json``) is rewritten after each step.
The training runs and the meshes run on ``--backend``/``--workers``/``--address`` (default: serial, one
process per lane); neither depends on them.

```text
usage: python -m hybridctl.reproduce.table51 --seeds 1 2 [--box-sizes 0.4 0.3 0.2]
       [--max-states 20000] [--epochs 100 40] [--out RECORD] [--merge RECORD ...]
Two processes can share the work folder on different seeds with their own ``--out``; then
``python -m hybridctl.reproduce.table51 --merge A.json B.json`` copies their runs into the record and rewrites the summary
(per-regime means and medians, per-seed sign tests against the thesis' claims, ``table51.png``).
```
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from hybridctl.io import atomic_write_text
from hybridctl.analysis import build_mesh
from hybridctl.envs.sections import HopperApexMap, x_pushes
from hybridctl.learn.ars import ARS
from hybridctl.reproduce.common import (RESULTS, add_backend_flags, backend_cli_args, backend_options,
                                       check_backend_flags, command_line, machine_info, recorded_path)

NOISE = ["--set", "train_action_noise=0.01", "--set", "train_obs_noise=0.001"]   # thesis Ch. 5 appendix
REGIMES = {"standard": ("plain", "identity"), "fractal": ("plain", "mesh-upper"),
           "standard noise": ("noise", "identity"), "fractal noise": ("noise", "mesh-upper")}


# ARS V2-t settings per env (every other field: ARSConfig's thesis values, step 0.02 and noise 0.025)
ARS_SETTINGS = {
    # Chapter 4's reduced scale (hybridctl.reproduce.table41): N 8 / b 4 as Mania et al. 2018
    # Table 9 for Hopper, their reward shift 1 (thesis: N 50 / b 20)
    "Hopper-v5": ["n_directions=8", "top_directions=4", "reward_shift=1"],
    # Mania et al. 2018 Table 9, Walker2d-v1 (at N 8 / b 4 no seed walked: README, Table 4.1)
    "Walker2d-v5": ["n_directions=40", "top_directions=30", "step_size=0.03", "noise=0.025", "reward_shift=1"],
}


def ars_command(hc: str, seed: int, env: str = "Hopper-v5", backend: list[str] | None = None) -> list[str]:
    """The ``hybridctl train ars`` prefix every run of a seed shares (``ARS_SETTINGS[env]``); ``backend``:
    its ``--backend``/``--workers``/``--address`` (default ``--backend serial``)."""
    return [hc, "train", "ars", env, "--seed", str(seed), *(backend or ["--backend", "serial"]), "--quiet",
            *[arg for setting in ARS_SETTINGS[env] for arg in ("--set", setting)]]


def train_pretrain(hc: str, seed: int, work: Path, kind: str, epochs: int, env: str = "Hopper-v5",
                   backend: list[str] | None = None) -> Path:
    """Train (or resume, or extend to more ``epochs``) the identity pretrain ``work/sSEED/pretrain-KIND``
    (``plain``, or ``noise`` with the thesis' training noise) on ``backend`` (:func:`ars_command`);
    returns its folder."""
    extra = NOISE if kind == "noise" else []
    base = work / f"s{seed}" / f"pretrain-{kind}"
    progress = base / "final" / "progress.json"
    if not (progress.is_file() and (base / "eval.json").is_file()
            and json.loads(progress.read_text())["epoch"] >= epochs):
        subprocess.run([*ars_command(hc, seed, env, backend), *extra, "--epochs", str(epochs), "--out", str(base),
                        "--resume"], check=True)
    return base


def train_regime(hc: str, seed: int, work: Path, folder: str, kind: str, post: str, pretrain: int,
                 more: int, env: str = "Hopper-v5", backend: list[str] | None = None) -> Path:
    """Train (or resume) one continuation ``work/sSEED/FOLDER`` of the ``kind`` pretrain
    (``plain`` or ``noise``) with post-processor ``post`` on ``backend`` (:func:`ars_command`); trains
    the pretrain first if missing. Returns the final checkpoint dir. Also used by
    :mod:`hybridctl.reproduce.table44`."""
    extra = NOISE if kind == "noise" else []
    base = train_pretrain(hc, seed, work, kind, pretrain, env, backend)
    out = work / f"s{seed}" / folder
    if not (out / "eval.json").is_file():
        resumable = any(out.glob("checkpoint*")) or (out / "final").is_dir()   # final/ alone resumes
        start = ["--resume"] if resumable else ["--init", str(base / "final")]
        subprocess.run([*ars_command(hc, seed, env, backend), *extra, "--epochs", str(pretrain + more),
                        "--postprocess", post, "--out", str(out), *start], check=True)
    return out / "final"


def train(hc: str, seed: int, work: Path, pretrain: int, more: int, backend: list[str] | None = None) -> dict:
    """Train (or resume) the four regimes of one seed on ``backend`` (:func:`ars_command`); returns
    regime -> final checkpoint dir."""
    return {regime: train_regime(hc, seed, work, regime.replace(" ", "-"), kind, post, pretrain, more,
                                 backend=backend)
            for regime, (kind, post) in REGIMES.items()}


def meshes(policy_dir: Path, box_sizes, max_states: int, work: Path, parallel: dict | None = None) -> dict:
    """Mesh sizes of one policy at each box size (thesis Table 5.1's pushes); ``parallel``: the meshes'
    ``backend``/``workers``/``address`` (default serial)."""
    agent = ARS.load(policy_dir, backend="serial")
    section = HopperApexMap(agent.frozen_policy())
    evaluation = json.loads((policy_dir.parent / "eval.json").read_text())
    row = {"policy": recorded_path(policy_dir), "return": evaluation.get("mean_return", evaluation.get("return")),
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
                          max_states=max_states, batch_size=256, progress=False, **(parallel or {"backend": "serial"}),
                          checkpoint=work / f"mesh-d{d:g}.npz", resume=True, checkpoint_minutes=2)
        row["meshes"].append({"box_size": d, "states": mesh.size, "complete": mesh.complete,
                              "transitions_to_failure": int((mesh.successors == 0).sum()),
                              "wall_time_s": mesh.wall_time})
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="*", default=[],
                        help="seeds to train (what is missing) and mesh; none: only --merge and rewrite the summary")
    parser.add_argument("--box-sizes", type=float, nargs="+", default=[0.4, 0.3, 0.2])
    parser.add_argument("--max-states", type=int, default=20000)
    parser.add_argument("--epochs", type=int, nargs=2, default=[100, 40], metavar=("P", "C"))
    parser.add_argument("--work", default=str(RESULTS / "ch5" / "table51_runs"),
                        help="training runs and mesh checkpoints; resumed from (default: the committed ones)")
    parser.add_argument("--out", default=str(RESULTS / "ch5" / "table51.json"))
    parser.add_argument("--merge", nargs="+", default=[], metavar="RECORD",
                        help="runs of other records (e.g. two processes' --out files) to copy into --out first")
    add_backend_flags(parser, "serial", "the training runs and the meshes")
    args = parser.parse_args(argv)
    check_backend_flags(args, parser)
    if not (args.seeds or args.merge):
        parser.error("give --seeds to run or --merge records to combine")
    torch.set_num_threads(1)
    hc = str(Path(sys.executable).with_name("hybridctl"))
    work = Path(args.work)
    out = Path(args.out)
    record = json.loads(out.read_text()) if out.is_file() else {"runs": {}}
    # every command that wrote runs into this record, oldest first (a merge brings its sources' commands)
    commands = record.get("commands", [record["command"]] if "command" in record else [])
    for other in args.merge:
        merged = json.loads(Path(other).read_text())
        record["runs"].update(merged["runs"])
        commands += [c for c in merged.get("commands", [merged.get("command")]) if c and c not in commands]
    command = command_line("hybridctl.reproduce.table51", argv)
    record["commands"] = commands + [command]
    record.update({"command": command, "machine": machine_info(),
                   "pushes": "25 along x in [-15, 15] N (thesis Table 5.1)", "epochs": args.epochs,
                   "ars": "8 directions, best 4, reward shift 1, step 0.02, noise 0.025 (Ch. 4 reduced scale)",
                   "training_noise": "actions 0.01, observations 0.001 (thesis Ch. 5 appendix)"})
    for seed in args.seeds:
        finals = train(hc, seed, work, *args.epochs, backend=backend_cli_args(args))
        for regime, final in finals.items():
            key = f"s{seed}/{regime}"
            row = meshes(final, args.box_sizes, args.max_states, work / f"s{seed}" / regime.replace(" ", "-"),
                         backend_options(args))
            progress = json.loads((final / "progress.json").read_text())
            # cumulative over the pretrain and the continuation (the run's own clock, kept across resumes)
            row.update({"epochs": progress["epoch"], "env_steps": progress["env_steps"],
                        "train_wall_time_s": progress["wall_time"]})
            record["runs"][key] = {"seed": seed, "regime": regime, **row}
            print(json.dumps(record["runs"][key]), flush=True)
            atomic_write_text(out, json.dumps(record, indent=1) + "\n")
    record["table"] = table(record)
    record["paired"] = paired(record)
    atomic_write_text(out, json.dumps(record, indent=1) + "\n")
    plot(record, out.with_suffix(".png"))
    return 0


# A policy counts in the summary if it hops and its mean 1,000-step return reaches this (table44.py's bar):
# a policy that falls at the first push has a mesh of a few states, which is no sign of robustness.
MIN_RETURN = 2000.0


def counted(run: dict) -> bool:
    """Whether a run enters the summary: it hops and reaches MIN_RETURN."""
    return bool(run.get("hops")) and run["return"] >= MIN_RETURN


def table(record: dict) -> dict:
    """Mesh size per regime and box size over the seeds whose policy counts (:func:`counted`).

    ``mean_states`` is None where a mesh stopped at ``--max-states`` (its size is then only a
    lower bound, kept in ``lower_bound_mean``); ``median_states`` stays exact while fewer than
    half the meshes stopped."""
    out = {}
    for regime in REGIMES:
        every = [r for r in record["runs"].values() if r["regime"] == regime]
        rows = [r for r in every if counted(r)]
        meshes: dict[str, list] = {}      # box size -> (states, complete, transitions to failure) per policy
        for r in rows:
            for m in r.get("meshes", []):
                meshes.setdefault(f"{m['box_size']:g}", []).append(
                    (m["states"], m["complete"], m["transitions_to_failure"]))
        sizes = {d: [n if done else None for n, done, _ in v] for d, v in meshes.items()}
        out[regime] = {"seeds": len(every), "hopping": sum(bool(r.get("hops")) for r in every), "counted": len(rows),
                       "excluded": {f"s{r['seed']}": ("does not hop" if not r.get("hops") else
                                                      f"return {r['return']:.0f} < {MIN_RETURN:g}")
                                    for r in every if not counted(r)},
                       "mean_states": {d: (float(np.mean(v)) if v and None not in v else None)
                                       for d, v in sizes.items()},
                       "lower_bound_mean": {d: float(np.mean([n for n, _, _ in v])) for d, v in meshes.items() if v},
                       "median_states": {d: _median(v) for d, v in sizes.items()},
                       # a small mesh can also mean a policy that falls: count the meshes with a failing push
                       "meshes_with_failures": {d: sum(f > 0 for _, _, f in v) for d, v in meshes.items()},
                       "states": sizes}
    return out


def _median(values: list) -> float | None:
    """Median where stopped meshes (None) count as larger than every complete one; None if that
    leaves the median undetermined."""
    ordered = sorted(v for v in values if v is not None) + [None] * values.count(None)
    if not ordered:
        return None
    middle = ordered[(len(ordered) - 1) // 2: len(ordered) // 2 + 1]
    return None if None in middle else float(np.mean(middle))


def mesh_sizes(record: dict) -> dict:
    """(seed, regime, box size) -> (states, complete) for every counted policy's mesh."""
    return {(r["seed"], r["regime"], f"{m['box_size']:g}"): (m["states"], m["complete"])
            for r in record["runs"].values() if counted(r) for m in r.get("meshes", [])}


def paired(record: dict) -> dict:
    """Per-seed comparisons behind the thesis' claims (Sec. 5.4.1: noise shrinks the mesh, the fractal
    reward shrinks it more, both together most), as sign tests over the seeds where both meshes exist.

    A stopped mesh is a lower bound: it counts as larger than a complete one below it; a pair it
    leaves undecided is dropped. ``log_ratio_mean`` is the mean of log(states / baseline states)
    over the decided pairs of complete meshes (exp of it: the geometric-mean ratio)."""
    from scipy.stats import binomtest
    sizes = mesh_sizes(record)
    seeds = sorted({k[0] for k in sizes})
    boxes = sorted({k[2] for k in sizes}, key=float, reverse=True)
    comparisons = [("standard noise", "standard"), ("fractal", "standard"), ("fractal noise", "standard"),
                   ("fractal noise", "standard noise"), ("fractal noise", "fractal")]
    out = []
    for regime, baseline in comparisons:
        for d in boxes:
            smaller = larger = ties = 0
            logs = []
            for seed in seeds:
                a, b = sizes.get((seed, regime, d)), sizes.get((seed, baseline, d))
                if a is None or b is None:
                    continue
                (na, ca), (nb, cb) = a, b
                if ca and cb:
                    smaller, larger, ties = smaller + (na < nb), larger + (na > nb), ties + (na == nb)
                    logs.append(float(np.log(na / nb)))
                elif ca and na < nb:      # b stopped at nb states: it is larger still
                    smaller += 1
                elif cb and nb < na:
                    larger += 1
            decided = smaller + larger
            out.append({"regime": regime, "baseline": baseline, "box_size": d, "smaller": smaller,
                        "larger": larger, "ties": ties,
                        "sign_test_p": float(binomtest(smaller, decided).pvalue) if decided else None,
                        "geometric_mean_ratio": float(np.exp(np.mean(logs))) if logs else None})
    return out


def plot(record: dict, path: Path) -> None:
    """Mesh size per regime, one line per seed (log scale), one panel per box size."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    sizes = mesh_sizes(record)
    boxes = sorted({k[2] for k in sizes}, key=float, reverse=True)
    seeds = sorted({k[0] for k in sizes})
    regimes = ["standard", "standard noise", "fractal", "fractal noise"]     # the thesis' row order
    fig, axes = plt.subplots(1, len(boxes), figsize=(4.2 * len(boxes), 4.0), sharey=True, squeeze=False)
    for ax, d in zip(axes[0], boxes):
        for seed in seeds:
            pts = [(i, *sizes[(seed, r, d)]) for i, r in enumerate(regimes) if (seed, r, d) in sizes]
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "-", color="0.75", lw=0.8)
            ax.scatter([p[0] for p in pts], [p[1] for p in pts], s=14,
                       c=["C0" if p[2] else "C3" for p in pts], zorder=3)
        for i, r in enumerate(regimes):
            median = record["table"][r]["median_states"].get(d)
            if median is not None:
                ax.plot([i - 0.3, i + 0.3], [median, median], "k-", lw=2)
        ax.set(yscale="log", title=f"box size {d}", xticks=range(len(regimes)))
        ax.set_xticklabels([r.replace(" ", "\n") for r in regimes])
    axes[0][0].set_ylabel("reachable mesh states (red: stopped at the cap)")
    fig.suptitle(f"Table 5.1: hopper meshes, 25 pushes of +-15 N, {len(seeds)} seeds (lines: one seed; bars: median)",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
