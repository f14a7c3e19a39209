"""Figures of fine-tuning (thesis Ch. 6): returns before and after, failure rates, the training curve."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _finish(fig, path: str | Path | None):
    """Lay the figure out; write it to ``path`` (PNG) and close it when a path is given."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=110)
        plt.close(fig)
    return fig


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
    return _finish(fig, path)


def plot_return_table(rows: list[dict], path: str | Path | None = None, title: str = "returns before and after"):
    """Table 6.1 as a picture: per agent, mean ± std of the deterministic returns before fine-tuning,
    after, and (where recorded) after training on with its own algorithm. ``rows``: dicts with
    ``label``, ``before`` / ``after`` / optional ``continued`` (each with mean_return, std_return).
    Returns are scaled per agent by |before mean| so agents of different envs share one axis."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(max(6, 1.1 * len(rows) + 2), 3.8))
    width = 0.27
    for k, (key, colour) in enumerate((("before", "C0"), ("after", "C1"), ("continued", "C2"))):
        xs, ys, es = [], [], []
        for i, row in enumerate(rows):
            if row.get(key) is None:
                continue
            scale = max(abs(row["before"]["mean_return"]), 1e-9)
            xs.append(i + (k - 1) * width)
            ys.append(row[key]["mean_return"] / scale)
            es.append(row[key]["std_return"] / scale)
        if xs:
            ax.bar(xs, ys, width, yerr=es, capsize=3, color=colour,
                   label={"before": "pretrained", "after": "fine-tuned", "continued": "own algorithm, more steps"}[key])
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xticks(range(len(rows)), [r["label"] for r in rows], rotation=30, ha="right", fontsize=8)
    ax.set(ylabel="return / |pretrained mean|", title=title)
    ax.legend(fontsize=8)
    return _finish(fig, path)


def plot_failure_table(rows: list[dict], path: str | Path | None = None,
                       title: str = "early terminations (95 % Wilson intervals)"):
    """Table 6.2 as a picture: early-termination rate before / after per agent with 95 % intervals.
    ``rows``: dicts with ``label`` and ``before`` / ``after`` evaluations (failure_rate, failure_interval)."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(max(5, 1.2 * len(rows) + 2), 3.6))
    for k, (key, colour) in enumerate((("before", "C0"), ("after", "C1"))):
        rates = np.array([100 * r[key]["failure_rate"] for r in rows])
        lo = np.array([100 * r[key]["failure_interval"][0] for r in rows])
        hi = np.array([100 * r[key]["failure_interval"][1] for r in rows])
        ax.bar(np.arange(len(rows)) + (k - 0.5) * 0.38, rates, 0.38,
               yerr=np.maximum([rates - lo, hi - rates], 0), capsize=4,   # rounding can put lo a hair above 0
               color=colour, label=key)
    ax.set_xticks(range(len(rows)), [r["label"] for r in rows], fontsize=8)
    ax.set(ylabel="early terminations (%)", title=title)
    ax.legend(fontsize=8)
    return _finish(fig, path)


def plot_dimension_table(rows: list[dict], path: str | Path | None = None,
                         title: str = "mesh dimension and return, dimension reward (eq. 6.1 / 6.2)"):
    """Table 6.3 as a picture: mean mesh dimension (left) and return (right, scaled by |before|)
    before / after fine-tuning with the dimension reward. ``rows`` as :func:`plot_return_table`
    with ``mean_dimension`` / ``std_dimension`` in the evaluations."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(max(8, 2.2 * len(rows) + 3), 3.6))
    x = np.arange(len(rows))
    for k, (key, colour) in enumerate((("before", "C0"), ("after", "C1"))):
        axes[0].bar(x + (k - 0.5) * 0.38, [r[key]["mean_dimension"] for r in rows], 0.38,
                    yerr=[r[key].get("std_dimension") or 0 for r in rows], capsize=4, color=colour, label=key)
        scale = [max(abs(r["before"]["mean_return"]), 1e-9) for r in rows]
        axes[1].bar(x + (k - 0.5) * 0.38, [r[key]["mean_return"] / s for r, s in zip(rows, scale)], 0.38,
                    yerr=[r[key]["std_return"] / s for r, s in zip(rows, scale)], capsize=4, color=colour, label=key)
    for ax, label in zip(axes, ("mesh dimension (mean of lower, upper)", "return / |before mean|")):
        ax.set_xticks(x, [r["label"] for r in rows], fontsize=8)
        ax.set(ylabel=label)
        ax.legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    return _finish(fig, path)
