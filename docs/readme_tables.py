"""Print the result tables of the documentation (docs/results/, markdown) from run directories,
so every number there comes from a `results.csv` / `claims.csv` a command wrote (the site's
`<!-- table: KIND DIR -->` directive prints them at build time, docs/site_hooks.py).

    python docs/readme_tables.py manipulator DIR     # reproduce panda (paper or toolkit setting)
    python docs/readme_tables.py paper-pair DIR DIR2 # two --setting paper runs side by side
    python docs/readme_tables.py informative DIR     # reproduce panda --setting informative
    python docs/readme_tables.py hrc DIR             # reproduce hrc
    python docs/readme_tables.py compare DIR         # compare (final task count)
    python docs/readme_tables.py robustness DIR      # robustness
    python docs/readme_tables.py calibrate DIR       # calibrate

Cells follow the small-n rule of the figures (`camo_sbi.diagnostics.style.cell_text`): with
at least 5 runs (or seeds) the mean ± the half-width of the 95% Student-t CI of the mean,
with fewer the mean and the range (min–max), never an interval built from 2 values; each
table's heading says which. Angles are in degrees (`display_metric`). Rows whose method had a
non-ok status in any cell are marked with a dagger and the statuses are listed under the table.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from camo_sbi.diagnostics.style import cell_rule, cell_text, display_metric, method_order


def _fmt_values(v, digits: int) -> str:
    """One cell (`cell_text`, the figures' rule), ``digits`` decimals."""
    def f(x):
        return f"{x:.{digits}f}"
    return cell_text(v, fmt=f, ci_fmt=f)


def _marks(df: pd.DataFrame, by: list[str]) -> tuple[dict, list[str]]:
    bad = df[df.status.astype(str) != "ok"]
    keys = bad.groupby(by[0] if len(by) == 1 else by).groups if len(bad) else {}
    marks = {k: "†" for k in keys}
    notes = sorted(bad.status.astype(str).str.replace(r"\d+(\.\d+)?", "#", regex=True).unique()) if len(bad) else []
    return marks, notes


def _table(header: list[str], rows: list[list[str]]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out)


PRIMARY = ("cartesian_error_mm", "joint_error_deg", "precision", "recall", "f1")


def claims_table(path: Path) -> str:
    """The claims on the primary metrics (claims.csv also holds the reference-metric rows)."""
    c = pd.read_csv(path)
    c = c[c.statistic.astype(str).str.split(":").str[0].str.split(" ").str[0].isin(PRIMARY)
          | ~c.statistic.astype(str).str.contains("_")]
    rows = []
    for _, r in c.iterrows():
        setting = f" ({r.setting})" if "setting" in c and isinstance(r.setting, str) and "/" in r.setting else ""
        ci = (f"[{r.ci_low:.3g}, {r.ci_high:.3g}]" if np.isfinite(r.ci_low) else "–")
        variant = str(r.variant) if "variant" in c and isinstance(r.variant, str) and r.variant != "-" else ""
        method = f"{r.method} [{variant}]" if variant else r.method
        rows.append([f"{r.claim}{setting}", method, str(r.baseline), str(r.statistic).split(":")[0],
                     f"{r.value:.3g}", ci, f"{r.p_value:.2g}", r.test, "**yes**" if r.holds else "no"])
    return _table(["claim", "method", "vs", "statistic", "value", "95% CI", "p (Holm)", "paired test", "holds"], rows)


def manipulator(d: Path) -> str:
    df = display_metric(pd.read_csv(d / "results.csv"))
    marks, notes = _marks(df, ["method"])
    ks = sorted(df.n_tasks.unique())
    show = [k for k in (1, 2, 3, 5, 10) if k in ks] or ks
    parts = []
    for metric, unit, dig in (("cartesian_error_mm", "mm", 1), ("joint_error_deg", "deg", 2),
                              ("limit_error_binding_deg", "deg", 1), ("limit_error_free_deg", "deg", 1)):
        sub = df[df.metric == metric]
        rows = []
        for m in method_order(sub.method):
            cells = []
            for k in show:
                v = sub[(sub.method == m) & (sub.n_tasks == k)].value.to_numpy(float)
                cells.append(_fmt_values(v, dig))
            rows.append([m + marks.get(m, "")] + cells)
        parts.append(f"**{metric}** [{unit}], {cell_rule(df.run.nunique())}, by observed tasks:\n\n"
                     + _table(["method"] + [str(k) for k in show], rows))
    last = df[df.n_tasks == max(ks)]
    rows = []
    for m in method_order(last.method):
        r = [m + marks.get(m, "")]
        for metric in ("eq2_cartesian", "eq2_joint", "reference_cartesian", "reference_joint"):
            v = last[(last.method == m) & (last.metric == metric)].value.to_numpy(float)
            r.append(_fmt_values(v, 3))
        rows.append(r)
    parts.append(f"The paper's Eq. 2 and the authors' code's metric after {max(ks)} tasks (summed over the test goals):\n\n"
                 + _table(["method", "eq2_cartesian [m]", "eq2_joint [deg]", "reference_cartesian [m]",
                           "reference_joint [deg]"], rows))
    if notes:
        parts.append("† " + "; ".join(notes))
    parts.append(_binding(df))
    if (d / "claims.csv").exists():
        parts.append(claims_table(d / "claims.csv"))
    return "\n\n".join(parts)


def _binding(df: pd.DataFrame) -> str:
    from camo_sbi.evaluation.claims import binding_line

    return binding_line(df)


def informative(d: Path) -> str:
    """Error vs observed reaches on prediction, the binding bounds and reachability; the claims."""
    df = display_metric(pd.read_csv(d / "results.csv"))
    marks, notes = _marks(df, ["method"])
    ks = sorted(df.n_tasks.unique())
    show = [k for k in (1, 2, 3, 5, 10) if k in ks] or ks
    parts = [_binding(df)]
    for metric, unit, dig in (("cartesian_error_mm", "mm", 1), ("limit_error_binding_deg", "deg", 1),
                              ("reachability_f1", "", 3)):
        sub = df[df.metric == metric]
        rows = [[m + marks.get(m, "")] + [_fmt_values(sub[(sub.method == m) & (sub.n_tasks == k)].value
                                                      .to_numpy(float), dig) for k in show]
                for m in method_order(sub.method)]
        parts.append(f"**{metric}**{f' [{unit}]' if unit else ''}, {cell_rule(df.run.nunique())}, by observed "
                     "reaches:\n\n" + _table(["method"] + [str(k) for k in show], rows))
    if notes:
        parts.append("† " + "; ".join(notes))
    c = pd.read_csv(d / "claims.csv")
    rows = [[r.method, r.baseline, str(r.statistic).split(" ")[0], f"{r.value:.3g}",
             f"[{r.ci_low:.3g}, {r.ci_high:.3g}]", f"{r.p_value:.2g}", "**yes**" if r.holds else "no"]
            for _, r in c.iterrows()]
    parts.append("Claims after the last reach (method − baseline; one-sided paired Wilcoxon over runs, Holm over "
                 "the table):\n\n" + _table(["method", "vs", "metric", "mean diff", "95% CI", "p (Holm)", "holds"],
                                             rows))
    return "\n\n".join(parts)


def hrc(d: Path) -> str:
    df = pd.read_csv(d / "results.csv")
    df = df[df.method != "truth"]
    marks, notes = _marks(df, ["method"])
    last = df[df.n_tasks == df.n_tasks.max()]
    rows = []
    for prior in last.prior.unique():
        for m in method_order(last[last.prior == prior].method):
            r = [prior, m + marks.get(m, "")]
            for metric, dig in (("precision", 3), ("recall", 3), ("f1", 3), ("limit_error_free_deg", 1)):
                v = last[(last.prior == prior) & (last.method == m) & (last.metric == metric)].value.to_numpy(float)
                r.append(_fmt_values(v, dig) if v.size else "–")
            rows.append(r)
    out = (f"After {df.n_tasks.max()} tasks, {cell_rule(df.run.nunique())}:\n\n"
           + _table(["prior", "method", "precision", "recall", "F1", "free-limit error [deg]"], rows))
    if notes:
        out += "\n\n† " + "; ".join(notes)
    if (d / "claims.csv").exists():
        out += "\n\n" + claims_table(d / "claims.csv")
    return out


def compare(d: Path) -> str:
    df = pd.read_csv(d / "results.csv")
    marks, notes = _marks(df, ["method", "budget"])
    last = df[df.n_tasks == df.n_tasks.max()]
    metrics = [("cartesian_error_mm", "held-out Cartesian [mm]", 1), ("joint_error_deg", "held-out joint [deg]", 2),
               ("limit_error_deg", "limit error [deg]", 1), ("limit_error_binding_deg", "binding-limit error [deg]", 1),
               ("ppc_cartesian_error_mm", "posterior-predictive [mm]", 1), ("n_simulations", "simulations", 0),
               ("wall_time", "wall time [s]", 2)]
    metrics = [m for m in metrics if m[0] in set(last.metric)]
    rows = []
    for m in method_order(last.method):
        for b in sorted(last[last.method == m].budget.unique()):
            sub = last[(last.method == m) & (last.budget == b)]
            r = [m + marks.get((m, b), ""), str(b)]
            for metric, _, dig in metrics:
                v = sub[sub.metric == metric].value.to_numpy(float)
                r.append(_fmt_values(v, dig) if v.size else "–")
            rows.append(r)
    out = (f"After {df.n_tasks.max()} observed tasks, {cell_rule(df.seed.nunique(), 'seeds')}:\n\n"
           + _table(["method", "budget"] + [m[1] for m in metrics], rows))
    if notes:
        out += "\n\n† " + "; ".join(notes)
    return out


def robustness(d: Path) -> str:
    t = pd.read_csv(d / "robustness.csv")
    return _table(list(t.columns), [[f"{v:.3g}" if isinstance(v, float) else str(v) for v in r]
                                    for r in t.itertuples(index=False)])


def calibrate(d: Path) -> str:
    t = pd.read_csv(d / "coverage.csv")
    return _table(list(t.columns), [[f"{v:.3g}" if isinstance(v, float) else str(v) for v in r]
                                    for r in t.itertuples(index=False)])


_SHORT_STATISTIC = {  # claims.csv's statistic column, in short
    "CAMO is below": "cartesian_error_mm, method − baseline at the worst k; holds if every k is below",
    "CAMO converges": "convergence gap after 3 tasks (mm): max(|e3 − eK|, later rise); holds if it learned "
                      "(p) and the gap's upper CI ≤ 0.25 × the 1→K improvement",
    "CS is as good": "cartesian_error_mm after K, CS − JS; TOST margin ±10% of JS",
    "CAMO is significantly": "joint_error_deg after K, method − baseline",
    "": "see claims.csv",
}


def paper_pair(d1: Path, d2: Path) -> str:
    """Two ``--setting paper`` runs (e.g. the Panda and the authors' DH arm) side by side: each
    metric after 1, 3 and the last number of tasks, the binding reaches, and the claims of the
    authors' variants and of Algorithm 1 as written against naive / nominal."""
    dfs = [display_metric(pd.read_csv(d / "results.csv")) for d in (d1, d2)]
    names = [str(df.model.iloc[0]) for df in dfs]
    parts = []
    ks = [sorted({1, 3, int(df.n_tasks.max())} & set(df.n_tasks.unique())) for df in dfs]
    marks = [_marks(df, ["method"])[0] for df in dfs]
    for metric, unit, dig in (("cartesian_error_mm", "mm", 1), ("joint_error_deg", "deg", 2),
                              ("limit_error_binding_deg", "deg", 1), ("limit_error_free_deg", "deg", 1)):
        methods = method_order(pd.concat([df[df.metric == metric].method for df in dfs]))
        rows = []
        for m in methods:
            cells = []
            for df, kk, mk in zip(dfs, ks, marks, strict=True):
                sub = df[(df.metric == metric) & (df.method == m)]
                cells += [_fmt_values(sub[sub.n_tasks == k].value.to_numpy(float), dig) + (mk.get(m, "") if k == kk[-1]
                                                                                          else "") for k in kk]
            rows.append([m] + cells)
        header = ["method"] + [f"{n}, k={k}" for n, kk in zip(names, ks, strict=True) for k in kk]
        parts.append(f"**{metric}** [{unit}], {cell_rule(dfs[0].run.nunique())}, after k observed tasks:\n\n"
                     + _table(header, rows))
    notes = sorted(set(sum((_marks(df, ["method"])[1] for df in dfs), [])))
    if notes:
        parts.append("† " + "; ".join(notes))
    parts += [f"{n}: {_binding(df)}" for n, df in zip(names, dfs, strict=True)]
    cl = [pd.read_csv(d / "claims.csv") for d in (d1, d2)]
    keep = ["camo-seq", "camo-seq-cs", "camo-js", "camo-cs"]
    key = ["claim", "method", "baseline"]
    rows = []
    cl = [c[c.method.isin(keep) & c.statistic.astype(str).str.split(":").str[0].str.split(" ").str[0].isin(PRIMARY)]
          for c in cl]
    both = cl[0].merge(cl[1], on=key, suffixes=("_a", "_b"))
    for _, r in both.iterrows():
        short = next(v for k, v in _SHORT_STATISTIC.items() if r.claim.startswith(k))
        row = [r.claim, f"{r.method} [{r.variant_a}]", str(r.baseline), short, r.test_a]
        for s_ in ("_a", "_b"):
            row.append(f"{r['value' + s_]:.3g} (p {r['p_value' + s_]:.2g}) " + ("**holds**" if r["holds" + s_] else "fails"))
        rows.append(row)
    parts.append(_table(["claim", "method [variant]", "vs", "statistic", "paired test", *names], rows))
    return "\n\n".join(parts)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("kind", choices=["manipulator", "paper-pair", "informative", "hrc", "compare", "robustness",
                                    "calibrate"])
    p.add_argument("dir", type=Path)
    p.add_argument("dir2", type=Path, nargs="?")
    a = p.parse_args(argv)
    if a.kind == "paper-pair":
        if a.dir2 is None:
            p.error("paper-pair: needs two run directories")
        print(paper_pair(a.dir, a.dir2))
    else:
        print(globals()[a.kind](a.dir))
    return 0


if __name__ == "__main__":
    sys.exit(main())
