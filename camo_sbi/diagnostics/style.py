"""One look for every figure camo_sbi draws: the run figures, the report and the notebooks.

What it fixes, so a reader can compare figures with each other:

* **a colour, marker and line style per method** (`method_style`), the same in every
  figure: the inference methods in fixed colours, the baselines (naive, nominal, oracle,
  the HRC majority class and truth, and any method registered with
  ``Capabilities.baseline``) in greys/black with their own markers and dashes, any other
  name a deterministic fallback (a hash of the name, never its position in a legend);
* **what a band is**, said in the legend title (`band_label`): the mean and the 95%
  confidence interval of the mean over N runs (Student t), the statistic `mean_ci` computes
  for the figures and the report's tables alike;
* **small-n honesty**, one rule (`few_runs`: fewer than `SMALL_N` = 5 runs or seeds) for
  every figure and table: a figure then draws each run as a jittered dot and the mean as a
  line or bar, never a Student-t band; a table cell (`cell_text`) shows the mean and the
  range of the values instead of a ± interval; `band_label` and `cell_rule` say which;
* **degrees where a person reads an angle** (`display_metric`: a metric stored in radians
  is drawn and tabulated in degrees, its label saying so); the files keep radians;
* **a paper style** (`PAPER_RC`, `paper_style`, `paper_figure`): single-column
  (`SINGLE_COLUMN` = 3.5 in) and double-column (`DOUBLE_COLUMN` = 7 in) widths with fonts of
  at least `MIN_FONT_PT` = 8 pt at that size, and vector export (`save_figures`,
  `FIGURE_FORMATS`: png, pdf, svg; `parse_figure_formats` reads ``--figure-format``);
* **axes that fit the data**: integer ticks for task counts (`integer_ticks`), a log
  x axis only with at least two distinct positive x values (`plot_lines(logx=True)`), and
  a robust y scale (`robust_ylim`) when one series dwarfs the methods: the axis is clipped
  to the methods' range and the off-scale series are annotated with their largest value;
* **legends outside the data** (`figure_legend`: one legend to the right of the panels);
* **no pyplot state**: figures are `matplotlib.figure.Figure` objects (`new_figure`),
  written atomically (`save_figure`: the format is the path's suffix).

Plot primitives on tidy tables (columns ``method``, an x column and ``value``):
`plot_lines` (mean and CI band, or mean and dots, against x per method) and `plot_bars`
(mean and CI, or mean and dots, per method).
"""

from __future__ import annotations

import contextlib
import functools
import io
import textwrap
import zlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.markers import MarkerStyle
from matplotlib.ticker import FixedLocator, MaxNLocator, NullLocator, ScalarFormatter

from camo_sbi._io import atomic_write_bytes
from camo_sbi.diagnostics.numbers import (  # the text half, re-exported: style is the one look
    SMALL_N,
    band_label,
    cell_rule,
    cell_text,
    display_metric,
    few_runs,
    group_means,
    mean_ci,
    metric_label,
    number,
    run_counts,
    to_degrees,
)

__all__ = [
    "BASELINE_NAMES",
    "DOUBLE_COLUMN",
    "DWARF_FACTOR",
    "FIGURE_FORMATS",
    "MIN_FONT_PT",
    "MethodStyle",
    "PAPER_RC",
    "SINGLE_COLUMN",
    "SMALL_N",
    "Series",
    "band_label",
    "cell_rule",
    "cell_text",
    "display_metric",
    "few_runs",
    "figure_legend",
    "figure_png",
    "integer_ticks",
    "jitter",
    "mean_ci",
    "method_order",
    "method_style",
    "metric_label",
    "new_figure",
    "number",
    "paper_figure",
    "paper_style",
    "parse_figure_formats",
    "plot_bars",
    "plot_lines",
    "robust_ylim",
    "run_counts",
    "save_figure",
    "save_figures",
    "group_means",
    "to_degrees",
]

DWARF_FACTOR = 4.0
"""A series whose top exceeds this many times the methods' top is drawn off scale (`robust_ylim`)."""
SINGLE_COLUMN = 3.5
"""A single-column figure's width [in]."""
DOUBLE_COLUMN = 7.0
"""A double-column figure's width [in]."""
MIN_FONT_PT = 8
"""No text smaller than this [pt] at the figure's own size."""
FIGURE_FORMATS = ("png", "pdf", "svg")
PNG_DPI = 200  # 7 in -> 1400 px
PAPER_RC: dict[str, object] = {
    "font.size": 8,
    "axes.titlesize": 9,
    "axes.labelsize": 8,
    "xtick.labelsize": 8,
    "ytick.labelsize": 8,
    "legend.fontsize": 8,
    "legend.title_fontsize": 8,
    "figure.titlesize": 9,
    "axes.linewidth": 0.6,
    "grid.linewidth": 0.5,
    "lines.linewidth": 1.2,
    "lines.markersize": 4,
    "xtick.major.width": 0.6,
    "ytick.major.width": 0.6,
    "pdf.fonttype": 42,  # TrueType in the PDF: text stays text (searchable, editable)
    "svg.fonttype": "none",  # text as <text> elements, not paths
    "savefig.dpi": PNG_DPI,
}
"""matplotlib rcParams of every camo_sbi figure (`paper_style`): fonts >= 8 pt at 3.5 / 7 in."""


