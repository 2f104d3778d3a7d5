"""Simulator throughput: generated numba kernel vs the two baselines, measured in one run.

    python benchmarks/bench_simulator.py [--sizes 2000 5000] [--steps 100] [--repeats 7]

Franka Panda, float32, CPU. Every trajectory runs all T steps (goal tolerance 1e-9, so no
early exit) in all three implementations, so "trajectory-steps" mean the same thing:

  kernel  the generated numba kernel (`camo_sbi.simulators.kernel`), threads = NUMBA_NUM_THREADS
  (a)     the straightforward batched torch loop (`controller.reference_simulate`:
          pytorch_kinematics ``chain.jacobian(q, ret_eef_pose=True)`` + batched solve per step)
  (b)     one trajectory at a time, sample by sample (as the paper's code): the same torch
          controller with B = 1; a few trajectories are timed and the cost extrapolated to B

JIT compile time (first call, empty cache) and the first-call time of a fresh process
that loads the compiled kernel from the on-disk cache are reported separately.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numba  # noqa: E402
import torch  # noqa: E402

from camo_sbi.simulators import ControllerConfig, panda  # noqa: E402

_CACHED_PROBE = """
import time, torch
from camo_sbi.simulators import panda, ControllerConfig
sim = panda(controller=ControllerConfig(max_steps={T}, tol=1e-9))
theta = sim.bounds.reshape(-1).float()
t = time.perf_counter()
sim.simulate(theta, [0.4, 0.2, 0.5])
print(time.perf_counter() - t)
"""


def problem(sim, B: int, seed: int = 0):
    """theta from a box prior around the start posture (float32) and goals inside those limits."""
    g = torch.Generator().manual_seed(seed)
    b, s, n = sim.bounds, sim.start, sim.n_joints
    u = torch.rand(B, n, 2, generator=g, dtype=torch.float64)
    lo = b[:, 0] + (s - b[:, 0]) * u[..., 0]
    hi = s + (b[:, 1] - s) * u[..., 1]
    q = lo + (hi - lo) * torch.rand(B, n, generator=g, dtype=torch.float64)
    theta = torch.stack([lo, hi], -1).reshape(B, -1)
    return theta.float(), sim.forward_kinematics(q).float()


def best_of(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[2000, 5000])
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=7, help="kernel timings: best of N")
    ap.add_argument("--reference-repeats", type=int, default=2, help="baseline (a): best of N")
    ap.add_argument("--per-trajectory", type=int, default=5, help="baseline (b): trajectories timed")
    args = ap.parse_args(argv)
    T = args.steps

    cache = tempfile.mkdtemp(prefix="camo_sbi_bench_kernels_")
    os.environ["CAMO_SBI_KERNEL_CACHE"] = cache  # empty cache: the first call compiles

    cfg = ControllerConfig(max_steps=T, tol=1e-9)
    sim = panda(controller=cfg, backend="numba")
    ref = sim.with_config(backend="torch")
    torch_threads = torch.get_num_threads()
    load = os.getloadavg()[0]
    print(f"Panda (7 DOF), float32, CPU, T={T}; numba threads {numba.get_num_threads()}, "
          f"torch threads {torch_threads}; load average {load:.1f} on {os.cpu_count()} CPUs")
    if load > (os.cpu_count() or 1):
        print("WARNING: the machine is busy; timings (especially torch/OpenMP) are inflated.")

    theta, goals = problem(sim, 64)
    t = time.perf_counter()
    sim.simulate(theta, goals)
    compile_s = time.perf_counter() - t
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", _CACHED_PROBE.format(T=T)], capture_output=True,
                         text=True, env=env, cwd=ROOT, check=True)
    cached_s = float(out.stdout.strip().splitlines()[-1])
    print(f"kernel codegen + JIT compile (first call, empty cache): {compile_s:.2f} s")
    print(f"first call in a fresh process, kernel loaded from cache: {cached_s * 1e3:.0f} ms")

    # (b) one trajectory at a time, same controller, B = 1 (one torch thread: fastest for B = 1)
    theta_b, goals_b = problem(sim, args.per_trajectory, seed=1)
    torch.set_num_threads(1)
    ref.simulate(theta_b[0], goals_b[0])  # warm-up
    t = time.perf_counter()
    for i in range(args.per_trajectory):
        ref.simulate(theta_b[i], goals_b[i])
    per_traj = (time.perf_counter() - t) / args.per_trajectory
    torch.set_num_threads(torch_threads)
    print(f"(b) per-trajectory loop: {per_traj * 1e3:.1f} ms per {T}-step trajectory "
          f"({per_traj / T * 1e3:.2f} ms/step, {per_traj / T * 20 * 1e3:.1f} ms per 20 steps)")

    print()
    hdr = (f"{'B':>6} {'kernel':>10} {'steps/s':>10} {'(a) batched pk':>15} {'steps/s':>10} "
           f"{'x vs (a)':>9} {'(b) extrap.':>12} {'x vs (b)':>9} {'default cfg':>12}")
    print(hdr)
    print("-" * len(hdr))
    default_sim = panda(backend="numba")
    for B in args.sizes:
        theta, goals = problem(sim, B, seed=B)
        sim.simulate(theta, goals)
        t_k = best_of(lambda th=theta, g=goals: sim.simulate(th, g), args.repeats)
        t_a = float("inf")  # (a): best over torch thread counts (1 and the default)
        for nt in sorted({1, torch_threads}):
            torch.set_num_threads(nt)
            t_a = min(t_a, best_of(lambda th=theta, g=goals: ref.simulate(th, g), args.reference_repeats))
        torch.set_num_threads(torch_threads)
        t_b = per_traj * B
        default_sim.simulate(theta, goals)
        t_d = best_of(lambda th=theta, g=goals: default_sim.simulate(th, g), args.repeats)
        steps = B * T
        print(f"{B:>6} {t_k * 1e3:>8.1f}ms {steps / t_k:>10.3g} {t_a:>13.2f} s {steps / t_a:>10.3g} "
              f"{t_a / t_k:>8.0f}x {t_b:>10.1f} s {t_b / t_k:>8.0f}x {t_d * 1e3:>10.1f}ms")
    print("\nkernel/(a) run every trajectory for all T steps (tol 1e-9); 'default cfg' is the kernel with "
          "the default ControllerConfig (1 cm tolerance, early exit per trajectory).\n"
          "(a) is the best over torch threads {1, default}; (b) uses one torch thread.")
    print(f"numba threading layer: {numba.threading_layer()}; load average now {os.getloadavg()[0]:.1f}")
    shutil.rmtree(cache, ignore_errors=True)


if __name__ == "__main__":
    main()
