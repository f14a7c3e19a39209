"""Thesis Fig. 7.1 on our acrobot: the return along random parameter directions, and the BPTT
gradient norm against the horizon (why full backpropagation through chaotic dynamics explodes).

    python -m hybridctl.reproduce.fig71     # -> results/ch7/fig71.json, fig71_landscape.png,
                                            #    fig71_gradient_norms.png (about a minute, one core)

The policies are the thesis' GRU at its initialisation (zero weights perturbed by N(0, 0.05^2),
as the author's code), on the Ch. 7 acrobot task of hybridctl.experiments.apg_study (reward
-phi1^2 - phi2^2 in its smooth form, 0.05 s policy steps), from hanging down +- 0.01.
"""

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from hybridctl import io
from hybridctl.experiments.apg_study import task_system
from hybridctl.learn.apg import APG, APGConfig, gradient_norms_by_horizon, returns_along_direction
from hybridctl.reproduce.common import RESULTS, command_line, machine_info
from hybridctl.viz import plot_gradient_norms, plot_return_landscape

SEED = 0
HORIZONS_LANDSCAPE = (25, 50, 100, 200, 400)       # policy steps of 0.05 s: 1.25 s .. 20 s
HORIZONS_GRADIENT = (5, 10, 25, 50, 100, 200, 400)
SCALES = np.linspace(-10.0, 10.0, 41)            # |d| = 1 over ~1,000 weights: s = 10 moves each by ~0.3


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=RESULTS / "ch7",
                        help="folder of fig71.json and the two PNGs (default results/ch7)")
    args = parser.parse_args(argv)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(1)
    start = time.perf_counter()
    system = task_system("acrobot")
    agent = APG(system, APGConfig(method="papg", population=8, elites=1, reward_kind="angle_cosine",
                                  start_noise=0.01, dtype="float64", seed=SEED))
    x0 = agent.starts(4, [SEED, 7])
    gen = torch.Generator().manual_seed(SEED)
    direction = torch.randn(agent.pop.n_params, generator=gen, dtype=torch.float64)
    direction /= direction.norm()
    landscape = {f"T = {h}": returns_along_direction(agent.system, agent.pop, x0, h, agent.substeps, direction,
                                                      SCALES)
                 for h in HORIZONS_LANDSCAPE}
    agent.pop.from_flat(agent.members.to(agent.pop.dtype))
    norms = gradient_norms_by_horizon(agent.system, agent.pop, x0, HORIZONS_GRADIENT, agent.substeps)
    record = {"system": "acrobot", "task": "hybridctl.experiments.apg_study.TASKS['acrobot']", "seed": SEED,
              "policy": agent.pop.describe(), "period_s": agent.period, "starts": x0.tolist(),
              "scales": SCALES.tolist(), "landscape": landscape, "gradient_norms": norms,
              "wall_time_s": time.perf_counter() - start, "command": command_line("hybridctl.reproduce.fig71", argv),
              "machine": machine_info()}
    io.write_json(out / "fig71.json", record)
    plot_return_landscape(SCALES, landscape, out / "fig71_landscape.png",
                          title="acrobot: return along one random direction (GRU at init)")
    plot_gradient_norms(norms, out / "fig71_gradient_norms.png", title="acrobot: BPTT gradient norm, 8 GRU policies")
    for row in norms:
        print(f"T {row['horizon']:4d}: median |grad| {np.median(row['grad_norm']):.3g}")
    print(f"wrote {out / 'fig71.json'} in {record['wall_time_s']:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
