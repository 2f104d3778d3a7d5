"""One self-contained HTML report for a run directory (opens offline, no external assets).

Why one module of ~1000 lines: one report, section by section (each section a function of the
run directory); the figures themselves live in `figures` and `style`.

Reads, from ``run_dir`` (every input optional)::

    config.json        run settings                          -> "Settings"
    results.csv        tidy: task, subject, method, budget,  -> "Comparison table",
                       seed, n_tasks, metric, value             "Error vs tasks", "Error vs budget"
    posteriors/*.nc    InferenceData from arviz_io            -> "Posteriors", "Diagnostics"
    estimates/*.nc     the same, for point estimates (`files`)
    coverage.csv       method, alpha, coverage[, coordinate,  -> "Calibration"
                       task, ...] (central_interval_coverage)

Every section is always present (``<section id=...>`` with a stable id); missing
inputs give a "not available: <reason>" note. Figures are drawn on plain
``matplotlib.figure.Figure`` objects (no pyplot state, rendered by Agg) in the paper style
of `camo_sbi.diagnostics.style` and embedded as base64 PNG ``data:`` URIs; with
``figure_formats`` each figure is also written to ``figure_dir`` (e.g. as PDF and SVG).
Angles are shown in degrees (the files keep radians); cells and captions follow the small-n
rule of `camo_sbi.diagnostics.style.cell_text`.

The HTML comes from the jinja2 templates of `camo_sbi.diagnostics.pages` (the layout and
the macros for a section, a table, a figure, a note): every string a section passes them (method,
subject, joint and file names, captions, error messages, table cells) is escaped by autoescaping;
a section body is the `Markup` those macros return.

Cached per input digest: the page records (``<meta name="camo-sbi-report-inputs">``) the sha256
of everything it was built from (the files above, the title, ``max_posteriors``, the corner and
figure-format options, the package version, the source of the diagnostics modules that draw
it and the bytes of its templates); `write_report` on the same inputs returns the existing page
without rebuilding it (``force=True`` rebuilds). With ``progress=True`` a tqdm bar on stderr names each section.

The jobs that hold the GIL without drawing (the simulations of the predictive reaches, the
C2ST classifiers of the posterior comparison) go to one helper process
(`camo_sbi.diagnostics.report_helper`) as soon as the posteriors are loaded, and run there
while this process draws; the same calls, so the same numbers; a job the helper could not do
is done here.
"""

from __future__ import annotations

import base64
import contextlib
import contextvars
import datetime as _dt
import hashlib
import io
import json
import os
import re
import textwrap
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from camo_sbi._files import parse_json, read_json
from camo_sbi._io import atomic_write_text
from camo_sbi.diagnostics.pages import Markup, join, page, part, table_parts, template_bytes

if TYPE_CHECKING:  # matplotlib is imported by the sections that draw: checking a cached report needs none
    from matplotlib.figure import Figure

__all__ = ["SECTIONS", "RESULTS_COLUMNS", "figure_files", "figure_html", "report_digest", "report_is_current",
           "table_html", "write_page", "write_report"]
_DIGEST_META = "camo-sbi-report-inputs"
_DRAWING_MODULES = ("report", "pages", "figures", "style", "arviz_io", "calibration")

SECTIONS: tuple[tuple[str, str], ...] = (
    ("settings", "Settings"),
    ("comparison-table", "Comparison table"),
    ("error-vs-tasks", "Error vs tasks"),
    ("error-vs-budget", "Error vs budget"),
    ("posteriors", "Posteriors"),
    ("posterior-predictive", "Posterior-predictive reaches"),
    ("posterior-comparison", "Posterior comparison"),
    ("calibration", "Calibration"),
    ("diagnostics", "Diagnostics"),
)
RESULTS_COLUMNS = ("task", "subject", "method", "budget", "seed", "n_tasks", "metric", "value")
"""Required columns of results.csv; an optional ``status`` column marks non-ok runs."""
_MAX_TABLE_ROWS = 400
_MAX_C2ST_PAIRS = 12  # each costs ~1 s (500 draws per side, 5-fold random forest)
_C2ST_SEED, _C2ST_DRAWS = 0, 500
_PPC_DRAWS = 50
_CORNER_LIMITS = 4
_DAGGER = "†"
_DPI = 140  # a 7 in figure -> 980 px in the 1200 px page (8 pt text -> 16 px)
# (directory, formats, names used) while write_report runs with figure_formats: every figure
# drawn is also written there
_FIGURE_SINK: contextvars.ContextVar[tuple[Path, tuple[str, ...], set] | None] = contextvars.ContextVar(
    "camo_sbi_report_figures", default=None)
_CORNER_CHOICE: contextvars.ContextVar[list[str] | None] = contextvars.ContextVar(
    "camo_sbi_report_corner", default=None)

# --------------------------------------------------------------------------- small html helpers


def _note(msg: str) -> Markup:
    return part("note", msg)


def _error(msg: str) -> Markup:
    """A problem the reader must act on (not a missing input): marked, and logged as a warning."""
    import logging

    logging.getLogger(__name__).warning("report: %s", msg)
    return part("error", msg)


def _meta(text: str) -> Markup:
    return part("meta", text)


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", text.lower()).strip("_")[:60] or "figure"


def _fig_html(fig: Figure, caption: str, alt: str | None = None) -> Markup:
    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png", dpi=_DPI)
        sink = _FIGURE_SINK.get()
        if sink is not None:
            from camo_sbi.diagnostics.style import save_figures

            folder, formats, used = sink
            name = f"{len(used) + 1:02d}_{_slug(alt or caption)}"
            used.add(name)
            save_figures(fig, folder / f"{name}.png", formats)
    finally:
        _empty(fig)
    # the toolkit's own PNG bytes as a data: URI (base64: autoescaping has nothing to change)
    src = "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")
    return part("figure", src, caption, alt or caption)


def _empty(fig: Figure) -> None:
    """Clear ``fig`` once it is saved: its axes are removed first, so `Figure.clear` does not
    clear each of them (which rebuilds every axis's ticks only to throw them away)."""
    for ax in tuple(fig.axes):
        fig.delaxes(ax)
    fig.clear()


def _table_html(df: pd.DataFrame, *, index: bool = True, float_format: str = "{:.4g}") -> Markup:
    total = len(df)
    shown = df.iloc[:_MAX_TABLE_ROWS]
    return part("table", table_parts(shown, index=index, float_format=float_format), shown=len(shown), total=total)


def _captioned(df: pd.DataFrame, caption: str) -> Markup:
    """``df`` as an HTML table (no index) with ``caption``."""
    return part("table", table_parts(df, index=False), caption=caption)


def _guard(build: Callable[[], Markup]) -> Markup:
    """Run a section builder; an unexpected error becomes a note instead of a broken report."""
    try:
        return build()
    except Exception as exc:  # noqa: BLE001 - the report must always be written
        return _note(f"error while building this section ({type(exc).__name__}: {exc})")


