"""Inference time of npe-amortized for one new person (5 reaches) vs per-task NPE, timed in the same run.

    python benchmarks/bench_amortized.py ESTIMATOR.pt [--model panda] [--repeats 5] [--npe-budget 500]
        [--combine smc,mcmc] [--draws 1000] [--cold 3]

``--cold N``: the cold load of the file in N fresh processes each (after torch and the body
model are imported, as in any command), today's path (`load_estimator`: the sha256 check, the
NSF rebuilt as `sbi_adapter.NsfReader` from the metadata, weights loaded; no sbi import)
against the previous one (sbi's flow built, which imports sbi, then the weights loaded);
and, for a set-form estimator, one person's ``--draws`` draws from both flows in this process
(the same seed gives the same draws; asserted).

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

_COLD = {
    "now": "from camo_sbi.inference.amortized import load_estimator; load_estimator(PATH)",
    "before": ("import json; from camo_sbi.inference import amortized as A; "
               "from camo_sbi.inference import amortized_flows as F; "
               "b = torch.load(PATH, weights_only=True); m = json.loads(b['metadata']); "
               "s = A.TrainConfig.from_json(m['settings']); n = sum(h > l for l, h in zip(m['prior']['low'], "
               "m['prior']['high'])); [F.new_flow(s, n, m['features'][sp]['n_kept'], 0).load_state_dict("
               "{k[len(sp) + 1:]: v for k, v in b['state_dict'].items() if k.startswith(sp + '.')}) "
               "for sp in s.spaces]"),
}


def _cold_loads(path: str, model: str, n: int) -> None:
    import subprocess
    import sys

    out = {}
    for arm, code in _COLD.items():
        prog = ("import sys, time, torch; from camo_sbi.experiments.subjects import build_model; "
                f"build_model({model!r}); PATH = {path!r}; c, w = time.process_time(), time.perf_counter(); "
                f"{code}; print(time.perf_counter() - w, time.process_time() - c, 'sbi' in sys.modules)")
        runs = [subprocess.run([sys.executable, "-c", prog], capture_output=True, text=True, check=True)
                .stdout.split() for _ in range(n)]
        out[arm] = (np.median([float(r[0]) for r in runs]), np.median([float(r[1]) for r in runs]), runs[0][2])
        print(f"cold load, {arm:6s}: {out[arm][0]:.2f} s wall, {out[arm][1]:.2f} s CPU (median of {n} fresh "
              f"processes; sbi imported: {out[arm][2]})")
    print(f"cold load ratio before / now: wall {out['before'][0] / out['now'][0]:.1f}x, "
          f"CPU {out['before'][1] / out['now'][1]:.1f}x")


def _reader_vs_sbi(est, tasks, draws: int) -> None:
    import json

    import torch

    from camo_sbi.inference import amortized as A
    from camo_sbi.inference import amortized_flows as F

    blob = torch.load(est.path, weights_only=True)
    meta = json.loads(blob["metadata"])
    sbi_flows = {}
    for sp in est.spaces:
        f = F.new_flow(est.settings, int(est.free_mask.sum()), meta["features"][sp]["n_kept"], 0)
        f.load_state_dict({k[len(sp) + 1:]: v for k, v in blob["state_dict"].items() if k.startswith(sp + ".")})
        sbi_flows[sp] = f.eval()
    other = A.AmortizedEstimator(meta, sbi_flows)
    times = {}
    for label, e in (("now (NsfReader)", est), ("before (sbi flow)", other)):
        cpu, wall = [], []
        for i, task in enumerate(tasks):
            c0, w0 = time.process_time(), time.perf_counter()
            theta, _ = e.sample_set(task.observations, "joint", draws, i)
            wall.append(time.perf_counter() - w0)
            cpu.append(time.process_time() - c0)
            times.setdefault(i, []).append(theta)
        print(f"one person, {draws} draws, {label:18s}: wall {np.mean(wall):.3f} s (max {np.max(wall):.3f}), "
              f"cpu {np.mean(cpu):.3f} s")
    assert all(torch.equal(a, b) for a, b in times.values()), "the two flows gave different draws"
    print("  the same seeds gave the same draws from both flows")


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("estimator")
    p.add_argument("--model", default="panda")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--npe-budget", type=int, default=500)
    p.add_argument("--tasks", type=int, default=5)
    p.add_argument("--combine", default="smc,mcmc", help="npe-amortized samplers to time (comma-separated)")
    p.add_argument("--draws", type=int, default=1000, help="npe-amortized posterior draws per person")
    p.add_argument("--cold", type=int, default=3, help="fresh processes per cold-load arm (0: skip)")
    args = p.parse_args()
    if args.cold > 0:
        _cold_loads(args.estimator, args.model, args.cold)
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
             {"estimator_path": args.estimator, "n_posterior_samples": args.draws}
             | ({} if c == "set flow" else {"combine": c})) for c in samplers]
    if est.form == "set":
        _reader_vs_sbi(est, tasks, args.draws)
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
