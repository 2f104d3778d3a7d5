"""`camo-sbi describe`: the body model in words and in a figure (joints, axes, signs, frames).

    camo-sbi describe --model human [--height 1.6 --sex female] --out runs/describe
    camo-sbi describe --urdf tests/data/arm7.urdf --ee tool --out runs/describe

Prints one row per actuated joint, base to tip: its name, type, axis in its own joint frame
and in the base frame at the zero posture, the joint centre's position in the base frame at
the zero posture, what a positive and a negative angle mean, the range and the start posture
(degrees for revolute joints, metres for prismatic ones); then the base frame, the end
effector and where it lies at the zero posture and at the start posture. Writes
``OUT/<model>_joints.csv`` (the same table) and ``OUT/<model>_model.png`` (the chain at its
zero posture in 3-D with each joint's axis drawn as an arrow, and the start posture dashed).

Positive directions: the registered human model has them in words
(`camo_sbi.simulators.human.JOINT_SIGNS`); any other model gets the right-hand rule about
the base-frame axis ("+ = right-hand rotation about +y (base frame, zero posture)").
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from camo_sbi.experiments.models import add_model_arguments, model_from_args

if TYPE_CHECKING:
    import numpy as np

__all__ = ["add_arguments", "describe_frames", "joint_table", "main", "plot_model"]

_AXIS_NAMES = {(1, 0, 0): "+x", (-1, 0, 0): "-x", (0, 1, 0): "+y", (0, -1, 0): "-y", (0, 0, 1): "+z",
               (0, 0, -1): "-z"}
_BASE_WORDS = {
    "human": ("base link 'base' on the FLOOR under the mid-point of the hip joint centres; x forward "
              "(anterior), y to the person's left, z up (ROS REP-103); the pelvis is fixed, the trunk "
              "moves only through torso_flexion and torso_rotation"),
}
_MODEL_WORDS = {
    "human": ("the RIGHT arm (7 joints) on a 2-joint trunk; zero posture = anatomical standing posture, "
              "arm hanging at the side, palm facing the thigh, thumb forward, elbow straight; angles are "
              "the model's joint angles (a Y-X-Z shoulder sequence of flexion, abduction, rotation), not "
              "ISB clinical angles"),
}


def _axis_text(v: np.ndarray) -> str:
    import numpy as np

    r = np.round(v, 6)
    key = tuple(int(x) for x in r) if np.all(np.isin(r, (-1.0, 0.0, 1.0))) else None
    if key in _AXIS_NAMES:
        return _AXIS_NAMES[key]
    return "(" + ", ".join(f"{x:+.3f}" for x in v) + ")"


def _zero_frames(spec) -> tuple[np.ndarray, np.ndarray]:
    """(n, 4, 4) joint frames and (4, 4) end-effector pose in the base frame at q = 0."""
    import numpy as np

    return spec.joint_frames(np.zeros(spec.n_joints))


def _chain_points(spec, q: np.ndarray) -> np.ndarray:
    """(n + 1, 3) joint centres and the end effector in the base frame at posture ``q``."""
    import numpy as np

    frames, tip = spec.joint_frames(np.asarray(q, dtype=np.float64))
    return np.vstack([frames[:, :3, 3], tip[None, :3, 3]])


def _signs(kind: str) -> dict:
    if kind == "human":
        from camo_sbi.simulators.human import JOINT_SIGNS

        return dict(JOINT_SIGNS)
    return {}


def joint_table(sim, kind: str = "urdf"):
    """One row per actuated joint, base to tip (a pandas DataFrame; see the module docstring)."""
    import numpy as np
    import pandas as pd

    spec = sim.spec
    frames, _ = _zero_frames(spec)
    bounds = sim.bounds.double().numpy()
    start = sim.start.double().numpy()
    words = _signs(kind)
    rows = []
    for k, name in enumerate(spec.joint_names):
        rev = spec.joint_types[k] == "revolute"
        world = frames[k][:3, :3] @ spec.axes[k]
        conv = (lambda v: float(np.degrees(v))) if rev else float
        unit = "deg" if rev else "m"
        if name in words:
            pos, neg = words[name]
        else:
            move = "rotation" if rev else "translation"
            pos = f"right-hand {move} about {_axis_text(world)} (base frame, zero posture)"
            neg = f"the opposite {move}"
        rows.append({"index": k, "joint": name, "type": spec.joint_types[k],
                     "axis_joint_frame": _axis_text(spec.axes[k]), "axis_base_frame": _axis_text(world),
                     "centre_x_m": round(float(frames[k][0, 3]), 4), "centre_y_m": round(float(frames[k][1, 3]), 4),
                     "centre_z_m": round(float(frames[k][2, 3]), 4), "positive": pos, "negative": neg,
                     "lower": round(conv(bounds[k, 0]), 3), "upper": round(conv(bounds[k, 1]), 3),
                     "start": round(conv(start[k]), 3), "unit": unit})
    return pd.DataFrame(rows)


def describe_frames(sim, kind: str = "urdf") -> list[str]:
    """Lines naming the base frame, the model, the end effector and where it lies."""

    spec = sim.spec
    _, tip0 = _zero_frames(spec)
    tip_start = _chain_points(spec, sim.start.double().numpy())[-1]
    lines = [f"base frame: {_BASE_WORDS.get(kind, f'the URDF link {spec.base_link!r}')}"]
    if kind in _MODEL_WORDS:
        lines.append(f"model: {_MODEL_WORDS[kind]}")
    lines.append(f"joint order (the columns of a recording, --start, --limits): {', '.join(spec.joint_names)}")
    where = "half a hand length distal to the wrist joint centre, near the third metacarpal head" \
        if kind == "human" else "the --ee link"
    lines.append(f"end effector: {spec.end_effector!r} ({where}); at the zero posture "
                 f"({', '.join(f'{v:.3f}' for v in tip0[:3, 3])}) m, at the start posture "
                 f"({', '.join(f'{v:.3f}' for v in tip_start)}) m, base frame")
    return lines


def plot_model(sim, kind: str = "urdf", title: str = ""):
    """The chain at its zero posture (solid) and start posture (dashed) in 3-D, each joint's axis
    drawn as an arrow at its centre (zero posture), the base frame's axes, the end effector."""
    import numpy as np

    from camo_sbi.diagnostics.style import DOUBLE_COLUMN, new_figure, paper_style

    spec = sim.spec
    frames, _ = _zero_frames(spec)
    zero = _chain_points(spec, np.zeros(spec.n_joints))
    moved = _chain_points(spec, sim.start.double().numpy())
    with paper_style():
        fig, _ = new_figure(1, 1, figsize=(DOUBLE_COLUMN, 5.2))
        fig.clear()
        fig.set_layout_engine("none")  # the 3-D axes and the joint list are placed by hand
        ax = fig.add_axes((0.32, 0.02, 0.66, 0.9), projection="3d")
        ax.plot(*zero.T, color="k", lw=2, marker="o", ms=3, label="zero posture")
        ax.plot(*moved.T, color="0.5", lw=1.2, ls="--", label="start posture")
        pts = np.vstack([zero, moved])
        size = max(float(np.ptp(pts, axis=0).max()), 0.2)
        arrow = 0.12 * size
        colors = [f"C{k % 10}" for k in range(spec.n_joints)]
        seen: dict = {}  # joints sharing a centre (the shoulder's three): numbers side by side
        for k in range(spec.n_joints):
            c = frames[k][:3, 3]
            a = frames[k][:3, :3] @ spec.axes[k]
            ax.quiver(*c, *(arrow * a), color=colors[k], lw=1.5, arrow_length_ratio=0.25)
            key = tuple(np.round(c, 3))
            n_here = seen.get(key, 0)
            seen[key] = n_here + 1
            ax.text(*(c + arrow * a * 1.2 + np.array([0, 0, 0.03 * size * n_here])), str(k + 1), color=colors[k],
                    fontsize=8, fontweight="bold")
        ax.scatter(*zero[-1], color="C3", marker="*", s=60, label=f"end effector {spec.end_effector}")
        legend = "\n".join(f"{k + 1} {name}: axis {_axis_text(frames[k][:3, :3] @ spec.axes[k])}"
                           for k, name in enumerate(spec.joint_names))
        fig.text(0.01, 0.5, legend, fontsize=7, va="center", ha="left", family="monospace")
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        mid, half = 0.5 * (lo + hi), 0.6 * float((hi - lo).max()) + arrow
        for setter, m in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), mid, strict=True):
            setter(m - half, m + half)
        corner = mid - half
        for v, lab in zip(np.eye(3), ("x", "y", "z"), strict=True):  # the base frame's directions
            ax.quiver(*corner, *(0.25 * half * v), color="0.3", lw=1, arrow_length_ratio=0.2)
            ax.text(*(corner + 0.3 * half * v), lab, color="0.3", fontsize=8)
        ax.set_box_aspect((1, 1, 1))
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_zlabel("z [m]")
        ax.view_init(elev=15, azim=-60)
        ax.legend(loc="upper left", fontsize=7, frameon=False)
        ax.set_title((title or "joint axes at the zero posture") + "\narrows: + rotation by the right-hand "
                     "rule; grey triad: the base frame's x, y, z", fontsize=8)
    return fig


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_model_arguments(p, limits=False)
    p.add_argument("--out", type=Path, default=Path("runs/describe"),
                   help="directory receiving <model>_joints.csv and <model>_model.png")


def main(args) -> int:
    from camo_sbi._io import atomic_write_text
    from camo_sbi.diagnostics.style import save_figure

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a directory")
    model = model_from_args(args)
    sim = model.build()
    kind = model.kind
    table = joint_table(sim, kind)
    for line in describe_frames(sim, kind):
        print(line)
    import pandas as pd

    shown = table[["index", "joint", "axis_base_frame", "positive", "negative", "lower", "upper", "start", "unit"]]
    with pd.option_context("display.max_colwidth", 60, "display.width", 200):
        print(shown.to_string(index=False))
    csv = atomic_write_text(out / f"{model.name}_joints.csv", table.to_csv(index=False))
    png = save_figure(plot_model(sim, kind, title=f"{model.name}: joint axes at the zero posture"),
                      out / f"{model.name}_model.png")
    print(f"table: {csv}  figure: {png}")
    return 0
