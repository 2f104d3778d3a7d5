"""Calibration verdicts read from measured coverage, not written into the code.

``camo-sbi calibrate`` writes ``coverage.csv`` (central-interval coverage per method, coordinate
and alpha over synthetic subjects). The measured runs behind the documentation are kept in
``docs/calibration/*/``; the rows this module needs from them (the pooled deviation per model and
method) are the package file ``diagnostics/calibration_measured.csv``, written from those
``coverage.csv`` files by ``python docs/calibration/measured.py`` (and checked against them by
``tests/test_docs_site.py``, so the package file cannot drift from the measurements).

A verdict is a rule applied to the measured numbers (`verdict`), never a word typed per method.
Standard library only: `infer` reads it without importing pandas' or matplotlib's plotting.
"""

from __future__ import annotations

import csv
import functools
import io
from collections.abc import Iterable, Mapping
from importlib import resources

__all__ = ["CALIBRATED_TOL", "MEASURED", "UNTOUCHED_MEASURED", "binomial_below", "calibration_verdict",
           "calibration_verdicts", "measured_rows", "untouched_rows", "untouched_verdict", "untouched_verdicts", "untouched_word",
           "verdict"]

CALIBRATED_TOL = 0.03
"""|mean(coverage - alpha)| below this is "calibrated" (the same tolerance ``calibrate`` reports
as "~calibrated")."""
MILD, STRONG = 0.06, 0.2
"""mean |coverage - alpha| below MILD: "mildly", at or above STRONG: "strongly" over/under-confident."""
MEASURED = "calibration_measured.csv"
FIELDS = ("model", "method", "mean_abs_dev", "mean_dev", "cov@0.5", "cov@0.9", "point_estimate", "source")


@functools.cache
def _package_text(name: str) -> str:
    """A measured package file's text, read once per process (`limits_table` asks per method)."""
    return resources.files("camo_sbi.diagnostics").joinpath(name).read_text()


def verdict(mean_dev: float, mean_abs_dev: float, point_estimate: bool) -> str:
    """The words for one method's pooled coverage deviation (negative: intervals too narrow)."""
    if point_estimate:
        return "a point estimate, not a posterior"
    if abs(mean_dev) < CALIBRATED_TOL:
        return "calibrated"
    side = "over-confident" if mean_dev < 0 else "under-confident"
    if mean_abs_dev < MILD:
        return f"mildly {side}"
    return f"strongly {side}" if mean_abs_dev >= STRONG else side


def measured_rows(coverage: Iterable[Mapping], source: str) -> list[dict]:
    """One row per (model, method) from the rows of a ``coverage.csv`` (its ``overall``
    coordinate): the mean |coverage - alpha|, the mean coverage - alpha, the coverage at
    alpha = 0.5 and 0.9."""
    groups: dict[tuple[str, str], list[Mapping]] = {}
    for r in coverage:
        if r["coordinate"] == "overall":
            groups.setdefault((str(r["task"]), str(r["method"])), []).append(r)
    out = []
    for (model, method), rows in sorted(groups.items()):
        dev = [float(r["coverage"]) - float(r["alpha"]) for r in rows]
        at = {round(float(r["alpha"]), 6): float(r["coverage"]) for r in rows}
        out.append({"model": model, "method": method, "mean_abs_dev": sum(map(abs, dev)) / len(dev),
                    "mean_dev": sum(dev) / len(dev), "cov@0.5": at.get(0.5, float("nan")),
                    "cov@0.9": at.get(0.9, float("nan")),
                    "point_estimate": str(rows[0]["point_estimate"]).strip().lower() == "true", "source": source})
    return out


def _csv_text(rows: list[dict], fields: tuple[str, ...]) -> str:
    """A package file's text: ``fields`` as columns, floats to 6 significant digits."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k]) for k in fields})
    return buf.getvalue()


def write_measured(rows: list[dict]) -> str:
    """The package file's text (what ``docs/calibration/measured.py`` writes)."""
    return _csv_text(rows, FIELDS)


def calibration_verdicts(text: str | None = None) -> list[dict]:
    """The measured rows with their verdict, in file order (``text``: a file's content; default
    the package's measured file)."""
    if text is None:
        text = _package_text(MEASURED)
    rows = []
    for r in csv.DictReader(io.StringIO(text)):
        row = {"model": r["model"], "method": r["method"], "source": r["source"],
               "point_estimate": r["point_estimate"] == "True",
               **{k: float(r[k]) for k in ("mean_abs_dev", "mean_dev", "cov@0.5", "cov@0.9")}}
        row["verdict"] = verdict(row["mean_dev"], row["mean_abs_dev"], row["point_estimate"])
        rows.append(row)
    return rows


def calibration_verdict(method: str, model: str) -> str:
    """The measured calibration verdict of ``method`` on ``model`` (or, on a model not measured,
    on the models that were)."""
    if method in ("nominal", "oracle"):
        return "a point (no posterior)"
    rows = calibration_verdicts()
    models = list(dict.fromkeys(r["model"] for r in rows))
    if model in models:
        return next((r["verdict"] for r in rows if r["model"] == model and r["method"] == method), "not calibrated")
    seen = [f"{r['model']}: {r['verdict']}" for m in models for r in rows if r["model"] == m and r["method"] == method]
    return f"not calibrated on this model ({'; '.join(seen)})" if seen else "not calibrated"