@dataclass(frozen=True)
class MethodStyle:
    """How one method is drawn: ``color``, ``marker``, ``linestyle``; ``baseline`` for the greys."""

    color: str
    marker: str
    linestyle: str = "-"
    baseline: bool = False

    def line_kwargs(self) -> dict:
        return {"color": self.color, "marker": self.marker, "linestyle": self.linestyle}


# the inference methods: colour-blind-friendly (Okabe-Ito / tab10), never grey
_METHODS: dict[str, MethodStyle] = {
    "camo": MethodStyle("#0072B2", "o"),          # blue
    "camo-js": MethodStyle("#56B4E9", "o"),       # sky blue
    "camo-cs": MethodStyle("#CC79A7", "v"),       # reddish purple
    "camo-hull": MethodStyle("#009E73", "D"),     # bluish green
    "camo-seq": MethodStyle("#8c564b", "P"),      # brown
    "abc-smc": MethodStyle("#E69F00", "s"),       # orange
    "npe": MethodStyle("#D55E00", "^"),           # vermillion
    "npe-amortized": MethodStyle("#F0E442", "<"),  # yellow
    "exact-likelihood": MethodStyle("#332288", "*", (0, (3, 1, 1, 1))),  # indigo: the Bayes limit, not SBI
}
# the baselines: greys and black, each with its own marker and dashes
_BASELINES: dict[str, MethodStyle] = {
    "naive": MethodStyle("#555555", "s", "--", True),
    "nominal": MethodStyle("#999999", "^", ":", True),
    "oracle": MethodStyle("#000000", "D", "-.", True),
    "majority": MethodStyle("#777777", "x", (0, (5, 2, 1, 2)), True),
    "truth": MethodStyle("#000000", "*", (0, (1, 1)), True),
}
BASELINE_NAMES = tuple(_BASELINES)
# deterministic fallbacks for names outside the tables (a hash picks one): no grey, none of the above
_FALLBACK_COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#e377c2", "#bcbd22", "#17becf",
                    "#393b79", "#637939", "#8c6d31", "#843c39", "#7b4173", "#3182bd")
_FALLBACK_MARKERS = ("o", "s", "^", "v", "D", "P", "X", "<", ">", "h")
_FALLBACK_GREYS = ("#333333", "#666666", "#888888", "#aaaaaa")


def _base_name(name: str) -> str:
    """``"naive (point estimate)"`` -> ``"naive"``: a label's method name."""
    return str(name).split(" (", 1)[0].strip()


def _registered_baseline(name: str) -> bool:
    from camo_sbi.inference.registry import get_method

    try:
        return bool(get_method(name).capabilities.baseline)
    except ValueError:
        return False


