"""Figures of fine-tuning (thesis Ch. 6): returns before and after, failure rates, the training curve."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_finetune_report(before: dict, after: dict, history: list[dict], path: str | Path | None = None,
                         title: str = ""):
    """Three panels: histogram of the deterministic episode returns before / after, early-termination
    rate with 95 % Wilson intervals, and the mean training return per update. Writes ``path``
    (PNG) when given; returns the figure."""
    import matplotlib
    if path is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    r0, r1 = np.asarray(before["returns"], float), np.asarray(after["returns"], float)
    both = np.concatenate([r0, r1]) if r0.size + r1.size else np.zeros(1)
    bins = np.linspace(both.min(), both.max() + 1e-9, 25)
    axes[0].hist(r0, bins=bins, alpha=0.6, label=f"before {r0.mean():.1f} ± {r0.std():.1f}")
    axes[0].hist(r1, bins=bins, alpha=0.6, label=f"after {r1.mean():.1f} ± {r1.std():.1f}")
    axes[0].set(xlabel="episode return (deterministic)", ylabel="episodes", title="returns")
    axes[0].legend(fontsize=8)
    rates = [before.get("failure_rate", 0.0), after.get("failure_rate", 0.0)]
    intervals = [before.get("failure_interval", (0, 0)), after.get("failure_interval", (0, 0))]
    err = np.array([[r - lo for r, (lo, hi) in zip(rates, intervals)], [hi - r for r, (lo, hi) in zip(rates, intervals)]])
    axes[1].bar(["before", "after"], np.array(rates) * 100, yerr=np.maximum(err, 0) * 100, capsize=6,
                color=["C0", "C1"])
    axes[1].set(ylabel="early terminations (%)", title=f"failure rate ({before.get('episodes', '?')} episodes, 95 % CI)")
    if history:
        u = [h["update"] for h in history]
        axes[2].plot(u, [h["mean_raw_return"] for h in history], label="mean raw return")
        if any(h.get("mean_return") != h.get("mean_raw_return") for h in history):
            axes[2].plot(u, [h["mean_return"] for h in history], label="training return (with D)")
        axes[2].legend(fontsize=8)
    axes[2].set(xlabel="update", ylabel="return of the 2n perturbed policies", title="training")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=110)
        plt.close(fig)
    return fig