# ------------------------------------------------------------------ the bounds no reach touched
UNTOUCHED_MEASURED = "untouched_measured.csv"
"""Per model and method, the coverage of the 90% intervals on the binding bounds no training reach
touched (`docs/studies/exact_binding_bounds.py`'s rows, written by
``python docs/studies/exact_binding/measured.py``; checked against them by tests/test_docs_site.py)."""
UNTOUCHED_FIELDS = ("model", "method", "bounds", "covered", "coverage90", "p_below", "seeds", "source")
UNTOUCHED_NOMINAL, UNTOUCHED_TOL = 0.90, 0.05
"""A method is calibrated on untouched bounds when its 90% intervals cover within 0.05 of 0.90 (issue 35)."""


def binomial_below(covered: int, n: int, p: float = UNTOUCHED_NOMINAL) -> float:
    """One-sided P(X <= covered) for X ~ Binomial(n, p): how surprising so few covered bounds
    would be if the intervals held their nominal coverage."""
    from math import comb

    return float(sum(comb(n, k) * p**k * (1 - p) ** (n - k) for k in range(covered + 1)))


def untouched_rows(rows: Iterable[Mapping], source: str) -> list[dict]:
    """One row per (model, method) from `exact_binding_bounds.py`'s rows: the untouched binding
    bounds, how many the method's 90% interval covered (empty for a point estimate), the coverage,
    the one-sided binomial p of so few (`binomial_below`), and the seeds pooled."""
    groups: dict[tuple[str, str], list[Mapping]] = {}
    for r in rows:
        if str(r["touched"]).strip() == "False":
            groups.setdefault((str(r["model"]), str(r["method"])), []).append(r)
    out = []
    for (model, method), g in groups.items():
        cov = [str(r["covered90"]).strip() for r in g]
        point = all(c == "" for c in cov)
        covered = sum(c == "True" for c in cov)
        out.append({"model": model, "method": method, "bounds": len(g), "covered": "" if point else covered,
                    "coverage90": "" if point else covered / len(g),
                    "p_below": "" if point else binomial_below(covered, len(g)),
                    "seeds": " ".join(sorted({str(r["seed"]) for r in g}, key=int)), "source": source})
    return out


def write_untouched(rows: list[dict]) -> str:
    """The package file's text (what ``docs/studies/exact_binding/measured.py`` writes)."""
    return _csv_text(rows, UNTOUCHED_FIELDS)


def untouched_word(covered: int, n: int) -> str:
    """The rule on ``covered`` of ``n`` untouched bounds: within `UNTOUCHED_TOL` of
    `UNTOUCHED_NOMINAL` "calibrated"; outside it "over-confident" / "under-confident" when a
    one-sided binomial test at the nominal coverage gives p < 0.05, else "coverage below (above)
    0.90, too few bounds to tell"; each followed by "on untouched bounds"."""
    cov = covered / n
    if abs(cov - UNTOUCHED_NOMINAL) <= UNTOUCHED_TOL + 1e-12:  # 17 of 20 is at the edge, in
        return "calibrated on untouched bounds"
    side = "below" if cov < UNTOUCHED_NOMINAL else "above"
    p = binomial_below(covered, n) if side == "below" else 1.0 - binomial_below(covered - 1, n)  # P(X >= covered)
    if p < 0.05:
        return ("over-confident" if side == "below" else "under-confident") + " on untouched bounds"
    return f"coverage {side} 0.90 on untouched bounds, too few to tell (binomial p={p:.2g})"


def untouched_verdicts(text: str | None = None) -> list[dict]:
    """The measured untouched-bound rows with their verdict (``text``: a file's content; default
    the package's file). A point estimate has no interval; the others get `untouched_word`'s rule."""
    if text is None:
        text = _package_text(UNTOUCHED_MEASURED)
    out = []
    for r in csv.DictReader(io.StringIO(text)):
        row = {"model": r["model"], "method": r["method"], "bounds": int(r["bounds"]), "seeds": r["seeds"],
               "source": r["source"]}
        if r["coverage90"] == "":
            row.update(covered=None, coverage90=float("nan"), p_below=float("nan"),
                       verdict="a point estimate (no interval)")
        else:
            cov, k, n = float(r["coverage90"]), int(r["covered"]), int(r["bounds"])
            row.update(covered=k, coverage90=cov, p_below=float(r["p_below"]))
            row["verdict"] = (f"{untouched_word(k, n)}: its 90% intervals covered {k} of {n} untouched binding "
                              f"bounds (seeds {row['seeds']})")
        out.append(row)
    return out


def untouched_verdict(method: str, model: str) -> tuple[float, str]:
    """(coverage, verdict) of ``method``'s 90% intervals on the bounds no reach touched, measured
    on ``model`` (NaN and "not measured ..." otherwise; on another model, the measured models'
    verdicts are named)."""
    if method in ("nominal", "oracle"):
        return float("nan"), "a point (no posterior)"
    rows = untouched_verdicts()
    mine = [r for r in rows if r["method"] == method]
    hit = next((r for r in mine if r["model"] == model), None)
    if hit is not None:
        return hit["coverage90"], hit["verdict"]
    if any(r["model"] == model for r in rows) or not mine:
        return float("nan"), "not measured on untouched bounds"
    return float("nan"), "not measured on this model (" + "; ".join(
        f"{r['model']}: {r['verdict'].split(':')[0]}" for r in mine) + ")"