# --------------------------------------------------------------------------- inputs


def _flatten(d, prefix: str = "") -> list[tuple[str, str]]:
    rows = []
    if isinstance(d, dict):
        for k, v in d.items():
            rows += _flatten(v, f"{prefix}.{k}" if prefix else str(k))
    else:
        rows.append((prefix or "value", d if isinstance(d, str) else json.dumps(d)))
    return rows


def _load_results(run_dir: Path) -> tuple[pd.DataFrame | None, str]:
    p = run_dir / "results.csv"
    if not p.is_file():
        return None, "results.csv not found in the run directory"
    try:
        df = pd.read_csv(p)
    except Exception as exc:  # noqa: BLE001
        return None, f"results.csv could not be read ({type(exc).__name__}: {exc})"
    missing = [c for c in RESULTS_COLUMNS if c not in df.columns]
    if missing:
        return None, f"results.csv lacks columns {missing} (expected {list(RESULTS_COLUMNS)})"
    df = df.copy()
    for c in ("value", "budget", "n_tasks"):
        df[c] = pd.to_numeric(df[c], errors="coerce")
    df = df[np.isfinite(df["value"])]
    if df.empty:
        return None, "results.csv has no rows with a finite value"
    for c in ("task", "subject", "method", "metric"):
        df[c] = df[c].astype(str)
    if "status" in df:
        df["status"] = df["status"].fillna("ok").astype(str)
    return df, ""


def _load_posteriors(run_dir: Path, limit: int):
    """-> list of (path, idata or None, error message), note."""
    from camo_sbi.diagnostics.files import saved_files

    files = saved_files(run_dir)  # posteriors/*.nc, then the point estimates' estimates/*.nc
    if not files:
        return [], "no posteriors/*.nc or estimates/*.nc files in the run directory"
    from camo_sbi.diagnostics import arviz_io

    out = []
    for p in files[:limit]:
        try:
            out.append((p, arviz_io.load_netcdf(p), ""))
        except Exception as exc:  # noqa: BLE001
            out.append((p, None, f"{type(exc).__name__}: {exc}"))
    note = f"showing {limit} of {len(files)} posterior files" if len(files) > limit else ""
    return out, note


# --------------------------------------------------------------------------- sections


def _settings(run_dir: Path) -> Markup:
    p = run_dir / "config.json"
    if not p.is_file():
        return _note("config.json not found in the run directory")
    try:
        cfg = read_json(p, "config.json")
    except ValueError as exc:
        return _note(f"config.json could not be parsed ({exc})")
    rows = _flatten(cfg)
    if not rows:
        return _note("config.json is empty")
    return _table_html(pd.DataFrame(rows, columns=["setting", "value"]), index=False)


def _ci_cell(values) -> str:
    from camo_sbi.diagnostics.style import cell_text

    return cell_text(values)


def _budget_text(b) -> str:
    return "any budget" if pd.isna(b) else f"{b:g}"


def _table_metrics(names) -> list[str]:
    """The metrics of ``names`` with a table of their own, in the catalog's order (unknown ones
    last, by name): not the per-joint families (`_joint_table`) nor what describes the task
    rather than a method (``group="task"``: the binding counts, said beside the tables)."""
    from camo_sbi.evaluation import catalog

    def own_table(n):
        m = catalog.find(n)
        return m is None or not (m.per_joint or m.group == "task")

    return [n for n in catalog.ordered(names) if own_table(n)]


def _status_marks(sub: pd.DataFrame) -> dict[str, list[str]]:
    """{method: its distinct non-ok statuses} in ``sub`` (empty without a status column)."""
    if "status" not in sub:
        return {}
    bad = sub[sub["status"].astype(str) != "ok"]
    return {m: sorted(g["status"].astype(str).unique()) for m, g in bad.groupby("method")}


def _metric_table(sub: pd.DataFrame, metric: str, marks: dict[str, list[str]]) -> Markup:
    from camo_sbi.diagnostics.style import display_metric, method_order, metric_label

    m = display_metric(sub[sub["metric"] == metric])
    budgets = sorted(m["budget"].unique(), key=lambda b: (pd.isna(b), b))
    rows = []
    for method in method_order(m["method"]):
        g = m[m["method"] == method]
        row = {"method": method + (f" {_DAGGER}" if method in marks else "")}
        for b in budgets:
            vals = g[g["budget"].isna()] if pd.isna(b) else g[g["budget"] == b]
            row[_budget_text(b)] = _ci_cell(vals["value"].to_numpy()) if len(vals) else "–"
        rows.append(row)
    return _captioned(pd.DataFrame(rows), metric_label(metric))


def _joint_table(sub: pd.DataFrame, marks: dict[str, list[str]], metric) -> Markup:
    """One table of a per-joint metric family (``metric``: its catalog entry): methods as
    rows, joints as columns, at the largest budget."""
    from camo_sbi.diagnostics.style import method_order

    m = sub[sub["metric"].map(metric.matches)]
    bmax = m["budget"].max()
    m = m[(m["budget"] == bmax) | m["budget"].isna()]
    joints = list(dict.fromkeys(x[len(metric.prefix):] for x in m["metric"]))
    rows = []
    for method in method_order(m["method"]):
        g = m[m["method"] == method]
        rows.append({"method": method + (f" {_DAGGER}" if method in marks else ""),
                     **{j: _ci_cell(g.loc[g["metric"] == metric.row(j), "value"].to_numpy())
                        for j in joints}})
    cap = f"{metric.display_label('each joint')}, budget {_budget_text(bmax)}"
    return part("wide", _captioned(pd.DataFrame(rows), cap))


def _comparison(res: pd.DataFrame | None, why: str) -> Markup:
    from camo_sbi.diagnostics.style import cell_rule
    from camo_sbi.evaluation import catalog

    if res is None:
        return _note(why)
    out = []
    groups = list(res.groupby(["task", "subject"], sort=True))
    for (task, subject), tdf in groups:
        n_last = tdf["n_tasks"].max()
        sub = tdf[(tdf["n_tasks"] == n_last) | tdf["n_tasks"].isna()]
        seeds = sub.groupby(["method", "budget", "metric"], dropna=False)["value"].count()
        n = sorted(set(int(v) for v in seeds))
        marks = _status_marks(sub)
        metrics = _table_metrics(sub["metric"].unique())
        if len(groups) > 1:
            out.append(part("heading", f"task {task}, subject {subject}"))
        out.append(_meta(f"After {n_last:g} observed tasks. Each cell: {cell_rule(n, 'seeds')} "
                         "(the same rule as the figures); methods as rows, simulation budgets per observed task "
                         "as columns. Angles in degrees."))
        out.append(_binding_note(sub))
        out.append(part("tables", join(_metric_table(sub, m, marks) for m in metrics)))
        for family in (m for m in catalog.METRICS if m.per_joint):
            if sub["metric"].map(family.matches).any():
                out.append(_joint_table(sub, marks, family))
        if marks:
            lines = "; ".join(f"{m}: {', '.join(st)}" for m, st in marks.items())
            out.append(_meta(f'{_DAGGER} some runs of this method did not end with status "ok" '
                             f"(their rows are still averaged): {lines}."))
    return join(out)


