"""The binding-bound table of docs/guide/reference_posteriors.md from the rows here.

    python docs/studies/exact_binding/table.py 7        # one seed
    python docs/studies/exact_binding/table.py 7 11     # both, pooled (coverage as k/n)

Per method (every file ``{model}_s{seed}*.csv`` of the seeds asked for), per body, on the binding
bounds no training reach touched and on those one touched: the mean |error| [deg] and the 90 %
intervals' coverage as covered / bounds ("-" for a point estimate; "fb" counts rows whose result
fell back or failed).
"""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd

HERE = Path(__file__).resolve().parent
ORDER = ("exact-likelihood", "naive", "nominal (the prior's full range; computed, not run)", "camo", "camo-seq", "camo-touched", "camo-hull", "abc-smc", "npe", "nle",
         "nre", "fmpe", "npse", "tsnpe")


def load(seeds: list[int]) -> pd.DataFrame:
    # {model}_s{seed}.csv and {model}_s{seed}_{others,camo}.csv (not "_s1*", which would take seed 11 for 1)
    files = [f for s in seeds for pattern in (f"*_s{s}.csv", f"*_s{s}_*.csv") for f in sorted(HERE.glob(pattern))]
    frames = [pd.read_csv(f) for f in files]
    df = pd.concat(frames, ignore_index=True)
    return df.drop_duplicates(["model", "seed", "run", "method", "bound"])


def cell(g: pd.DataFrame) -> str:
    if g.empty:
        return "not run | -"
    cov = g.covered90.dropna()
    covtext = "-" if cov.empty else f"{int(cov.astype(bool).sum())}/{len(cov)}"
    return f"{g.error_deg.mean():.1f} | {covtext}"


def nominal_rows(df: pd.DataFrame) -> pd.DataFrame:
    """The nominal baseline on the same bounds: |the prior's outer bound - truth| (the `nominal`
    method's estimate, `prior.outer_theta()`), computed from the rows' subjects, not a run."""
    import numpy as np

    from camo_sbi.experiments.models import ModelSpec, subject_limits
    from camo_sbi.priors import BoxPrior

    out = df[df.method == "naive"].copy()
    for model in set(out.model):
        spec = ModelSpec(kind=model)
        sim = spec.build()
        outer = BoxPrior(sim.bounds, sim.start).outer_theta().numpy()
        for subject in set(out[out.model == model].subject):
            truth = subject_limits(spec, sim, subject).numpy()
            rows = (out.model == model) & (out.subject == subject)
            out.loc[rows, "error_deg"] = np.degrees(np.abs(outer - truth))[out.loc[rows, "bound"].to_numpy()]
    out["method"] = "nominal (the prior's full range; computed, not run)"
    return out


def main(argv: list[str]) -> int:
    seeds = [int(a) for a in argv] or [7]
    df = load(seeds)
    df["touched"] = df.touched.astype(str) == "True"
    df = pd.concat([df, nominal_rows(df)], ignore_index=True)
    cols = [(m, t) for m in ("panda", "human") for t in (False, True)]
    head = " | ".join(f"{m} {'touched' if t else 'untouched'} (n={int(((df.model == m) & (df.touched == t) & (df.method == 'naive')).sum())}): error | coverage"
                      for m, t in cols)
    print(f"seeds {' '.join(map(str, seeds))}\n\n| method | {head} |\n|---|" + "---|" * (2 * len(cols)))
    for meth in [m for m in ORDER if m in set(df.method)] + sorted(set(df.method) - set(ORDER)):
        d = df[df.method == meth]
        fb = int((d.status.astype(str) != "ok").sum())
        name = f"{meth} (fb: {fb} of {len(d)} rows)" if fb else meth
        seeds_run = sorted(set(d.seed))
        if seeds_run != sorted(seeds):
            name += f" (seed {' '.join(map(str, seeds_run))} only)"
        print(f"| {name} | " + " | ".join(cell(d[(d.model == m) & (d.touched == t)]) for m, t in cols) + " |")
    print("| oracle (the true limits) | " + " | ".join("0.0 | -" for _ in cols) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
