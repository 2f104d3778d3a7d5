"""The recording schema (`camo_sbi.io.recordings` describes it): its columns, the `Table` a file is
read into (columns as float arrays, and where each row came from), the checks of its layout
(`check_layout`), its reaches (`reach_rows`) and its joint values against the model's range
(`joint_values`: the noise allowance, clipping, "use --degrees"); and writing it
(`save_recordings`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from camo_sbi._io import atomic_write_bytes, atomic_write_text
from camo_sbi.task import NoiseModel, Observation

__all__ = ["BOUND_SLACK", "EE_COLUMNS", "GOAL_COLUMNS", "K_SIGMA", "Table", "check_layout", "joint_types",
           "joint_values", "reach_rows", "save_recordings"]

REACH, STEP, TIME = "reach", "step", "time"
GOAL_COLUMNS = ("goal_x", "goal_y", "goal_z")
EE_COLUMNS = ("ee_x", "ee_y", "ee_z")
K_SIGMA = 4.0
"""Values may exceed the model's range by K_SIGMA noise standard deviations (4: one in ~16 000
noise-free samples at a bound is wrongly refused)."""
BOUND_SLACK = 1e-6
"""Absolute slack (rad / m) beyond the model's range for rounding in files written by others."""
GOAL_TOL = 1e-9


def joint_types(simulator) -> tuple[str, ...]:
    spec = getattr(simulator, "spec", None)
    types = getattr(spec, "joint_types", None)
    return tuple(types) if types is not None else ("revolute",) * simulator.n_joints



@dataclass
class Table:
    """Columns of a recording file as float arrays, and where each row came from."""

    path: Path
    columns: dict[str, np.ndarray]
    rows: np.ndarray  # CSV line numbers, or NPZ array indices
    row_word: str  # "line" or "row"
    sources: dict | None = None  # column -> where its values come from (a BVH channel and its map entry)

    def where(self, column: str, i: int) -> str:
        return f"{self.path}: column {column!r}, {self.row_word} {int(self.rows[i])}"



def check_layout(table: Table, joint_names: list[str], goal: str = "columns") -> tuple[bool, bool]:
    """Check the columns against the schema: (has joint columns, has ee columns)."""
    cols = table.columns
    path = table.path
    need = f"a recording needs {REACH}, {STEP} (or {TIME} in seconds), {', '.join(GOAL_COLUMNS)} (or --goal " \
           f"final for free reaching), then the joint columns and/or {', '.join(EE_COLUMNS)}"
    if REACH not in cols:
        raise ValueError(f"{path}: column {REACH!r} is missing ({need})")
    if STEP in cols and TIME in cols:
        raise ValueError(f"{path}: column {TIME!r}: give {STEP} or {TIME}, not both")
    if STEP not in cols and TIME not in cols:
        raise ValueError(f"{path}: column {STEP!r} is missing ({need})")
    has_goal = any(c in cols for c in GOAL_COLUMNS)
    if goal == "final" and has_goal:
        raise ValueError(f"--goal: final takes each reach's last position as its goal; {path} has goal columns "
                         f"(drop --goal final to use them)")
    if goal != "final":
        for c in GOAL_COLUMNS:
            if c not in cols:
                raise ValueError(f"{path}: column {c!r} is missing ({need})")
    known = {REACH, STEP, TIME, *GOAL_COLUMNS, *EE_COLUMNS, *joint_names}
    for c in cols:
        if c not in known:
            raise ValueError(f"{path}: column {c!r} is unknown: not a joint of the model (its joints: "
                             f"{', '.join(joint_names)}) nor one of {REACH}, {STEP}, {TIME}, goal_*, ee_*")
    has_q = any(j in cols for j in joint_names)
    has_ee = any(c in cols for c in EE_COLUMNS)
    for group, present in ((joint_names, has_q), (EE_COLUMNS, has_ee)):
        missing = [c for c in group if c not in cols]
        if present and missing:
            raise ValueError(f"{path}: column {missing[0]!r} is missing (give every column of "
                             f"{', '.join(group)} or none)")
    if not (has_q or has_ee):
        raise ValueError(f"{path}: column {joint_names[0]!r} is missing: a recording needs the joint columns "
                         f"({', '.join(joint_names)}) and/or {', '.join(EE_COLUMNS)}")
    for c, a in cols.items():
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            raise ValueError(f"{table.where(c, bad[0])}: NaN or inf ({a[bad[0]]!r})")
    for c in (REACH, STEP):
        if c not in cols:
            continue
        a = cols[c]
        bad = np.flatnonzero(a != np.round(a))
        if bad.size:
            raise ValueError(f"{table.where(c, bad[0])}: expected an integer, got {a[bad[0]]!r}")
    return has_q, has_ee


