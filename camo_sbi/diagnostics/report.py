"""One self-contained HTML report for a run directory (opens offline, no external assets).

Reads, from ``run_dir`` (every input optional)::

    config.json        run settings                          -> "Settings"
    results.csv        tidy: task, subject, method, budget,  -> "Comparison table",
                       seed, n_tasks, metric, value             "Error vs tasks", "Error vs budget"
    posteriors/*.nc    InferenceData from arviz_io            -> "Posteriors", "Diagnostics"
    coverage.csv       method, alpha, coverage[, coordinate,  -> "Calibration"
                       task, ...] (central_interval_coverage)

Every section is always present (``<section id=...>`` with a stable id); missing
inputs give a "not available: <reason>" note. Figures are drawn on plain
``matplotlib.figure.Figure`` objects (no pyplot state, rendered by Agg) and
embedded as base64 PNG ``data:`` URIs.
"""

from __future__ import annotations

import base64
import contextlib
import datetime as _dt
import html
import io
import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from camo_sbi._io import atomic_write_text

__all__ = ["SECTIONS", "RESULTS_COLUMNS", "figure_html", "table_html", "write_page", "write_report"]

SECTIONS: tuple[tuple[str, str], ...] = (
    ("settings", "Settings"),
    ("comparison-table", "Comparison table"),
    ("error-vs-tasks", "Error vs tasks"),
    ("error-vs-budget", "Error vs budget"),
    ("posteriors", "Posteriors"),
    ("posterior-comparison", "Posterior comparison"),
    ("calibration", "Calibration"),
    ("diagnostics", "Diagnostics"),
)
RESULTS_COLUMNS = ("task", "subject", "method", "budget", "seed", "n_tasks", "metric", "value")
_MAX_TABLE_ROWS = 400
_MAX_C2ST_PAIRS = 12  # each costs ~1 s (500 draws per side, 5-fold random forest)
_MAX_METRIC_PANELS = 9

_CSS = """
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:0 auto;max-width:1200px;
padding:1em 2em;color:#222;background:#fff}
h1{border-bottom:2px solid #446;padding-bottom:.2em}
h2{border-bottom:1px solid #ccd;margin-top:2em}
nav ul{columns:2;list-style:none;padding-left:0}
table{border-collapse:collapse;font-size:12px;margin:.5em 0 1em}
th,td{border:1px solid #ccd;padding:2px 6px;text-align:right}
th{background:#eef}
td:first-child,th:first-child{text-align:left}
.note{background:#fff6e0;border-left:4px solid #e0a000;padding:.4em .8em}
.meta{color:#666;font-size:12px}
figure{margin:.5em 0 1.5em}
figcaption{font-size:12px;color:#555}
img{max-width:100%;height:auto;border:1px solid #eee}
details{margin:.4em 0}
summary{cursor:pointer;font-weight:600}
"""


# --------------------------------------------------------------------------- small html helpers


def _esc(x) -> str:
    return html.escape(str(x), quote=True)


def _note(msg: str) -> str:
    return f'<p class="note">not available: {_esc(msg)}</p>'


def _fig_html(fig: Figure, caption: str, alt: str | None = None) -> str:
    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png", dpi=90)
    finally:
        fig.clear()
    data = base64.b64encode(buf.getvalue()).decode("ascii")
    return (f'<figure><img src="data:image/png;base64,{data}" alt="{_esc(alt or caption)}">'
            f"<figcaption>{_esc(caption)}</figcaption></figure>")


def _table_html(df: pd.DataFrame, *, index: bool = True, float_format: str = "{:.4g}") -> str:
    note = ""
    if len(df) > _MAX_TABLE_ROWS:
        note = f'<p class="meta">showing the first {_MAX_TABLE_ROWS} of {len(df)} rows</p>'
        df = df.iloc[:_MAX_TABLE_ROWS]
    return note + df.to_html(index=index, escape=True, border=0, na_rep="–",
                             float_format=lambda v: float_format.format(v))


def _guard(build: Callable[[], str]) -> str:
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
    return df, ""


def _load_posteriors(run_dir: Path, limit: int):
    """-> list of (path, idata or None, error message), note."""
    d = run_dir / "posteriors"
    files = sorted(d.glob("*.nc")) if d.is_dir() else []
    if not files:
        return [], "no posteriors/*.nc files in the run directory"
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


def _settings(run_dir: Path) -> str:
    p = run_dir / "config.json"
    if not p.is_file():
        return _note("config.json not found in the run directory")
    try:
        cfg = json.loads(p.read_text())
    except (OSError, ValueError) as exc:
        return _note(f"config.json could not be parsed ({exc})")
    rows = _flatten(cfg)
    if not rows:
        return _note("config.json is empty")
    return _table_html(pd.DataFrame(rows, columns=["setting", "value"]), index=False)


