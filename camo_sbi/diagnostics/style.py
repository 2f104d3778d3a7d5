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
* **no pyplot state**: figures are `matplotlib.figure.Figure` objects (`new_figure`),
  written atomically (`save_figure`: the format is the path's suffix).

The plot primitives on tidy tables, drawn in this look, are `camo_sbi.diagnostics.plot_primitives`:
`plot_lines`, `plot_bars`, axes that fit the data (`integer_ticks`, `robust_ylim`) and legends
outside the data (`figure_legend`).
"""

from __future__ import annotations

import contextlib
import functools
import io
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.figure import Figure

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
    "FIGURE_FORMATS",
    "MIN_FONT_PT",
    "MethodStyle",
    "PAPER_RC",
    "SINGLE_COLUMN",
    "SMALL_N",
    "band_label",
    "cell_rule",
    "cell_text",
    "display_metric",
    "few_runs",
    "figure_png",
    "mean_ci",
    "method_order",
    "method_style",
    "metric_label",
    "new_figure",
    "number",
    "paper_figure",
    "paper_style",
    "parse_figure_formats",
    "run_counts",
    "save_figure",
    "save_figures",
    "group_means",
    "to_degrees",
]

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
