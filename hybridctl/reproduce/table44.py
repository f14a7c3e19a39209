"""Thesis Table 4.4 with its protocol, on the hopper (and the walker): failure rates of identity against
mesh post-processed ARS policies under action noise, observation noise and pushes.

Protocol (thesis Sec. 4.4, Table 4.4):

1. **Policies.** Per seed, ARS on ``Hopper-v5`` at Chapter 4's reduced scale (8 directions, best 4,
   reward shift 1): ``P`` identity epochs, then ``C`` more epochs with ``identity``, ``mesh-lower``
   or ``mesh-upper`` from that checkpoint (thesis: 750 + 250 at N 50 / b 20). They live in the
   Table 5.1 work folder (``results/ch5/table51_runs``, trained by the same function), where
   ``standard`` is the identity run and ``fractal`` the mesh-upper one; ``mesh-lower`` is added.
   A seed counts only if its identity policy hops (mean 1,000-step return >= ``--min-return``) and
   survives undisturbed 10,000-step episodes (at most 10 % of ``--grid-episodes`` fail): a policy
   that falls on its own would set the failure rate before any disturbance does.
2. **Grid search.** For each disturbance kind, the identity policies of all counted seeds run
   ``--grid-episodes`` episodes per seed of 10,000 steps at each level of a coarse grid; three
   geometric points are then tried between the two levels that bracket 20 % failures. The level whose
   pooled failure rate is closest to 0.2 is kept (thesis: "the parameter for which the identity post
   processor failed in roughly 20 percent of cases").
3. **Evaluation.** Every variant of every counted seed runs ``--episodes`` fresh episodes (other env
   seeds than the grid search, so the chosen level's identity rate is not biased towards 0.2) of
   10,000 steps at the chosen levels and without disturbance. Failure = early termination.
   Reported: pooled failures with 95 % Wilson intervals, failures per seed, and in how many seeds the
   post-processed policy failed less often than that seed's identity policy.

Pushes follow the thesis: at every step with probability 0.2 (the thesis' rate) a force of fixed
magnitude at a uniform random angle in the x-z plane on the torso; the magnitude is searched.
HalfCheetah-v5 never terminates (no failure to count). No Walker2d-v5 seed walked at Chapter 4's
scale (README, Table 4.1); ``--env Walker2d-v5`` takes the seeds :mod:`hybridctl.reproduce.walker_seeds` trained with
Mania et al.'s Walker2d settings (150 identity epochs, or more for a seed ``walker_seeds`` extended,
then 40 with each variant; grids hold the thesis' walker levels 0.15 / 0.03 / 1 N) and writes
``results/ch4/table44-walker2d.json``.

Every per-seed measurement (one policy, one condition, one episode count, one env seed) is kept in
``WORK/table44.cache.json``, next to the policies, as soon as it is made: a run that is cut off resumes
where it stopped, and a run with more seeds reuses the cells it shares with an earlier one. A cell is
reused only for the same policy weights (a hash of ``model.pt`` and ``normalization.json``).
``--fresh`` ignores the cache.

The failure-rate episodes and the training runs run on ``--backend``/``--workers``/``--address``
(default: serial, one thread; the MuJoCo envs' episodes of a condition step together on the batched
stepper's ``--workers`` threads); the numbers do not depend on them.

```text
usage: python -m hybridctl.reproduce.table44 --seeds 1 2 3 4 [--env Walker2d-v5] [--episodes 25]
       [--grid-episodes 10] [--train-only] [--fresh] [--backend serial] [--workers 1] [--address HOST:PORT]
```
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from hybridctl.io import write_json
from hybridctl.learn import failure_rates
from hybridctl.learn.ars import ARS
from hybridctl.learn.robustness import wilson_interval
from hybridctl.reproduce.common import (add_backend_flags, backend_cli_args, check_backend_flags, command_line,
                                       machine_info, recorded_path)
from hybridctl.reproduce import table51

# variant -> (folder in the Table 5.1 work folder, post-processor of the continuation)
VARIANTS = {"identity": ("standard", "identity"), "mesh-lower": ("mesh-lower", "mesh-lower"),
            "mesh-upper": ("fractal", "mesh-upper")}
PUSH_RATE = 0.2          # thesis Table 4.4 (c): rate .2 for every env
# Per env: coarse grids (each holds the thesis' level for that env), the thesis' Table 4.4 row,
# the work folder that holds (or gets) the policies, the epochs P + C and the record.
ENVS = {
    "Hopper-v5": {
        "grids": {"action_noise": [0.02, 0.05, 0.1, 0.2, 0.4], "obs_noise": [0.005, 0.01, 0.02, 0.05, 0.1],
                  "push": [1.0, 3.0, 10.0, 30.0, 100.0]},
        "thesis": {"action_noise": {"level": 0.05, "identity": 0.19, "mesh-lower": 0.10},
                   "obs_noise": {"level": 0.02, "identity": 0.20, "mesh-lower": 0.25},
                   "push": {"level": [1.0, 0.2], "identity": 0.17, "mesh-lower": 0.10}},
        "work": "results/ch5/table51_runs", "epochs": [100, 40], "out": "results/ch4/table44.json"},
    "Walker2d-v5": {
        "grids": {"action_noise": [0.05, 0.15, 0.3, 0.6, 1.0], "obs_noise": [0.01, 0.03, 0.1, 0.3],
                  "push": [1.0, 3.0, 10.0, 30.0, 100.0]},
        "thesis": {"action_noise": {"level": 0.15, "identity": 0.28, "mesh-lower": 0.03},
                   "obs_noise": {"level": 0.03, "identity": 0.18, "mesh-lower": 0.10},
                   "push": {"level": [1.0, 0.2], "identity": 0.20, "mesh-lower": 0.00}},
        # the seeds hybridctl.reproduce.walker_seeds trained (Mania et al.'s Walker2d settings, table51.ARS_SETTINGS)
        "work": "results/ch4/walker_runs", "epochs": [150, 40], "out": "results/ch4/table44-walker2d.json"},
}
TARGET = 0.2


def pretrain_epochs(work: Path, seed: int, epochs: int) -> int:
    """The identity epochs a seed's continuations start from: ``epochs``, or more where its pretrain was
    extended (``walker_seeds --train 250`` for a seed that fell at 150), so that every variant of the
    seed continues the same checkpoint for the same ``C`` epochs."""
    progress = work / f"s{seed}" / "pretrain-plain" / "final" / "progress.json"
    return max(epochs, json.loads(progress.read_text())["epoch"]) if progress.is_file() else epochs


def condition(kind: str, level: float) -> dict:
    """A failure_rates condition for one disturbance kind and level."""
    return {"push": (PUSH_RATE, level)} if kind == "push" else {kind: level}


def policy_fingerprint(final: Path) -> str:
    """A short hash of a saved policy's weights and normalisation statistics: cached cells of a policy
    that was retrained since do not match."""
    digest = hashlib.sha256()
    for name in ("model.pt", "normalization.json"):
        digest.update((final / name).read_bytes())
    return digest.hexdigest()[:16]


class CellCache:
    """Per-seed failure counts already measured, on disk at ``path`` (rewritten atomically after each
    cell; ``None``: in memory only), keyed by the policy's fingerprint, the condition, the episode
    count and the env seed."""

    def __init__(self, path: Path | None):
        self.path = path
        self.cells = json.loads(path.read_text()) if path is not None and path.is_file() else {}

    @staticmethod
    def key(policy: str, cond: dict, episodes: int, seed: int) -> str:
        return json.dumps([policy, cond, episodes, seed], sort_keys=True)

    def get(self, key: str) -> dict | None:
        return self.cells.get(key)

    def put(self, key: str, value: dict) -> None:
        self.cells[key] = value
        if self.path is not None:
            write_json(self.path, self.cells, indent=0)


def pooled(agents: dict, cond: dict, episodes: int, seed: int, workers: int, cache: CellCache,
           fingerprints: dict, backend: str = "serial", address: str | None = None) -> dict:
    """Failures of each seed's policy under one condition, and the pooled rate with its interval.

    ``agents`` maps a training seed to its policy and ``fingerprints`` to that policy's
    ``policy_fingerprint``; a cell already in ``cache`` is read back instead of run again.
    ``backend``, ``workers``, ``address``: where :func:`failure_rates` runs the episodes (a cell does
    not depend on them)."""
    per_seed = {}
    for s, agent in agents.items():
        key = CellCache.key(fingerprints[s], cond, episodes, seed + 1000 * s)
        cell = cache.get(key)
        if cell is None:
            cluster = {} if address is None else {"address": address}
            r = failure_rates(agent, conditions={"c": cond}, episodes=episodes, episode_steps=10_000,
                              seed=seed + 1000 * s, backend=backend, workers=workers, **cluster)["c"]
            cell = {"failures": r["failures"], "mean_steps": r["mean_steps"], "mean_return": r["mean_return"]}
            cache.put(key, cell)
        per_seed[str(s)] = cell
    failures, n = sum(v["failures"] for v in per_seed.values()), episodes * len(agents)
    return {"failures": failures, "episodes": n, "failure_rate": failures / n,
            "interval95": wilson_interval(failures, n), "per_seed": per_seed}


def grid_search(agents: dict, kind: str, grid: list, episodes: int, seed: int, workers: int, log,
                cache: CellCache, fingerprints: dict, backend: str = "serial", address: str | None = None) -> dict:
    """Coarse grid, then three geometric points inside the bracket of 20 %; keep the closest level
    (``backend``, ``workers``, ``address``: as for :func:`pooled`)."""
    tried = {}

    def run(level):
        if level not in tried:
            t = time.time()
            tried[level] = pooled(agents, condition(kind, level), episodes, seed, workers, cache, fingerprints,
                                  backend, address)
            log(f"  grid {kind} {level:g}: {tried[level]['failures']}/{tried[level]['episodes']} "
                f"({time.time() - t:.0f} s)")
        return tried[level]["failure_rate"]

    for level in grid:
        run(level)
    levels = sorted(tried)
    below = [lv for lv in levels if tried[lv]["failure_rate"] <= TARGET]
    above = [lv for lv in levels if tried[lv]["failure_rate"] > TARGET]
    if below and above and max(below) < min(above):
        lo, hi = max(below), min(above)
        for f in (0.25, 0.5, 0.75):
            run(float(f"{lo * (hi / lo) ** f:.3g}"))
    best = min(tried, key=lambda lv: (abs(tried[lv]["failure_rate"] - TARGET), lv))
    return {"chosen": best, "tried": {f"{lv:g}": tried[lv] for lv in sorted(tried)}}


def summary(record: dict) -> dict:
    """Per condition: pooled failure rate per variant, and seeds where a post-processor failed less."""
    out = {}
    for cname, rows in record["evaluation"].items():
        entry = {v: {"failure_rate": r["failure_rate"], "interval95": r["interval95"], "failures": r["failures"],
                     "episodes": r["episodes"]} for v, r in rows.items()}
        ident = rows["identity"]["per_seed"]
        for v in rows:
            if v != "identity":
                fewer = sum(rows[v]["per_seed"][s]["failures"] < ident[s]["failures"] for s in ident)
                more = sum(rows[v]["per_seed"][s]["failures"] > ident[s]["failures"] for s in ident)
                entry[v]["seeds_fewer_failures_than_identity"] = int(fewer)
                entry[v]["seeds_more_failures_than_identity"] = int(more)
        out[cname] = entry
    return out


def figure(record: dict, path: Path) -> None:
    """Bars of the pooled failure rates with their 95 % intervals, one group per condition."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    conds = list(record["evaluation"])
    fig, ax = plt.subplots(figsize=(8, 3.6))
    width = 0.8 / len(VARIANTS)
    for i, v in enumerate(VARIANTS):
        rates = [record["evaluation"][c][v]["failure_rate"] for c in conds]
        lo = [r - record["evaluation"][c][v]["interval95"][0] for c, r in zip(conds, rates)]
        hi = [record["evaluation"][c][v]["interval95"][1] - r for c, r in zip(conds, rates)]
        ax.bar(np.arange(len(conds)) + (i - 1) * width, rates, width, yerr=[lo, hi], capsize=3, label=v)
    ax.axhline(TARGET, color="k", lw=0.7, ls=":")
    ax.set_xticks(np.arange(len(conds)), conds, fontsize=8)
    ax.set_ylabel("failure rate (10,000 steps)")
    ax.set_title(f"{record.get('env', 'Hopper-v5')}, {len(record['seeds'])} seeds x {record['episodes']} episodes, "
                 "95 % Wilson intervals")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", choices=list(ENVS), default="Hopper-v5")
    parser.add_argument("--seeds", type=int, nargs="+", required=True)
    parser.add_argument("--episodes", type=int, default=25, help="evaluation episodes per seed and condition")
    parser.add_argument("--grid-episodes", type=int, default=10, help="grid-search episodes per seed and level")
    parser.add_argument("--epochs", type=int, nargs=2, metavar=("P", "C"), help="default: the env's (ENVS)")
    parser.add_argument("--min-return", type=float, default=2000.0,
                        help="a seed counts if its identity policy's mean 1,000-step return reaches this")
    add_backend_flags(parser, "serial", "the failure-rate episodes (MuJoCo envs: on the batched stepper's --workers "
                      "threads) and the training runs", workers=1)
    parser.add_argument("--train-only", action="store_true",
                        help="train (or resume) the seeds' variants and stop: no grid search, no record")
    parser.add_argument("--fresh", action="store_true",
                        help="measure every cell again (default: reuse WORK/table44.cache.json, same policy weights only)")
    parser.add_argument("--work", help="default: the env's (ENVS), relative to the working directory")
    parser.add_argument("--out", help="default: results/ch4/table44.json (hopper) or results/ch4/table44-walker2d.json")
    args = parser.parse_args(argv)
    check_backend_flags(args, parser)
    if min(args.episodes, args.grid_episodes) < 1:
        parser.error("--episodes and --grid-episodes must be >= 1")
    profile = ENVS[args.env]
    args.epochs = args.epochs or profile["epochs"]
    args.work = args.work or profile["work"]
    args.out = args.out or profile["out"]
    torch.set_num_threads(1)
    hc = str(Path(sys.executable).with_name("hybridctl"))
    work, out, start = Path(args.work), Path(args.out), time.time()
    out.parent.mkdir(parents=True, exist_ok=True)

    def log(msg):
        print(f"[{time.time() - start:6.0f} s] {msg}", flush=True)

    record = {"command": command_line("hybridctl.reproduce.table44", argv),
              "machine": machine_info(), "episodes": args.episodes, "grid_episodes": args.grid_episodes,
              "episode_steps": 10_000, "push_rate": PUSH_RATE, "env": args.env,
              f"thesis_{args.env.split('-')[0].lower()}": profile["thesis"],
              "training": f"ARS {args.env}, {', '.join(table51.ARS_SETTINGS[args.env])}, {args.epochs[0]} identity "
                          f"epochs (or the seed's extended pretrain: runs/*/pretrain_epochs) + {args.epochs[1]} with the variant's post-processor (thesis 750 + 250, N 50 / b 20)",
              "runs": {}}
    agents = {v: {} for v in VARIANTS}
    prints = {v: {} for v in VARIANTS}   # variant -> seed -> policy fingerprint (the cache's key)
    cache = CellCache(work / "table44.cache.json" if not args.fresh else None)
    for seed in args.seeds:
        pretrain = pretrain_epochs(work, seed, args.epochs[0])
        for variant, (folder, post) in VARIANTS.items():
            final = table51.train_regime(hc, seed, work, folder, "plain", post, pretrain, args.epochs[1], env=args.env,
                                         backend=backend_cli_args(args))
            agent = ARS.load(final, backend="serial")
            evaluation = json.loads((final.parent / "eval.json").read_text())
            progress = json.loads((final / "progress.json").read_text())
            record["runs"][f"s{seed}/{variant}"] = {
                "policy": recorded_path(final),
                "return": evaluation["mean_return"], "pretrain_epochs": pretrain, "epochs": progress["epoch"],
                "env_steps": progress["env_steps"], "train_wall_time_s": progress["wall_time"]}
            agents[variant][seed] = agent
            prints[variant][seed] = policy_fingerprint(final)
        log(f"seed {seed}: " + ", ".join(f"{v} {record['runs'][f's{seed}/{v}']['return']:.0f}" for v in VARIANTS))
    if args.train_only:
        return 0
    record["undisturbed_identity"] = {}
    for s in args.seeds:
        if record["runs"][f"s{s}/identity"]["return"] >= args.min_return:
            record["undisturbed_identity"][str(s)] = pooled({s: agents["identity"][s]}, {}, args.grid_episodes, 1,
                                                            args.workers, cache, prints["identity"], args.backend,
                                                            args.address)["failures"]
    counted = [s for s in args.seeds if record["runs"][f"s{s}/identity"]["return"] >= args.min_return
               and record["undisturbed_identity"][str(s)] <= 0.1 * args.grid_episodes]
    record["seeds"] = counted
    record["seeds_dropped"] = {
        str(s): (f"identity return {record['runs'][f's{s}/identity']['return']:.0f} < {args.min_return:g}"
                 if str(s) not in record["undisturbed_identity"] else
                 f"identity fails {record['undisturbed_identity'][str(s)]}/{args.grid_episodes} undisturbed episodes")
        for s in args.seeds if s not in counted}
    log(f"seeds counted: {counted}; dropped: {record['seeds_dropped']}")
    if len(counted) < 1:
        raise SystemExit(f"no seed's identity policy moves on {args.env}; train more seeds")
    agents = {v: {s: a for s, a in agents[v].items() if s in counted} for v in VARIANTS}

    record["grid"] = {}
    for kind, grid in profile["grids"].items():
        log(f"grid search {kind}")
        record["grid"][kind] = grid_search(agents["identity"], kind, grid, args.grid_episodes, 1, args.workers, log,
                                           cache, prints["identity"], args.backend, args.address)
        write_json(out, record, indent=1)
    conditions = {"none": {}}
    for kind, g in record["grid"].items():
        name = f"push {g['chosen']:g} N at rate {PUSH_RATE:g}" if kind == "push" else \
            f"{kind.replace('_', ' ').replace('obs', 'observation')} {g['chosen']:g}"
        conditions[name] = condition(kind, g["chosen"])
    record["evaluation"] = {}
    for cname, cond in conditions.items():
        record["evaluation"][cname] = {}
        for variant in VARIANTS:
            t = time.time()
            # eval env seeds (2) differ from the grid's (1)
            r = pooled(agents[variant], cond, args.episodes, 2, args.workers, cache, prints[variant], args.backend,
                       args.address)
            record["evaluation"][cname][variant] = {"condition": cond, **r}
            log(f"{cname} {variant}: {r['failures']}/{r['episodes']} "
                f"{[v['failures'] for v in r['per_seed'].values()]} ({time.time() - t:.0f} s)")
        write_json(out, record, indent=1)
    record["table"] = summary(record)
    record["wall_time_s"] = time.time() - start
    write_json(out, record, indent=1)
    figure(record, out.with_suffix(".png"))
    log(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