def _fmt_cell(mean: float, std: float, n: int) -> str:
    if n > 1 and np.isfinite(std):
        return f"{mean:.4g} ± {std:.2g} (n={n})"
    return f"{mean:.4g} (n={n})"


def _comparison(res: pd.DataFrame | None, why: str) -> str:
    if res is None:
        return _note(why)
    keys = ["task", "subject", "method", "budget", "n_tasks"]
    g = res.groupby(keys + ["metric"], dropna=False)["value"].agg(["mean", "std", "count"]).reset_index()
    g["cell"] = [_fmt_cell(m, s, int(n)) for m, s, n in zip(g["mean"], g["std"], g["count"], strict=True)]
    wide = g.pivot_table(index=keys, columns="metric", values="cell", aggfunc="first", dropna=False)
    wide = wide.dropna(how="all").reset_index()
    wide.columns.name = None
    for c in ("budget", "n_tasks"):
        wide[c] = wide[c].map(lambda v: "–" if pd.isna(v) else f"{v:g}")
    return ('<p class="meta">mean ± standard deviation over seeds (n = number of seeds) for each '
            "task, subject, method, simulation budget and number of observed tasks.</p>"
            + _table_html(wide, index=False))


def _panel_grid(metrics: list[str]) -> tuple[Figure, np.ndarray]:
    k = len(metrics)
    ncol = min(3, k)
    nrow = int(np.ceil(k / ncol))
    fig = Figure(figsize=(4.2 * ncol, 3.2 * nrow), layout="constrained")
    axes = np.asarray(fig.subplots(nrow, ncol, squeeze=False)).reshape(-1)
    for ax in axes[k:]:
        ax.set_visible(False)
    return fig, axes


def _largest(df: pd.DataFrame, by: str) -> pd.DataFrame:
    """Rows of each method at that method's largest value of ``by`` (NaN kept if it has none)."""
    parts = []
    for _, g in df.groupby("method"):
        top = g[by].max()
        parts.append(g if pd.isna(top) else g[(g[by] == top) | g[by].isna()])
    return pd.concat(parts)


def _xy_figures(res: pd.DataFrame | None, why: str, x: str, fixed: str, xlabel: str) -> str:
    if res is None:
        return _note(why)
    if res[x].nunique(dropna=True) < 2:
        vals = sorted(res[x].dropna().unique().tolist())
        return _note(f"results.csv has fewer than two distinct {x} values ({vals})")
    parts = []
    for task, tdf in res.groupby("task"):
        sub = _largest(tdf, fixed)
        metrics = sorted(sub["metric"].unique())
        shown = metrics[:_MAX_METRIC_PANELS]
        fig, axes = _panel_grid(shown)
        xs_all = sub[x].dropna()
        log = bool(len(xs_all) and xs_all.min() > 0 and xs_all.max() / xs_all.min() >= 10)
        for ax, metric in zip(axes, shown, strict=False):
            mdf = sub[sub["metric"] == metric]
            for i, (method, g) in enumerate(mdf.groupby("method")):
                color = f"C{i % 10}"
                agg = g.groupby(x)["value"].agg(["mean", "std"]).reset_index()
                if len(agg) >= 2:
                    ax.errorbar(agg[x], agg["mean"], yerr=agg["std"].fillna(0), marker="o", ms=4,
                                capsize=3, color=color, label=method)
                else:  # a single x (or none, e.g. a budget-free baseline): a reference line
                    ax.axhline(g["value"].mean(), ls="--", color=color, label=f"{method} (constant)")
            ax.set_title(metric, fontsize=10)
            ax.set_xlabel(xlabel, fontsize=9)
            if log:
                ax.set_xscale("log")
            ax.legend(fontsize=7)
        cap = (f"task {task}: mean ± sd over seeds and subjects vs {xlabel}; each method at its largest "
               f"{fixed.replace('_', ' ')}.")
        if len(metrics) > len(shown):
            cap += f" Showing {len(shown)} of {len(metrics)} metrics."
        parts.append(_fig_html(fig, cap, alt=f"{xlabel} figure for task {task}"))
    return "".join(parts)