def reach_rows(table: Table, goal: str = "columns") -> list[np.ndarray]:
    """Row indices of each reach (consecutive rows, steps or times strictly increasing, >= 2 samples)."""
    order = STEP if STEP in table.columns else TIME
    reach, step = table.columns[REACH], table.columns[order]
    starts = np.flatnonzero(np.r_[True, reach[1:] != reach[:-1]])
    bounds = np.r_[starts, reach.shape[0]]
    seen: dict[float, int] = {}
    out = []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        rid = reach[a]
        if rid in seen:
            raise ValueError(f"{table.where(REACH, a)}: reach {int(rid)} continues here after other reaches "
                             f"(its rows must be consecutive; it started at {table.row_word} {seen[rid]})")
        seen[rid] = int(table.rows[a])
        idx = np.arange(a, b)
        if idx.size < 2:
            raise ValueError(f"{table.where(order, a)}: reach {int(rid)} has a single sample; a reach needs its "
                             f"start posture and at least one more sample")
        d = np.diff(step[idx])
        bad = np.flatnonzero(d <= 0)
        if bad.size:
            i = idx[bad[0] + 1]
            raise ValueError(f"{table.where(order, i)}: {order} {step[i]:g} does not increase (previous {order} "
                             f"{step[i - 1]:g}) within reach {int(rid)}")
        for c in (GOAL_COLUMNS if goal != "final" else ()):
            g = table.columns[c][idx]
            bad = np.flatnonzero(np.abs(g - g[0]) > GOAL_TOL)
            if bad.size:
                i = idx[bad[0]]
                raise ValueError(f"{table.where(c, i)}: the goal changes within reach {int(rid)} ({g[bad[0]]!r} "
                                 f"here, {g[0]!r} on its first row); one goal per reach")
        out.append(idx)
    return out


def joint_values(table: Table, simulator, degrees: bool, noise: NoiseModel,
                  clip_warnings: list | None = None, clipped: list | None = None, why: str = "clip") -> np.ndarray:
    """(rows, n) joint values in radians, checked against the model's range and clipped within noise.
    With ``clip_warnings`` (a list; ``out_of_range`` "clip", or "auto" on the ISB landmarks' angles:
    ``why`` names it) values beyond the range are clipped onto it too, one warning per joint (how
    many samples, by how much at most, which frames) appended to the list, and one row per bound
    ({"joint", "bound", "samples", "beyond"}: the most beyond, degrees or metres) appended to ``clipped``."""
    names = list(simulator.joint_names)
    types = joint_types(simulator)
    b = simulator.bounds.to(torch.float64).numpy()
    q = np.stack([table.columns[j] for j in names], axis=1)
    rev = np.array([t == "revolute" for t in types])
    if degrees:
        q[:, rev] = np.radians(q[:, rev])
    tol = K_SIGMA * noise.sigma("joint") + BOUND_SLACK
    below, above = q < b[:, 0] - tol, q > b[:, 1] + tol
    outside = below | above
    if outside.any() and clip_warnings is not None:
        for j in np.flatnonzero(outside.any(axis=0)):
            unit, f = ("deg", np.degrees) if rev[j] else ("m", float)
            sides = []
            for bound, mask, excess in (("lower", below[:, j], b[j, 0] - q[:, j]), ("upper", above[:, j], q[:, j] - b[j, 1])):
                if not mask.any():
                    continue
                rows = table.rows[np.flatnonzero(mask)]
                sides.append(f"{int(mask.sum())} {'below' if bound == 'lower' else 'above'} its {bound} bound "
                             f"{f(b[j, 0 if bound == 'lower' else 1]):.1f} {unit} (at most {f(excess.max()):.1f} "
                             f"{unit} beyond; {table.row_word}s {int(rows.min())}-{int(rows.max())})")
                if clipped is not None:
                    clipped.append({"joint": names[j], "bound": bound, "samples": int(mask.sum()),
                                    "beyond": float(f(excess.max()))})
            clip_warnings.append(
                f"{table.path}: {names[j]}: OUTSIDE THE MODEL'S RANGE [{f(b[j, 0]):.1f}, {f(b[j, 1]):.1f}] {unit} in "
                f"{int(outside[:, j].sum())} of {q.shape[0]} samples: {'; '.join(sides)}; clipped onto it "
                f"(--out-of-range {why}): that bound's estimate is the model's range, not the person's (marked ! in "
                f"the limits table, limits.csv: clipped_samples); if no person could go there, check "
                f"{table.sources[names[j]]['entry'].split(';')[0] if table.sources and names[j] in table.sources else 'the file'}"
                f"; --out-of-range error stops instead")
        return np.clip(q, b[:, 0], b[:, 1])
    if outside.any():
        i, j = (int(v) for v in np.argwhere(outside)[0])
        value = table.columns[names[j]][i]
        if table.sources and names[j] in table.sources:  # computed from a source, in radians already
            src = table.sources[names[j]]
            given = f"{src['what']} = {src['raw'](value):.2f} deg gives " if "raw" in src else f"{src['what']} give "
            raise ValueError(
                f"{table.path}: frame {int(table.rows[i])}: {given}"
                f"{names[j]} = {np.degrees(value):.2f} deg, outside the model's range [{np.degrees(b[j, 0]):.1f}, "
                f"{np.degrees(b[j, 1]):.1f}] deg by more than {K_SIGMA:g} noise sigma "
                f"({np.degrees(tol):.2g} deg): check {src['entry']}")
        msg = (f"{table.where(names[j], i)}: {value:.6g} lies outside the model's range "
               f"[{b[j, 0]:.6g}, {b[j, 1]:.6g}] {'rad' if types[j] == 'revolute' else 'm'} by more than "
               f"{K_SIGMA:g} noise sigma ({tol:.3g})")
        if not degrees and rev[j]:
            as_rad = np.radians(q[:, rev])
            fits = ((as_rad >= b[rev, 0] - tol) & (as_rad <= b[rev, 1] + tol)).all()
            if fits:
                raise ValueError(msg + "; the joint values look like degrees: use --degrees (degrees=True)")
        raise ValueError(msg)
    return np.clip(q, b[:, 0], b[:, 1])


