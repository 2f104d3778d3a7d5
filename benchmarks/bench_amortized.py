"""Inference time of npe-amortized for one new person (5 reaches) vs per-task NPE, timed in the same run.

    python benchmarks/bench_amortized.py ESTIMATOR.pt [--model panda] [--repeats 5] [--npe-budget 500]
        [--combine smc,mcmc]

A set-form estimator has no combining sampler (one flow sample): ``--combine`` is ignored
and its one row is "npe-amortized (set flow)".

Prints the load average, the estimator's one-off load time, then per inference (mean and
max over ``--repeats`` persons): wall and CPU seconds, the simulations counted by the budget
wrapper (0 for npe-amortized) and the effective sample size, for each sampler of
``--combine`` (the default SMC, and the population MCMC that was the default before); the
reference is per-task NPE on the same persons at ``--npe-budget`` simulations per reach
(``--npe-budget 0`` skips it); the ratios are reference / each sampler, and MCMC / SMC.
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
    p.add_argument("--combine", default="smc,mcmc", help="npe-amortized samplers to time (comma-separated)")
    args = p.parse_args()
    samplers = [c for c in args.combine.split(",") if c]

    from camo_sbi.experiments.subjects import build_model, subject_names, subject_theta
    from camo_sbi.inference.amortized import load_estimator
    from camo_sbi.inference.registry import run_method
    from camo_sbi.scenarios.reaching import make_reaching_task

    print(f"load average before: {os.getloadavg()}")
    sim = build_model(args.model)
    t0 = time.perf_counter()
    est = load_estimator(args.estimator)
    print(f"estimator load (once per process): {time.perf_counter() - t0:.2f} s  ({est.form} form)")
    if est.form == "set":  # one flow sample, no combining sampler: --combine does not apply
        samplers = ["set flow"]
    names = subject_names(args.model)
    tasks = [make_reaching_task(sim, subject_theta(sim, args.model, names[i % len(names)]), n_train=args.tasks,
                                n_test=1, seed=i) for i in range(args.repeats)]
    rows = {}
    runs = [(f"npe-amortized ({c})", "npe-amortized", 1,
             {"estimator": args.estimator} | ({} if c == "set flow" else {"combine": c})) for c in samplers]
    ref = f"npe (per task, b={args.npe_budget})"
    if args.npe_budget > 0:
        runs.append((ref, "npe", args.npe_budget, {}))
    for label, method, budget, cfg in runs:
        wall, cpu, sims, ess = [], [], [], []
        for i, task in enumerate(tasks):
            c0, w0 = time.process_time(), time.perf_counter()
            res = run_method(method, task, budget=budget, seed=i, config=cfg)
            wall.append(time.perf_counter() - w0)
            cpu.append(time.process_time() - c0)
            sims.append(res.n_simulations)
            ess.append(res.ess)
        rows[label] = (np.mean(wall), np.mean(cpu), np.mean(sims), np.mean(ess), np.max(wall))
        print(f"{label:28s} wall {np.mean(wall):7.2f} s (max {np.max(wall):.2f})  cpu {np.mean(cpu):7.2f} s  "
              f"simulations {np.mean(sims):7.0f}  ESS {np.mean(ess):8.1f}  ({args.tasks} reaches, {len(tasks)} persons)")
    for label in rows:
        if label.startswith("npe-amortized") and ref in rows:
            a, r = rows[label], rows[ref]
            print(f"ratio per-task NPE / {label}: wall {r[0] / a[0]:.1f}x  cpu {r[1] / a[1]:.1f}x")
    if "npe-amortized (smc)" in rows and "npe-amortized (mcmc)" in rows:
        print(f"ratio MCMC / SMC: wall {rows['npe-amortized (mcmc)'][0] / rows['npe-amortized (smc)'][0]:.1f}x")
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