def _posteriors(posts, why: str) -> str:
    if not posts:
        return _note(why)
    from camo_sbi.diagnostics import arviz_io

    out = [f'<p class="meta">{_esc(why)}</p>'] if why else []
    groups: dict[tuple, list[tuple[str, object]]] = {}
    for path, idata, err in posts:
        if idata is None:
            out.append(_note(f"{path.name} could not be read ({err})"))
            continue
        a = idata.posterior.attrs
        try:
            fig = arviz_io.plot_posterior(idata)
            out.append(f"<h3>{_esc(path.name)}</h3>" + _fig_html(
                fig, f"{path.name}: method {a.get('method', '?')}, {a.get('n_simulations', '?')} simulations, "
                     f"{a.get('n_tasks', '?')} tasks; density with 94% HDI, truth in orange when known."))
        except Exception as exc:  # noqa: BLE001
            out.append(_note(f"{path.name}: posterior plot failed ({type(exc).__name__}: {exc})"))
        joints = tuple(str(j) for j in idata.posterior["joint"].values)
        key = (str(a.get("task", "")), str(a.get("subject", "")), joints)
        groups.setdefault(key, []).append((str(a.get("method", path.stem)), idata, path.stem))
    for (task, subject, _), members in groups.items():
        names = [m for m, _, _ in members]
        if len(set(names)) < len(names):  # same method twice: disambiguate by budget / seed
            names = [" ".join([m] + [f"{k}={d.posterior.attrs[k]}" for k in ("budget", "seed")
                                     if k in d.posterior.attrs]) for m, d, _ in members]
        if len(set(names)) < len(names):  # still ambiguous: by file
            names = [f"{m} ({stem})" for m, _, stem in members]
        label = ", ".join(x for x in (f"task {task}" if task else "", f"subject {subject}" if subject else "") if x)
        try:
            fig = arviz_io.plot_forest([d for _, d, _ in members], names)
            out.append(f"<h3>Forest plot{': ' + _esc(label) if label else ''}</h3>" + _fig_html(
                fig, f"94% HDI and quartiles of every limit across methods{' for ' + label if label else ''}."))
        except Exception as exc:  # noqa: BLE001
            out.append(_note(f"forest plot failed ({type(exc).__name__}: {exc})"))
    return "".join(out)


def _calibration(run_dir: Path) -> str:
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
    out.append('<p class="meta">coverage − α over all levels (negative: over-confident).</p>'
               + _table_html(tab, index=False))
    return "".join(out)


def _posterior_comparison_table(posts) -> pd.DataFrame:
    """Pairwise W1 / C2ST between methods' posteriors for the same subject, budget, seed, tasks."""
    import itertools

    from camo_sbi.diagnostics import arviz_io
    from camo_sbi.diagnostics.calibration import c2st

    groups: dict[tuple, list] = {}
    for _, idata, _ in posts:
        if idata is None:
            continue
        a = idata.posterior.attrs
        draws = np.asarray(idata.posterior["limits"].values)
        draws = draws.reshape(-1, draws.shape[-2] * draws.shape[-1])
        if draws.shape[0] < 20:  # a point estimate (naive) is not a posterior to compare
            continue
        key = (a.get("subject", "–"), a.get("budget", "–"), a.get("seed", "–"), a.get("n_tasks", "–"))
        groups.setdefault(key, []).append((str(a.get("method", "?")), idata, draws))
    rows, n_c2st = [], 0
    for (subject, budget, seed, n_tasks), members in sorted(groups.items(), key=lambda kv: str(kv[0])):
        for (ma, ia, da), (mb, ib, db) in itertools.combinations(sorted(members, key=lambda m: m[0]), 2):
            free = (da.std(axis=0) > 0) | (db.std(axis=0) > 0)
            w1 = arviz_io.compare_marginals(ia, ib)["wasserstein"].to_numpy()[free]
            acc = float("nan")
            if n_c2st < _MAX_C2ST_PAIRS:
                acc = c2st(da[:, free], db[:, free], 0, max_samples=500)
                n_c2st += 1
            rows.append({"subject": subject, "budget": budget, "seed": seed, "n_tasks": n_tasks,
                         "method A": ma, "method B": mb, "mean W1 over free marginals": float(w1.mean()),
                         "max W1": float(w1.max()), "C2ST accuracy": acc})
    return pd.DataFrame(rows)


def _posterior_comparison(posts, why: str) -> str:
    if not posts:
        return _note(why)
    table = _posterior_comparison_table(posts)
    if table.empty:
        return _note("needs at least two sampled posteriors (not point estimates) for the same "
                     "subject, budget and seed")
    return ('<p class="meta">Wasserstein-1 distance between the two methods\' marginals over the '
            "free limits (same units as the posteriors), and classifier two-sample test accuracy "
            "(C2ST, sbi's random-forest metric on 500 draws per side: 0.5 = indistinguishable, 1 = "
            f"disjoint; computed for the first {_MAX_C2ST_PAIRS} pairs). Point estimates are left out. "
            "No method is a ground-truth reference here: compare with the calibration section to "
            "see which posteriors are trustworthy.</p>"
            + _table_html(table, index=False))


