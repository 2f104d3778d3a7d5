"""Benchmark of the distance stage of a task: exact DTW between one observation and B candidates.

Per task (one observed reach, B simulated candidates of T <= 100 steps) it times, in one run:

* references: a plain numba DTW over all pairs (two-row table, no pruning, one thread) and,
  if installed, dtaidistance's C DTW (``dtw_ndim``, ``inner_dist="euclidean"``: the same
  definition) over all pairs, sequential and with its own parallel matrix;
* ``dtw_distances`` exact on every candidate (all threads, and one thread);
* ``dtw_distances(keep_best=500)`` and ``dtw_distances(epsilon=q10)`` (q10: the 10% quantile of
  the distances, about what CAMO/ABC accept);

and checks that every value reported equals the plain reference (1e-9) and that the pruned
results are bit-identical to the full ones. Trajectories: real Franka Panda reaches from
``camo_sbi.simulators.panda()`` (joint space D = 7 and Cartesian D = 3) when it is available,
plus smooth synthetic reaching curves with a full-length (100-step) observation; the Panda
simulation stage is timed too, for comparison.
Compile times (numba, cached on disk afterwards) are reported separately.

    python benchmarks/bench_distances.py                  # B = 2000 and 5000, 3 Panda tasks
    python benchmarks/bench_distances.py --synthetic --tasks 1 --sizes 5000
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import torch
from numba import njit

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from camo_sbi.inference.distances import dtw_distances  # noqa: E402


@njit(cache=True)
def plain_dtw_all(x, sim, lengths, out):
    """The textbook two-row DTW of x against every sim[b, :lengths[b]] (no pruning)."""
    n, D = x.shape
    for b in range(sim.shape[0]):
        m = lengths[b]
        prev = np.full(m + 1, np.inf)
        cur = np.full(m + 1, np.inf)
        prev[0] = 0.0
        for i in range(n):
            cur[0] = np.inf
            for j in range(m):
                acc = 0.0
                for k in range(D):
                    d = x[i, k] - sim[b, j, k]
                    acc += d * d
                cur[j + 1] = np.sqrt(acc) + min(prev[j], prev[j + 1], cur[j])
            prev, cur = cur, prev
        out[b] = prev[m]


def best_of(repeats, fn, *args, **kwargs):
    """(min wall seconds over ``repeats`` calls of fn(*args, **kwargs), last result)."""
    walls, res = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = fn(*args, **kwargs)
        walls.append(time.perf_counter() - t0)
    return min(walls), res


def dtai_pairs(dtw_ndim, x, series):
    return [dtw_ndim.distance_fast(x, s, inner_dist="euclidean") for s in series]


def dtai_matrix(dtw_ndim, x, series):
    block = ((0, 1), (1, len(series) + 1))
    return dtw_ndim.distance_matrix_fast(
        [x] + series, block=block, compact=True, parallel=True, inner_dist="euclidean"
    )


def bench_case(obs, traj, length, B, args, dtw_ndim):
    """Times (ms) of the references and of dtw_distances on the first B candidates; checks."""
    sim_np = np.ascontiguousarray(traj[:B].numpy(), dtype=np.float64)
    lens_np = length[:B].numpy().astype(np.int64)
    x = np.ascontiguousarray(obs.numpy(), dtype=np.float64)
    sim_t, lens_t = traj[:B], length[:B]
    t = {}
    ref = np.empty(B)
    t["plain"], _ = best_of(1, plain_dtw_all, x, sim_np, lens_np, ref)
    t["dtai"] = t["dtai_par"] = float("nan")
    if dtw_ndim is not None:
        series = [sim_np[b, : lens_np[b]] for b in range(B)]
        t["dtai"], dref = best_of(1, dtai_pairs, dtw_ndim, x, series)
        t["dtai_par"], _ = best_of(1, dtai_matrix, dtw_ndim, x, series)
        assert np.allclose(np.asarray(dref), ref, rtol=1e-9, atol=1e-9)
    r = args.repeats
    t["full"], full = best_of(r, dtw_distances, obs, sim_t, lens_t)
    t["full1"], full1 = best_of(r, dtw_distances, obs, sim_t, lens_t, workers=1)
    full = full.numpy()
    assert np.allclose(full, ref, rtol=1e-9, atol=1e-9), "full DTW != plain reference"
    assert np.array_equal(full1.numpy(), full), "the thread count changed the values"
    k = args.keep_best
    t["keep"], kept = best_of(r, dtw_distances, obs, sim_t, lens_t, keep_best=k)
    best = np.argsort(full, kind="stable")[:k]
    want = np.full(B, np.inf)
    want[best] = full[best]
    assert np.array_equal(kept.numpy(), want), "keep_best differs from the full DTW"
    eps = float(np.quantile(full, 0.1))
    t["eps"], acc = best_of(r, dtw_distances, obs, sim_t, lens_t, epsilon=eps)
    assert np.array_equal(acc.numpy(), np.where(full < eps, full, np.inf)), "epsilon differs"
    return {key: v * 1e3 for key, v in t.items()}, x.shape[0], lens_np.mean()


def panda_tasks(n_tasks, B, seed):
    """[(name, observed q, observed ee, Trajectories, simulate seconds)] for real Panda reaches."""
    from camo_sbi.priors import BoxPrior
    from camo_sbi.scenarios.reaching import make_reaching_task
    from camo_sbi.simulators import panda

    sim = panda()
    prior = BoxPrior(sim.bounds, sim.start)
    true = prior.sample(1, np.random.default_rng(seed))[0]
    task = make_reaching_task(sim, true, n_train=n_tasks, n_test=1, seed=seed)
    out = []
    for i, o in enumerate(task.observations):
        theta = prior.sample(B, np.random.default_rng([seed, i]))
        theta[:, 0::2] = torch.minimum(theta[:, 0::2], o.start)
        theta[:, 1::2] = torch.maximum(theta[:, 1::2], o.start)
        sim.simulate(theta[:8], o.goal, o.start)  # warm-up
        t0 = time.perf_counter()
        traj = sim.simulate(theta, o.goal, o.start)
        t_sim = time.perf_counter() - t0
        out.append((f"panda task {i}", o.q, o.ee, traj.q, traj.ee, traj.length, t_sim))
    return out


def synthetic_tasks(n_tasks, B, seed, T=100):
    """Smooth reaching-like curves (minimum-jerk profile plus a wiggle), joint D=7, Cart. D=3."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_tasks):
        lens = rng.integers(30, T + 1, size=B + 1)
        lens[-1] = T  # the observation
        s = np.clip(np.arange(T)[None, :] / (lens[:, None] - 1), 0.0, 1.0)
        prof = (10 * s**3 - 15 * s**4 + 6 * s**5)[..., None]
        trajs = []
        for D in (7, 3):
            start = rng.normal(size=D)
            goal = start + rng.normal(size=D)
            g = goal + 0.3 * rng.normal(size=(B + 1, 1, D))
            wiggle = 0.1 * rng.normal(size=(B + 1, 1, D)) * np.sin(np.pi * s)[..., None]
            trajs.append(torch.from_numpy(start + prof * (g - start) + wiggle))
        q, ee = trajs
        n = int(lens[-1])
        out.append(
            (
                f"synthetic task {i}",
                q[-1, :n],
                ee[-1, :n],
                q[:B],
                ee[:B],
                torch.from_numpy(lens[:B]),
                float("nan"),
            )
        )
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tasks", type=int, default=3)
    ap.add_argument("--sizes", type=int, nargs="+", default=[2000, 5000])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--keep-best", type=int, default=500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--synthetic", action="store_true", help="skip the Panda simulator")
    args = ap.parse_args()

    try:
        from dtaidistance import dtw_ndim
    except ImportError:  # optional reference
        dtw_ndim = None

    print(f"CPUs: {len(os.sched_getaffinity(0))}, load average: {os.getloadavg()}")
    # compile times (first calls; numba caches them on disk, later runs load them)
    rng = np.random.default_rng(0)
    xs, ss = rng.normal(size=(20, 3)), rng.normal(size=(40, 20, 3))
    t0 = time.perf_counter()
    dtw_distances(xs, ss)
    t1 = time.perf_counter()
    dtw_distances(xs, ss, keep_best=3)
    t2 = time.perf_counter()
    plain_dtw_all(xs, ss, np.full(40, 20), np.empty(40))
    t3 = time.perf_counter()
    print(
        f"compile or cache load: dtw_distances full {t1 - t0:.2f} s, pruned +{t2 - t1:.2f} s, "
        f"plain reference {t3 - t2:.2f} s"
    )

    big = max(args.sizes)
    tasks = []
    if not args.synthetic:
        try:
            tasks = panda_tasks(args.tasks, big, args.seed)
        except Exception as exc:  # the simulator is optional here
            print(f"Panda simulator unavailable ({type(exc).__name__}: {exc}); synthetic data")
    # synthetic reaches always included: a full-length observation (n = 100)
    tasks += synthetic_tasks(args.tasks if not tasks else 1, big, args.seed)

    header = (
        f"{'task':<16}{'space':<6}{'B':>5}{'n':>4}{'m':>4} |{'plain1t':>8}{'dtai1t':>8}"
        f"{'dtaiPar':>8} |{'full':>7}{'full1t':>7}{'keep':>7}{'eps':>7} |"
        f"{'plain/full':>11}{'plain/keep':>11}{'plain/eps':>10}{'dtaiPar/keep':>13} |"
        f"{'simulate':>9}"
    )
    print(
        f"\nwall-clock ms (min of {args.repeats} calls; references once); keep = keep_best="
        f"{args.keep_best}, eps = epsilon at the 10% quantile; simulate = the simulator on the "
        f"{big} candidates of the task"
    )
    print(header)
    print("-" * len(header))
    for name, oq, oee, q, ee, length, t_sim in tasks:
        for space, obs, traj in (("joint", oq, q), ("cart", oee, ee)):
            for B in args.sizes:
                t, n, m = bench_case(obs, traj, length, B, args, dtw_ndim)
                print(
                    f"{name:<16}{space:<6}{B:>5}{n:>4}{m:>4.0f} |"
                    f"{t['plain']:>8.1f}{t['dtai']:>8.1f}{t['dtai_par']:>8.1f} |"
                    f"{t['full']:>7.1f}{t['full1']:>7.1f}{t['keep']:>7.1f}{t['eps']:>7.1f} |"
                    f"{t['plain'] / t['full']:>11.1f}{t['plain'] / t['keep']:>11.1f}"
                    f"{t['plain'] / t['eps']:>10.1f}{t['dtai_par'] / t['keep']:>13.1f} |"
                    f"{t_sim * 1e3:>9.1f}"
                )
    print(
        "\nall checks passed: every reported value equals the plain DTW (1e-9); keep_best and "
        "epsilon results are bit-identical to the full computation"
    )


if __name__ == "__main__":
    main()
