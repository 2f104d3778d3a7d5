"""Issue 33's measurement table from ``reproduce panda --setting misspecified`` runs.

    python benchmarks/summarize_misspecification.py DIR/panda_controller DIR/panda_minimum-jerk ... > table.md

Each argument is an ``--out`` folder (its ``results.csv``, or the finished cells of a run still
going). Per body, generator and method after all tasks: the mean +- sd over runs of
``limit_error_binding_deg``, ``cartesian_error_mm``, ``reachability_f1``, the share of
recordings the model check flags, and per human-like generator the paired test (Wilcoxon
signed-rank over the runs both folders finished, the same subjects and goals) against the same
method with the exact model, with the ratio of the mean binding-bound errors.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import wilcoxon

METRICS = ("limit_error_binding_deg", "cartesian_error_mm", "reachability_f1", "model_check_flagged")


def load(folder: Path) -> pd.DataFrame:
    res = folder / "results.csv"
    files = [res] if res.exists() else sorted((folder / "cells").glob("*.csv"))
    df = pd.concat([pd.read_csv(f) for f in files], ignore_index=True)
    gen = folder.name.split("_", 1)[1]
    df["generator"] = gen
    return df[df.n_tasks == df.n_tasks.max()]


def main(argv) -> int:
    df = pd.concat([load(Path(a)) for a in argv], ignore_index=True)
    lines = []
    for body, b in df.groupby("model"):
        runs = b.groupby("generator").run.nunique().to_dict()
        lines.append(f"\n### {body} (runs finished per generator: {runs})\n")
        lines.append("| generator | method | binding-bound error [deg] | Cartesian error [mm] | reachability F1 | "
                     "flagged by the model check |")
        lines.append("|---|---|---|---|---|---|")
        for (g, m), x in b.groupby(["generator", "method"], sort=False):
            cells = []
            for metric in METRICS:
                v = x[x.metric == metric].value
                cells.append("n/a" if v.empty else f"{v.mean():.3g} +- {v.std(ddof=1) if len(v) > 1 else 0:.2g}")
            lines.append(f"| {g} | {m} | " + " | ".join(cells) + " |")
        lines.append("\nPaired against the exact model (same method, same runs): mean binding-bound error ratio "
                     "(generator / controller) and Wilcoxon p (two-sided), then the same for the Cartesian error.\n")
        lines.append("| generator | method | runs | binding error ratio | p | Cartesian error ratio | p |")
        lines.append("|---|---|---|---|---|---|---|")
        exact = b[b.generator == "controller"]
        for g in [g for g in b.generator.unique() if g != "controller"]:
            for m in b.method.unique():
                row = [g, m]
                n_runs = None
                for metric in ("limit_error_binding_deg", "cartesian_error_mm"):
                    a = exact[(exact.method == m) & (exact.metric == metric)].set_index("run").value
                    c = b[(b.generator == g) & (b.method == m) & (b.metric == metric)].set_index("run").value
                    common = a.index.intersection(c.index)
                    n_runs = len(common)
                    if n_runs < 2 or a[common].mean() == 0:
                        row += ["n/a", "n/a"]
                        continue
                    d = c[common] - a[common]
                    p = wilcoxon(d).pvalue if np.any(d != 0) else 1.0
                    row += [f"{c[common].mean() / a[common].mean():.2f}", f"{p:.3g}"]
                lines.append(f"| {row[0]} | {row[1]} | {n_runs} | " + " | ".join(row[2:]) + " |")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
