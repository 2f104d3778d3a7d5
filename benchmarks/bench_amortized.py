"""Inference time of npe-amortized for one new person (5 reaches) vs per-task NPE, timed in the same run.

    python benchmarks/bench_amortized.py ESTIMATOR.pt [--model panda] [--repeats 5] [--npe-budget 500]

Prints the load average, the estimator's one-off load time, then per inference (mean over
``--repeats`` persons): wall and CPU seconds, the simulations counted by the budget wrapper
(0 for npe-amortized) and the effective sample size; the reference is per-task NPE on the
same persons at ``--npe-budget`` simulations per reach; the ratio is reference / amortized.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("estimator")
    p.add_argument("--model", default="panda")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--npe-budget", type=int, default=500)
    p.add_argument("--tasks", type=int, default=5)
    args = p.parse_args()

    from camo_sbi.experiments.subjects import build_model, subject_names, subject_theta
    from camo_sbi.inference.amortized import load_estimator
    from camo_sbi.inference.registry import run_method
    from camo_sbi.scenarios.reaching import make_reaching_task

    print(f"load average before: {os.getloadavg()}")
    sim = build_model(args.model)
    t0 = time.perf_counter()
    load_estimator(args.estimator)
    print(f"estimator load (once per process): {time.perf_counter() - t0:.2f} s")
    names = subject_names(args.model)
    tasks = [make_reaching_task(sim, subject_theta(sim, args.model, names[i % len(names)]), n_train=args.tasks,
                                n_test=1, seed=i) for i in range(args.repeats)]
    rows = {}
    for label, method, budget, cfg in (("npe-amortized", "npe-amortized", 1, {"estimator": args.estimator}),
                                       (f"npe (per task, b={args.npe_budget})", "npe", args.npe_budget, {})):
        wall, cpu, sims, ess = [], [], [], []
        for i, task in enumerate(tasks):
            c0, w0 = time.process_time(), time.perf_counter()
            res = run_method(method, task, budget=budget, seed=i, config=cfg)
            wall.append(time.perf_counter() - w0)
            cpu.append(time.process_time() - c0)
            sims.append(res.n_simulations)
            ess.append(res.ess)
        rows[label] = (np.mean(wall), np.mean(cpu), np.mean(sims), np.mean(ess))
        print(f"{label:28s} wall {np.mean(wall):7.2f} s  cpu {np.mean(cpu):7.2f} s  simulations {np.mean(sims):7.0f}"
              f"  ESS {np.mean(ess):8.1f}  ({args.tasks} reaches, mean of {len(tasks)})")
    a, r = rows["npe-amortized"], rows[f"npe (per task, b={args.npe_budget})"]
    print(f"ratio per-task NPE / npe-amortized: wall {r[0] / a[0]:.1f}x  cpu {r[1] / a[1]:.1f}x")
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
