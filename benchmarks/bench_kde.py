"""Benchmark of CAMO's KDE stage (`camo_sbi.inference.kde.GaussianKDE.log_density`).

It times, in one run, on the shapes of the paper setting's camo-hull (m = 2000 centres per
task, d = 14 free limits, N queries):

* the reference: the one-pass online logsumexp over row-major centres (the kernel the
  toolkit used before, copied here verbatim);
* the library's kernel (two passes over transposed centres).

and checks the two agree to 1e-12 relative. Both use all numba threads.

    python benchmarks/bench_kde.py                 # m = 2000, N = 2000 and 16000
    python benchmarks/bench_kde.py --m 7000 --n 1000
"""

from __future__ import annotations

import argparse
import math
import time

import numba
import numpy as np


@numba.njit(parallel=True)
def reference_log_kernel_sums(xs, ps, out):  # pragma: no cover - compiled
    n, d = xs.shape
    m = ps.shape[0]
    for i in numba.prange(n):
        best = np.inf
        acc = 0.0
        for j in range(m):
            d2 = 0.0
            for k in range(d):
                t = xs[i, k] - ps[j, k]
                d2 += t * t
            if d2 < best:
                acc = acc * math.exp(-0.5 * (best - d2)) + 1.0 if best < np.inf else 1.0
                best = d2
            else:
                acc += math.exp(-0.5 * (d2 - best))
        out[i] = -0.5 * best + math.log(acc)


def _best(f, repeats):
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        f()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None) -> int:
    from camo_sbi.inference.kde import GaussianKDE

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--m", type=int, default=2000, help="kernel centres")
    p.add_argument("--d", type=int, default=14, help="dimensions")
    p.add_argument("--n", default="2000,16000", help="comma-separated numbers of query points")
    p.add_argument("--bandwidth", type=float, default=0.25)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    centres = rng.uniform(-2.5, 2.5, size=(args.m, args.d))
    kde = GaussianKDE(centres, args.bandwidth)
    ps = np.ascontiguousarray(kde.points.numpy() * kde._inv_sd.numpy())
    print(f"numba threads: {numba.get_num_threads()}; m = {args.m}, d = {args.d}, bandwidth {args.bandwidth}")
    print(f"{'N':>7} {'reference ms':>13} {'library ms':>11} {'ratio':>6} {'max rel diff':>13}")
    for n in (int(v) for v in args.n.split(",")):
        x = rng.uniform(-2.5, 2.5, size=(n, args.d))
        xs = np.ascontiguousarray(x * kde._inv_sd.numpy())
        ref = np.empty(n)
        reference_log_kernel_sums(xs[:2], ps, ref[:2])  # compile
        kde.log_density(x[:2])
        t_ref = _best(lambda xs=xs, ref=ref: reference_log_kernel_sums(xs, ps, ref), args.repeats)
        t_lib = _best(lambda x=x: kde.log_density(x), args.repeats)
        lib = kde.log_density(x).numpy() - kde._log_norm
        rel = float(np.max(np.abs(lib - ref) / np.maximum(np.abs(ref), 1e-300)))
        if rel > 1e-12:
            raise SystemExit(f"library and reference disagree: max relative difference {rel:.3g}")
        print(f"{n:>7} {t_ref * 1e3:>13.1f} {t_lib * 1e3:>11.1f} {t_ref / t_lib:>6.2f} {rel:>13.2e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
