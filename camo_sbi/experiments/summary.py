"""The ``--json`` summary of a command, read back from what the command wrote.

    {"command": "compare", "exit_code": 0, "error": null, "seconds": 3.1,
     "out": "runs/tiny", "written": ["runs/tiny/results.csv", ...], "cells_written": 6,
     "statuses": {"camo": {"ok": 2}, "abc-smc": {"fallback: low effective sample size ...": 1}},
     "headline": {"at": {"n_tasks": 2, "budget": 200},
                  "mean": {"camo": {"cartesian_error_mm": 12.3, "wall_time": 0.2, ...}, ...}},
     "claims": [{"claim": ..., "method": ..., "baseline": ..., "holds": true}, ...]}

``written``: the files under ``--out`` (or the ``--out`` file itself) modified since the command
started, except the per-cell files under ``cells/`` and ``work/`` directories (counted in
``cells_written``);
a re-run that rebuilt nothing writes nothing. ``statuses``: per method, how many results
(one per method, seed / run, number of tasks, ...) carry each status. ``headline``: per method,
the mean of the headline metrics over the largest number of observed tasks at the largest budget
(``results.csv`` of compare / reproduce / robustness), the mean |coverage - alpha| (calibrate), or
the estimated limits in degrees (infer). Missing files give empty fields, never an error.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

__all__ = ["print_summary", "run_summary", "summary_metrics"]


def summary_metrics() -> list[str]:
    """The metrics a summary averages: the catalog's headline metrics and the costs
    (`camo_sbi.evaluation.catalog`: ``headline``, ``group="cost"``), in its order."""
    from camo_sbi.evaluation import catalog

    return [m.name for m in catalog.METRICS if (m.headline or m.group == "cost") and not m.per_joint]

_GROUPS = ("task", "subject", "method", "prior", "condition")
_NOT_LISTED = ("cells", "work")


def _out_path(args) -> Path | None:
    for name in ("out", "output"):
        v = getattr(args, name, None)
        if v is not None:
            return Path(v)
    run_dir = getattr(args, "run_dir", None)
    return Path(run_dir) if run_dir is not None else None


def _written(out: Path, started: float) -> tuple[list[str], int]:
    if out.is_file():
        return ([str(out)] if out.stat().st_mtime >= started else []), 0
    if not out.is_dir():
        return [], 0
    listed, cells = [], 0
    for p in sorted(out.rglob("*")):
        if not p.is_file() or p.name == "run.lock" or p.stat().st_mtime < started:
            continue
        parts = set(p.relative_to(out).parts[:-1])
        if parts & set(_NOT_LISTED):
            cells += "cells" in parts and p.suffix == ".csv"
        else:
            listed.append(str(p))
    return listed, cells


def _finite(v):
    v = float(v)
    return v if math.isfinite(v) else None


def _table_summary(df) -> tuple[dict, dict]:
    statuses, headline = {}, {}
    if "status" in df.columns and "method" in df.columns:
        results = df.drop(columns=[c for c in ("metric", "value") if c in df.columns]).drop_duplicates()
        for (method, status), n in results.groupby(["method", "status"], sort=False).size().items():
            statuses.setdefault(str(method), {})[str(status)] = int(n)
    if not {"method", "metric", "value"} <= set(df.columns):
        return statuses, headline
    at = {}
    for col in ("n_tasks", "budget"):
        if col in df.columns:
            at[col] = df[col].max().item()
            df = df[df[col] == df[col].max()]
    df = df[df["metric"].isin(summary_metrics())]
    # the method, and whatever else varies (a study's models and subjects, hrc's priors, robustness's conditions)
    groups = [c for c in _GROUPS if c in df.columns and (c == "method" or df[c].nunique() > 1)]
    mean = {}
    for key, g in df.groupby(groups, sort=False):
        key = key if isinstance(key, tuple) else (key,)
        mean[" / ".join(str(k) for k in key)] = {m: _finite(v) for m, v in g.groupby("metric")["value"].mean().items()}
    return statuses, {"at": at, "mean": mean}


def run_summary(command: str, args, exit_code: int, error: str | None, *, started: float) -> dict:
    """The summary as a JSON-ready dict (see the module docstring)."""
    out = _out_path(args)
    summary = {"command": command, "exit_code": int(exit_code), "error": error,
               "seconds": round(time.time() - started, 3), "out": None if out is None else str(out),
               "written": [], "cells_written": 0, "statuses": {}, "headline": {}, "claims": []}
    if out is None:
        return summary
    summary["written"], summary["cells_written"] = _written(out, started - 1e-3)
    if not out.is_dir():
        return summary
    import pandas as pd

    def read(name):
        try:
            return pd.read_csv(out / name) if (out / name).is_file() else None
        except (OSError, ValueError, pd.errors.ParserError):
            return None

    results = read("results.csv")
    if results is not None and "metric" in results.columns:
        summary["statuses"], summary["headline"] = _table_summary(results)
    coverage = read("coverage.csv")
    if coverage is not None and {"coordinate", "alpha", "coverage", "method"} <= set(coverage.columns):
        overall = coverage[coverage["coordinate"] == "overall"]
        summary["headline"] = {"mean_abs_coverage_error": {
            str(m): _finite((g["coverage"] - g["alpha"]).abs().mean()) for m, g in overall.groupby("method")}}
    limits = read("limits.csv")
    if limits is not None and {"method", "joint", "bound", "estimate_deg", "status"} <= set(limits.columns):
        summary["statuses"] = {str(m): {str(s): 1 for s in g["status"].unique()}
                               for m, g in limits.groupby("method", sort=False)}
        summary["headline"] = {"estimate_deg": {
            str(m): {f"{r.joint} {r.bound}": _finite(r.estimate_deg) for r in g.itertuples()}
            for m, g in limits.groupby("method", sort=False)}}
    claims = read("claims.csv")
    if claims is not None and {"claim", "method", "baseline", "holds"} <= set(claims.columns):
        summary["claims"] = [{"claim": str(r.claim), "method": str(r.method), "baseline": str(r.baseline),
                              "holds": None if pd.isna(r.holds) else str(r.holds).lower() == "true"}
                             for r in claims.itertuples()]
    return summary


def print_summary(command: str, args, exit_code: int, error: str | None, *, started: float, file=None) -> None:
    """Print `run_summary` as one JSON document."""
    print(json.dumps(run_summary(command, args, exit_code, error, started=started), indent=2),
          file=sys.stdout if file is None else file, flush=True)