def _diagnostics(posts, why: str) -> str:
    if not posts:
        return _note(why)
    from camo_sbi.diagnostics import arviz_io

    meta_rows, out = [], []
    keys = ("method", "budget", "n_simulations", "wall_time", "n_tasks", "units", "resampled",
            "weights_ess", "n_samples_original", "task", "subject")
    for path, idata, err in posts:
        if idata is None:
            out.append(_note(f"{path.name} could not be read ({err})"))
            continue
        a = idata.posterior.attrs
        meta_rows.append({"file": path.name, **{k: a.get(k, "–") for k in keys}})
        body = ['<p class="meta">arviz summary (one chain of independent draws: no r_hat).</p>',
                _table_html(arviz_io.summary(idata))]
        with contextlib.suppress(ValueError):
            body.append('<p class="meta">Posterior 94% HDI width relative to the prior '
                        "(1: uninformed by the observations, 0: pinned down).</p>"
                        + _table_html(arviz_io.posterior_width(idata)))
        with contextlib.suppress(ValueError):
            body.append('<p class="meta">Position of the true limit in each marginal '
                        "(posterior quantile; near 0 or 1: the truth is in a tail).</p>"
                        + _table_html(arviz_io.truth_position(idata)))
        is_open = " open" if len(posts) <= 4 else ""
        out.append(f"<details{is_open}><summary>{_esc(path.name)}</summary>{''.join(body)}</details>")
    head = _table_html(pd.DataFrame(meta_rows), index=False) if meta_rows else ""
    return head + "".join(out)


# --------------------------------------------------------------------------- entry point


def write_report(run_dir, out_path, *, title: str | None = None, max_posteriors: int = 24) -> Path:
    """Write one self-contained HTML report for ``run_dir`` to ``out_path`` (atomically).

    Args:
        run_dir: directory holding any of config.json, results.csv, posteriors/*.nc, coverage.csv.
        out_path: the .html file to write (parent directories are created).
        title: page title (default: "camo_sbi report: <run_dir name>").
        max_posteriors: at most this many netCDF posteriors are plotted.

    Returns:
        The path written. Sections (ids): settings, comparison-table, error-vs-tasks,
        error-vs-budget, posteriors, posterior-comparison, calibration, diagnostics.
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

    res, res_why = _load_results(run_dir)
    try:
        posts, post_why = _load_posteriors(run_dir, max_posteriors)
    except Exception as exc:  # noqa: BLE001
        posts, post_why = [], f"posteriors could not be loaded ({type(exc).__name__}: {exc})"

    bodies = {
        "settings": _guard(lambda: _settings(run_dir)),
        "comparison-table": _guard(lambda: _comparison(res, res_why)),
        "error-vs-tasks": _guard(lambda: _xy_figures(res, res_why, "n_tasks", "budget", "number of observed tasks")),
        "error-vs-budget": _guard(lambda: _xy_figures(res, res_why, "budget", "n_tasks", "simulation budget")),
        "posteriors": _guard(lambda: _posteriors(posts, post_why)),
        "posterior-comparison": _guard(lambda: _posterior_comparison(posts, post_why)),
        "calibration": _guard(lambda: _calibration(run_dir)),
        "diagnostics": _guard(lambda: _diagnostics(posts, post_why)),
    }
    return write_page(out_path, title, [(sid, name, bodies[sid]) for sid, name in SECTIONS],
                      meta=f"run directory: {run_dir.resolve()}")


def figure_html(fig: Figure, caption: str, alt: str | None = None) -> str:
    """A matplotlib figure as an embedded PNG ``<figure>`` (the figure is cleared)."""
    return _fig_html(fig, caption, alt)


def table_html(df: pd.DataFrame, *, index: bool = False, float_format: str = "{:.4g}") -> str:
    """A DataFrame as an HTML table (at most the first 400 rows)."""
    return _table_html(df, index=index, float_format=float_format)


def write_page(out_path, title: str, sections, *, meta: str = "") -> Path:
    """Write a self-contained HTML page atomically: ``sections`` is [(id, heading, html body)].

    Every section gets ``<section id=...>``; ``meta`` is a line under the title (escaped).
    """
    nav = "".join(f'<li><a href="#{sid}">{_esc(name)}</a></li>' for sid, name, _ in sections)
    body = "".join(f'<section id="{sid}"><h2>{_esc(name)}</h2>{html_}</section>\n'
                   for sid, name, html_ in sections)
    stamp = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    doc = (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        f"<title>{_esc(title)}</title><style>{_CSS}</style></head><body>"
        f"<h1>{_esc(title)}</h1>"
        f'<p class="meta">{_esc(meta) + " · " if meta else ""}generated {stamp}</p>'
        f"<nav><ul>{nav}</ul></nav>\n{body}</body></html>\n"
    )
    atomic_write_text(out_path, doc)
    return Path(out_path)
