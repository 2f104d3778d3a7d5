"""Which verdicts of the informative-setting and active-design pages hold under two seeds (issue 35 item 5).

A claim holds only if it holds under both seeds. The runs (30 per body and design; about 25 s for
the random-design runs and 60 s for the active ones on 2 cores):

    for s in 0 1; do
      for model in panda human; do
        camo-sbi reproduce panda --model $model --setting informative --runs 30 --seed $s \\
            --out RUNS/s$s/informative_$model
        for d in random active; do
          camo-sbi reproduce panda --model $model --setting informative --design $d --design-method camo-seq \\
              --methods camo-seq,camo-hull --runs 30 --seed $s --out RUNS/s$s/${model}_$d
        done
      done
      python docs/studies/active_design.py --runs-dir RUNS/s$s --no-figure --out-table docs/studies/active_design_s$s.csv
    done
    python docs/studies/two_seeds.py --runs RUNS --seeds 0,1

``--runs`` copies each informative run's claims.csv into ``docs/studies/informative_claims_s{S}.csv``
(the run folders hold MBs of rows; the claims are what the pages state). Without ``--runs`` the
committed files are read. Either way it writes ``docs/studies/two_seeds.csv``, one row per verdict:

- ``study = informative``: method better than a baseline after 10 reaches (one-sided paired
  Wilcoxon over 30 runs, Holm over each run's table), as ``reproduce`` writes it to claims.csv;
- ``study = active-design claims``: the same test inside each design's runs (camo-seq and
  camo-hull only);
- ``study = active vs random``: active design better than random for a method and metric
  (two-sided paired Wilcoxon, Holm over the 18 tests, and the mean difference in the better
  direction), from ``active_design_s{S}.csv``;

with each seed's value, p-value and verdict, ``holds_both`` and ``agree`` (the seeds give the
same verdict). It prints the verdicts the seeds disagree on.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from camo_sbi.evaluation.catalog import get as metric_info

HERE = Path(__file__).resolve().parent
MODELS = ("panda", "human")
KEY = ["study", "model", "design", "method", "baseline", "metric"]
CLAIM_COLUMNS = ["model", "method", "baseline", "metric", "value", "ci_low", "ci_high", "p_value", "holds",
                 "few_reaches", "binding_test_reaches_min"]


def collect(runs: Path, seed: int) -> None:
    """RUNS/s{seed}/informative_{model}/claims.csv -> informative_claims_s{seed}.csv."""
    frames = []
    for model in MODELS:
        path = runs / f"s{seed}" / f"informative_{model}" / "claims.csv"
        if not path.is_file():
            raise SystemExit(f"--runs: {path} is missing (run the commands in this script's docstring)")
        c = pd.read_csv(path)
        c["model"] = model
        c["metric"] = c.claim.str.extract(r"on (\w+)")[0]
        frames.append(c[CLAIM_COLUMNS])
    pd.concat(frames, ignore_index=True).to_csv(HERE / f"informative_claims_s{seed}.csv", index=False,
                                                float_format="%.4g")


def verdicts(seed: int) -> pd.DataFrame:
    """Every verdict of one seed: study, model, design, method, baseline, metric, value, p, holds."""
    inf = pd.read_csv(HERE / f"informative_claims_s{seed}.csv")
    inf = inf.assign(study="informative", design="random")
    claims = pd.read_csv(HERE / f"active_design_s{seed}_claims.csv").assign(study="active-design claims")
    table = pd.read_csv(HERE / f"active_design_s{seed}.csv")
    table = table[table.method != "nominal"]  # uses no data: not tested
    better = [(d < 0) if metric_info(m).lower_is_better else (d > 0)
              for d, m in zip(table.active_minus_random, table.metric, strict=True)]
    design = pd.DataFrame({"study": "active vs random", "model": table.model, "design": "active - random",
                           "method": table.method, "baseline": "random design", "metric": table.metric,
                           "value": table.active_minus_random, "p_value": table.p_holm,
                           "holds": [bool(b) and p < 0.05 for b, p in zip(better, table.p_holm, strict=True)]})
    cols = KEY + ["value", "p_value", "holds"]
    return pd.concat([inf[cols], claims[cols], design[cols]], ignore_index=True)


def combine(seeds: list[int]) -> pd.DataFrame:
    a, b = (verdicts(s) for s in seeds)
    both = a.merge(b, on=KEY, how="outer", suffixes=(f"_s{seeds[0]}", f"_s{seeds[1]}"), validate="one_to_one")
    ha, hb = both[f"holds_s{seeds[0]}"], both[f"holds_s{seeds[1]}"]
    if ha.isna().any() or hb.isna().any():
        missing = both[ha.isna() | hb.isna()][KEY].to_string(index=False)
        raise SystemExit(f"a verdict is in one seed's files only:\n{missing}")
    both["holds_both"] = ha.astype(bool) & hb.astype(bool)
    both["agree"] = ha.astype(bool) == hb.astype(bool)
    return both


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=Path, help="folder with s{S}/informative_{model} runs (copies their claims)")
    p.add_argument("--seeds", default="0,1", help="two seeds (default 0,1)")
    p.add_argument("--out", type=Path, default=HERE / "two_seeds.csv")
    args = p.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    if len(seeds) != 2:
        raise SystemExit(f"--seeds: two seeds, got {args.seeds!r}")
    if args.runs is not None:
        for s in seeds:
            collect(args.runs, s)
    both = combine(seeds)
    both.to_csv(args.out, index=False, float_format="%.4g")
    for study, g in both.groupby("study", sort=False):
        print(f"{study}: {len(g)} verdicts; hold under both seeds {int(g.holds_both.sum())}, "
              f"under neither {int((~g[f'holds_s{seeds[0]}'].astype(bool) & ~g[f'holds_s{seeds[1]}'].astype(bool)).sum())}, "
              f"the seeds disagree on {int((~g.agree).sum())}")
    split = both[~both.agree]
    if len(split):
        with pd.option_context("display.width", 200, "display.max_columns", 20):
            print("\nverdicts that one seed makes and the other breaks:")
            print(split.to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    print(f"table: {args.out}")


if __name__ == "__main__":
    main()
