"""`camo-sbi demo`: simulate reaches under different joint limits and plot them."""

from __future__ import annotations

import time
from pathlib import Path

import matplotlib.pyplot as plt
import torch

from camo_sbi.experiments.models import model_from_args
from camo_sbi.experiments.plots import save_figure
from camo_sbi.priors import BoxPrior

__all__ = ["main"]


def main(args) -> int:
    if args.batch < 1:
        raise ValueError("--batch: must be >= 1")
    from camo_sbi.simulators import sample_goals

    model = model_from_args(args)
    sim = model.build()
    prior = BoxPrior(sim.bounds, sim.start)
    theta = prior.sample(args.batch, args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    goal = sample_goals(sim, sim.bounds, 1, gen)[0]
    sim.simulate(theta[:2].to(torch.float32), goal.to(torch.float32))  # compile / warm up
    t0 = time.perf_counter()
    traj = sim.simulate(theta.to(torch.float32), goal.to(torch.float32))
    dt = time.perf_counter() - t0
    out = Path(args.out)
    fig = plt.figure(figsize=(11, 4.5))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    for b in range(min(args.batch, 32)):
        e = traj.trimmed(b, "cartesian").numpy()
        ax.plot(e[:, 0], e[:, 1], e[:, 2], lw=0.8, color="C0" if bool(traj.reached[b]) else "C3")
    g = goal.numpy()
    ax.scatter([g[0]], [g[1]], [g[2]], color="k", marker="*", s=80)
    ax.set_title(f"{model.name}: {args.batch} limit vectors, one goal\n(blue reached, red not)")
    ax2 = fig.add_subplot(1, 2, 2)
    j = 1
    for b in range(min(args.batch, 8)):
        q = traj.trimmed(b, "joint")[:, j].numpy()
        line, = ax2.plot(q, lw=1)
        ax2.axhline(float(theta[b, 2 * j]), color=line.get_color(), ls=":", lw=0.8)
        ax2.axhline(float(theta[b, 2 * j + 1]), color=line.get_color(), ls=":", lw=0.8)
    ax2.set_xlabel("step")
    ax2.set_ylabel(f"{sim.joint_names[j]} [rad] (dotted: its limits)")
    save_figure(fig, out / "demo.png")
    print(f"{model.name}: {sim.n_joints} joints {sim.joint_names}")
    print(f"simulated {args.batch} x {traj.q.shape[1]} steps in {dt * 1e3:.1f} ms; "
          f"reached {int(traj.reached.sum())}/{args.batch}; mean length {traj.length.float().mean():.1f}")
    print(f"figure: {out / 'demo.png'}")
    return 0