def _binding_note(sub: pd.DataFrame) -> Markup:
    """How many held-out and observed reaches the restriction touches, beside the tables
    (`evaluation.claims.binding_line`); nothing for results that do not record it."""
    from camo_sbi.evaluation.claims import binding_line

    if not (sub["metric"] == "binding_test_reaches").any():
        return Markup("")
    return _meta(f"{binding_line(sub)}.")


def _largest(df: pd.DataFrame, by: str) -> pd.DataFrame:
    """Rows of each method at that method's largest value of ``by`` (NaN kept if it has none)."""
    parts = []
    for _, g in df.groupby("method"):
        top = g[by].max()
        parts.append(g if pd.isna(top) else g[(g[by] == top) | g[by].isna()])
    return pd.concat(parts)


def _xy_figures(res: pd.DataFrame | None, why: str, x: str, fixed: str, xlabel: str) -> Markup:
    from camo_sbi.diagnostics.style import display_metric, few_runs, paper_style, run_counts
    from camo_sbi.evaluation import catalog

    if res is None:
        return _note(why)
    res = display_metric(res)  # angles in degrees
    if res[x].nunique(dropna=True) < 2:
        vals = sorted(res[x].dropna().unique().tolist())
        return _note(f"results.csv has fewer than two distinct {x} values ({vals}): no figure "
                     "(the comparison tables hold the values)")
    parts = []
    for task, tdf in res.groupby("task"):
        sub = _largest(tdf, fixed)
        metrics = _table_metrics(sub["metric"].unique())
        # the headline metrics, and any the catalog does not know (no flag says they are not)
        shown = catalog.headline(metrics) + [m for m in metrics if catalog.find(m) is None]
        if not shown:
            parts.append(_note(f"task {task}: no headline metric in results.csv, no figure (the tables hold "
                               "the values)"))
            continue
        with paper_style():
            fig = _xy_panels(sub, shown, x, xlabel)
        cap = (f"task {task}: each method at its largest {fixed.replace('_', ' ')}; line = mean, "
               + ("dots = each seed and subject (fewer than 5: no confidence band)."
                  if few_runs(run_counts(sub, x)) else
                  "band = 95% confidence interval of the mean over seeds and subjects (Student t)."))
        if len(metrics) > len(shown):
            cap += f" Showing the {len(shown)} headline metrics of {len(metrics)} (all are in the tables)."
        parts.append(_fig_html(fig, cap, alt=f"{xlabel} figure for task {task}"))
    return join(parts)


def _xy_panels(sub: pd.DataFrame, shown: list[str], x: str, xlabel: str) -> Figure:
    """One panel per metric of ``shown`` against ``x``, one legend below."""
    from camo_sbi.diagnostics.plot_primitives import figure_legend, plot_lines
    from camo_sbi.diagnostics.style import (
        band_label,
        method_style,
        metric_label,
        new_figure,
        run_counts,
    )

    ncol = min(3, len(shown))
    nrow = int(np.ceil(len(shown) / ncol))
    fig, axes = new_figure(nrow, ncol, width="double", aspect=0.75)
    flat = axes.reshape(-1)
    for ax in flat[len(shown):]:
        ax.set_visible(False)
    for ax, metric in zip(flat, shown, strict=False):
        mdf = sub[sub["metric"] == metric]
        plot_lines(mdf[mdf[x].notna()], x=x, ax=ax, logx=x == "budget", ylabel="",
                   title=textwrap.fill(metric_label(metric), 34), legend=False)
        for method, g in mdf[mdf[x].isna()].groupby("method"):  # budget-free: a constant line
            ax.axhline(g["value"].mean(), label=method, **{**method_style(method).line_kwargs(), "marker": None})
        ax.set_xlabel(xlabel)
    figure_legend(fig, flat[: len(shown)], title=band_label(run_counts(sub, x)))
    return fig


# --------------------------------------------------------------------------- posteriors


def _attr(idata, key, default=None):
    return idata.posterior.attrs.get(key, default)


def _words(idata, *, method: bool = True) -> str:
    """A posterior's cell in words: method, budget, seed (and subject)."""
    parts = [str(_attr(idata, "method", "?"))] if method else []
    if _attr(idata, "budget") is not None:
        parts.append(f"budget {_attr(idata, 'budget')}")
    if _attr(idata, "seed") is not None:
        parts.append(f"seed {_attr(idata, 'seed')}")
    if _attr(idata, "n_tasks") is not None:
        parts.append(f"{_attr(idata, 'n_tasks')} tasks")
    return ", ".join(parts)


def _is_point(idata) -> bool:
    from camo_sbi.diagnostics import arviz_io

    return arviz_io.draws_kind(idata) == arviz_io.DRAWS_POINT or _attr(idata, "n_samples_original", 2) == 1


def _cells(posts):
    """{(task, subject): {(budget, seed): [(method, idata, path)]}} and the readable errors."""
    groups: dict[tuple, dict[tuple, list]] = {}
    errors = []
    for path, idata, err in posts:
        if idata is None:
            errors.append(_note(f"{path.name} could not be read ({err})"))
            continue
        key = (str(_attr(idata, "task", "")), str(_attr(idata, "subject", "")))
        cell = (_attr(idata, "budget"), _attr(idata, "seed"))
        groups.setdefault(key, {}).setdefault(cell, []).append((str(_attr(idata, "method", path.stem)), idata, path))
    return groups, errors


def _chosen(cells: dict) -> tuple:
    """The cell shown in full: the largest budget, then the smallest seed."""
    def key(c):
        b, s = c
        return (-(float(b) if isinstance(b, (int, float, np.number)) else -np.inf),
                float(s) if isinstance(s, (int, float, np.number)) else np.inf)
    return sorted(cells, key=key)[0]


def _cell_words(cell) -> str:
    b, s = cell
    parts = []
    if b is not None:
        parts.append(f"budget {b} simulations per observed task")
    if s is not None:
        parts.append(f"seed {s}")
    return ", ".join(parts) or "the posteriors"


def _group_words(task: str, subject: str) -> str:
    return ", ".join(x for x in (f"task {task}" if task else "", f"subject {subject}" if subject else "") if x)


