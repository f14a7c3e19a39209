"""Matplotlib figures: one trajectory of the hybrid controller, and balance maps.

Figures are returned open (the caller closes them, ``plt.close(fig)``) and saved
as PNG when a path is given. The Agg backend is selected when no display is
available; library code never calls ``plt.show``.
"""

from __future__ import annotations

import os
import sys
import textwrap
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

# Headless Linux: choose Agg before pyplot is first imported (never switch a running backend).
if ("matplotlib.pyplot" not in sys.modules and sys.platform.startswith("linux")
        and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY")
        and not os.environ.get("MPLBACKEND")):
    matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from .angles import wrap_about_goal  # noqa: E402,F401  (re-exported: its home before the split)

if TYPE_CHECKING:
    from hybridctl.systems import System

__all__ = ["plot_trajectory", "plot_balance_map", "wrap_about_goal"]

# Balance-map colours by outcome: the legend labels the same three.
BALANCE_COLOURS = {"not balanced": "tab:red", "balanced": "black", "diverged": "tab:orange"}


def _array(name: str, value, ndims: tuple[int, ...]) -> np.ndarray:
    if hasattr(value, "detach"):  # torch tensor
        value = value.detach().cpu().numpy()
    array = np.asarray(value, dtype=float)
    if array.ndim not in ndims or array.size == 0:
        raise ValueError(f"{name} must be a non-empty {' or '.join(map(str, ndims))}-D array, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} contains NaN or Inf")
    return array


def _save(fig, path) -> None:
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=100)


