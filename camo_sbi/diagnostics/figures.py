"""The one hand-drawn posterior figure, on plain arrays, in the shared style.

* `plot_predictive`: observed end-effector paths against posterior-predictive paths,
  one column per reach, top view (x-y) and side view (x-z). Hand-drawn because arviz's
  posterior-predictive plots (``plot_ppc``) draw distributions of scalar observations,
  not paths in space.

* `plot_limits`: the inferred limits a clinician reads first: per joint the model's range
  (grey bar), the recorded range (black), each method's estimate and 90% interval in degrees,
  bounds no reach exercised drawn hollow ("not exercised" in the legend).

The forest and corner plots of the limits are arviz's (`camo_sbi.diagnostics.arviz_io`:
``plot_forest``, ``plot_corner`` over ``arviz.plot_pair``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from camo_sbi.diagnostics.plot_primitives import figure_legend
from camo_sbi.diagnostics.style import method_order, method_style, new_figure, paper_figure

__all__ = ["plot_limits", "plot_predictive", "plot_speed"]


@paper_figure
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
    fig, axes = new_figure(2, m, width="double" if m > 1 else "single", aspect=0.9, legend_rows=3)
    views = (("x", "y", 0, 1), ("x", "z", 0, 2))
    for i in range(m):
        obs = np.asarray(observed[i], dtype=float)
        for r, (xl, yl, a, b) in enumerate(views):
            ax = axes[r, i]
            for meth in method_order(predicted):
                st = method_style(meth)
                paths = predicted[meth][i]
                # the draws as one collection (one artist per panel and method, not one line per draw)
                segs = [np.asarray(p, dtype=float)[:, [a, b]] for p in paths]
                ax.add_collection(LineCollection(segs, colors=st.color, linewidths=0.7,
                                                 alpha=max(0.08, min(0.5, 8 / max(1, len(paths)))),
                                                 gid=f"draws:{meth}"), autolim=True)
                ax.plot([], [], color=st.color, lw=1.5, label=f"{meth}: {len(paths)} posterior draws")
            ax.plot(obs[:, a], obs[:, b], color="k", lw=2)
            ax.plot(obs[0, a], obs[0, b], "o", color="k", ms=4)
            if goals is not None:
                ax.plot(goals[i, a], goals[i, b], "*", color="k", ms=11, mfc="white")
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_xlabel(f"{xl} [m]")
            ax.set_ylabel(f"{yl} [m]")
            ax.grid(alpha=0.3)
            if r == 0:
                ax.set_title(f"reach {i + 1}: top view" if i == 0 else f"reach {i + 1}")
            elif i == 0:
                ax.set_title("side view")
    handles = [Line2D([], [], color="k", lw=2, label="observed reach"),
               Line2D([], [], color="k", marker="o", ls="none", ms=4, label="start"),
               Line2D([], [], color="k", marker="*", ls="none", ms=10, mfc="white", label="goal")]
    figure_legend(fig, axes)
    fig.legend(handles=handles, loc="outside lower right", frameon=False, ncols=3)
    if title:
        fig.suptitle(title)
    return fig


def _unknown(value) -> bool:
    """An empty ``exercised`` cell (None, or NaN after a CSV round trip): not applicable."""
    return value is None or (isinstance(value, float) and np.isnan(value))


@paper_figure
def plot_limits(table, ranges: Mapping[str, tuple[float, float]], *, title: str = "") -> Figure:
    """Per joint (one row), the model's range ``ranges[joint]`` (degrees) as a grey bar, the
    recorded range (``observed_min_deg`` .. ``observed_max_deg``, when the table has them) as a
    black bar inside it, and for each method of ``table`` (the limits table: method, joint, bound,
    estimate_deg, lower_90_deg, upper_90_deg, exercised) its two bounds: a marker at the estimate
    and a line over the 90% interval. A bound with ``exercised`` False is drawn hollow (the
    legend says "not exercised"). The x axis spans every range and estimate, with a margin."""
    joints = [j for j in ranges if j in set(table["joint"])]
    if not joints:
        raise ValueError("table: no joint with a range in degrees to draw")
    methods = method_order(table["method"].unique())
    n = len(joints)
    fig, axes = new_figure(1, 1, width="double", figsize=(7.0, 0.9 + 0.42 * n * max(1, len(methods)) ** 0.5))
    ax = axes[0, 0]
    span = max(1, len(methods))
    observed = "observed_min_deg" in table and table["observed_min_deg"].notna().any()
    xs = []
    for r, joint in enumerate(joints):
        y0 = n - 1 - r
        lo, hi = ranges[joint]
        xs += [lo, hi]
        ax.barh(y0, hi - lo, left=lo, height=0.8, color="0.88", edgecolor="0.6", lw=0.5,
                label="model range" if r == 0 else None, zorder=1)
        rows_j = table[table["joint"] == joint]
        if observed:
            o_lo, o_hi = float(rows_j["observed_min_deg"].iloc[0]), float(rows_j["observed_max_deg"].iloc[0])
            ax.barh(y0, max(o_hi - o_lo, 0.3), left=o_lo, height=0.12, color="k", zorder=2,
                    label="recorded range (functional)" if r == 0 else None)
        for k, m in enumerate(methods):
            st = method_style(m)
            y = y0 + 0.3 - 0.6 * (k + 0.5) / span
            for _, row in rows_j[rows_j["method"] == m].iterrows():
                ax.plot([row["lower_90_deg"], row["upper_90_deg"]], [y, y], color=st.color, lw=1.4, zorder=3)
                hollow = not _unknown(row["exercised"]) and not bool(row["exercised"])
                ax.plot(row["estimate_deg"], y, marker=st.marker, ms=5, ls="none", color=st.color,
                        mfc="white" if hollow else st.color, zorder=4)
                xs += [row["lower_90_deg"], row["upper_90_deg"], row["estimate_deg"]]
            if r == 0:
                ax.plot([], [], marker=st.marker, ms=5, color=st.color, lw=1.4, label=m)
    ax.plot([], [], marker="o", ls="none", color="0.3", mfc="white", label="not exercised (hollow)")
    xs = np.asarray([x for x in xs if np.isfinite(x)], dtype=float)
    pad = 0.04 * float(np.ptp(xs)) + 2.0
    ax.set_xlim(float(xs.min()) - pad, float(xs.max()) + pad)  # nothing clipped: every bar and marker shows
    ax.set_yticks(range(n), list(reversed(joints)))
    ax.set_ylim(-0.6, n - 0.4)
    ax.set_xlabel("model joint angle [deg] (not ISB clinical angles); marker: estimate, line: 90% interval")
    ax.grid(axis="x", alpha=0.3)
    figure_legend(fig, ax, ncols=4)  # four columns hold the longest label within the figure's width
    if title:
        fig.suptitle(title)
    return fig


@paper_figure
def plot_speed(time, speed, cuts, *, title: str = "") -> Figure:
    """The hand speed [m/s] over time [s] with each reach found shaded and numbered from 0
    (``cuts``: [(start, end)] in seconds)."""
    t = np.asarray(time, dtype=float)
    v = np.asarray(speed, dtype=float)
    fig, axes = new_figure(1, 1, width="double", figsize=(7.0, 2.4))
    ax = axes[0, 0]
    ax.plot(t, v, color="k", lw=0.8)
    top = float(v.max()) if v.size else 1.0
    for k, (a, b) in enumerate(cuts):
        ax.axvspan(a, b, color="C0", alpha=0.18, lw=0)
        ax.text(0.5 * (a + b), 1.02 * top, str(k), ha="center", va="bottom", fontsize=7, color="C0")
    ax.set_ylim(0, 1.12 * top + 1e-9)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("hand speed [m/s]")
    ax.grid(alpha=0.3)
    if title:
        ax.set_title(title)
    return fig
