"""Two run folders of the same design, paired by run: does B beat A?

    python benchmarks/compare_runs.py A_DIR B_DIR [--metrics limit_error_binding_deg,cartesian_error_mm]

Each folder is a ``reproduce panda`` (or any grid) ``--out`` with a tidy ``results.csv`` (or the
finished cells of a run still going), made with the same seed, subjects and goals (so run i of
A and run i of B saw the same data) and differing in one option (for example CAMO's
``--keep-best``/``--bandwidth``, or ``--reach-model``). Per method and metric after the last
task: the mean over the runs both finished in A and in B, the ratio B / A and the two-sided
Wilcoxon signed-rank p of the paired differences.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import wilcoxon


def load(folder: Path) -> pd.DataFrame:
    res = folder / "results.csv"
    files = [res] if res.exists() else sorted((folder / "cells").glob("*.csv"))
    if not files:
        raise SystemExit(f"{folder}: no results.csv and no finished cells")
    df = pd.concat([pd.read_csv(f) for f in files], ignore_index=True)
    return df[df.n_tasks == df.n_tasks.max()]


def paired(a: pd.DataFrame, b: pd.DataFrame, method: str, metric: str) -> tuple[float, float, float, int]:
    """(mean in A, mean in B, two-sided Wilcoxon p of B - A, runs) over the runs of ``method`` that
    both tidy tables hold for ``metric``; NaNs and the count when fewer than 2 runs pair."""
    x = a[(a.method == method) & (a.metric == metric)].set_index("run").value
    y = b[(b.method == method) & (b.metric == metric)].set_index("run").value
    common = x.index.intersection(y.index)
    if len(common) < 2:
        return float("nan"), float("nan"), float("nan"), len(common)
    d = y[common] - x[common]
    return x[common].mean(), y[common].mean(), (wilcoxon(d).pvalue if np.any(d != 0) else 1.0), len(common)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("a", type=Path)
    p.add_argument("b", type=Path)
    p.add_argument("--metrics", default="limit_error_binding_deg,cartesian_error_mm,reachability_f1")
    args = p.parse_args(argv)
    a, b = load(args.a), load(args.b)
    rows = []
    for metric in args.metrics.split(","):
        for m in a.method.unique():
            mean_a, mean_b, pval, n = paired(a, b, m, metric)
            if n < 2:
                continue
            rows.append({"metric": metric, "method": m, "runs": n, "A": round(mean_a, 3),
                         "B": round(mean_b, 3), "B / A": round(mean_b / mean_a, 3) if mean_a else float("nan"),
                         "wilcoxon_p": float(f"{pval:.3g}")})
    print(f"A = {args.a}\nB = {args.b}")
    print(pd.DataFrame(rows).to_string(index=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