def _break_at_wraps(times: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Insert NaN where a wrapped angle jumps by more than pi, so the line is not drawn across."""
    jumps = np.flatnonzero(np.abs(np.diff(values)) > np.pi) + 1
    if jumps.size == 0:
        return times, values
    return np.insert(times, jumps, np.nan), np.insert(values, jumps, np.nan)


def plot_trajectory(times, states, inputs, gate, system: "System",
                    path: str | Path | None = None, title: str | None = None):
    """Figure of one run: a subplot per state, the input(s), and the gate mode.

    ``times`` (T,), ``states`` (T, n_states), ``inputs`` (T, n_actions) or (T,),
    ``gate`` (T,) with 0 = swing-up policy, 1 = LQR. Angles (the spec's
    ``state.angles``) are labelled in rad and drawn wrapped about the goal, in
    [goal - pi, goal + pi) (:func:`wrap_about_goal`; the line breaks where it wraps), with
    the goal as a dotted line. The action limit is drawn as dashed lines. Saves a PNG at
    ``path`` when given; returns the open Figure.
    """
    times = _array("times", times, (1,))
    states = _array("states", states, (2,))
    inputs = _array("inputs", inputs, (1, 2))
    inputs = inputs.reshape(len(inputs), -1)
    gate = _array("gate", gate, (1,))
    T = len(times)
    if states.shape != (T, system.n_states):
        raise ValueError(f"states must have shape ({T}, {system.n_states}) to match times, got {states.shape}")
    if inputs.shape != (T, system.n_actions):
        raise ValueError(f"inputs must have shape ({T}, {system.n_actions}) or ({T},), got {inputs.shape}")
    if gate.shape != (T,) or not np.isin(gate, (0.0, 1.0)).all():
        raise ValueError(f"gate must have shape ({T},) with values in {{0, 1}}, got shape {gate.shape}")

    n_rows = system.n_states + 2
    fig, axes = plt.subplots(n_rows, 1, sharex=True, figsize=(8, 1.6 * n_rows), squeeze=False)
    axes = axes[:, 0]
    shown = wrap_about_goal(states, system)
    n_q = system.n_states // 2
    for i, name in enumerate(system.state_names):
        ax = axes[i]
        is_rate = i >= n_q
        is_angle = (i % n_q) in system.angle_indices
        if is_angle and not is_rate:
            ax.plot(*_break_at_wraps(times, shown[:, i]), lw=1.2)
            goal = float(system.goal[i])
            ax.set_ylim(goal - np.pi - 0.3, goal + np.pi + 0.3)
            for edge in (goal - np.pi, goal + np.pi):   # where the drawn angle wraps
                ax.axhline(edge, color="0.8", lw=0.6, ls=(0, (1, 3)))
            ax.text(0.995, 0.96, "wrapped to goal +- pi", transform=ax.transAxes, ha="right", va="top",
                    fontsize=7, color="0.4")
        else:
            ax.plot(times, states[:, i], lw=1.2)
        ax.set_ylabel(f"{name} [{system.state_unit(i)}]")
        ax.axhline(system.goal[i], color="0.6", lw=0.8, ls=":")
    ax = axes[system.n_states]
    unit = system.action_unit
    for j, name in enumerate(system.action_names):
        ax.plot(times, inputs[:, j], lw=1.0, label=name)
    for k, limit in enumerate((system.action_limit, -system.action_limit)):
        ax.axhline(limit, color="k", ls="--", lw=0.8,
                   label=f"limit +-{system.action_limit:g}{' ' + unit if unit else ''}" if k == 0 else None)
    ax.set_ylabel(", ".join(system.action_names) + (f" [{unit}]" if unit else ""))
    ax.legend(loc="upper right", fontsize=7, ncol=system.n_actions + 1, frameon=False)
    ax = axes[-1]
    ax.step(times, gate, where="post", color="tab:green")
    ax.set_yticks([0, 1], ["swing-up", "LQR"])
    ax.set_ylim(-0.2, 1.2)
    ax.set_ylabel("gate")
    ax.set_xlabel("time [s]")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    fig.suptitle(title or f"{system.name} trajectory")
    fig.tight_layout()
    _save(fig, path)
    return fig


def plot_balance_map(th1_values, th2_values, balanced, path: str | Path | None = None,
                     title: str | None = None, diverged=None,
                     axis_labels: tuple[str, str] = ("initial th1 [rad]", "initial th2 [rad]")):
    """Balance map (thesis Fig. 3.6 style): black where the run from (th1, th2) balanced, red where not.

    ``th1_values`` (N1,) and ``th2_values`` (N2,) are the initial angles (rad) of
    the grid, ``balanced`` an (N1, N2) boolean array indexed [th1, th2]. ``diverged``
    (optional, same shape) marks runs that diverged: drawn orange, and labelled in the
    legend when any did. The legend names each colour (balanced, not balanced[, diverged]);
    the title gets the balanced fraction (wrapped between words, never inside a path).
    ``axis_labels``: the x and y labels (a cart-pole map varies the cart position and the pole
    angle, not two link angles). Saves a PNG at ``path`` when given; returns the open Figure.
    """
    th1 = _array("th1_values", th1_values, (1,))
    th2 = _array("th2_values", th2_values, (1,))
    for name, values in (("th1_values", th1), ("th2_values", th2)):
        if np.any(np.diff(values) <= 0):
            raise ValueError(f"{name} must be strictly increasing")
    balanced = np.asarray(balanced)
    if balanced.shape != (len(th1), len(th2)):
        raise ValueError(f"balanced must have shape ({len(th1)}, {len(th2)}) = (len(th1_values), "
                         f"len(th2_values)), got {balanced.shape}")
    if balanced.dtype != bool and not np.isin(balanced, (0, 1)).all():
        raise ValueError("balanced must be boolean (or 0/1)")
    balanced = balanced.astype(bool)
    fraction = balanced.mean() if balanced.size else 0.0
    outcome = balanced.astype(int)  # 0 not balanced, 1 balanced, 2 diverged
    labels = ["not balanced", "balanced"]
    if diverged is not None:
        diverged = np.asarray(diverged)
        if diverged.shape != balanced.shape:
            raise ValueError(f"diverged must have the shape of balanced {balanced.shape}, got {diverged.shape}")
        diverged = diverged.astype(bool)
        if diverged.any():
            outcome[diverged & ~balanced] = 2
            labels.append("diverged")

    fig, ax = plt.subplots(figsize=(5.5, 5.4))
    cmap = ListedColormap([BALANCE_COLOURS[label] for label in labels])
    ax.pcolormesh(_edges(th1), _edges(th2), outcome.T, cmap=cmap, vmin=-0.5, vmax=len(labels) - 0.5,
                  edgecolors="white", linewidth=0.3 if balanced.size <= 2500 else 0.0)
    handles = [Patch(facecolor=BALANCE_COLOURS[label], edgecolor="0.5", label=label)
               for label in ("balanced", *[lb for lb in labels if lb != "balanced"])]
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=len(handles),
              fontsize=8, frameon=False)
    ax.set_xlabel(axis_labels[0])
    ax.set_ylabel(axis_labels[1])
    ax.set_aspect("equal" if _span(th1) and _span(th2) else "auto")
    heading = title or "balance map"
    full = f"{heading}: {100 * fraction:.1f}% balanced ({balanced.sum()}/{balanced.size})"
    # controller paths make long titles: wrap between words only, so a path is never broken mid-word
    ax.set_title("\n".join(textwrap.wrap(full, 48, break_long_words=False, break_on_hyphens=False)), fontsize=10)
    fig.tight_layout()
    _save(fig, path)
    return fig


def _span(values: np.ndarray) -> float:
    return float(values.max() - values.min()) if values.size else 0.0


def _edges(centres: np.ndarray) -> np.ndarray:
    """Cell edges around grid centres (unit width for a single centre)."""
    if centres.size == 1:
        return np.array([centres[0] - 0.5, centres[0] + 0.5])
    mid = (centres[1:] + centres[:-1]) / 2
    return np.concatenate([[2 * centres[0] - mid[0]], mid, [2 * centres[-1] - mid[-1]]])
