"""Simulator throughput: generated numba kernel vs the two baselines, measured in one run.

    python benchmarks/bench_simulator.py [--sizes 2000 5000] [--steps 100] [--repeats 7]
    python benchmarks/bench_simulator.py --joints 4,8,16 [--sizes 2000]    (growth with n)
    python benchmarks/bench_simulator.py --device cuda                     (the GPU arm)

``--joints``: instead of the Panda table, a generated serial chain of n revolute joints
(alternating z/y axes, 0.6 m long in all, ``chain_urdf``) for each n, the kernel's cost per
trajectory-step at each B, and the ratio of each n's cost to the previous n's (the issue's
target: 8 -> 16 joints at most 2.5x).

``--device cuda``: the torch backend (`controller.reference_simulate`) on the GPU at each B,
with its ratio against the numba kernel on the CPU measured in the same run. Without a CUDA
device the arm is skipped with a message (the GPU path is never needed on CPU).

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
import math
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


def chain_urdf(n: int) -> str:
    """A serial chain of ``n`` revolute joints (axes alternating z, y; links 0.6/n m) ending at "tool"."""
    links = "".join(f'<link name="l{i}"/>' for i in range(n + 1)) + '<link name="tool"/>'
    step = 0.6 / n
    joints = "".join(
        f'<joint name="j{i}" type="revolute"><parent link="l{i}"/><child link="l{i + 1}"/>'
        f'<origin xyz="0 0 {step if i else 0.1:.4f}" rpy="0 0 0"/><axis xyz="0 {i % 2} {1 - i % 2}"/>'
        f'<limit lower="-2.5" upper="2.5" effort="1" velocity="1"/></joint>' for i in range(n))
    tool = (f'<joint name="tip" type="fixed"><parent link="l{n}"/><child link="tool"/>'
            f'<origin xyz="0 0 {step:.4f}" rpy="0 0 0"/></joint>')
    return f'<?xml version="1.0"?><robot name="chain{n}">{links}{joints}{tool}</robot>'


def growth(joints: list[int], sizes: list[int], T: int, repeats: int) -> None:
    """Kernel cost per trajectory-step for chains of each joint count (float32, every step run).

    The joint counts are timed in interleaved rounds (each round times every n once), so a change
    of the machine's load during the run hits every n alike; the minimum over the rounds is
    kept, for wall time and for the process's CPU time (all threads), printed side by side.
    """
    print(f"generated chains, float32, CPU, T={T}, every trajectory runs all T steps; numba threads "
          f"{numba.get_num_threads()}; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    runs = {}
    for n in joints:
        sim = from_urdf_chain(n, T)
        for B in sizes:
            theta, goals = problem(sim, B, seed=B)
            sim.simulate(theta, goals)  # compile / load
            runs[n, B] = (lambda s=sim, th=theta, g=goals: s.simulate(th, g))
    wall = {k: float("inf") for k in runs}
    cpu = dict(wall)
    for _ in range(repeats):
        for k, fn in runs.items():
            t, c = time.perf_counter(), time.process_time()
            fn()
            wall[k] = min(wall[k], time.perf_counter() - t)
            cpu[k] = min(cpu[k], time.process_time() - c)
    head = " ".join(f"{'B=' + str(B) + ' us/step':>16} {'x prev n':>9} {'CPU us/step':>12} {'x prev n':>9}"
                    for B in sizes)
    print(f"{'n':>4} {head}")
    for i, n in enumerate(joints):
        cells = []
        for B in sizes:
            for tab in (wall, cpu):
                v = tab[n, B] / (B * T)
                prev = tab[joints[i - 1], B] / (B * T) if i else None
                cells.append(f"{v * 1e6:>{16 if tab is wall else 12}.4f} "
                             + (f"{v / prev:>8.2f}x" if prev else f"{'-':>9}"))
        print(f"{n:>4} " + " ".join(cells))
    if len(joints) >= 2:
        a, b = joints[-2], joints[-1]
        for B in sizes:
            r, rc = wall[b, B] / wall[a, B], cpu[b, B] / cpu[a, B]
            print(f"{a} -> {b} joints, B={B}: {r:.2f}x per step wall, {rc:.2f}x CPU (joint ratio {b / a:.1f}; "
                  f"growth exponent {math.log(r) / math.log(b / a):.2f} wall; target: at most 2.5x)")


def from_urdf_chain(n: int, T: int):
    from camo_sbi.simulators import from_urdf

    return from_urdf(chain_urdf(n), "tool", start=[0.3 * (-1) ** i for i in range(n)],
                     controller=ControllerConfig(max_steps=T, tol=1e-9), backend="numba")


def gpu_arm(sim, sizes: list[int], repeats: int) -> None:
    """The torch backend on CUDA against the numba kernel on the CPU, or a message without a GPU."""
    if not torch.cuda.is_available():
        print("--device cuda: no CUDA device here (torch.cuda.is_available() is False); the GPU arm is "
              "skipped. The numba kernel above is the CPU path and needs no GPU.")
        return
    ref = sim.with_config(backend="torch")
    name = torch.cuda.get_device_name(0)
    print(f"\nGPU arm: torch backend on {name} vs the numba kernel on the CPU (same problems)")
    for B in sizes:
        theta, goals = problem(sim, B, seed=B)
        sim.simulate(theta, goals)
        t_k = best_of(lambda th=theta, g=goals: sim.simulate(th, g), repeats)
        th, g = theta.cuda(), goals.cuda()

        def on_gpu(th=th, g=g):
            ref.simulate(th, g)
            torch.cuda.synchronize()

        on_gpu()  # warm-up (CUDA context, kernels)
        t_g = best_of(on_gpu, repeats)
        print(f"  B={B:>6}: numba CPU {t_k * 1e3:8.1f} ms, torch CUDA {t_g * 1e3:8.1f} ms, "
              f"ratio numba / CUDA {t_k / t_g:.2f}x")


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
    ap.add_argument("--joints", default=None, help="comma-separated joint counts: the growth table instead")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                    help="cuda: also time the torch backend on the GPU (skipped with a message without one)")
    args = ap.parse_args(argv)
    T = args.steps
    if args.joints:
        joints = [int(v) for v in args.joints.split(",") if v.strip()]
        if not joints or any(n < 1 for n in joints):
            ap.error("--joints: give positive joint counts, e.g. 4,8,16")
        growth(joints, args.sizes, T, args.repeats)
        if args.device == "cuda":
            gpu_arm(from_urdf_chain(joints[-1], T), args.sizes, args.repeats)
        return

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
    if args.device == "cuda":
        gpu_arm(sim, args.sizes, args.repeats)
    shutil.rmtree(cache, ignore_errors=True)


if __name__ == "__main__":
    main()