def _limits_figure(members, caption_extra: str = "") -> Markup:
    from camo_sbi.diagnostics import arviz_io

    fig = arviz_io.plot_forest([d for _, d, _ in members], [m for m, _, _ in members])
    truth = ("; the black row is the true limit" if any(arviz_io.true_limits(d) is not None for _, d, _ in members)
             else "")
    return _fig_html(fig, "Every joint limit per method, in degrees (arviz forest plot): median (dot), quartiles "
                          "(thick), 94% highest-density interval (thin); a dot alone is a baseline's point "
                          "estimate" + truth + "." + caption_extra, alt="limits per method")


def _corner_selection(members, chosen: Sequence[str] | None = None) -> tuple[list[tuple[int, int]], list[str], str]:
    """The (joint, bound) limits of the corner plot and why they were chosen.

    ``chosen`` (``--corner-limits``, names like ``panda_joint4_lo``) wins. Otherwise, when
    the truth is stored: the restricted limits (the true limit lies inside the prior's
    range, not at its edge), most restricted first; without a truth (or when none is
    restricted): the limits whose posterior moved most from the prior (Wasserstein-1
    distance between the posterior and prior marginals, relative to the prior's width,
    averaged over the methods). At most _CORNER_LIMITS, never a fixed one.
    """
    from camo_sbi.diagnostics import arviz_io

    _, joints = arviz_io.limit_draws(members[0][1])
    if chosen:
        return arviz_io.parse_limit_names(list(chosen), joints), joints, "the limits asked for (--corner-limits)"
    draws = [arviz_io.limit_draws(d)[0].reshape(-1, 2 * len(joints)) for _, d, _ in members]
    free = np.any([np.ptp(d, axis=0) > 0 for d in draws], axis=0)
    idata = members[0][1]
    low, high = arviz_io.prior_box(idata)
    truth = arviz_io.true_limits(idata)
    if truth is not None and low is not None:
        t, lo, hi = truth.reshape(-1), low.reshape(-1), high.reshape(-1)
        width = np.where(hi > lo, hi - lo, np.nan)
        # how far the true limit sits inside the prior's range, from the edge it restricts
        inside = np.where(np.arange(t.size) % 2 == 0, t - lo, hi - t) / width
        order = [int(k) for k in np.argsort(-inside) if free[k] and np.isfinite(inside[k]) and inside[k] > 1e-6]
        if len(order) >= 2:
            return ([(k // 2, k % 2) for k in order[:_CORNER_LIMITS]], joints,
                    "the restricted limits (true limit inside the prior's range; most restricted first)")
    moved = arviz_io.moved_from_prior(idata, [d for d in draws])
    order = [int(k) for k in np.argsort(-moved) if free[k] and np.isfinite(moved[k])]
    return ([(k // 2, k % 2) for k in order[:_CORNER_LIMITS]], joints,
            "the limits whose posteriors moved most from the prior (Wasserstein-1 distance to the prior's "
            "marginal, relative to its width)")


def _corner_figure(posterior, points) -> Markup:
    from camo_sbi.diagnostics import arviz_io

    sel, joints, why = _corner_selection(posterior, _CORNER_CHOICE.get())
    if len(sel) < 2:
        return _note("a corner plot needs at least two free limits with a posterior")
    fig = arviz_io.plot_corner([d for _, d, _ in posterior], [m for m, _, _ in posterior], sel,
                               points={m: d for m, d, _ in points})
    names = ", ".join(arviz_io.limit_name(joints[j], b) for j, b in sel)
    truth = ("black lines and crosses: the truth; "
             if any(arviz_io.true_limits(d) is not None for _, d, _ in posterior) else "")
    return _fig_html(fig, f"Corner plot (arviz pair plot, one per method, overlaid) of {len(sel)} limits in "
                          f"degrees: {why}: {names}. Densities of the draws on the diagonal, pairs of draws "
                          f"below; {truth}markers and dashed lines: baselines' "
                          "point estimates. `--corner-limits a,b,c` chooses others.", alt="corner plot")


def _posteriors(posts, why: str) -> Markup:
    if not posts:
        return _note(why)
    from camo_sbi.diagnostics import arviz_io

    out = [_meta(why)] if why else []
    groups, errors = _cells(posts)
    out += errors
    for (task, subject), cells in groups.items():
        chosen = _chosen(cells)
        members = sorted(cells[chosen], key=lambda m: m[0])
        label = _group_words(task, subject)
        posterior = [m for m in members if not _is_point(m[1])]
        points = [m for m in members if _is_point(m[1])]
        out.append(part("heading", f"{label + ': ' if label else ''}{_cell_words(chosen)}"))
        out.append(_guard(lambda members=members: _limits_figure(members)))
        if posterior:
            out.append(_guard(lambda p=posterior, q=points: _corner_figure(p, q)))
            for method, idata, _ in posterior:
                def marginals(idata=idata, method=method):
                    fig = arviz_io.plot_posterior(idata)
                    truth = "; dashed black: the truth" if arviz_io.true_limits(idata) is not None else ""
                    return _fig_html(fig, f"{method}: marginal posterior of every limit (arviz's KDE of the "
                                          f"draws), its mean and its 94% HDI (the black bar){truth}.")
                out.append(part("details", f"Marginal posteriors: {_words(idata)}", _guard(marginals)))
        others = [c for c in cells if c != chosen]
        for cell in sorted(others, key=lambda c: (str(c[0]), str(c[1]))):
            ms = sorted(cells[cell], key=lambda m: m[0])
            out.append(part("details", f"Limits per method, {_cell_words(cell)}",
                            _guard(lambda ms=ms: _limits_figure(ms))))
    return join(out)


def _simulator(task: str, idata):
    """`_model_simulator` of the ``model_spec`` stored with ``idata``."""
    return _model_simulator(task, _attr(idata, "model_spec"))


def _model_simulator(task: str, raw):
    """(the simulator the posteriors were computed with, None) or (None, exactly why not).

    Rebuilt from the ``model_spec`` attribute the run stored with each posterior (the
    `ModelSpec` as JSON: model, its settings such as height and sex, URDF path and sha256, end
    effector, start, joints), never from the model's name alone: a --height 1.6 human is drawn
    1.6 m tall. A registered model is built by `camo_sbi.simulators.registry`; a model that is
    not registered here gives an `UnknownModel` reason (the section marks it as an error).
    """
    if raw is None:
        return None, (f"the posterior files of {task!r} do not record their model's settings (written before "
                      "camo-sbi stored them): run the command again into a new --out to draw these figures")
    try:
        spec = parse_json(raw, "model_spec")
        kind = spec["kind"]
    except (TypeError, ValueError, KeyError) as exc:
        return None, f"the posterior files' model_spec is unreadable ({type(exc).__name__}: {exc})"
    from camo_sbi.simulators import from_urdf, registry

    kwargs = {}
    if spec.get("start") is not None:
        kwargs["start"] = list(spec["start"])
    if spec.get("joints") is not None:
        kwargs["joints"] = list(spec["joints"])
    try:
        if kind != "urdf":
            if kind not in registry.model_names():
                return None, UnknownModel(
                    f"the body model {kind!r} of the posterior files is not registered in this camo_sbi "
                    f"(registered: {', '.join(registry.model_names())}): register it "
                    "(camo_sbi.simulators.registry.register_model) before building the report")
            return registry.build_model(kind, spec, **kwargs), None
        path = Path(str(spec.get("urdf")))
        try:
            text = path.read_text()
        except OSError as exc:
            return None, f"the URDF {path} the run used cannot be read ({exc.strerror or exc})"
        if spec.get("digest") and hashlib.sha256(text.encode()).hexdigest() != spec["digest"]:
            return None, f"the URDF {path} changed since the run (its sha256 differs from the one recorded)"
        return from_urdf(text, spec.get("ee"), **kwargs), None
    except ValueError as exc:
        return None, f"the run's model cannot be rebuilt ({exc})"


class UnknownModel(str):
    """The reason `_simulator` gives for a model this registry does not know (shown as an error)."""


def _observed(idata) -> dict[str, np.ndarray] | None:
    if "observed_data" not in idata.groups():
        return None
    od = idata.observed_data
    need = ("observed_ee", "observed_length", "observed_goal", "observed_start")
    if not all(k in od for k in need):
        return None
    return {k: np.asarray(od[k].values) for k in need}


def _predictive_paths(sim, draws: np.ndarray, obs: dict[str, np.ndarray], n_reaches: int) -> list[list[np.ndarray]]:
    """For each observed reach, the end-effector paths of the draws (S, 2n) from its start to its goal."""
    import torch

    from camo_sbi.evaluation.evaluate import predictive_trajectories

    goals = torch.as_tensor(obs["observed_goal"][:n_reaches], dtype=torch.float64)
    starts = torch.as_tensor(obs["observed_start"][:n_reaches], dtype=torch.float64)
    traj = predictive_trajectories(sim, draws, starts, goals)
    S = draws.shape[0]
    return [[traj.trimmed(s * n_reaches + i, "cartesian").numpy() for s in range(S)] for i in range(n_reaches)]


def _predictive_inputs(with_obs):
    """(observed arrays, reaches shown, per method the posterior draws simulated (radians))."""
    from camo_sbi.diagnostics import arviz_io

    obs = _observed(with_obs[0][1])
    n_reaches = min(4, int(obs["observed_length"].shape[0]))
    picks = []
    for _, idata in with_obs:
        d, _ = arviz_io.limit_draws(idata)
        flat = d.reshape(d.shape[0], -1)
        if str(_attr(idata, "units", "rad")) == "deg":
            flat = np.radians(flat)
        picks.append(flat[np.linspace(0, flat.shape[0] - 1, min(_PPC_DRAWS, flat.shape[0])).astype(int)])
    return obs, n_reaches, picks


def predictive_paths(task: str, model_spec, picks, obs, n_reaches: int):
    """The predictive section's simulations (run by the helper process, or here): ``(per pick
    the paths of `_predictive_paths`, None)``, or ``(None, why not)`` when the model cannot be
    rebuilt (`_model_simulator`)."""
    sim, why_not = _model_simulator(task, model_spec)
    if sim is None:
        return None, why_not
    return [_predictive_paths(sim, pick, obs, n_reaches) for pick in picks], None


def _with_observed(cells) -> list[tuple[str, object]]:
    """(method, idata) of the chosen cell's sampled posteriors that hold observed reaches."""
    members = [m for m in sorted(cells[_chosen(cells)], key=lambda m: m[0]) if not _is_point(m[1])]
    return [(m, d) for m, d, _ in members if _observed(d) is not None]


def _predictive(posts, why: str) -> Markup:
    if not posts:
        return _note(why)
    from camo_sbi.diagnostics.figures import plot_predictive

    groups, _ = _cells(posts)
    out = []
    for (task, subject), cells in groups.items():
        with_obs = _with_observed(cells)
        label = _group_words(task, subject)
        if not with_obs:
            out.append(_note(f"{label or 'these posteriors'}: the posterior files hold no observed reaches "
                             "to compare with"))
            continue
        obs, n_reaches, picks = _predictive_inputs(with_obs)
        pre = _PREFETCH.get()
        done = pre.helper.result(pre.predictive.get((task, subject))) if pre is not None else None
        # the helper's answer, else this process's: (None, why) or (paths per method, None); a
        # model the helper could not rebuild may be registered in this process only (register_model
        # at run time), so that answer is redone here
        if done is None or done[0] is None:
            done = predictive_paths(task, _attr(with_obs[0][1], "model_spec"), picks, obs, n_reaches)
        all_paths, why_not = done
        if all_paths is None:
            mark = _error if isinstance(why_not, UnknownModel) else _note
            out.append(mark(f"{label or 'these posteriors'}: {why_not}"))
            continue
        observed = [obs["observed_ee"][i, : int(obs["observed_length"][i])] for i in range(n_reaches)]
        for (method, idata), pick, paths in zip(with_obs, picks, all_paths, strict=True):
            fig = plot_predictive(observed, {method: paths}, goals=obs["observed_goal"],
                                  title=f"{method}: {_words(idata, method=False)}")
            out.append(part("heading", _words(idata)) + _fig_html(
                fig, f"The observed reaches (black, the first {n_reaches}) against the end-effector paths "
                     f"simulated with {len(pick)} posterior draws for the same starts and goals (thin "
                     "lines): top view (x–y) and side view (x–z), metres. Draws that reproduce the "
                     "observation lie on the black path.", alt=f"posterior-predictive reaches of {method}"))
    return join(out)


def _calibration(run_dir: Path) -> Markup:
    p = run_dir / "coverage.csv"
    if not p.is_file():
        return _note("calibration was not computed (coverage.csv not found in the run directory)")
    from camo_sbi.diagnostics.calibration import plot_coverage

    df = pd.read_csv(p)
    missing = {"method", "alpha", "coverage"} - set(df.columns)
    if missing:
        return _note(f"coverage.csv lacks columns {sorted(missing)}")
    coord = "overall"
    if "coordinate" in df:
        df["coordinate"] = df["coordinate"].astype(str)
        if coord not in set(df["coordinate"]):
            coord = str(df["coordinate"].iloc[0])
    out = []
    tasks = sorted(df["task"].astype(str).unique()) if "task" in df else [None]
    for task in tasks:
        sub = df if task is None else df[df["task"].astype(str) == task]
        fig = plot_coverage(sub, coordinate=coord, title=f"Coverage ({coord})" + (f", task {task}" if task else ""))
        out.append(_fig_html(fig, "Empirical coverage of central credible intervals vs credibility level; "
                                  "the dashed diagonal is perfect calibration, below it is over-confident"
                                  + (f" (task {task})." if task else ".")))
    sel = df[df["coordinate"] == coord] if "coordinate" in df else df
    keys = ["task", "method"] if "task" in sel else ["method"]
    dev = sel.assign(dev=sel["coverage"] - sel["alpha"])
    tab = dev.groupby(keys)["dev"].agg(mean_deviation="mean",
                                       max_abs_deviation=lambda v: float(np.max(np.abs(v)))).reset_index()
    out.append(_meta("coverage − α over all levels (negative: over-confident).") + _table_html(tab, index=False))
    return join(out)


def _posterior_comparison_table(posts) -> pd.DataFrame:
    """Pairwise W1 / C2ST between methods' posteriors for the same subject, budget, seed, tasks."""
    pre = _PREFETCH.get()
    if pre is not None and pre.posts is posts and pre.comparison is not None:
        rows, pairs, jobs = pre.comparison
        done = [pre.helper.result(j) for j in jobs]
    else:
        rows, pairs = _comparison_rows(posts)
        done = [None] * len(pairs)
    todo = [p for p, acc in zip(pairs, done, strict=True) if acc is None]
    for (i, _, _), acc in zip(pairs, done, strict=True):
        if acc is not None:
            rows[i]["C2ST accuracy"] = acc
    if todo:  # no helper process (or a job failed there): here, in threads
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(max_workers=max(1, min(len(todo), os.cpu_count() or 1))) as pool:
            for (i, _, _), acc in zip(todo, pool.map(lambda p: _c2st(*p[1:]), todo), strict=True):
                rows[i]["C2ST accuracy"] = acc
    return pd.DataFrame(rows)


def _c2st(a: np.ndarray, b: np.ndarray) -> float:
    return c2st_accuracy(a, b, _C2ST_SEED, _C2ST_DRAWS)


def c2st_accuracy(a: np.ndarray, b: np.ndarray, seed: int, max_samples: int) -> float:
    """The comparison table's C2ST (`camo_sbi.diagnostics.calibration.c2st`; also run by the helper)."""
    from camo_sbi.diagnostics.calibration import c2st

    return float(c2st(a, b, seed, max_samples=max_samples))


def _comparison_rows(posts) -> tuple[list[dict], list[tuple[int, np.ndarray, np.ndarray]]]:
    """The comparison table's rows (C2ST still NaN) and its C2ST pairs: (row, draws A, draws B)."""
    import itertools

    from camo_sbi.diagnostics import arviz_io

    groups: dict[tuple, list] = {}
    for _, idata, _ in posts:
        if idata is None:
            continue
        a = idata.posterior.attrs
        draws = arviz_io.limit_draws(idata)[0]  # every stored sample (the posterior group holds a few)
        draws = draws.reshape(draws.shape[0], -1)
        if draws.shape[0] < 20:  # a point estimate (naive) is not a posterior to compare
            continue
        key = (a.get("subject", "–"), a.get("budget", "–"), a.get("seed", "–"), a.get("n_tasks", "–"))
        groups.setdefault(key, []).append((str(a.get("method", "?")), idata, draws))
    rows, pairs = [], []
    for (subject, budget, seed, n_tasks), members in sorted(groups.items(), key=lambda kv: str(kv[0])):
        for (ma, ia, da), (mb, ib, db) in itertools.combinations(sorted(members, key=lambda m: m[0]), 2):
            free = (da.std(axis=0) > 0) | (db.std(axis=0) > 0)
            w1 = arviz_io.compare_marginals(ia, ib)["wasserstein"].to_numpy()[free] * _to_deg(ia)
            if len(pairs) < _MAX_C2ST_PAIRS:
                pairs.append((len(rows), da[:, free], db[:, free]))
            rows.append({"subject": subject, "budget": budget, "seed": seed, "n_tasks": n_tasks,
                         "method A": ma, "method B": mb, "mean W1 over free marginals [deg]": float(w1.mean()),
                         "max W1 [deg]": float(w1.max()), "C2ST accuracy": float("nan")})
    return rows, pairs


def _posterior_comparison(posts, why: str) -> Markup:
    if not posts:
        return _note(why)
    table = _posterior_comparison_table(posts)
    if table.empty:
        return _note("needs at least two sampled posteriors (not point estimates) for the same "
                     "subject, budget and seed")
    return (_meta("Wasserstein-1 distance between the two methods' marginals over the "
                  "free limits (degrees), and classifier two-sample test accuracy "
                  "(C2ST, sbi's random-forest metric on 500 draws per side: 0.5 = indistinguishable, 1 = "
                  f"disjoint; computed for the first {_MAX_C2ST_PAIRS} pairs). Point estimates are left out. "
                  "No method is a ground-truth reference here: compare with the calibration section to "
                  "see which posteriors are trustworthy.")
            + _table_html(table, index=False))


_SUMMARY_ANGLES = ("mean", "sd", "mcse_mean", "mcse_sd", "truth")  # and every hdi_* column
_WIDTH_ANGLES = ("hdi_lower", "hdi_upper", "posterior_width", "prior_width")


def _to_deg(idata) -> float:
    """The factor from a file's limits to degrees (1 when it holds degrees already)."""
    return 1.0 if str(_attr(idata, "units", "rad")) == "deg" else float(np.degrees(1.0))


def _in_degrees(df: pd.DataFrame, idata, columns) -> pd.DataFrame:
    """``df`` with its angle ``columns`` (and hdi_* columns) in degrees, the headers saying so."""
    f = _to_deg(idata)
    cols = [c for c in df.columns if c in columns or str(c).startswith("hdi_")]
    out = df.copy()
    for c in cols:
        out[c] = out[c].astype(float) * f
    return out.rename(columns={c: f"{c} [deg]" for c in cols})


def _diagnostics(posts, why: str) -> Markup:
    if not posts:
        return _note(why)
    from camo_sbi.diagnostics import arviz_io
    from camo_sbi.diagnostics.style import number

    meta_rows, out = [], []
    for path, idata, err in posts:
        if idata is None:
            out.append(_note(f"{path.name} could not be read ({err})"))
            continue
        a = idata.posterior.attrs
        kind = arviz_io.draws_kind(idata)
        ess = a.get("weights_ess")
        meta_rows.append({
            "method": a.get("method", "–"), "budget": a.get("budget", "–"), "seed": a.get("seed", "–"),
            "subject": a.get("subject", "–"), "tasks": a.get("n_tasks", "–"),
            "simulations": a.get("n_simulations", "–"),
            "wall time [s]": number(a["wall_time"]) if "wall_time" in a else "–",
            "compile time [s]": number(a["compile_time"]) if "compile_time" in a else "–",
            "draws": kind,
            "effective samples (Kish)": "–" if ess is None or kind == arviz_io.DRAWS_POINT
            else f"{float(ess):.1f} of {a.get('n_samples_original', '?')}",
            "status": a.get("status", "–")})
        if kind == arviz_io.DRAWS_POINT:
            continue
        if kind == arviz_io.DRAWS_RESAMPLED:
            head = (f"draws resampled from {a.get('n_samples_original', '?')} weighted samples whose weights imply "
                    f"{float(ess):.1f} effective samples (Kish, (Σw)²/Σw²); MCMC columns (mcse, ess_bulk, "
                    "ess_tail, r_hat) are left out: they would count the repeated draws.")
        else:
            head = "independent draws in one chain: ess as arviz computes it, no r_hat (needs several chains)."
        body = [_meta(f"arviz summary, in degrees (the file holds {_attr(idata, 'units', 'rad')}); {head}"),
                _table_html(_in_degrees(arviz_io.summary(idata), idata, _SUMMARY_ANGLES))]
        with contextlib.suppress(ValueError):
            body.append(_meta("Posterior 94% HDI width relative to the prior "
                              "(1: uninformed by the observations, 0: pinned down).")
                        + _table_html(_in_degrees(arviz_io.posterior_width(idata), idata, _WIDTH_ANGLES)))
        with contextlib.suppress(ValueError):
            body.append(_meta("Position of the true limit in each marginal "
                              "(posterior quantile; near 0 or 1: the truth is in a tail).")
                        + _table_html(_in_degrees(arviz_io.truth_position(idata), idata, ("truth",))))
        body.insert(0, _meta(f"file {path.parent.name}/{path.name}"))
        out.append(part("details", _words(idata), join(body)))
    head = Markup("")
    if meta_rows:
        head = (_meta("One row per posterior file. Point estimates (baselines) have no posterior diagnostics.")
                + part("wide", _table_html(pd.DataFrame(meta_rows), index=False)))
    return head + join(out)


# --------------------------------------------------------------------------- entry point


def _inputs_digest(run_dir: Path, title: str, max_posteriors: int, options) -> str:
    """sha256 of everything the report of ``run_dir`` is built from (see the module docstring)."""
    from camo_sbi import __version__

    h = hashlib.sha256(json.dumps([__version__, title, max_posteriors, options], default=str).encode())
    h.update(template_bytes())  # the page's templates: a changed template rebuilds the report
    here = Path(__file__).parent
    files = [here / f"{m}.py" for m in _DRAWING_MODULES]
    files += [run_dir / n for n in ("config.json", "results.csv", "coverage.csv")]
    from camo_sbi.diagnostics.files import saved_files

    posts = saved_files(run_dir)
    h.update(json.dumps([f"{p.parent.name}/{p.name}" for p in posts]).encode())
    for p in files + posts[:max_posteriors]:
        h.update(p.name.encode() + b"\0")
        if p.is_file():
            h.update(hashlib.sha256(p.read_bytes()).digest())
    return h.hexdigest()


def report_digest(path) -> str | None:
    """The input digest recorded in a report written by `write_report` (None: none recorded)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096).decode("utf-8", "replace")
    except OSError:
        return None
    m = re.search(rf'<meta name="{_DIGEST_META}" content="([0-9a-f]{{64}})">', head)
    return m.group(1) if m else None


def _options(corner_limits, figure_formats, figure_dir) -> list:
    return [None if corner_limits is None else [str(c) for c in corner_limits],
            None if not figure_formats else [str(f) for f in figure_formats],
            None if figure_dir is None else str(figure_dir)]


def report_is_current(run_dir, out_path, *, title: str | None = None, max_posteriors: int = 24,
                      corner_limits: Sequence[str] | None = None, figure_formats: Sequence[str] | None = None,
                      figure_dir=None) -> bool:
    """True if ``out_path`` is a report `write_report` built from ``run_dir``'s current inputs
    with these options."""
    run_dir, out_path = Path(run_dir), Path(out_path)
    title = title or f"camo_sbi report: {run_dir.resolve().name}"
    digest = _inputs_digest(run_dir, title, max_posteriors, _options(corner_limits, figure_formats, figure_dir))
    return out_path.is_file() and report_digest(out_path) == digest


def write_report(run_dir, out_path, *, title: str | None = None, max_posteriors: int = 24,
                 corner_limits: Sequence[str] | None = None, figure_formats: Sequence[str] | None = None,
                 figure_dir=None, force: bool = False, progress: bool = False) -> Path:
    """Write one self-contained HTML report for ``run_dir`` to ``out_path`` (atomically).

    Args:
        run_dir: directory holding any of config.json, results.csv, posteriors/*.nc, coverage.csv.
        out_path: the .html file to write (parent directories are created).
        title: page title (default: "camo_sbi report: <run_dir name>").
        max_posteriors: at most this many netCDF posteriors are plotted.
        corner_limits: the limits of the corner plot (``["panda_joint4_lo", ...]``, as
            ``--corner-limits``); default: the restricted ones when the truth is known, else
            those that moved most from the prior.
        figure_formats: also write every figure of the report in these formats (png, pdf,
            svg) to ``figure_dir`` (default: ``<out_path's folder>/report_figures``).
        force: rebuild even if ``out_path`` was built from the same inputs (module docstring).
        progress: a tqdm bar on stderr, one step per section.

    Returns:
        The path written. Sections (ids): settings, comparison-table, error-vs-tasks,
        error-vs-budget, posteriors, posterior-predictive, posterior-comparison, calibration,
        diagnostics.
    """
    if not isinstance(run_dir, (str, os.PathLike)):
        raise TypeError(f"run_dir: expected str or PathLike, got {type(run_dir).__name__}")
    if not isinstance(out_path, (str, os.PathLike)):
        raise TypeError(f"out_path: expected str or PathLike, got {type(out_path).__name__}")
    if title is not None and not isinstance(title, str):
        raise TypeError(f"title: expected str or None, got {type(title).__name__}")
    if isinstance(max_posteriors, bool) or not isinstance(max_posteriors, int) or max_posteriors < 1:
        raise ValueError(f"max_posteriors: expected an int >= 1, got {max_posteriors!r}")
    run_dir, out_path = Path(run_dir), Path(out_path)
    if not run_dir.is_dir():
        raise ValueError(f"run_dir: {run_dir} is not a directory")
    if out_path.exists() and out_path.is_dir():
        raise ValueError(f"out_path: {out_path} is a directory")
    title = title or f"camo_sbi report: {run_dir.resolve().name}"
    if corner_limits is not None and (isinstance(corner_limits, str) or not isinstance(corner_limits, Sequence)):
        raise TypeError(f"corner_limits: expected a list of limit names, got {type(corner_limits).__name__}")
    digest = _inputs_digest(run_dir, title, max_posteriors, _options(corner_limits, figure_formats, figure_dir))
    if not force and out_path.is_file() and report_digest(out_path) == digest:
        return out_path
    folder = Path(figure_dir) if figure_dir is not None else out_path.parent / "report_figures"
    corner_token = _CORNER_CHOICE.set(None if corner_limits is None else [str(c) for c in corner_limits])
    try:
        with figure_files(folder, figure_formats):
            return _write_report(run_dir, out_path, title, max_posteriors, digest, progress)
    finally:
        _CORNER_CHOICE.reset(corner_token)


@contextlib.contextmanager
def figure_files(folder, formats: Sequence[str] | None):
    """Inside the block every figure `figure_html` embeds is also written to ``folder`` in
    each of ``formats`` (``01_<alt text>.pdf``, ...); ``formats`` None or empty: nothing is."""
    sink = None
    if formats:
        from camo_sbi.diagnostics.style import parse_figure_formats

        Path(folder).mkdir(parents=True, exist_ok=True)
        sink = (Path(folder), parse_figure_formats(list(formats)), set())
    token = _FIGURE_SINK.set(sink)
    try:
        yield
    finally:
        _FIGURE_SINK.reset(token)


def _write_report(run_dir: Path, out_path: Path, title: str, max_posteriors: int, digest: str,
                  progress: bool) -> Path:
    from camo_sbi.diagnostics.files import saved_files
    from camo_sbi.diagnostics.report_helper import Helper

    # the helper process starts now (it imports while this process does) when there is work for it
    with Helper(enabled=_USE_HELPER and bool(saved_files(run_dir))) as helper:
        return _build_report(run_dir, out_path, title, max_posteriors, digest, progress, helper)


def _build_report(run_dir: Path, out_path: Path, title: str, max_posteriors: int, digest: str,
                  progress: bool, helper) -> Path:
    from tqdm import tqdm

    bar = tqdm(total=len(SECTIONS) + 1, desc="report", unit="section", disable=not progress)
    bar.set_postfix_str("loading results and posteriors")
    res, res_why = _load_results(run_dir)
    try:
        posts, post_why = _load_posteriors(run_dir, max_posteriors)
    except Exception as exc:  # noqa: BLE001
        posts, post_why = [], f"posteriors could not be loaded ({type(exc).__name__}: {exc})"
    token = _PREFETCH.set(_prefetch(posts, helper))
    try:
        return _sections(run_dir, out_path, title, digest, bar, res, res_why, posts, post_why)
    finally:
        _PREFETCH.reset(token)


def _sections(run_dir, out_path, title, digest, bar, res, res_why, posts, post_why) -> Path:
    bar.update()

    builders = {
        "settings": lambda: _settings(run_dir),
        "comparison-table": lambda: _comparison(res, res_why),
        "error-vs-tasks": lambda: _xy_figures(res, res_why, "n_tasks", "budget", "number of observed tasks"),
        "error-vs-budget": lambda: _xy_figures(res, res_why, "budget", "n_tasks", "simulations per observed task"),
        "posteriors": lambda: _posteriors(posts, post_why),
        "posterior-predictive": lambda: _predictive(posts, post_why),
        "posterior-comparison": lambda: _posterior_comparison(posts, post_why),
        "calibration": lambda: _calibration(run_dir),
        "diagnostics": lambda: _diagnostics(posts, post_why),
    }
    bodies = {}
    with bar:
        for sid, name in SECTIONS:
            bar.set_postfix_str(name)
            bodies[sid] = _guard(builders[sid])
            bar.update()
    return write_page(out_path, title, [(sid, name, bodies[sid]) for sid, name in SECTIONS],
                      meta=f"run directory: {run_dir.resolve()}", digest=digest)


class _Prefetched:
    """What `_prefetch` handed the helper process for one report (read by the sections)."""

    def __init__(self, posts, helper):
        self.posts, self.helper = posts, helper
        self.predictive: dict[tuple, int | None] = {}  # (task, subject) -> the helper's simulation job
        self.comparison = None  # (rows, pairs, the helper's C2ST jobs)


_PREFETCH: contextvars.ContextVar[_Prefetched | None] = contextvars.ContextVar(
    "camo_sbi_report_prefetch", default=None)
_USE_HELPER = True  # tests switch the helper process off to compare


def _prefetch(posts, helper) -> _Prefetched | None:
    """Hand the helper the simulations of the predictive reaches (first) and the C2ST pairs of the
    posterior comparison; None (the sections do it all) when there is nothing to hand over or
    this fails."""
    if not posts:
        return None
    pre = _Prefetched(posts, helper)
    try:
        groups, _ = _cells(posts)
        for (task, subject), cells in groups.items():
            with_obs = _with_observed(cells)
            if with_obs:
                obs, n_reaches, picks = _predictive_inputs(with_obs)
                pre.predictive[(task, subject)] = helper.submit(
                    "predictive_paths", task, _attr(with_obs[0][1], "model_spec"), picks, obs, n_reaches)
        rows, pairs = _comparison_rows(posts)
        pre.comparison = (rows, pairs, [helper.submit("c2st", a, b, _C2ST_SEED, _C2ST_DRAWS) for _, a, b in pairs])
    except Exception:  # noqa: BLE001 - the sections do the work themselves (and report its errors)
        return None
    return pre


def figure_html(fig: Figure, caption: str, alt: str | None = None) -> Markup:
    """A matplotlib figure as an embedded PNG ``<figure>`` (the figure is cleared); ``caption``
    and ``alt`` are text (escaped)."""
    return _fig_html(fig, caption, alt)


def table_html(df: pd.DataFrame, *, index: bool = False, float_format: str = "{:.4g}") -> Markup:
    """A DataFrame as an HTML table (at most the first 400 rows); every cell is text (escaped)."""
    return _table_html(df, index=index, float_format=float_format)


def write_page(out_path, title: str, sections, *, meta: str = "", digest: str | None = None) -> Path:
    """Write a self-contained HTML page atomically: ``sections`` is [(id, heading, body)].

    Rendered by the templates of `camo_sbi.diagnostics.pages` (page.html.j2): every section
    gets ``<section id=...>``; ``title``, headings and ``meta`` (a line under the title) are
    text and escaped; a body is `Markup` built from `pages.part` fragments (`figure_html`,
    `table_html`, ...), and a plain ``str`` body is shown as text, escaped, never as markup.
    ``digest`` (hex sha256 of the page's inputs) is recorded for `report_digest`.
    """
    if not isinstance(title, str):
        raise TypeError(f"title: expected str, got {type(title).__name__}")
    if digest is not None and not re.fullmatch(r"[0-9a-f]{64}", str(digest)):
        raise ValueError(f"digest: expected a hex sha256 or None, got {digest!r}")
    sections = [(str(sid), str(name), body if isinstance(body, Markup) else join([body]))
                for sid, name, body in sections]
    stamp = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    doc = page(title=title, digest_meta=_DIGEST_META, digest=digest, meta=meta, stamp=stamp, sections=sections)
    atomic_write_text(out_path, doc)
    return Path(out_path)
