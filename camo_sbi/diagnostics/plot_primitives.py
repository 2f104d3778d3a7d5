"""The plot primitives of the one look (`camo_sbi.diagnostics.style`), on tidy tables (columns
``method``, an x column and ``value``): `plot_lines` (mean and CI band, or mean and dots, against
x per method) and `plot_bars` (mean and CI, or mean and dots, per method), each method in its
`method_style` and under the small-n rule (`few_runs`).

Axes that fit the data: integer ticks for task counts (`integer_ticks`), a log x axis only with
at least two distinct positive x values (`plot_lines(logx=True)`), and a robust y scale
(`robust_ylim`) when one series dwarfs the methods: the axis is clipped to the methods' range
and the off-scale series are annotated with their largest value. Legends outside the data
(`figure_legend`: one legend for the panels of a figure). Runs as dots spread without random
state (`jitter`).
"""

from __future__ import annotations

import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.markers import MarkerStyle
from matplotlib.ticker import FixedLocator, MaxNLocator, NullLocator, ScalarFormatter

from camo_sbi.diagnostics.numbers import SMALL_N, band_label, few_runs, group_means, number
from camo_sbi.diagnostics.style import (
    MIN_FONT_PT,
    method_order,
    method_style,
    new_figure,
    paper_style,
)

__all__ = ["DWARF_FACTOR", "SMALL_N", "Series", "figure_legend", "integer_ticks", "jitter", "plot_bars", "plot_lines",
           "robust_ylim"]

DWARF_FACTOR = 4.0
"""A series whose top exceeds this many times the methods' top is drawn off scale (`robust_ylim`)."""


def integer_ticks(ax: Axes, values=None, axis: str = "x") -> None:
    """Integer ticks only: at ``values`` when there are at most 12, else a MaxNLocator(integer)."""
    target = ax.xaxis if axis == "x" else ax.yaxis
    vals = None if values is None else sorted({int(v) for v in np.asarray(values, dtype=float)
                                               if np.isfinite(v)})
    if vals and len(vals) <= 12:
        target.set_major_locator(FixedLocator(vals))
    else:
        target.set_major_locator(MaxNLocator(integer=True))
    target.set_minor_locator(NullLocator())


def _log_x(ax: Axes, values) -> bool:
    """Log x axis with ticks at the x values, when there are >= 2 distinct positive ones."""
    vals = np.unique(np.asarray(values, dtype=float))
    vals = vals[np.isfinite(vals)]
    if vals.size < 2 or vals.min() <= 0:
        return False
    ax.set_xscale("log")
    if vals.size <= 12:
        ax.xaxis.set_major_locator(FixedLocator(vals))
        fmt = ScalarFormatter()
        fmt.set_scientific(False)
        ax.xaxis.set_major_formatter(fmt)
        ax.xaxis.set_minor_locator(NullLocator())
    return True


_fmt = number


@dataclass(frozen=True)
class Series:
    """One drawn series for `robust_ylim`: x, mean and the band's lower/upper edges (arrays)."""

    x: np.ndarray
    mean: np.ndarray
    low: np.ndarray
    high: np.ndarray


