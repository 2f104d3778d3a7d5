"""Issue 33: how often the reproduction check (`camo_sbi.diagnostics.misspecification`) flags a
recording, on exact-model data (false alarms) and under the human-like generators (power).

Per recording: a subject of the model's informative design (goals from the nominal workspace),
10 observed reaches, moved by ``--generators``; the method's posterior on them; the check.

    python benchmarks/bench_misspecification_detector.py --model panda --method camo-js --runs 30 \\
        --out docs/guide/detector/panda_camo-js_s0.csv

Prints per generator the share of recordings flagged (Holm-adjusted recording p < 0.05, and the
pooled p < 0.05), and writes one row per recording.

    python benchmarks/bench_misspecification_detector.py --summarize ROWS.csv [ROWS.csv ...]

prints the guide's table from such files: per body, method and base seed, the share of recordings
flagged under each generator (the exact model's share is the false-alarm rate), with a 95%
Wilson interval.
"""

from __future__ import annotations

import argparse
import re
import time

import numpy as np
import pandas as pd

from camo_sbi._validation import derive_seed
from camo_sbi.diagnostics.misspecification import check_reproduction
from camo_sbi.inference.registry import run_method
from camo_sbi.scenarios.generators import make_generator, misspecified_observations
from camo_sbi.scenarios.reaching import make_reaching_task
from camo_sbi.simulators import registry


def _wilson(k: int, n: int) -> tuple[float, float]:
    z = 1.959964
    c = (k + z * z / 2) / (n + z * z)
    h = z * np.sqrt(k * (n - k) / n + z * z / 4) / (n + z * z)
    return c - h, c + h


def summarize(paths) -> str:
    frames = []
    for path in paths:
        x = pd.read_csv(path)
        if "seed" not in x:  # rows written before the column existed: the base seed from the name (..._s<seed>.csv)
            m = re.search(r"_s(\d+)\.csv$", str(path))
            x["seed"] = int(m.group(1)) if m else 0
        frames.append(x)
    df = pd.concat(frames, ignore_index=True)
    lines = ["| body | method | base seed | exact model (false alarms) | minimum-jerk | via-point |", "|---|---|---|---|---|---|"]
    for (body, method, seed), x in df.groupby(["model", "method", "seed"], sort=False):
        cells = []
        for g in ("controller", "minimum-jerk", "via-point"):
            f = x[x.generator == g].flagged.astype(bool)
            if f.empty:
                cells.append("n/a")
                continue
            lo, hi = _wilson(int(f.sum()), len(f))
            cells.append(f"{int(f.sum())}/{len(f)} = {f.mean():.0%} ({lo:.0%}-{hi:.0%})")
        lines.append(f"| {body} | {method} | {seed} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    import sys

    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--summarize":
        print(summarize(argv[1:]))
        return 0
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default="panda")
    p.add_argument("--method", default="camo-js")
    p.add_argument("--budget", type=int, default=2000)
    p.add_argument("--runs", type=int, default=30)
    p.add_argument("--reaches", type=int, default=10)
    p.add_argument("--generators", default="controller,via-point,minimum-jerk")
    p.add_argument("--statistic", default="onset")
    p.add_argument("--test", default="rank")
    p.add_argument("--tolerance-mm", type=float, default=10.0)
    p.add_argument("--prior-share", type=float, default=None, help="share of prior draws in the reference "
                   "(default: the check's own default)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    d = registry.get_model(args.model)
    sim = d.build()
    subjects = list(d.informative)
    rows = []
    for g in args.generators.split(","):
        for run in range(args.runs):
            t0 = time.perf_counter()
            subject = subjects[run % len(subjects)]
            theta = d.informative[subject](sim)
            task = make_reaching_task(sim, theta, n_train=args.reaches, n_test=1, seed=derive_seed(args.seed, run),
                                      workspace="nominal")
            if g != "controller":
                task, _ = misspecified_observations(task, make_generator(sim, g, seed=derive_seed(args.seed, run, 5)))
            res = run_method(args.method, task, budget=args.budget, seed=derive_seed(args.seed, run, 1))
            c = check_reproduction(task, res, seed=derive_seed(args.seed, run, 2), statistic=args.statistic,
                                   test=args.test, tolerance_mm=args.tolerance_mm,
                                   **({} if args.prior_share is None else {"prior_share": args.prior_share}))
            rows.append({"model": args.model, "generator": g, "run": run, "subject": subject, "method": args.method, "seed": args.seed,
                         "statistic": args.statistic, "test": args.test, "prior_share": args.prior_share, "status": c.status,
                         "p_recording": c.p_recording, "p_pooled": c.p_pooled, "flagged": c.flagged,
                         "flagged_pooled": bool(c.p_pooled < c.alpha), "reaches_flagged": len(c.flagged_reaches),
                         "min_p_reach": float(np.min(c.p_reach)), "median_distance_mm": float(np.median(c.distance_mm)),
                         "wall_s": time.perf_counter() - t0})
            print(rows[-1], flush=True)
            pd.DataFrame(rows).to_csv(args.out, index=False)
    df = pd.DataFrame(rows)
    print(df.groupby("generator")[["flagged", "flagged_pooled"]].agg(["mean", "count"]).to_string())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
