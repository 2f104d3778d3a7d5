"""How a value, a table cell and a metric are written for a person: no matplotlib.

The text half of `camo_sbi.diagnostics.style` (which re-exports every name here), apart so
that what prints a table (the commands' summaries on a re-run of a finished grid, the report's
tables) needs numpy, pandas and scipy only: the small-n rule (`few_runs`, `cell_text`,
`cell_rule`, `band_label`), the mean and its Student-t interval (`mean_ci`, `group_means`,
`run_counts`), numbers without exponents (`number`) and metrics in words and degrees
(`metric_label`, `display_metric`, `to_degrees`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import pandas as pd
from scipy import stats

__all__ = ["CONFIDENCE", "SMALL_N", "band_label", "cell_rule", "cell_text", "display_metric", "few_runs",
           "group_means", "mean_ci", "metric_label", "number", "run_counts", "summary_table", "to_degrees"]

CONFIDENCE = 0.95
SMALL_N = 5
"""With fewer runs (or seeds) than this, no confidence interval is drawn or written (`few_runs`)."""


# --------------------------------------------------------------------------- words

def metric_label(metric: str) -> str:
    """A metric's name in words with its unit as a person reads it, from the metric catalog
    (`camo_sbi.evaluation.catalog`; angles in degrees: `display_metric` converts the values
    of a metric stored in radians); a name the catalog does not know, in words."""
    from camo_sbi.evaluation import catalog

    metric = str(metric)
    m = catalog.find(metric)
    if m is None:
        return metric.replace("_", " ")
    return m.display_label(metric[len(m.prefix):] if m.per_joint else None)


def to_degrees(x):
    """Radians to degrees (arrays, scalars and DataFrame columns alike)."""
    return np.degrees(x)


def display_metric(df: pd.DataFrame, metric_col: str = "metric", value_col: str = "value") -> pd.DataFrame:
    """A tidy table with the values of metrics stored in radians converted to degrees (for a
    figure or a table; `metric_label` names the unit). Other rows are returned unchanged."""
    if metric_col not in df.columns:
        return df
    from camo_sbi.evaluation import catalog

    radians = {n for n in df[metric_col].astype(str).unique()
               if (m := catalog.find(n)) is not None and m.unit == "rad"}
    rad = df[metric_col].astype(str).isin(radians)
    if not rad.any():
        return df
    out = df.copy()
    out.loc[rad, value_col] = to_degrees(out.loc[rad, value_col].astype(float))
    return out


def few_runs(n_runs) -> bool:
    """The small-n rule of every figure and table: True when some shown value averages fewer
    than `SMALL_N` runs (``n_runs``: an int or the counts seen); then no interval is drawn."""
    counts = [int(n) for n in np.atleast_1d(n_runs) if int(n) > 0]
    return bool(counts) and min(counts) < SMALL_N


def _count_text(n_runs) -> str:
    counts = sorted({int(n) for n in np.atleast_1d(n_runs)})
    if not counts:
        raise ValueError("n_runs: no counts given")
    return str(counts[0]) if len(counts) == 1 else f"{counts[0]}–{counts[-1]}"


def band_label(n_runs, confidence: float = CONFIDENCE, *, geometric: bool = False) -> str:
    """What a band (or its absence) is, for a legend title or caption: ``n_runs`` an int or
    the counts seen; ``geometric`` for a log axis (`plot_lines(logy=True)` averages log10
    values). Fewer than `SMALL_N` runs: the dots are the runs, the line their mean."""
    n = _count_text(n_runs)
    counts = sorted({int(v) for v in np.atleast_1d(n_runs)})
    if counts[-1] < 2:
        return f"mean of {n} run (no interval)"
    if few_runs(counts):
        mean = "geometric mean" if geometric else "mean"
        return f"dots: each of {n} runs, line: {mean}\n(fewer than {SMALL_N} runs: no CI band)"
    if geometric:
        return f"geometric mean and {confidence:.0%} CI\nover {n} runs (Student t on log10)"
    return f"mean and {confidence:.0%} CI of the mean\nover {n} runs (Student t)"


def _range_text(lo: str, hi: str) -> str:
    return f"{lo} to {hi}" if lo.startswith("-") or hi.startswith("-") else f"{lo}–{hi}"


def cell_text(values, fmt: Callable[[float], str] | None = None,
              ci_fmt: Callable[[float], str] | None = None) -> str:
    """One table cell for the values of a group (the small-n rule of `few_runs`):
    ``mean ± half-width`` of the 95% CI of the mean (Student t) with at least `SMALL_N`
    values, ``mean (min–max)`` with 2 to 4, the value alone with one (or identical ones).
    ``fmt`` formats the mean and range (default `number`), ``ci_fmt`` the half-width
    (default: 2 significant digits)."""
    fmt = fmt or number
    ci_fmt = ci_fmt or (lambda v: number(v, 2))
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return "–"
    m, half = mean_ci(v)
    lo, hi = float(v.min()), float(v.max())
    if v.size == 1 or hi - lo <= 1e-9 * max(1.0, abs(m)):
        return fmt(m)
    if few_runs(v.size):
        return f"{fmt(m)} ({_range_text(fmt(lo), fmt(hi))})"
    return f"{fmt(m)} ± {ci_fmt(half)}"


def cell_rule(n_runs, unit: str = "runs", confidence: float = CONFIDENCE) -> str:
    """What the cells of `cell_text` hold, for a table's caption (``unit``: "runs", "seeds")."""
    n = _count_text(n_runs)
    counts = sorted({int(v) for v in np.atleast_1d(n_runs)})
    if counts[-1] < 2:
        return f"the value of {n} {unit.rstrip('s')} (no interval)"
    if few_runs(counts):
        return (f"mean (min–max) over {n} {unit}; fewer than {SMALL_N} {unit}, so no confidence "
                "interval")
    return f"mean ± half-width of the {confidence:.0%} confidence interval of the mean over {n} {unit} (Student t)"


