"""Views of reachable-state meshes and their Markov chains (thesis Figs. 5.4-5.6, Tables 5.1-5.2).

>>> viz.plot_transition_sparsity(mesh.transition_matrix(), path="sparsity.png")     # Fig. 5.4
>>> viz.plot_cumulative_mass(mesh.transition_matrix(), path="mass.png")             # Fig. 5.5
>>> viz.plot_mesh_states(mesh, path="states.png")                                   # Fig. 5.6
>>> viz.plot_mesh_sizes(mesh_sizes(...), path="sizes.png")                          # Table 5.1/5.2
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def _figure(ax, size=(5, 4)):
    import matplotlib.pyplot as plt

    if ax is not None:
        return ax.figure, ax, False
    fig, ax = plt.subplots(figsize=size, constrained_layout=True)
    return fig, ax, True


def _finish(fig, own: bool, path):
    import matplotlib.pyplot as plt

    if path is not None:
        fig.savefig(path, dpi=120)
    if own:
        plt.close(fig)
    return fig


def plot_transition_sparsity(T, ax=None, path=None, max_points: int = 2_000_000):
    """Every non-zero T[i, j] as an equal dot (Fig. 5.4); a random subset above ``max_points``."""
    T = sp.coo_matrix(T)
    fig, ax, own = _figure(ax)
    rows, cols = T.row, T.col
    if rows.size > max_points:
        keep = np.random.default_rng(0).choice(rows.size, max_points, replace=False)
        rows, cols = rows[keep], cols[keep]
    ax.scatter(cols, rows, s=max(0.05, min(4.0, 2e4 / max(rows.size, 1))), c="k", marker=".", linewidths=0)
    ax.set(xlim=(-0.5, T.shape[1] - 0.5), ylim=(T.shape[0] - 0.5, -0.5), xlabel="next state j", ylabel="state i",
           title=f"transition matrix: {T.shape[0]} states, {T.nnz} non-zeros")
    return _finish(fig, own, path)


def plot_cumulative_mass(T, failure: int = 0, ax=None, path=None, label=None):
    """Fraction of states against the fraction of transitions they receive (Fig. 5.5)."""
    from ..analysis.markov import cumulative_transition_mass

    x, y = cumulative_transition_mass(T, failure)
    fig, ax, own = _figure(ax)
    at20 = float(np.interp(0.2, x, y))
    ax.plot(100 * x, 100 * y, label=label or f"20 % of states receive {100 * at20:.0f} % of transitions")
    ax.set(xlabel="% of mesh states (most visited first)", ylabel="% of transition mass", xlim=(0, 100), ylim=(0, 101))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    return _finish(fig, own, path)


def plot_mesh_states(mesh, highlight=None, ax=None, path=None, share: float = 0.99):
    """Mesh states, the ones behind ``share`` of all failures in red (Fig. 5.6).

    States of two or more dimensions are projected on their first two principal components;
    one-dimensional states are drawn against their one-step failure probability.
    """
    from ..analysis.reachable import failure_states

    red = failure_states(mesh, share) if highlight is None else np.asarray(highlight, dtype=np.int64)
    fig, ax, own = _figure(ax)
    x = mesh.representatives
    mask = np.zeros(mesh.size, dtype=bool)
    mask[red] = True
    if x.shape[1] == 1:
        xs, ys = x[:, 0], mesh.failure_probability()
        ax.set(xlabel=(mesh.settings.get("state_names") or ["state"])[0], ylabel="one-step failure probability")
    else:
        centred = x - x.mean(axis=0)
        _, sv, vt = np.linalg.svd(centred / np.where(x.std(axis=0) > 0, x.std(axis=0), 1.0), full_matrices=False)
        proj = centred / np.where(x.std(axis=0) > 0, x.std(axis=0), 1.0) @ vt[:2].T
        xs, ys = proj[:, 0], proj[:, 1]
        explained = (sv[:2] ** 2).sum() / (sv ** 2).sum()
        ax.set(xlabel="PC 1", ylabel="PC 2", title=f"mesh states on 2 principal components ({explained:.0%} of variance)")
    ax.scatter(xs[~mask], ys[~mask], s=4, c="tab:blue", label="mesh states")
    ax.scatter(xs[mask], ys[mask], s=6, c="tab:red", label=f"{mask.sum()} states with {share:.0%} of failures")
    ax.legend(fontsize=8)
    return _finish(fig, own, path)


def plot_mesh_sizes(rows: list[dict], ax=None, path=None, label=None):
    """Mesh size against box size (log-log), with the reachable-set dimension (Tables 5.1-5.2)."""
    from ..analysis.reachable import reachable_dimension

    fig, ax, own = _figure(ax)
    d = np.array([r["box_size"] for r in rows])
    m = np.array([r["states"] for r in rows])
    dim = reachable_dimension(rows)
    ax.loglog(d, m, "o-", label=label or f"dimension {dim:.2f}")
    ax.set(xlabel="box size d", ylabel="mesh states")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return _finish(fig, own, path)


def plot_mfpt_vs_roughness(record: dict, ax=None, path=None):
    """MFPT (log axis) against slope std in degrees: the refined mesh as a line, Monte Carlo as points
    with 95 % error bars, and the regimes shaded: where Monte Carlo ran, where the mesh is the only
    estimate, where the chain never fails in float64 (drawn as arrows at the top).

    ``record``: what :func:`hybridctl.experiments.mfpt_vs_roughness` returns (or its JSON).
    """
    rows = sorted(record["rows"], key=lambda r: r["slope_std"])
    fig, ax, own = _figure(ax, size=(6, 4))
    deg = np.array([r["slope_std_deg"] for r in rows])
    mesh = np.array([np.inf if r.get("never_fails") else np.nan if r["mesh_mfpt"] is None else r["mesh_mfpt"]
                     for r in rows], dtype=float)      # JSON writes infinity as null, with never_fails true
    finite = np.isfinite(mesh)
    ax.semilogy(deg[finite], mesh[finite], "o-", color="tab:blue", label="refined mesh")
    mc = [r for r in rows if r["monte_carlo"]["status"] == "run"]
    if mc:
        x = np.array([r["slope_std_deg"] for r in mc])
        y = np.array([r["monte_carlo"]["mean_steps_to_failure"] for r in mc])
        lo = np.array([r["monte_carlo"]["interval95"][0] for r in mc])
        hi = np.array([r["monte_carlo"]["interval95"][1] for r in mc])
        runs = mc[0]["monte_carlo"]["episodes"]
        ax.errorbar(x, y, yerr=[y - lo, hi - y], fmt="s", ms=4, capsize=3, color="tab:orange",
                    label=f"Monte Carlo, {runs:,} runs, 95 %")
    top = np.nanmax(mesh[finite]) * 10 if finite.any() else 1e9
    never = deg[np.isinf(mesh)]
    if never.size:
        ax.scatter(never, np.full(never.size, top), marker="^", color="k", label="never fails (float64)")
    mids = 0.5 * (deg[1:] + deg[:-1])       # each sigma's band reaches half way to its neighbours
    first, last = (deg[0] - (mids[0] - deg[0]), deg[-1] + (deg[-1] - mids[-1])) if deg.size > 1 else \
        (deg[0] - 0.5, deg[0] + 0.5)
    edges = np.concatenate([[first], mids, [last]])
    shades = {"run": ("tab:green", "Monte Carlo affordable"), "skipped": ("tab:red", "mesh only"),
              "never": ("0.6", "chain never fails")}
    shown = set()
    for k, (r, m) in enumerate(zip(rows, mesh)):
        kind = "never" if np.isposinf(m) else r["monte_carlo"]["status"] if np.isfinite(m) else None
        if kind is None:
            continue
        colour, text = shades[kind]
        ax.axvspan(edges[k], edges[k + 1], color=colour, alpha=0.12, lw=0, label=None if kind in shown else text)
        shown.add(kind)
    ax.set(xlabel="slope std sigma (degrees)", ylabel="mean first-passage time (steps)",
           title=f"{record.get('map', 'mesh')}, mean slope {record.get('slope_mean', float('nan')):g} rad, box "
                 f"{record.get('box_size', float('nan')):g}")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper right")
    return _finish(fig, own, path)