def method_style(name: str) -> MethodStyle:
    """The style of method ``name`` (a label like ``"naive (point estimate)"`` uses its method's).

    Registered methods in the fixed table keep their colours; a registered baseline outside
    it gets a grey; any other name a colour and marker chosen by a hash of the name.
    """
    if not isinstance(name, str):
        raise TypeError(f"name: expected a str, got {type(name).__name__}")
    base = _base_name(name)
    if base in _METHODS:
        return _METHODS[base]
    if base in _BASELINES:
        return _BASELINES[base]
    h = zlib.crc32(base.encode("utf-8"))
    marker = _FALLBACK_MARKERS[(h // 7) % len(_FALLBACK_MARKERS)]
    if _registered_baseline(base):
        return MethodStyle(_FALLBACK_GREYS[h % len(_FALLBACK_GREYS)], marker, "--", True)
    return MethodStyle(_FALLBACK_COLORS[h % len(_FALLBACK_COLORS)], marker)


def method_order(names: Iterable[str]) -> list[str]:
    """Unique names in legend order: the inference methods (table order, then the rest
    alphabetically), then the baselines (naive, nominal, oracle, majority, truth, others)."""
    uniq = list(dict.fromkeys(str(n) for n in names))
    known = list(_METHODS) + list(_BASELINES)

    def key(n: str):
        b = _base_name(n)
        return (method_style(n).baseline, known.index(b) if b in known else len(known), n)

    return sorted(uniq, key=key)


# --------------------------------------------------------------------------- figures and axes


@contextlib.contextmanager
def paper_style():
    """`PAPER_RC` in force inside the block (matplotlib.rc_context; nothing global changes)."""
    with matplotlib.rc_context(PAPER_RC):
        yield


def paper_figure(fn):
    """Decorator: ``fn`` draws its figure under `paper_style` (text sizes are fixed when an
    artist is made, so the style must be in force while drawing)."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with paper_style():
            return fn(*args, **kwargs)
    return wrapper


def _width(width) -> float:
    if width in ("single", None):
        return SINGLE_COLUMN
    if width == "double":
        return DOUBLE_COLUMN
    if isinstance(width, bool) or not isinstance(width, (int, float)) or not width > 0:
        raise ValueError(f"width: expected 'single', 'double' or inches > 0, got {width!r}")
    return float(width)


def new_figure(nrows: int = 1, ncols: int = 1, *, width: str | float | None = None, aspect: float = 0.72,
               legend_rows: int = 2, figsize: tuple[float, float] | None = None,
               **subplot_kw) -> tuple[Figure, np.ndarray]:
    """A pyplot-free Figure (constrained layout) at a paper width and its (nrows, ncols) axes.

    ``width``: "single" (3.5 in), "double" (7 in) or inches; default single for one column
    of panels, double for more. Each panel is ``aspect`` times as high as wide (its height
    kept within 1.5-2.8 in), plus room for ``legend_rows`` rows of a legend below
    (`figure_legend`). ``figsize`` overrides all of it. Draw under `paper_style` for its fonts.
    """
    if figsize is None:
        w = _width(width if width is not None else ("single" if ncols == 1 else "double"))
        panel_h = min(2.8, max(1.5, aspect * w / ncols))
        figsize = (w, panel_h * nrows + 0.18 * legend_rows + 0.2)
    fig = Figure(figsize=figsize, layout="constrained")
    axes = np.asarray(fig.subplots(nrows, ncols, squeeze=False, **subplot_kw))
    return fig, axes


def parse_figure_formats(text) -> tuple[str, ...]:
    """``"png,pdf,svg"`` -> ("png", "pdf", "svg"): the ``--figure-format`` list, checked."""
    if isinstance(text, (list, tuple)):
        items = [str(t).strip().lower() for t in text]
    elif isinstance(text, str):
        items = [t.strip().lower().lstrip(".") for t in text.split(",") if t.strip()]
    else:
        raise TypeError(f"--figure-format: expected a comma-separated str, got {type(text).__name__}")
    bad = [t for t in items if t not in FIGURE_FORMATS]
    if bad or not items:
        raise ValueError(f"--figure-format: expected a comma-separated subset of {','.join(FIGURE_FORMATS)}, "
                         f"got {text!r}")
    return tuple(dict.fromkeys(items))


def figure_bytes(fig: Figure, fmt: str = "png", dpi: int = PNG_DPI) -> bytes:
    """The figure as ``fmt`` (png, pdf, svg) bytes, at its own size (fonts keep their points)."""
    if fmt not in FIGURE_FORMATS:
        raise ValueError(f"fmt: expected one of {FIGURE_FORMATS}, got {fmt!r}")
    buf = io.BytesIO()
    if fig.get_layout_engine() is None:  # keep a figure's own (e.g. constrained) layout
        fig.tight_layout()
    meta = {"pdf": {"Creator": "camo_sbi", "CreationDate": None},
            "svg": {"Creator": "camo_sbi", "Date": None}}.get(fmt)  # no date: same figure, same bytes
    with matplotlib.rc_context({"svg.fonttype": "none", "pdf.fonttype": 42, "svg.hashsalt": "camo_sbi"}):
        fig.savefig(buf, format=fmt, dpi=dpi, metadata=meta)
    return buf.getvalue()


def figure_png(fig: Figure, dpi: int = PNG_DPI) -> bytes:
    """The figure as PNG bytes."""
    return figure_bytes(fig, "png", dpi)


def _release(fig: Figure) -> None:
    manager = getattr(fig.canvas, "manager", None)
    if manager is not None:  # made by pyplot: release it from pyplot's registry
        import matplotlib.pyplot as plt

        plt.close(fig)


def save_figure(fig: Figure, path, dpi: int = PNG_DPI) -> Path:
    """Write ``fig`` to ``path`` atomically in the format its suffix names (.png, .pdf,
    .svg); a pyplot-managed figure is closed."""
    path = Path(path)
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in FIGURE_FORMATS:
        raise ValueError(f"path: expected a .png, .pdf or .svg file, got {path.name}")
    data = figure_bytes(fig, fmt, dpi)
    _release(fig)
    return Path(atomic_write_bytes(path, data))


def save_figures(fig: Figure, path, formats: Sequence[str] = ("png",), dpi: int = PNG_DPI) -> list[Path]:
    """Write ``fig`` once per format, ``path`` with each format's suffix (``out/fig.png``,
    ``out/fig.pdf``, ...), atomically; returns the paths written."""
    formats = parse_figure_formats(list(formats))
    path = Path(path)
    out = []
    for fmt in formats:
        target = path.with_suffix("." + fmt)
        atomic_write_bytes(target, figure_bytes(fig, fmt, dpi))
        out.append(target)
    _release(fig)
    return out


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