# --------------------------------------------------------------------------- statistics


def mean_ci(values, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Mean and half-width of the Student-t confidence interval of the mean (0 for one value)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return float("nan"), float("nan")
    if v.size == 1:
        return float(v[0]), 0.0
    half = stats.t.ppf(0.5 + confidence / 2, v.size - 1) * v.std(ddof=1) / np.sqrt(v.size)
    return float(v.mean()), float(half)


def group_means(df: pd.DataFrame, x: str | None, hue: str = "method", value: str = "value") -> pd.DataFrame:
    """Columns hue, [x,] mean, ci (95% half-width, `mean_ci`), n per group of a tidy table."""
    keys = [hue] if x is None else [hue, x]
    missing = [c for c in keys + [value] if c not in df.columns]
    if missing:
        raise ValueError(f"df: missing columns {missing}")
    rows = []
    for k, g in df.groupby(keys, sort=True, dropna=False):
        m, c = mean_ci(g[value])
        k = k if isinstance(k, tuple) else (k,)
        rows.append({**dict(zip(keys, k, strict=True)), "mean": m, "ci": c, "n": int(g[value].notna().sum())})
    return pd.DataFrame(rows, columns=keys + ["mean", "ci", "n"])


def run_counts(df: pd.DataFrame, x: str | None = None, hue: str = "method", by: Sequence[str] = ()) -> np.ndarray:
    """How many runs (finite values) each plotted point of ``df`` averages, for `band_label`
    (per hue, x, the columns ``by`` (e.g. the panel's prior) and, when the table has one, metric)."""
    keys = ([hue] if x is None else [hue, x]) + list(by) + (["metric"] if "metric" in df.columns else [])
    return df.groupby(keys, dropna=False)["value"].count().to_numpy()


def number(v: float, digits: int = 3) -> str:
    """``v`` with ``digits`` significant digits and no exponent (1234.5 -> "1,235", 0.000123 -> "0.000123")."""
    v = float(v)
    if not np.isfinite(v):
        return "–"
    if abs(v) >= 10 ** (digits - 1):
        return f"{v:,.0f}"
    return np.format_float_positional(v, precision=digits, unique=False, fractional=False, trim="-")


def summary_table(last: pd.DataFrame, metrics: Sequence[str], *, unit: str = "seeds", block: str | None = None) -> str:
    """A commands' printed summary of tidy rows (``method``, ``metric``, ``value``, and ``block``
    when given): the metrics as rows in words with their units (angles in degrees) in ``metrics``'
    order, the methods as columns in their order, one block per value of ``block`` (e.g. the
    budget), each cell `cell_text` of its values (the small-n rule: no interval from fewer than
    `SMALL_N`), and the rule said once on the first line (``unit``: what the values are; "values"
    when there is more than one subject)."""
    shown = display_metric(last)
    methods = list(dict.fromkeys(shown["method"]))
    if "subject" in shown.columns and shown["subject"].nunique() > 1:
        unit = "values"
    keys = ["metric", "method"] + ([block] if block else [])
    lines = [f"each cell: {cell_rule(shown.groupby(keys)['value'].size().to_numpy(), unit)}"]
    for b, part in (shown.groupby(block, sort=True) if block else [(None, shown)]):
        t = part.groupby(["metric", "method"])["value"].apply(cell_text).unstack("method")
        t = t.reindex(index=[m for m in metrics if m in t.index], columns=methods).fillna("–")
        t.index = [metric_label(m) for m in t.index]
        t.index.name = f"{block} {number(b)}" if block else "metric"
        lines.append(t.to_string())
    return "\n".join(lines)
