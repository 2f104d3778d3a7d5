"""Per-task CAMO cost split into simulation, distance and KDE, against a plain reference.

    python benchmarks/bench_camo.py [--tasks 10] [--samples 2000 5000] [--keep-best 100 500]

For each setting, one continual CAMO run observes ``--tasks`` Panda tasks; the table gives
the per-task time of each stage (mean over tasks after a warm-up task, which pays the JIT
compile). The reference, measured in the same run, is the same algorithm done plainly:
the batched pytorch-kinematics controller (`controller.reference_simulate`), a plain
numba DTW over every candidate without pruning, and the joint density recomputed from
scratch over all kept vectors at every task (O(n^2) over tasks), as a straightforward
implementation of Algorithm 1 would.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from camo_sbi.experiments.subjects import subject_theta  # noqa: E402
from camo_sbi.inference.camo import Camo, CamoConfig  # noqa: E402
from camo_sbi.inference.kde import GaussianKDE  # noqa: E402
from camo_sbi.scenarios.reaching import make_reaching_task  # noqa: E402
from camo_sbi.simulators import panda  # noqa: E402


def fast_run(sim, task, n_samples, keep_best):
    camo = Camo(sim, task.prior, CamoConfig(keep_best=keep_best), n_samples=n_samples, seed=0)
    obs = task.observations
    camo.observe(obs[0].start, obs[0].goal, obs[0].q)  # warm-up: JIT compile
    camo = Camo(sim, task.prior, CamoConfig(keep_best=keep_best), n_samples=n_samples, seed=0)
    t0 = time.perf_counter()
    for o in obs:
        camo.observe(o.start, o.goal, o.q)
    total = time.perf_counter() - t0
    r = camo.records
    k = len(r)
    return (sum(x.time_simulate for x in r) / k, sum(x.time_distance for x in r) / k,
            sum(x.time_kde for x in r) / k, total / k, camo)


def reference_run(sim, task, n_samples, keep_best, camo_fast):
    """Plain implementation of the same stages; returns per-task times and the estimate."""
    import numpy as np

    from camo_sbi.inference.distances import dtw_distances
    ref_sim = sim.with_config(backend="torch")
    ts = td = tk = 0.0
    kept, kdes = [], []
    for i, o in enumerate(task.observations):
        rng = np.random.default_rng([0, i])
        theta = task.prior.sample(n_samples, rng)
        lo = torch.minimum(theta[:, 0::2], o.start)
        hi = torch.maximum(theta[:, 1::2], o.start)
        theta[:, 0::2], theta[:, 1::2] = lo, hi
        t0 = time.perf_counter()
        traj = ref_sim.simulate(theta.float(), o.goal.float(), o.start.float())
        t1 = time.perf_counter()
        d = dtw_distances(o.q, traj.q, traj.length, workers=1)  # no pruning, one thread
        t2 = time.perf_counter()
        keep = torch.argsort(d, stable=True)[:keep_best]
        kept.append(theta[keep])
        kdes.append(GaussianKDE(theta[keep], CamoConfig().bandwidth))
        allv = torch.cat(kept)
        logp = sum(k.log_density(allv) for k in kdes)  # recomputed from scratch: O(n^2)
        est = allv[int(torch.argmax(logp))]
        t3 = time.perf_counter()
        ts, td, tk = ts + t1 - t0, td + t2 - t1, tk + t3 - t2
    n = len(task.observations)
    return ts / n, td / n, tk / n, est


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--tasks", type=int, default=10)
    ap.add_argument("--samples", type=int, nargs="+", default=[2000, 5000])
    ap.add_argument("--keep-best", type=int, nargs="+", default=[100, 500])
    ap.add_argument("--skip-reference", action="store_true")
    args = ap.parse_args()
    sim = panda()
    true = subject_theta(sim, "panda", "elbow_restricted")
    task = make_reaching_task(sim, true, n_train=args.tasks, n_test=1, seed=1)
    print(f"CAMO per-task cost, Panda, {args.tasks} tasks, float32 simulation, torch threads={torch.get_num_threads()}")
    hdr = f"{'b':>6} {'k':>5} | {'sim ms':>8} {'dist ms':>8} {'kde ms':>8} {'task ms':>8}"
    if not args.skip_reference:
        hdr += f" | {'ref sim':>8} {'ref dist':>9} {'ref kde':>8} | {'speed-up':>8}"
    print(hdr)
    for b, k in zip(args.samples, args.keep_best, strict=False):
        s, d, kd, tot, camo = fast_run(sim, task, b, k)
        line = f"{b:>6} {k:>5} | {s * 1e3:8.1f} {d * 1e3:8.1f} {kd * 1e3:8.1f} {tot * 1e3:8.1f}"
        if not args.skip_reference:
            rs, rd, rk, est = reference_run(sim, task, b, k, camo)
            line += f" | {rs * 1e3:8.1f} {rd * 1e3:9.1f} {rk * 1e3:8.1f} | {(rs + rd + rk) / tot:7.1f}x"
        print(line)
    print("distance stage <= simulation stage is the target for the fast path")


if __name__ == "__main__":
    main()
