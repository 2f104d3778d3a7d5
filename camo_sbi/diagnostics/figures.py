"""Posterior figures on plain arrays, in the shared style: limits per method, corner plot, predictive reaches.

Each function takes numpy arrays (no arviz objects), so the report and notebooks can draw
any method's output, and returns a pyplot-free `matplotlib.figure.Figure`:

* `plot_limits`: a forest of every limit per method (94% HDI, quartiles, median); a
  method with a single draw (a baseline's point estimate) is a marker, never a panel;
  the truth a black bar.
* `plot_corner`: a corner (pair) plot of a few limits, several methods overlaid in their
  colours, truth lines in black, point estimates as markers.
* `plot_predictive`: observed end-effector paths against posterior-predictive paths,
  one column per reach, top view (x-y) and side view (x-z).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from camo_sbi.diagnostics.style import figure_legend, method_order, method_style, new_figure

__all__ = ["hdi", "plot_corner", "plot_limits", "plot_predictive"]

BOUNDS = ("lower", "upper")


def hdi(x: np.ndarray, prob: float = 0.94) -> tuple[float, float]:
    """Shortest interval holding ``prob`` of the 1-D draws ``x``."""
    s = np.sort(np.asarray(x, dtype=float).reshape(-1))
    m = s.size
    if m == 0:
        raise ValueError("x: no draws")
    k = max(1, int(np.floor(prob * m)))
    if k >= m:
        return float(s[0]), float(s[-1])
    i = int(np.argmin(s[k:] - s[: m - k]))
    return float(s[i]), float(s[i + k])


def _check_draws(draws: Mapping[str, np.ndarray], n: int | None = None) -> dict[str, np.ndarray]:
    if not isinstance(draws, Mapping) or not draws:
        raise TypeError("draws: expected a non-empty {method: (S, n, 2) array} mapping")
    out = {}
    for k, v in draws.items():
        a = np.asarray(v, dtype=float)
        if a.ndim != 3 or a.shape[2] != 2 or (n is not None and a.shape[1] != n):
            raise ValueError(f"draws: {k!r} has shape {a.shape}, expected (S, {n or 'n'}, 2)")
        out[str(k)] = a
    return out


def plot_limits(draws: Mapping[str, np.ndarray], joints: Sequence[str], *, truth: np.ndarray | None = None,
                hdi_prob: float = 0.94, units: str = "rad", title: str = "") -> Figure:
    """Every (joint, bound) as a row group, one line per method: HDI (thin), quartiles (thick),
    median (dot); single-draw methods as their marker only; truth as a black bar.

    draws: {method: (S, n, 2)}; joints: n names; truth: (n, 2) or None.
    """
    joints = [str(j) for j in joints]
    d = _check_draws(draws, len(joints))
    order = method_order(d)
    rows = [(j, b) for j in joints for b in range(2)]
    per = len(order) + 1
    fig, axes = new_figure(1, 1, figsize=(9.5, 1.2 + 0.17 * per * len(rows)))
    ax = axes[0, 0]
    yticks, ylabels = [], []
    for r, (j, b) in enumerate(rows):
        base = -r * per
        yticks.append(base - (len(order) - 1) / 2)
        ylabels.append(f"{j}, {BOUNDS[b]}")
        if r % 2:
            ax.axhspan(base + 0.5, base - per + 0.5, color="0.96", lw=0, zorder=0)
        for i, m in enumerate(order):
            x = d[m][:, joints.index(j), b]
            y = base - i
            st = method_style(m)
            if np.ptp(x) == 0:
                ax.plot([x[0]], [y], linestyle="none", marker=st.marker, ms=6, color=st.color,
                        mec="white" if not st.baseline else st.color, label=m)
                continue
            lo, hi = hdi(x, hdi_prob)
            q1, q2, q3 = np.quantile(x, [0.25, 0.5, 0.75])
            ax.plot([lo, hi], [y, y], color=st.color, lw=1.2, label=m)
            ax.plot([q1, q3], [y, y], color=st.color, lw=3.2, solid_capstyle="butt")
            ax.plot([q2], [y], color=st.color, marker="o", ms=3.5, mec="white", mew=0.5)
        if truth is not None:
            t = float(np.asarray(truth)[joints.index(j), b])
            ax.plot([t, t], [base + 0.45, base - len(order) + 0.55], color="k", lw=1.6, label="truth")
    ax.set_yticks(yticks, ylabels, fontsize=8)
    ax.set_ylim(-len(rows) * per + 0.5, 0.5 + 0.5)
    ax.set_xlabel(f"limit [{units}]")
    ax.grid(alpha=0.3, axis="x")
    ax.set_title(title or f"joint limits per method: {hdi_prob:.0%} HDI (thin), quartiles (thick), median (dot)",
                 fontsize=10)
    figure_legend(fig, ax, title="method\n(a marker alone:\na point estimate)")
    return fig


def plot_corner(draws: Mapping[str, np.ndarray], labels: Sequence[str], *, truth: Sequence[float] | None = None,
                points: Mapping[str, Sequence[float]] | None = None, units: str = "rad",
                max_scatter: int = 400) -> Figure:
    """Corner plot of k limits: histograms on the diagonal, scatter below it, methods overlaid.

    draws: {method: (S, k) draws of the k limits named by ``labels``}; truth: (k,) or None;
    points: {method: (k,) point estimate} drawn as markers (baselines).
    """
    labels = [str(v) for v in labels]
    k = len(labels)
    if k < 2:
        raise ValueError("labels: a corner plot needs at least two limits")
    d = {}
    for m, v in draws.items():
        a = np.asarray(v, dtype=float)
        if a.ndim != 2 or a.shape[1] != k:
            raise ValueError(f"draws: {m!r} has shape {a.shape}, expected (S, {k})")
        d[str(m)] = a
    pts = {str(m): np.asarray(v, dtype=float).reshape(k) for m, v in (points or {}).items()}
    fig = Figure(figsize=(2.3 * k + 0.4, 2.1 * k + 0.4), layout="constrained")
    axes = np.asarray(fig.subplots(k, k, squeeze=False))
    everything = [a for a in d.values()] + [p[None] for p in pts.values()]
    if truth is not None:
        everything.append(np.asarray(truth, dtype=float).reshape(1, k))
    allv = np.concatenate(everything)
    lo, hi = np.nanmin(allv, axis=0), np.nanmax(allv, axis=0)
    pad = 0.05 * np.where(hi > lo, hi - lo, 1.0)
    lims = np.stack([lo - pad, hi + pad], axis=1)
    for r in range(k):
        for c in range(k):
            ax = axes[r, c]
            if c > r:
                ax.set_visible(False)
                continue
            for m in method_order(d):
                st = method_style(m)
                a = d[m]
                if r == c:
                    ax.hist(a[:, c], bins=30, range=tuple(lims[c]), density=True, histtype="step",
                            color=st.color, lw=1.3, label=m)
                else:
                    step = max(1, a.shape[0] // max_scatter)
                    ax.scatter(a[::step, c], a[::step, r], s=4, alpha=0.35, color=st.color, lw=0, label=m)
            for m in method_order(pts):
                st = method_style(m)
                if r == c:
                    ax.axvline(pts[m][c], color=st.color, ls=st.linestyle, lw=1.2, label=m)
                else:
                    ax.plot(pts[m][c], pts[m][r], marker=st.marker, color=st.color, ms=7, ls="none",
                            mec="white", label=m)
            if truth is not None:
                t = np.asarray(truth, dtype=float).reshape(k)
                ax.axvline(t[c], color="k", lw=1, label="truth")
                if r != c:
                    ax.axhline(t[r], color="k", lw=1)
                    ax.plot(t[c], t[r], marker="+", color="k", ms=9, mew=1.5)
            ax.set_xlim(*lims[c])
            if r != c:
                ax.set_ylim(*lims[r])
            else:
                ax.set_yticks([])
            ax.tick_params(labelsize=7)
            if r == k - 1:
                ax.set_xlabel(f"{labels[c]} [{units}]", fontsize=8)
            else:
                ax.set_xticklabels([])
            if c == 0 and r > 0:
                ax.set_ylabel(f"{labels[r]} [{units}]", fontsize=8)
            elif c > 0:
                ax.set_yticklabels([])
    figure_legend(fig, axes, title="diagonal: histogram\nbelow: draws\nblack: truth", loc="upper right")
    return fig


def plot_predictive(observed: Sequence[np.ndarray], predicted: Mapping[str, Sequence[np.ndarray]], *,
                    goals: np.ndarray | None = None, max_reaches: int = 4, title: str = "") -> Figure:
    """Observed end-effector paths (black) against posterior-predictive ones (method colour).

    observed: one (L, 3) path per reach; predicted: {method: one list per reach of (L_i, 3)
    paths (the draws)}; goals: (m, 3) or None. Columns: reaches (at most ``max_reaches``);
    rows: top view (x-y) and side view (x-z), metres, equal aspect.
    """
    m = min(len(observed), max_reaches)
    if m < 1:
        raise ValueError("observed: no reach to draw")
    fig, axes = new_figure(2, m, panel=(3.3, 3.0))
    views = (("x", "y", 0, 1), ("x", "z", 0, 2))
    for i in range(m):
        obs = np.asarray(observed[i], dtype=float)
        for r, (xl, yl, a, b) in enumerate(views):
            ax = axes[r, i]
            for meth in method_order(predicted):
                st = method_style(meth)
                paths = predicted[meth][i]
                for p in paths:
                    p = np.asarray(p, dtype=float)
                    ax.plot(p[:, a], p[:, b], color=st.color, lw=0.7, alpha=max(0.08, min(0.5, 8 / len(paths))))
                ax.plot([], [], color=st.color, lw=1.5, label=f"{meth}: {len(paths)} posterior draws")
            ax.plot(obs[:, a], obs[:, b], color="k", lw=2)
            ax.plot(obs[0, a], obs[0, b], "o", color="k", ms=4)
            if goals is not None:
                ax.plot(goals[i, a], goals[i, b], "*", color="k", ms=11, mfc="white")
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_xlabel(f"{xl} [m]", fontsize=8)
            ax.set_ylabel(f"{yl} [m]", fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
            if r == 0:
                ax.set_title(f"reach {i + 1}: top view" if i == 0 else f"reach {i + 1}", fontsize=9)
            elif i == 0:
                ax.set_title("side view", fontsize=9)
    handles = [Line2D([], [], color="k", lw=2, label="observed reach"),
               Line2D([], [], color="k", marker="o", ls="none", ms=4, label="start"),
               Line2D([], [], color="k", marker="*", ls="none", ms=10, mfc="white", label="goal")]
    figure_legend(fig, axes)
    fig.legend(handles=handles, loc="outside lower right", fontsize=8, frameon=False, ncols=3)
    if title:
        fig.suptitle(title, fontsize=10)
    return fig