# ----------------------------------------------------------------------------- writing


def _fmt(v: float) -> str:
    return repr(float(v))


def save_recordings(path, observations, simulator) -> Path:
    """Write ``observations`` in the recording format (CSV, or NPZ when ``path`` ends in .npz), atomically.

    Joint columns are written when every reach has a joint trajectory, the end-effector
    columns when every reach has one. Reaches are numbered 0, 1, ... and steps 0, 1, ...
    Values are written with full float64 precision (a CSV round trip is exact).
    """
    obs = tuple(observations)
    if not obs:
        raise ValueError("observations: nothing to write")
    for i, o in enumerate(obs):
        if not isinstance(o, Observation):
            raise TypeError(f"observations: item {i} is a {type(o).__name__}, not an Observation")
    names = list(simulator.joint_names)
    has_q = all(o.q is not None for o in obs)
    has_ee = all(o.ee is not None for o in obs)
    if not (has_q or has_ee):
        raise ValueError("observations: the reaches share no space (some have only q, others only ee)")
    header = [REACH, STEP, *GOAL_COLUMNS] + (names if has_q else []) + (list(EE_COLUMNS) if has_ee else [])
    blocks = []
    for r, o in enumerate(obs):
        L = o.length
        parts = [np.full((L, 1), r, float), np.arange(L, dtype=float)[:, None],
                 np.broadcast_to(o.goal.numpy(), (L, 3))]
        if has_q:
            parts.append(o.q.numpy())
        if has_ee:
            parts.append(o.ee.numpy())
        blocks.append(np.concatenate(parts, axis=1))
    data = np.concatenate(blocks)
    path = Path(path)
    if path.suffix.lower() == ".npz":
        import io

        buf = io.BytesIO()
        arrays = {c: (data[:, i].astype(np.int64) if c in (REACH, STEP) else data[:, i])
                  for i, c in enumerate(header)}
        np.savez(buf, **arrays)
        return atomic_write_bytes(path, buf.getvalue())
    lines = [",".join(header)]
    for row in data:
        lines.append(",".join([str(int(row[0])), str(int(row[1]))] + [_fmt(v) for v in row[2:]]))
    return atomic_write_text(path, "\n".join(lines) + "\n")
