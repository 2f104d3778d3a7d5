"""`camo-sbi demo`: simulate reaches under different joint limits and plot them.

``--out`` ending in ``.png`` is the figure's file; any other path is a directory that
receives ``demo.png``. ``--figure-format png,pdf,svg`` writes the same figure in each format
(``demo.pdf`` next to ``demo.png``, ...). Joint angles are drawn in degrees.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from camo_sbi.experiments.models import model_from_args
from camo_sbi.priors import BoxPrior

__all__ = ["REACHED_COLOR", "NOT_REACHED_COLOR", "LIMIT_COLOR", "figure_path", "main", "make_figure"]

REACHED_COLOR = "#0072B2"      # blue: the reach ended within the tolerance of the goal
NOT_REACHED_COLOR = "#E69F00"  # orange: it did not (a limit stopped it)
LIMIT_COLOR = "0.55"           # grey band and dashed edges: a sample's joint limits
_MAX_PATHS = 32
_JOINT_PANELS = 4


def figure_path(out) -> Path:
    """The PNG a demo writes: ``out`` itself when it ends in .png, else ``out/demo.png``."""
    out = Path(out)
    if out.suffix.lower() == ".png":
        return out
    if out.suffix:
        raise ValueError(f"--out: expected a directory or a .png file, got {out}")
    return out / "demo.png"


def _busiest_joint(traj, theta, n: int) -> int:
    """The joint whose limits stop the most steps (|q - limit| < 1e-6) in the first n samples."""
    q = traj.q[:n].to(torch.float64)
    lo, hi = theta[:n, 0::2].unsqueeze(1), theta[:n, 1::2].unsqueeze(1)
    steps = torch.arange(q.shape[1]).unsqueeze(0) < traj.length[:n].unsqueeze(1)
    at = ((q - lo).abs() < 1e-6) | ((q - hi).abs() < 1e-6)
    return int((at & steps.unsqueeze(-1)).sum(dim=(0, 1)).argmax())


def _pick_samples(reached: np.ndarray, k: int) -> list[int]:
    """Up to k sample indices, not-reached ones and reached ones alternating when both exist."""
    yes = [int(i) for i in np.flatnonzero(reached)]
    no = [int(i) for i in np.flatnonzero(~reached)]
    out = []
    while len(out) < k and (yes or no):
        for pool in (no, yes):
            if pool and len(out) < k:
                out.append(pool.pop(0))
    return sorted(out)


def make_figure(sim, model: str, theta: torch.Tensor, goal: torch.Tensor, traj):
    """Left: end-effector paths in 3-D (reached / not reached), the goal and the start.
    Right: one joint's trajectory for four samples inside their limits (grey band)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    from camo_sbi.diagnostics.style import DOUBLE_COLUMN, new_figure, paper_style

    with paper_style():
        return _make_figure(sim, model, theta, goal, traj, Line2D, Patch, new_figure, DOUBLE_COLUMN)


def _make_figure(sim, model, theta, goal, traj, Line2D, Patch, new_figure, width):
    batch = theta.shape[0]
    reached = traj.reached.numpy().astype(bool)
    fig, _ = new_figure(1, 1, figsize=(width, 4.4))
    fig.clear()
    grid = fig.add_gridspec(2, 3, width_ratios=(1.7, 1, 1), wspace=0.12)
    ax = fig.add_subplot(grid[:, 0], projection="3d")
    shown = min(batch, _MAX_PATHS)
    for b in range(shown):
        e = traj.trimmed(b, "cartesian").numpy()
        ax.plot(e[:, 0], e[:, 1], e[:, 2], lw=0.9, alpha=0.9,
                color=REACHED_COLOR if reached[b] else NOT_REACHED_COLOR)
    g = goal.numpy()
    s = traj.ee[0, 0].numpy()
    ax.scatter([g[0]], [g[1]], [g[2]], color="k", marker="*", s=140, depthshade=False)
    ax.scatter([s[0]], [s[1]], [s[2]], color="k", marker="o", s=30, depthshade=False)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    n_yes = int(reached[:shown].sum())
    ax.set_title(f"{model}: {shown} limit vectors, one goal\n"
                 f"({n_yes} reached, {shown - n_yes} stopped short)")
    ax.legend(handles=[Line2D([], [], color=REACHED_COLOR, label="reached the goal"),
                       Line2D([], [], color=NOT_REACHED_COLOR, label="not reached"),
                       Line2D([], [], color="k", marker="*", ls="none", ms=10, label="goal"),
                       Line2D([], [], color="k", marker="o", ls="none", ms=5, label="start")],
              loc="upper left", frameon=False)

    j = _busiest_joint(traj, theta, min(batch, _MAX_PATHS))
    picks = _pick_samples(reached[:shown], _JOINT_PANELS)
    lo_all, hi_all = (float(np.degrees(v)) for v in sim.bounds[j])
    axes = [fig.add_subplot(grid[r, 1 + c]) for r in range(2) for c in range(2)]
    for ax2, b in zip(axes, picks, strict=False):
        q = np.degrees(traj.trimmed(b, "joint")[:, j].numpy())
        lo, hi = float(np.degrees(theta[b, 2 * j])), float(np.degrees(theta[b, 2 * j + 1]))
        ax2.axhspan(lo, hi, color=LIMIT_COLOR, alpha=0.25, lw=0)
        for v in (lo, hi):
            ax2.axhline(v, color=LIMIT_COLOR, ls="--", lw=1)
        ax2.plot(q, lw=1.6, color=REACHED_COLOR if reached[b] else NOT_REACHED_COLOR)
        ax2.set_ylim(lo_all - 0.05 * (hi_all - lo_all), hi_all + 0.05 * (hi_all - lo_all))
        ax2.set_title(f"sample {b} ({'reached' if reached[b] else 'not reached'})")
        ax2.grid(alpha=0.3)
    for ax2 in axes[len(picks):]:
        ax2.set_visible(False)
    for ax2 in axes[2:]:
        ax2.set_xlabel("step")
    for ax2 in axes[0::2]:
        ax2.set_ylabel(f"{sim.joint_names[j]} [deg]")
    fig.legend(handles=[Patch(facecolor=LIMIT_COLOR, alpha=0.4, edgecolor=LIMIT_COLOR, ls="--",
                              label="the sample's limits of this joint"),
                        Line2D([], [], color=REACHED_COLOR, label="reached"),
                        Line2D([], [], color=NOT_REACHED_COLOR, label="not reached")],
               loc="outside lower right", ncols=3, frameon=False,
               title=f"right: joint {sim.joint_names[j]} (the one its limits stop most often);\n"
                     f"y range = the model's full range")
    return fig


def main(args) -> int:
    if args.batch < 1:
        raise ValueError("--batch: must be >= 1")
    path = figure_path(args.out)
    from camo_sbi.diagnostics.style import save_figures
    from camo_sbi.experiments.figure_options import figure_formats

    formats = figure_formats(args)
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
    paths = save_figures(make_figure(sim, model.name, theta.to(torch.float64), goal, traj), path, formats)
    print(f"{model.name}: {sim.n_joints} joints {sim.joint_names}")
    print(f"simulated {args.batch} x {traj.q.shape[1]} steps in {dt * 1e3:.1f} ms; "
          f"reached {int(traj.reached.sum())}/{args.batch}; mean length {traj.length.float().mean():.1f}")
    print(f"figure: {', '.join(str(p) for p in paths)}")
    return 0