def robust_ylim(ax: Axes, series: Mapping[str, Series], *, factor: float = DWARF_FACTOR,
                band_cap: float = 2.5, spread: str = "bands") -> list[str]:
    """Fit the y axis to the methods when a series dwarfs them; returns the off-scale names.

    A series is off scale when its largest mean exceeds ``factor`` times the largest mean of
    the non-baseline series (of all series, by the median, when all are baselines). When
    any is, or when a kept band reaches past ``band_cap`` times the largest kept mean (few
    runs make wide Student-t intervals), the axis spans the kept series' means and bands up
    to ``band_cap`` times their largest mean; the off-scale series are named with their
    largest mean in a free strip at the top, their points above the axis get a triangle on
    the top edge, and clipped bands are said to be clipped. Otherwise nothing changes.
    """
    if isinstance(factor, bool) or not isinstance(factor, (int, float)) or not factor > 1:
        raise ValueError(f"factor: expected a number > 1, got {factor!r}")
    peaks = {k: float(np.nanmax(v.mean)) for k, v in series.items() if len(v.mean) and np.isfinite(v.mean).any()}
    if len(peaks) < 2:
        return []
    methods = [v for k, v in peaks.items() if not method_style(k).baseline]
    ref = max(methods) if methods else float(np.median(list(peaks.values())))
    if not ref > 0:
        return []
    off = method_order([k for k, v in peaks.items() if v > factor * ref])
    kept = [k for k in peaks if k not in off]
    kept_mean = max(peaks[k] for k in kept)
    band_top = max(float(np.nanmax(series[k].high)) for k in kept)
    clipped_bands = band_top > band_cap * kept_mean
    if not off and not clipped_bands:
        return []
    low = min(float(np.nanmin(series[k].low)) for k in kept)
    high = min(band_top, band_cap * kept_mean)
    bottom = low - 0.04 * (high - low)
    top = bottom + 1.22 * (high - bottom)  # the strip above `high` holds the note
    ax.set_ylim(bottom, top)
    lines = []
    for name in off:
        lines.append(f"↑ {name} off scale (mean up to {_fmt(peaks[name])})")
        v = series[name]
        above = np.asarray(v.mean) > top
        if above.any():
            ax.plot(np.asarray(v.x)[above], np.full(int(above.sum()), top), linestyle="none", marker="^", ms=7,
                    color=method_style(name).color, clip_on=False, zorder=5)
    if clipped_bands:
        lines.append(f"{spread} clipped at the top")
    ax.text(0.99, 0.985, "\n".join(lines), transform=ax.transAxes, ha="right", va="top", fontsize=MIN_FONT_PT,
            color="0.25", bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": "0.8", "alpha": 0.9})
    return off


def figure_legend(fig: Figure, axes: Sequence[Axes] | np.ndarray | Axes, *, title: str | None = None,
                  loc: str = "outside lower center", fontsize: float = MIN_FONT_PT, ncols: int | None = None):
    """One legend for the figure, outside the panels (default: below them, as many columns
    as the width holds), built from the labelled artists of ``axes`` (first occurrence of
    each label, in method order)."""
    axs = [axes] if isinstance(axes, Axes) else list(np.asarray(axes, dtype=object).reshape(-1))
    handles: dict[str, object] = {}
    for ax in axs:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            if not lab.startswith("_"):
                handles.setdefault(lab, h)
    if not handles:
        return None
    order = method_order(handles)
    if ncols is None:
        ncols = 1 if "right" in loc or "left" in loc else max(1, int(fig.get_figwidth() // 1.15))
    return fig.legend([handles[k] for k in order], order, loc=loc, fontsize=fontsize, title=title,
                      title_fontsize=fontsize, frameon=False, alignment="left", ncols=min(ncols, len(order)))


def _legend_handle(name: str) -> Line2D:
    st = method_style(name)
    return Line2D([], [], label=name, markersize=5, **st.line_kwargs())


def _wrap(title: str, width: int = 44) -> str:
    """A panel title on lines of at most ``width`` characters (a 3.4 in panel holds ~50 at 9 pt)."""
    return "\n".join(textwrap.fill(line, width) for line in str(title).split("\n"))


def jitter(n: int, width: float) -> np.ndarray:
    """``n`` evenly spread offsets in [-width/2, width/2] (deterministic: no random state)."""
    if n <= 1:
        return np.zeros(max(n, 0))
    return np.linspace(-width / 2, width / 2, n)


def _x_step(xs: np.ndarray, log: bool) -> float:
    """The smallest gap between distinct x values (in log10 on a log axis), 1 if only one."""
    u = np.unique(xs[np.isfinite(xs)])
    if log:
        u = np.log10(u[u > 0])
    return float(np.min(np.diff(u))) if u.size > 1 else 1.0


def _dots(ax: Axes, data: pd.DataFrame, x: str | None, names: list[str], hue: str, *, log: bool,
          z: Mapping[str, float], positions: Mapping[str, float] | None = None) -> None:
    """Each run as a dot, jittered around its x (per method a little apart, so methods do not
    hide each other's runs)."""
    xs_all = data[x].to_numpy(dtype=float) if x is not None else np.zeros(len(data))
    step = _x_step(xs_all, log) if x is not None else 1.0
    spread = 0.5 * step if x is None else 0.3 * step
    for i, h in enumerate(names):
        g = data[data[hue].astype(str) == h]
        if g.empty:
            continue
        st = method_style(h)
        shift = (i - (len(names) - 1) / 2) * spread / max(len(names), 1) if x is not None else 0.0
        groups = [(positions[h], g)] if x is None else list(g.groupby(x, sort=True))
        for xv, gg in groups:
            vals = gg["value"].to_numpy(dtype=float)
            width = spread / max(len(names), 1) * 0.8 if x is not None else 0.35
            off = shift + jitter(vals.size, width)
            xp = float(xv) * 10.0**off if log else float(xv) + off
            filled = MarkerStyle(st.marker).is_filled()
            ax.scatter(xp, vals, s=9, color=st.color, marker=st.marker, alpha=0.7, lw=0.3 if filled else 0.8,
                       edgecolors="white" if filled else None, zorder=z.get(h, 3) + 0.5)


def plot_lines(df: pd.DataFrame, *, x: str = "n_tasks", hue: str = "method", ax: Axes | None = None,
               ylabel: str = "", title: str = "", logx: bool = False, logy: bool = False,
               robust: bool = True, legend: bool = True, factor: float = DWARF_FACTOR) -> Axes:
    """Mean of ``value`` against ``x`` per ``hue``, with a band for the 95% CI of the mean,
    or, with fewer than `SMALL_N` runs behind a point (`few_runs`), the runs as jittered dots.

    Each method in its `method_style`. ``x`` columns of integers (task counts) get integer
    ticks; ``logx`` is honoured only with at least two distinct positive x values (a single
    budget stays linear). A non-negative metric's band is not drawn below 0. ``robust``:
    `robust_ylim` clips a dwarfing series (not with ``logy``). ``legend``: draw a legend
    with the band's meaning as its title: below the axes when they are the figure's only
    axes, else inside in the emptiest corner; False for none (a figure of several panels
    gets one `figure_legend` instead). Returns the axes (a new Figure's when ``ax`` is None).
    """
    if not isinstance(df, pd.DataFrame):
        raise TypeError(f"df: expected a DataFrame, got {type(df).__name__}")
    if ax is None:
        with paper_style():
            _, axes = new_figure()
        ax = axes[0, 0]
    geometric = bool(logy)
    data = df
    if geometric:  # a log axis: the geometric mean and the CI of the mean of log10 values
        data = df[df["value"] > 0].assign(value=lambda d: np.log10(d["value"]))
    s = group_means(data, x, hue)
    few = few_runs(s["n"])
    nonneg = bool(len(df) and (df["value"] >= 0).all()) and not geometric
    series, zs = {}, {}
    names = method_order(s[hue].astype(str))
    logx_ok = logx and _log_x(ax, df[x].dropna())
    for h in names:
        g = s[s[hue].astype(str) == h].sort_values(x)
        st = method_style(h)
        xs, mean, ci = g[x].to_numpy(dtype=float), g["mean"].to_numpy(), g["ci"].fillna(0).to_numpy()
        if few:  # the points' spread, not an interval
            raw = data[data[hue].astype(str) == h].groupby(x)["value"]
            lower = raw.min().reindex(g[x]).to_numpy(dtype=float)
            upper = raw.max().reindex(g[x]).to_numpy(dtype=float)
        else:
            lower = np.clip(mean - ci, 0, None) if nonneg else mean - ci
            upper = mean + ci
        if geometric:
            mean, lower, upper = 10.0**mean, 10.0**lower, 10.0**upper
        z = 2.0 if st.baseline else 3.0  # the methods above the baselines' reference lines
        zs[h] = z
        ax.plot(xs, mean, ms=3.5, lw=1.3, label=h, zorder=z, **st.line_kwargs())
        if not few and (ci > 0).any():
            ax.fill_between(xs, lower, upper, color=st.color, alpha=0.15 if not st.baseline else 0.1, lw=0,
                            zorder=z - 1)
        series[h] = Series(xs, mean, lower, upper)
    if few:
        _dots(ax, df[df["value"] > 0] if geometric else df, x, names, hue, log=logx_ok, z=zs)
    xvals = df[x].dropna()
    integral = pd.api.types.is_integer_dtype(df[x]) or x in ("n_tasks", "budget", "run", "seed")
    if not logx_ok and len(xvals) and integral:
        integer_ticks(ax, xvals)
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel({"n_tasks": "observed tasks", "budget": "simulations per observed task"}.get(x, x.replace("_", " ")))
    ax.set_ylabel(_wrap(ylabel, 34))
    if title:
        ax.set_title(_wrap(title))
    ax.grid(alpha=0.3)
    if robust and not logy:
        robust_ylim(ax, series, factor=factor, spread="points" if few else "bands")
    if legend:
        alone = len(ax.figure.axes) == 1  # below the axes; beside other panels: inside, best corner
        where = {"loc": "upper left", "bbox_to_anchor": (0.0, -0.22), "ncols": 2} if alone else {"loc": "best"}
        if len(s):
            ax.legend(fontsize=MIN_FONT_PT, frameon=not alone, framealpha=0.85, title_fontsize=MIN_FONT_PT,
                      title=band_label(s["n"], geometric=geometric), alignment="left", **where)
    return ax


def plot_bars(df: pd.DataFrame, *, hue: str = "method", ax: Axes | None = None, ylabel: str = "",
              title: str = "", robust: bool = True, factor: float = DWARF_FACTOR) -> Axes:
    """One bar per ``hue``: the mean ``value`` with its 95% CI as an error bar, or, with fewer
    than `SMALL_N` runs (`few_runs`), with each run as a jittered dot, in method colours
    (baselines grey and hatched). A dwarfing bar is clipped (`robust_ylim`) and its value
    written on it. What the bars are is in the x-axis label. Returns the axes."""
    if not isinstance(df, pd.DataFrame):
        raise TypeError(f"df: expected a DataFrame, got {type(df).__name__}")
    if ax is None:
        with paper_style():
            _, axes = new_figure()
        ax = axes[0, 0]
    s = group_means(df, None, hue)
    few = few_runs(s["n"])
    order = method_order(s[hue].astype(str))
    s = s.set_index(s[hue].astype(str)).loc[order]
    xs = np.arange(len(order))
    for i, name in enumerate(order):
        st = method_style(name)
        ax.bar(i, s.loc[name, "mean"], yerr=None if few else s.loc[name, "ci"], capsize=4, color=st.color,
               alpha=(0.35 if few else 0.55) if st.baseline else (0.5 if few else 0.85),
               hatch="//" if st.baseline else None, edgecolor="0.2", lw=0.6, label=name)
    if few:
        _dots(ax, df, None, order, hue, log=False, z={}, positions={n: i for i, n in enumerate(order)})
    ax.set_xticks(xs, order, rotation=30 if len(order) > 3 else 0, ha="right" if len(order) > 3 else "center")
    ax.set_ylabel(_wrap(ylabel, 34))
    what = band_label(s["n"]).replace("\n", " ")
    if few:
        what = what.replace("line:", "bar:")
    ax.set_xlabel(_wrap(f"bars: {what}" if not few else what, 48))
    if title:
        ax.set_title(_wrap(title))
    ax.grid(alpha=0.3, axis="y")
    if robust:
        series = {}
        for i, n in enumerate(order):
            m, c = float(s.loc[n, "mean"]), float(np.nan_to_num(s.loc[n, "ci"]))
            v = df.loc[df[hue].astype(str) == n, "value"].to_numpy(dtype=float)
            lo, hi = (float(np.nanmin(v)), float(np.nanmax(v))) if few and v.size else (m - c, m + c)
            series[n] = Series(np.array([i]), np.array([m]), np.array([min(0.0, lo)]), np.array([hi]))
        off = robust_ylim(ax, series, factor=factor, spread="points" if few else "bands")
        top = ax.get_ylim()[1]
        for name in off:
            i = order.index(name)
            ax.text(i, 0.5 * top, f"{_fmt(s.loc[name, 'mean'])}\n↑", ha="center", va="center",
                    fontsize=MIN_FONT_PT, bbox={"fc": "white", "ec": "none", "alpha": 0.8})
    return ax
