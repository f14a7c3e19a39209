"""Figures of thesis Ch. 7 from plain records (lists and dicts of numbers), so ``viz`` needs nothing
from ``learn``: Fig. 7.1 (the return along random parameter directions; the gradient norm against
the horizon) and the method comparison of Tables 7.1 / 7.2 (return and stabilisation per method).

>>> from hybridctl.viz import plot_gradient_norms, plot_return_landscape, plot_method_comparison
>>> plot_gradient_norms(record["gradient_norms"], "fig71b.png", title="acrobot")
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["plot_return_landscape", "plot_gradient_norms", "plot_method_comparison", "plot_return_curves"]


def _save(fig, path: str | os.PathLike) -> Path:
    """Write ``fig`` atomically (a temporary PNG renamed into place) and close it."""
    import matplotlib.pyplot as plt

    from ..io import atomic_write

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        atomic_write(path, lambda f: fig.savefig(f, dpi=110, format="png"))
    finally:
        plt.close(fig)
    return path


def plot_return_landscape(scales, curves: dict, path: str | os.PathLike, title: str = "") -> Path:
    """Fig. 7.1 (left): the mean return R(theta + s d) against s, one line per label in ``curves``
    (e.g. one per horizon or per random direction d). ``curves``: {label: [return per scale]}."""
    import matplotlib.pyplot as plt

    if not curves:
        raise ValueError("curves must hold at least one {label: returns} entry")
    s = np.asarray(scales, dtype=float)
    fig, ax = plt.subplots(figsize=(6, 4))
    for label, values in curves.items():
        values = np.asarray(values, dtype=float)
        if values.shape != s.shape:
            raise ValueError(f"curve {label!r} has {values.size} values for {s.size} scales")
        ax.plot(s, values, lw=1.2, label=str(label))
    ax.set_xlabel("step s along a random unit direction d")
    ax.set_ylabel("mean return R(theta + s d)")
    ax.set_title(title or "return along random parameter directions")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return _save(fig, path)


def plot_gradient_norms(rows: list[dict], path: str | os.PathLike, title: str = "") -> Path:
    """Fig. 7.1 (right): the APG gradient norm against the horizon, log scale; ``rows`` as
    :func:`hybridctl.learn.apg.gradient_norms_by_horizon` returns them ({"horizon", "grad_norm": [K]}):
    the median over members with the range as a band."""
    import matplotlib.pyplot as plt

    if not rows:
        raise ValueError("rows must hold at least one {horizon, grad_norm} entry")
    horizon = np.array([r["horizon"] for r in rows], dtype=float)
    norms = [np.asarray(r["grad_norm"], dtype=float) for r in rows]
    median = np.array([np.nanmedian(n) for n in norms])
    low, high = np.array([np.nanmin(n) for n in norms]), np.array([np.nanmax(n) for n in norms])
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.fill_between(horizon, low, high, alpha=0.25, label="range over policies")
    ax.plot(horizon, median, "o-", label="median")
    ax.set_yscale("log")
    ax.set_xlabel("horizon T (policy steps)")
    ax.set_ylabel("|grad_theta R| (BPTT)")
    ax.set_title(title or "gradient norm against horizon")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    return _save(fig, path)


def plot_method_comparison(summary: list[dict], path: str | os.PathLike, title: str = "") -> Path:
    """Tables 7.1 / 7.2 as a figure: per system a panel with, per method, the held-out return (mean
    +- std over seeds) and the stabilisation rate printed above the bar. ``summary``: rows with
    system, method, return_mean, return_std, stabilised, seeds (``apg_study.summarize``)."""
    import matplotlib.pyplot as plt

    if not summary:
        raise ValueError("summary must hold at least one row")
    systems = list(dict.fromkeys(r["system"] for r in summary))
    fig, axes = plt.subplots(1, len(systems), figsize=(4.2 * len(systems), 3.8), squeeze=False)
    for ax, name in zip(axes[0], systems):
        rows = [r for r in summary if r["system"] == name]
        x = np.arange(len(rows))
        ax.bar(x, [r["return_mean"] for r in rows], yerr=[r["return_std"] for r in rows], color="tab:blue",
               alpha=0.75, capsize=3)
        for i, r in enumerate(rows):
            ax.annotate(f"{r['stabilised']:.0%}", (i, r["return_mean"]), textcoords="offset points",
                        xytext=(0, 4), ha="center", fontsize=8)
        ax.set_xticks(x, [r["method"] for r in rows], rotation=30)
        ax.set_title(f"{name} ({rows[0]['seeds']} seeds; % stabilised)", fontsize=9)
        ax.set_ylabel("held-out return")
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle(title or "Ch. 7 methods on the same task", fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


def plot_return_curves(runs: dict, path: str | os.PathLike, title: str = "") -> Path:
    """Training curves of APG-family runs side by side against interactions: the epoch's mean return
    (CE-APG, CEM: of the CEM mean's population; APG, PAPG: of the members), the best member's
    training return (the author's metric) and the median gradient norm (log scale). ``runs``: label
    -> progress rows (dicts with env_steps, mean_return, best_return, grad_norm: an APG run's
    progress.csv read by :func:`~hybridctl.viz.training.read_progress_rows`)."""
    import matplotlib.pyplot as plt

    runs = {label: rows for label, rows in runs.items() if rows}
    if not runs:
        raise ValueError("runs must hold at least one run with progress rows")
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    panels = (("mean_return", "mean training return", "linear"), ("best_return", "best member's return", "linear"),
              ("grad_norm", "median gradient norm", "log"))
    for ax, (key, label, scale) in zip(axes, panels):
        for name, rows in runs.items():
            ax.plot([r["env_steps"] for r in rows], [r.get(key, np.nan) for r in rows], label=name)
        ax.set_yscale(scale)
        ax.set_xlabel("interactions (K x N x T x iterations)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title or "APG-family runs", fontsize=10)
    fig.tight_layout()
    return _save(fig, path)
