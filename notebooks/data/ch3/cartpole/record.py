"""Record of the shipped SSAC cart-pole (models/policies/ssac-cartpole): Drake from hanging down,
the 21 x 21 balance map of (x, theta) starts at rest (Drake engine) and the torch engine's map.

    .venv/bin/python notebooks/data/ch3/cartpole/record.py   # ~1-2 min on 2 cores
"""
import json
import os
import platform
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch

from hybridctl import drake, experiments, systems
from hybridctl.experiments import balance_map

torch.set_num_threads(1)


def main():
    """Simulate, map and write drake_record.json beside this script."""
    ROOT = Path(__file__).resolve().parents[4]
    HERE = Path(__file__).resolve().parent
    POLICY = ROOT / "models" / "policies" / "ssac-cartpole"
    cartpole = systems.load("cartpole")
    diagram = experiments.build_named_diagram(cartpole, f"ssac:{POLICY}")
    traj = drake.simulate(diagram, np.zeros(4), duration=10.0)
    summary = traj.save(ROOT / "runs" / "ssac-cartpole-drake")
    start = time.perf_counter()
    drake_map = balance_map(cartpole, f"ssac:{POLICY}", grid=21, workers=os.cpu_count(), progress=False)
    drake_map.save(HERE / "balance_map_21")
    drake_wall = time.perf_counter() - start
    torch_map = balance_map(cartpole, f"ssac:{POLICY}", grid=21, engine="torch", progress=False)
    # the whole circle of pole angles and +-1 m of cart (the training starts were theta in [-pi, pi], x in +-0.5 m)
    start = time.perf_counter()
    wide_map = balance_map(cartpole, f"ssac:{POLICY}", grid=21, ranges=((-1.0, 1.0), (-np.pi, np.pi)),
                           workers=os.cpu_count(), progress=False)
    wide_wall = time.perf_counter() - start
    wide_map.save(HERE / "balance_map_21_wide")
    record = {
        "policy": "models/policies/ssac-cartpole",
        "from_hanging_down_drake": {"balanced": bool(traj.balanced), "return": summary["return"],
                                    "first_balance_time": summary["first_balance_time"],
                                    "final_state": np.asarray(traj.x[-1]).round(4).tolist()},
        "balance_map_21_drake": {"balanced_fraction": drake_map.fraction, "wall_time_s": drake_wall,
                                 "x_range": [-0.5, 0.5], "theta_range": [-0.3, 0.3],
                                 "folder": "notebooks/data/ch3/cartpole/balance_map_21"},
        "balance_map_21_wide_drake": {"balanced_fraction": wide_map.fraction, "wall_time_s": wide_wall,
                                      "x_range": [-1.0, 1.0], "theta_range": [-np.pi, np.pi],
                                      "folder": "notebooks/data/ch3/cartpole/balance_map_21_wide"},
        "balance_map_21_torch": {"balanced_fraction": torch_map.fraction, "wall_time_s": torch_map.wall_time},
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "python": sys.version.split()[0],
                    "torch": torch.__version__},
        "date": time.strftime("%Y-%m-%d %H:%M:%S %z"),
    }
    (HERE / "drake_record.json").write_text(json.dumps(record, indent=1))
    print(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
