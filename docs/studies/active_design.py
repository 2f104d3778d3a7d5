"""Active vs random design in the informative setting (issue 23 item 5): table, paired tests, figure.

    python docs/studies/active_design.py --runs-dir DIR [--out-figure docs/figures/active_vs_random.png | --no-figure]
        [--out-table docs/studies/active_design_s0.csv]

DIR holds the four reproduce outputs, made with the same seed (so run r has the same subject,
held-out goals and first reach under both designs; the comparison is paired by run):

    for model in panda human; do for d in random active; do
      camo-sbi reproduce panda --model $model --setting informative --design $d --design-method camo-seq \\
          --methods camo-seq,camo-hull --runs 30 --seed 0 --out DIR/${model}_$d; done; done

The committed tables are seed 0's (``active_design_s0.csv``, whose figure the results page shows)
and seed 1's (``--seed 1``, ``--out-table docs/studies/active_design_s1.csv --no-figure``);
``docs/studies/two_seeds.py`` says which verdicts hold under both.

Per model, method and metric (binding-bound error, reachability F1, Cartesian error): the mean
over runs after each number of reaches for both designs; after ``--at`` reaches, the paired
difference active - random and a two-sided Wilcoxon signed-rank test over runs, Holm-corrected
over the whole table (nominal uses no data, so it is shown and not tested); and the number of reaches after which the mean binding-bound error is
below 5 deg (``never`` when it is not within the reaches run). Reads each DIR's results.csv, or
its finished cells while a run is still going (then the table says how many runs it holds).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

from camo_sbi.diagnostics.style import new_figure, paper_style, save_figures
from camo_sbi.evaluation.catalog import get as metric_info
from camo_sbi.evaluation.claims import holm

METRICS = {"limit_error_binding_deg": "binding-bound error [deg]", "reachability_f1": "reachability F1",
           "cartesian_error_mm": "Cartesian error [mm]"}
METHODS = ("camo-seq", "camo-hull", "naive", "nominal")
THRESHOLD_DEG = 5.0


def load(d: Path) -> pd.DataFrame:
    if (d / "results.csv").exists():
        return pd.read_csv(d / "results.csv")
    return pd.concat([pd.read_csv(p) for p in sorted((d / "cells").glob("*.csv"))], ignore_index=True)


def reaches_below(means: pd.Series) -> str:
    below = means[means < THRESHOLD_DEG]
    return str(int(below.index.min())) if len(below) else "never"


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--runs-dir", type=Path, required=True)
    p.add_argument("--models", default="panda,human")
    p.add_argument("--at", type=int, default=None, help="reaches at which the designs are tested (default: the most)")
    p.add_argument("--out-figure", type=Path, default=Path("docs/figures/active_vs_random.png"))
    p.add_argument("--out-table", type=Path, default=Path("docs/studies/active_design_s0.csv"))
    p.add_argument("--no-figure", action="store_true", help="write the tables only")
    args = p.parse_args()
    models = args.models.split(",")
    data = {}
    for m in models:
        for design in ("random", "active"):
            df = load(args.runs_dir / f"{m}_{design}")
            data[m, design] = df[df.metric.isin(list(METRICS) + ["design_simulations", "design_wall_time"])]
    rows = []
    for m in models:
        r, a = data[m, "random"], data[m, "active"]
        runs = sorted(set(r.run) & set(a.run))
        at = args.at or int(min(r.n_tasks.max(), a.n_tasks.max()))
        for method in METHODS:
            for metric in METRICS:
                def table(df):
                    sel = df[(df.method == method) & (df.metric == metric) & df.run.isin(runs)]
                    return sel.pivot_table(index="run", columns="n_tasks", values="value", aggfunc="first")
                tr, ta = table(r), table(a)
                if tr.empty or ta.empty:
                    continue
                d = (ta[at] - tr[at]).dropna()
                if method == "nominal":  # uses no data: identical under both designs, not tested
                    pv = float("nan")
                else:
                    pv = float(stats.wilcoxon(d).pvalue) if np.count_nonzero(d) >= 2 else 1.0
                better = (d < 0) if metric_info(metric).lower_is_better else (d > 0)
                row = {"model": m, "method": method, "metric": metric, "reaches": at, "runs": len(d),
                       "random": tr[at].mean(), "active": ta[at].mean(), "active_minus_random": d.mean(),
                       "active_better_runs": int(better.sum()), "p_raw": pv}
                if metric == "limit_error_binding_deg":
                    row["reaches_below_5deg_random"] = reaches_below(tr.mean())
                    row["reaches_below_5deg_active"] = reaches_below(ta.mean())
                rows.append(row)
        ds = a[(a.metric == "design_wall_time") & a.run.isin(runs)].drop_duplicates("run").value
        print(f"{m}: {len(runs)} paired runs; active design time per run (9 choices) mean {ds.mean():.1f} s")
    out = pd.DataFrame(rows)
    out["p_holm"] = holm(out.p_raw.to_numpy())
    args.out_table.parent.mkdir(parents=True, exist_ok=True)
    out.to_csv(args.out_table, index=False, float_format="%.4g")
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        print(out.drop(columns="p_raw").to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    claims = []
    for m in models:
        for design in ("random", "active"):
            path = args.runs_dir / f"{m}_{design}" / "claims.csv"
            if path.exists():
                c = pd.read_csv(path)
                c["metric"] = c.claim.str.extract(r"on (\w+)")[0]
                claims.append(c.assign(model=m, design=design)[["model", "design", "method", "baseline", "metric",
                                                                "value", "p_value", "holds"]])
    if claims:
        claims = pd.concat(claims, ignore_index=True)
        claims.to_csv(args.out_table.with_name(args.out_table.stem + "_claims.csv"), index=False, float_format="%.4g")
        print(claims.to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    if not args.no_figure:
        _figure(data, models, args.out_figure)
    print(f"table: {args.out_table}" + ("" if args.no_figure else f"  figure: {args.out_figure}"))


def _figure(data, models, path: Path) -> None:
    colors = {"camo-seq": "C0", "camo-hull": "C1", "naive": "C2", "nominal": "0.5"}
    with paper_style():
        fig, axes = new_figure(len(models), len(METRICS), width="double", aspect=0.8)
        axes = np.asarray(axes).reshape(len(models), len(METRICS))
        for i, m in enumerate(models):
            for j, (metric, label) in enumerate(METRICS.items()):
                ax = axes[i, j]
                for design, ls in (("random", "--"), ("active", "-")):
                    df = data[m, design]
                    sel = df[df.metric == metric]
                    for method in METHODS:
                        s = sel[sel.method == method].groupby("n_tasks").value.mean()
                        if len(s):
                            ax.plot(s.index, s.values, ls, color=colors[method], label=f"{method}, {design}")
                if metric == "limit_error_binding_deg":
                    ax.axhline(THRESHOLD_DEG, color="k", lw=0.5, ls=":")
                ax.set_title(f"{m}: {label}")
                ax.set_xlabel("observed reaches")
        handles, labels = axes[0, 0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="outside lower center", ncols=4)
        save_figures(fig, path.with_suffix(""), ("png",))


if __name__ == "__main__":
    main()
