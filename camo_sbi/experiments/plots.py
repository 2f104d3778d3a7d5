"""Figures for experiment tables: means with 95% confidence intervals."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from matplotlib.ticker import MaxNLocator
from scipy import stats

__all__ = ["mean_ci", "plot_bars", "plot_lines", "save_figure"]


def mean_ci(values, confidence: float = 0.95) -> tuple[float, float]:
    """Mean and half-width of the Student-t confidence interval (0 for a single value)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return float("nan"), float("nan")
    if v.size == 1:
        return float(v[0]), 0.0
    half = stats.t.ppf(0.5 + confidence / 2, v.size - 1) * v.std(ddof=1) / np.sqrt(v.size)
    return float(v.mean()), float(half)


def _summary(df: pd.DataFrame, x: str, hue: str) -> pd.DataFrame:
    rows = []
    for (h, xv), g in df.groupby([hue, x], sort=True):
        m, c = mean_ci(g["value"])
        rows.append({hue: h, x: xv, "mean": m, "ci": c, "n": len(g)})
    return pd.DataFrame(rows)


def plot_lines(df: pd.DataFrame, *, x: str = "n_tasks", hue: str = "method", ax=None,
               ylabel: str = "", title: str = "", logx: bool = False, logy: bool = False):
    """Mean of ``value`` against ``x`` per ``hue`` with a shaded 95% CI. Returns the axes."""
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4))
    s = _summary(df, x, hue)
    for h, g in s.groupby(hue, sort=True):
        g = g.sort_values(x)
        ax.plot(g[x], g["mean"], marker="o", ms=3, label=str(h))
        lower = g["mean"] - g["ci"]
        if bool((df["value"] >= 0).all()):  # a non-negative metric: do not draw the band below 0
            lower = lower.clip(lower=0)
        ax.fill_between(g[x], lower, g["mean"] + g["ci"], alpha=0.2)
    ax.set_xlabel(x.replace("_", " "))
    if pd.api.types.is_integer_dtype(df[x]):
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    if logx:
        ax.set_xscale("log")
    if logy:
        ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return ax


def plot_bars(df: pd.DataFrame, *, hue: str = "method", ax=None, ylabel: str = "", title: str = ""):
    """Bar per ``hue`` of the mean ``value`` with 95% CI error bars. Returns the axes."""
    if ax is None:
        _, ax = plt.subplots(figsize=(5, 4))
    names, means, cis = [], [], []
    for h, g in df.groupby(hue, sort=True):
        m, c = mean_ci(g["value"])
        names.append(str(h))
        means.append(m)
        cis.append(c)
    ax.bar(names, means, yerr=cis, capsize=4, color=[f"C{i}" for i in range(len(names))])
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3, axis="y")
    return ax


def save_figure(fig, path) -> None:
    """Save atomically as PNG (150 dpi) and close the figure."""
    import io

    from camo_sbi.experiments.store import atomic_write_bytes

    buf = io.BytesIO()
    if fig.get_layout_engine() is None:  # keep a figure's own (e.g. constrained) layout
        fig.tight_layout()
    fig.savefig(buf, format="png", dpi=150)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
