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
import io
from collections.abc import Iterable, Mapping
from importlib import resources

__all__ = ["CALIBRATED_TOL", "MEASURED", "calibration_verdict", "calibration_verdicts", "measured_rows", "verdict"]

CALIBRATED_TOL = 0.03
"""|mean(coverage - alpha)| below this is "calibrated" (the same tolerance ``calibrate`` reports
as "~calibrated")."""
MILD, STRONG = 0.06, 0.2
"""mean |coverage - alpha| below MILD: "mildly", at or above STRONG: "strongly" over/under-confident."""
MEASURED = "calibration_measured.csv"
FIELDS = ("model", "method", "mean_abs_dev", "mean_dev", "cov@0.5", "cov@0.9", "point_estimate", "source")


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


def write_measured(rows: list[dict]) -> str:
    """The package file's text (what ``docs/calibration/measured.py`` writes)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=FIELDS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k]) for k in FIELDS})
    return buf.getvalue()


def calibration_verdicts(text: str | None = None) -> list[dict]:
    """The measured rows with their verdict, in file order (``text``: a file's content; default
    the package's measured file)."""
    if text is None:
        text = resources.files("camo_sbi.diagnostics").joinpath(MEASURED).read_text()
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
