"""Issue 33's measurement table from ``reproduce panda --setting misspecified`` runs.

    python benchmarks/summarize_misspecification.py DIR/panda_controller DIR/panda_minimum-jerk ... > table.md
    python benchmarks/summarize_misspecification.py --compact S0 S1 > readme_table.md

``--compact``: each argument is a folder of one seed's ``<body>_<generator>`` run folders; one
table per body, one row per method: each metric's mean over all seeds' runs (exact model ->
minimum-jerk -> via-point), and per human-like generator and seed the paired ratio to the exact
model of the binding-bound error with its Wilcoxon p (the README's table; the model check's
flag rates come from benchmarks/bench_misspecification_detector.py).

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
from compare_runs import load as load_results  # a sibling script: python benchmarks/<this file>
from compare_runs import paired

METRICS = ("limit_error_binding_deg", "cartesian_error_mm", "reachability_f1", "model_check_flagged")


def load(folder: Path) -> pd.DataFrame:
    """The folder's rows after its last task (`compare_runs.load`), its generator from its name."""
    df = load_results(folder)
    df["generator"] = folder.name.split("_", 1)[1]
    return df


def _paired(exact: pd.DataFrame, other: pd.DataFrame, method: str, metric: str) -> tuple[float, float, int]:
    """(mean ratio other / exact, Wilcoxon p, runs) over the runs both finished (NaNs when fewer
    than 2 pair or the exact model's mean is 0)."""
    mean_exact, mean_other, p, n = paired(exact, other, method, metric)
    if n < 2 or mean_exact == 0:
        return float("nan"), float("nan"), n
    return mean_other / mean_exact, p, n


def compact(seed_dirs: list[Path]) -> str:
    frames = []
    for k, sd in enumerate(seed_dirs):
        for f in sorted(p for p in sd.iterdir() if p.is_dir()):
            df = load(f)
            df["seed_dir"] = k
            frames.append(df)
    df = pd.concat(frames, ignore_index=True)
    gens = ["controller", "minimum-jerk", "via-point"]
    lines = []
    for body, b in df.groupby("model"):
        runs = b.groupby(["seed_dir", "generator"]).run.nunique()
        lines.append(f"\n**{body}** ({len(seed_dirs)} seeds x {int(runs.min())}-{int(runs.max())} runs per generator; "
                     "exact model -> minimum-jerk -> via-point)\n")
        lines.append("| method | binding-bound error [deg] | ratio to exact (Wilcoxon p), minimum-jerk, per seed | "
                     "ratio to exact (p), via-point, per seed | Cartesian error [mm] | reachability F1 |")
        lines.append("|---|---|---|---|---|---|")
        for m in b.method.unique():
            cells = []
            for metric, fmt in (("limit_error_binding_deg", "{:.1f}"), ("cartesian_error_mm", "{:.0f}"),
                                ("reachability_f1", "{:.2f}")):
                vals = []
                for g in gens:
                    v = b[(b.generator == g) & (b.method == m) & (b.metric == metric)].value
                    vals.append("n/a" if v.empty else fmt.format(v.mean()))
                cells.append(" -> ".join(vals) if set(vals) != {"n/a"} else "n/a")
            ratios = []
            for g in gens[1:]:
                per = []
                for k in range(len(seed_dirs)):
                    x = b[b.seed_dir == k]
                    r, p, n = _paired(x[x.generator == "controller"], x[x.generator == g], m, "limit_error_binding_deg")
                    per.append("n/a" if np.isnan(r) else f"{r:.2f} ({p:.2g})")
                ratios.append("; ".join(per))
            lines.append(f"| {m} | {cells[0]} | {ratios[0]} | {ratios[1]} | {cells[1]} | {cells[2]} |")
        cart = [_paired(b[(b.seed_dir == k) & (b.generator == "controller")], b[(b.seed_dir == k) & (b.generator == g)],
                        m, "cartesian_error_mm")
                for k in range(len(seed_dirs)) for g in gens[1:] for m in b.method.unique() if m != "oracle"]
        cart = [c for c in cart if not np.isnan(c[0])]
        if cart:
            lines.append(f"\nCartesian error, paired ratio to the exact model: {min(c[0] for c in cart):.2f}-"
                         f"{max(c[0] for c in cart):.2f}, Wilcoxon p <= {max(c[1] for c in cart):.2g} (every method but "
                         f"the oracle, both generators, every seed).")
    return "\n".join(lines)


def main(argv) -> int:
    if argv and argv[0] == "--compact":
        print(compact([Path(a) for a in argv[1:]]))
        return 0
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
                    ratio, p, n_runs = _paired(exact, b[b.generator == g], m, metric)
                    row += ["n/a", "n/a"] if np.isnan(ratio) else [f"{ratio:.2f}", f"{p:.3g}"]
                lines.append(f"| {row[0]} | {row[1]} | {n_runs} | " + " | ".join(row[2:]) + " |")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
