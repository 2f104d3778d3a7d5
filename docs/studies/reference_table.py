"""The sbibm-style table of `compare --reference` runs: C2ST (and MMD) to the reference per method and budget.

    python docs/studies/reference_table.py runs/vs-reference [runs/vs-reference-1e4 ...]

Reads each run's results.csv and prints a Markdown table: per method and budget, the mean (min-max
over the reference observations) of ``c2st``, ``mmd``, the binding-bound error and the simulations
used, with the method's status counts and whether it is simulation-based. Point estimates show
"not a posterior" instead of a C2ST.
"""

import sys

import pandas as pd


def cell(v: pd.Series, fmt: str) -> str:
    v = v.dropna()
    if v.empty:
        return "not a posterior"
    return f"{v.mean():{fmt}} ({v.min():{fmt}}-{v.max():{fmt}})" if len(v) > 1 else f"{v.iloc[0]:{fmt}}"


def main(paths) -> int:
    df = pd.concat([pd.read_csv(f"{p}/results.csv") for p in paths], ignore_index=True)
    rows = []
    for (m, b), g in df.groupby(["method", "budget"]):
        val = {k: g[g.metric == k].drop_duplicates("seed").value for k in
               ("c2st", "mmd", "limit_error_binding_deg", "n_simulations")}
        rows.append({"method": m + ("" if bool(g.simulation_based.iloc[0]) else " (not SBI: Bayes limit)"),
                     "budget": int(b), "observations": g.seed.nunique(),
                     "C2ST": cell(val["c2st"], ".3f"), "MMD^2": cell(val["mmd"], ".3f"),
                     "binding error [deg]": cell(val["limit_error_binding_deg"], ".1f"),
                     "simulations": cell(val["n_simulations"], ",.0f"),
                     "status": ", ".join(f"{s} x{n}" for s, n in g.drop_duplicates("seed").status.value_counts().items())})
    out = pd.DataFrame(rows).sort_values(["budget", "method"])
    print(out.to_markdown(index=False))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
