"""Training curves from a run's progress rows (progress.csv), for any learner.

Takes plain rows (dicts of numbers) or a progress.csv path, so ``viz`` needs nothing
from ``learn``.

>>> from hybridctl.viz import plot_training_curves
>>> plot_training_curves("runs/ssac-acrobot/progress.csv", "curves.png", title="SSAC on acrobot")
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import numpy as np

__all__ = ["plot_training_curves", "read_progress_rows"]

# (column, axis label); a second column drawn on the same axes, where there is one
SAC_PANELS = (("mean_return", "mean return (last 100 episodes)", None),
              ("success_rate", "success rate (last 100)", None),
              ("q_loss", "Q loss / policy loss", "pi_loss"),
              ("alpha", "alpha", None))


def read_progress_rows(path: str | os.PathLike) -> list[dict]:
    """The rows of a progress.csv as dicts of floats (empty cells -> NaN)."""
    with open(path, newline="") as fh:
        return [{k: float(v) if v not in ("", None) else math.nan for k, v in r.items()} for r in csv.DictReader(fh)]


def plot_training_curves(rows: list[dict] | str | os.PathLike, path: str | os.PathLike, title: str = "",
                         x_key: str = "env_steps") -> Path | None:
    """PNG with mean return, success rate, losses and alpha against ``x_key`` (None if no rows).

    ``rows``: progress rows (dicts) or the path of a progress.csv. The figure is written
    atomically (a temporary file renamed into place).
    """
    if isinstance(rows, (str, os.PathLike)):
        rows = read_progress_rows(rows)
    if not rows:
        return None
    from matplotlib.figure import Figure
    from matplotlib.ticker import EngFormatter

    x = np.array([r[x_key] for r in rows], dtype=float)
    fig = Figure(figsize=(10, 6.5), layout="constrained")
    axes = fig.subplots(2, 2, sharex=True)
    for ax, (key, label, second) in zip(axes.flat, SAC_PANELS):
        ax.plot(x, [r.get(key, math.nan) for r in rows], label=key)
        if second is not None:
            ax.plot(x, [r.get(second, math.nan) for r in rows], label=second)
            ax.set_yscale("symlog")
            ax.legend()
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel(x_key.replace("_", " "))
        ax.xaxis.set_major_formatter(EngFormatter(sep=""))
    if title:
        fig.suptitle(title)
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=90)
    tmp.replace(path)
    return path
