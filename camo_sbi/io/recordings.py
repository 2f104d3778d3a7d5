"""The recording format: observed reaches on disk, and their resampling to the controller's step.

One schema, one row per recorded sample (CSV with a header line, or NPZ with the same
names as 1-D arrays of equal length)::

    reach              int id of the reach; a reach's rows are consecutive in the file
    step               int, strictly increasing within a reach; the first row of a reach is
                       its start posture
    goal_x, goal_y, goal_z   the reach's Cartesian goal in metres (the model's base frame),
                       the same on every row of the reach
    <joint name> ...   one column per actuated joint of the model, named exactly as the
                       model's joints (radians; prismatic joints metres)
    ee_x, ee_y, ee_z   end-effector position in metres (base frame)

A file has the joint columns, the end-effector columns, or both (all of a group or none).
Any other column is an error. With both, the model's forward kinematics of each row's joint
values must lie within `EE_FK_TOL_M` (plus the noise allowance) of its ee_* values (a file
recorded at another link than the model's end effector is refused). With joint columns the start posture of a reach is its first
row; an end-effector-only file uses the model's start posture (``start=``, the CLI's
``--start``) for every reach and must begin each reach where that posture puts the end
effector (within `START_TOL_M` plus the noise allowance).

Noise allowance: joint values may lie beyond the model's range by at most
``K_SIGMA * sigma`` (sigma from the `NoiseModel`, plus `BOUND_SLACK` for rounding); such
values are clipped onto the bound (the limits can never lie outside the model's range),
farther ones are an error. ``degrees=True`` reads the revolute joint columns in degrees
(prismatic ones stay in metres). Joint values beyond the range that would fit it after a
degrees-to-radians conversion are reported as "use --degrees".

Every error is a ValueError that starts with the file name and names the column and the
row: the CSV line number (the header is line 1), or the array index in an NPZ file.

Resampling (`resample_to_controller`): a recorder samples at its own rate, the controller
moves once per step. Before any distance is computed the loader resamples each reach to
the controller's step: the recorder's rate R (recorded samples per controller step) is
estimated from the whole file (`estimate_rate`) and, unless it is 1, each reach is
linearly interpolated in normalised time to round((L - 1) / R) + 1 samples (``"time"``,
the default), or re-walked along its path with the controller's step law
(``"arclength"``). See the README for the measurement behind the default.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from camo_sbi._io import atomic_write_bytes, atomic_write_text
from camo_sbi.simulators.controller import ControllerConfig
from camo_sbi.task import NoiseModel, Observation

__all__ = ["BOUND_SLACK", "EE_COLUMNS", "GOAL_COLUMNS", "K_SIGMA", "RESAMPLE_MODES", "START_TOL_M",
           "estimate_rate", "load_goals", "load_recordings", "resample_to_controller", "save_recordings"]

REACH, STEP = "reach", "step"
GOAL_COLUMNS = ("goal_x", "goal_y", "goal_z")
EE_COLUMNS = ("ee_x", "ee_y", "ee_z")
K_SIGMA = 4.0
"""Values may exceed the model's range by K_SIGMA noise standard deviations (4: one in ~16 000
noise-free samples at a bound is wrongly refused)."""
BOUND_SLACK = 1e-6
"""Absolute slack (rad / m) beyond the model's range for rounding in files written by others."""
START_TOL_M = 0.005
"""An end-effector-only reach must start within this distance (plus the noise allowance) of
the end effector at the model's start posture."""
GOAL_TOL = 1e-9
EE_FK_TOL_M = 0.01
"""With joint and end-effector columns, FK of each row's joints must lie within this distance (plus
the noise allowance) of its ee_* values."""
RESAMPLE_MODES = ("time", "arclength")
RATE_SNAP = 0.15
"""An estimated rate within this relative distance of an integer is taken as that integer."""


def _controller(simulator) -> ControllerConfig:
    cfg = getattr(simulator, "config", None)
    return cfg if isinstance(cfg, ControllerConfig) else ControllerConfig()


def _joint_types(simulator) -> tuple[str, ...]:
    spec = getattr(simulator, "spec", None)
    types = getattr(spec, "joint_types", None)
    return tuple(types) if types is not None else ("revolute",) * simulator.n_joints


# ----------------------------------------------------------------------------- reading


@dataclass
class _Table:
    """Columns of a recording file as float arrays, and where each row came from."""

    path: Path
    columns: dict[str, np.ndarray]
    rows: np.ndarray  # CSV line numbers, or NPZ array indices
    row_word: str  # "line" or "row"

    def where(self, column: str, i: int) -> str:
        return f"{self.path}: column {column!r}, {self.row_word} {int(self.rows[i])}"


def _read_csv(path: Path) -> _Table:
    try:
        fh = path.open(newline="")
    except OSError as exc:
        raise ValueError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    with fh:
        reader = csv.reader(fh)
        header = None
        values: list[list[float]] = []
        lines: list[int] = []
        for row in reader:
            if not row or all(not c.strip() for c in row):
                continue
            if header is None:
                header = [c.strip() for c in row]
                dup = [c for c in header if header.count(c) > 1]
                if dup:
                    raise ValueError(f"{path}: column {dup[0]!r}, line {reader.line_num}: appears twice in the header")
                continue
            if len(row) != len(header):
                raise ValueError(f"{path}: line {reader.line_num}: has {len(row)} fields, the header has "
                                 f"{len(header)}")
            parsed = []
            for c, cell in zip(header, row, strict=True):
                try:
                    parsed.append(float(cell))
                except ValueError:
                    raise ValueError(f"{path}: column {c!r}, line {reader.line_num}: not a number: "
                                     f"{cell.strip()!r}") from None
            values.append(parsed)
            lines.append(reader.line_num)
    if header is None:
        raise ValueError(f"{path}: empty file (expected a header line and one row per sample)")
    if not values:
        raise ValueError(f"{path}: has a header but no samples")
    data = np.asarray(values, dtype=np.float64)
    return _Table(path, {c: data[:, i] for i, c in enumerate(header)}, np.asarray(lines), "line")


def _read_npz(path: Path) -> _Table:
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: np.asarray(z[k]) for k in z.files}
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read as NPZ ({exc})") from exc
    if not arrays:
        raise ValueError(f"{path}: holds no arrays")
    n = None
    for k, a in arrays.items():
        if a.ndim != 1:
            raise ValueError(f"{path}: column {k!r}: expected a 1-D array (one value per sample), got shape {a.shape}")
        if not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
            raise ValueError(f"{path}: column {k!r}: expected numbers, got dtype {a.dtype}")
        if n is None:
            n = a.shape[0]
        elif a.shape[0] != n:
            raise ValueError(f"{path}: column {k!r}: has {a.shape[0]} values, other columns have {n}")
    if n == 0:
        raise ValueError(f"{path}: has no samples")
    return _Table(path, {k: a.astype(np.float64) for k, a in arrays.items()}, np.arange(n), "row")


def _layout(table: _Table, joint_names: list[str]) -> tuple[bool, bool]:
    """Check the columns against the schema: (has joint columns, has ee columns)."""
    cols = table.columns
    path = table.path
    need = f"a recording needs {REACH}, {STEP}, {', '.join(GOAL_COLUMNS)}, then the joint columns and/or " \
           f"{', '.join(EE_COLUMNS)}"
    for c in (REACH, STEP, *GOAL_COLUMNS):
        if c not in cols:
            raise ValueError(f"{path}: column {c!r} is missing ({need})")
    known = {REACH, STEP, *GOAL_COLUMNS, *EE_COLUMNS, *joint_names}
    for c in cols:
        if c not in known:
            raise ValueError(f"{path}: column {c!r} is unknown: not a joint of the model (its joints: "
                             f"{', '.join(joint_names)}) nor one of {REACH}, {STEP}, goal_*, ee_*")
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
        a = cols[c]
        bad = np.flatnonzero(a != np.round(a))
        if bad.size:
            raise ValueError(f"{table.where(c, bad[0])}: expected an integer, got {a[bad[0]]!r}")
    return has_q, has_ee


def _reaches(table: _Table) -> list[np.ndarray]:
    """Row indices of each reach (consecutive rows, steps strictly increasing, >= 2 samples)."""
    reach, step = table.columns[REACH], table.columns[STEP]
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
            raise ValueError(f"{table.where(STEP, a)}: reach {int(rid)} has a single sample; a reach needs its "
                             f"start posture and at least one more sample")
        d = np.diff(step[idx])
        bad = np.flatnonzero(d <= 0)
        if bad.size:
            i = idx[bad[0] + 1]
            raise ValueError(f"{table.where(STEP, i)}: step {int(step[i])} does not increase (previous step "
                             f"{int(step[i - 1])}) within reach {int(rid)}")
        for c in GOAL_COLUMNS:
            g = table.columns[c][idx]
            bad = np.flatnonzero(np.abs(g - g[0]) > GOAL_TOL)
            if bad.size:
                i = idx[bad[0]]
                raise ValueError(f"{table.where(c, i)}: the goal changes within reach {int(rid)} ({g[bad[0]]!r} "
                                 f"here, {g[0]!r} on its first row); one goal per reach")
        out.append(idx)
    return out


def _joint_values(table: _Table, simulator, degrees: bool, noise: NoiseModel) -> np.ndarray:
    """(rows, n) joint values in radians, checked against the model's range and clipped within noise."""
    names = list(simulator.joint_names)
    types = _joint_types(simulator)
    b = simulator.bounds.to(torch.float64).numpy()
    q = np.stack([table.columns[j] for j in names], axis=1)
    rev = np.array([t == "revolute" for t in types])
    if degrees:
        q[:, rev] = np.radians(q[:, rev])
    tol = K_SIGMA * noise.sigma("joint") + BOUND_SLACK
    below, above = q < b[:, 0] - tol, q > b[:, 1] + tol
    outside = below | above
    if outside.any():
        i, j = (int(v) for v in np.argwhere(outside)[0])
        value = table.columns[names[j]][i]
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


def _check_ee_matches_fk(table: _Table, simulator, q: np.ndarray, ee: np.ndarray, noise: NoiseModel) -> None:
    """With both spaces recorded, the model's FK of the joint values must land near ee_*: a file
    recorded at another link than ``--ee`` (or for another robot) is refused, not inferred on."""
    fk = simulator.forward_kinematics(torch.from_numpy(q)).to(torch.float64).numpy()
    dist = np.linalg.norm(fk - ee, axis=1)
    lever = float(np.linalg.norm(ee, axis=1).max())  # joint noise moves the end effector by ~ lever * sigma
    tol = EE_FK_TOL_M + K_SIGMA * (math.sqrt(3) * noise.sigma("cartesian")
                                   + math.sqrt(simulator.n_joints) * lever * noise.sigma("joint"))
    i = int(np.argmax(dist))
    if dist[i] > tol:
        raise ValueError(f"{table.where('ee_x', i)}: the model's end effector at this row's joint values is "
                         f"{dist[i] * 1000:.1f} mm from ee_x, ee_y, ee_z (tolerance {tol * 1000:.1f} mm): was the "
                         f"recording made at another link than the model's end effector (--ee), or is it noisier than "
                         f"the noise model says (--noise-joint-deg {noise.joint_deg:g}, --noise-ee-mm {noise.ee_mm:g})?")


def load_recordings(path, simulator, *, degrees: bool = False, noise: NoiseModel | None = None,
                    start=None, resample: str | None = "time", rate: float | None = None,
                    ) -> tuple[Observation, ...]:
    """The observed reaches in the recording file ``path`` (CSV or .npz), for ``simulator``.

    Args:
        path: a CSV file (one row per sample, header line) or an .npz file (the same names as
            1-D arrays); the schema is in the module docstring.
        simulator: the body model; its joint names name the joint columns, its range bounds them.
        degrees: the revolute joint columns are in degrees.
        noise: the `NoiseModel` of the recording (the tolerance beyond the model's range).
        start: (n,) start posture of an end-effector-only recording (default: the model's).
        resample: "time" (default), "arclength" or None (no resampling): see
            `resample_to_controller`.
        rate: recorded samples per controller step (default: estimated from the file with
            `estimate_rate`).

    Returns:
        One `Observation` per reach, in file order (float64).

    Raises:
        ValueError starting with the file name and naming the column and the CSV line (the
        header is line 1) or NPZ row, for every malformed file (see the module docstring).
    """
    noise = NoiseModel() if noise is None else noise
    if not isinstance(noise, NoiseModel):
        raise TypeError(f"noise: expected a NoiseModel, got {type(noise).__name__}")
    if resample is not None and resample not in RESAMPLE_MODES:
        raise ValueError(f"resample: expected one of {RESAMPLE_MODES} or None, got {resample!r}")
    table = _read(path)
    names = list(simulator.joint_names)
    has_q, has_ee = _layout(table, names)
    reaches = _reaches(table)
    q_all = _joint_values(table, simulator, degrees, noise) if has_q else None
    ee_all = np.stack([table.columns[c] for c in EE_COLUMNS], axis=1) if has_ee else None
    goal_all = np.stack([table.columns[c] for c in GOAL_COLUMNS], axis=1)
    if not has_q:
        s = simulator.start if start is None else start
        s = torch.as_tensor(np.asarray(s, dtype=np.float64))
        if s.shape != (simulator.n_joints,):
            raise ValueError(f"start: expected shape ({simulator.n_joints},), got {tuple(s.shape)}")
        ee0 = simulator.forward_kinematics(s).to(torch.float64).numpy()
        tol = START_TOL_M + K_SIGMA * math.sqrt(3) * noise.sigma("cartesian")
        for idx in reaches:
            dist = float(np.linalg.norm(ee_all[idx[0]] - ee0))
            if dist > tol:
                raise ValueError(f"{table.where('ee_x', idx[0])}: reach {int(table.columns[REACH][idx[0]])} "
                                 f"starts {dist * 1000:.1f} mm from where the start posture puts the end "
                                 f"effector (tolerance {tol * 1000:.1f} mm): an end-effector-only recording "
                                 f"starts at the model's start posture (give it with --start)")
    if has_q and has_ee:
        _check_ee_matches_fk(table, simulator, q_all, ee_all, noise)
    obs = []
    for idx in reaches:
        q = torch.from_numpy(q_all[idx].copy()) if has_q else None
        st = q[0].clone() if has_q else s.clone()
        ee = torch.from_numpy(ee_all[idx].copy()) if has_ee else None
        obs.append(Observation(st, torch.from_numpy(goal_all[idx[0]].copy()), q, ee))
    obs = tuple(obs)
    if resample is None:
        return obs
    r = estimate_rate(obs, simulator) if rate is None else float(rate)
    if not (math.isfinite(r) and r > 0):
        raise ValueError(f"rate: expected a number > 0, got {rate!r}")
    return tuple(resample_to_controller(o, simulator, mode=resample, rate=r) for o in obs)


def _read(path) -> _Table:
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such file")
    return _read_npz(path) if path.suffix.lower() == ".npz" else _read_csv(path)


def load_goals(path, simulator, *, degrees: bool = False, noise: NoiseModel | None = None):
    """Goals to predict, from a CSV/NPZ with ``goal_x, goal_y, goal_z`` and optionally the start
    posture's joint columns (named as the model's joints; all of them or none).

    Returns (goals (M, 3) float64, starts (M, n) float64 or None). Errors name the file, the
    column and the line, as `load_recordings` does.
    """
    noise = NoiseModel() if noise is None else noise
    table = _read(path)
    names = list(simulator.joint_names)
    for c in GOAL_COLUMNS:
        if c not in table.columns:
            raise ValueError(f"{table.path}: column {c!r} is missing (goals need {', '.join(GOAL_COLUMNS)} "
                             f"and optionally the start posture's joint columns)")
    for c in table.columns:
        if c not in (*GOAL_COLUMNS, *names):
            raise ValueError(f"{table.path}: column {c!r} is unknown: not a joint of the model (its joints: "
                             f"{', '.join(names)}) nor one of {', '.join(GOAL_COLUMNS)}")
    has_q = any(j in table.columns for j in names)
    missing = [j for j in names if j not in table.columns]
    if has_q and missing:
        raise ValueError(f"{table.path}: column {missing[0]!r} is missing (give every joint of the start "
                         f"posture or none)")
    for c, a in table.columns.items():
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            raise ValueError(f"{table.where(c, bad[0])}: NaN or inf ({a[bad[0]]!r})")
    goals = torch.from_numpy(np.stack([table.columns[c] for c in GOAL_COLUMNS], axis=1))
    starts = torch.from_numpy(_joint_values(table, simulator, degrees, noise)) if has_q else None
    return goals, starts


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


# ----------------------------------------------------------------------------- resampling


def _ee_path(o: Observation, simulator) -> np.ndarray:
    if o.ee is not None:
        return o.ee.numpy()
    return simulator.forward_kinematics(o.q).to(torch.float64).numpy()


def _walk(path: np.ndarray, goal: np.ndarray, cfg: ControllerConfig) -> np.ndarray:
    """Arc-length positions where a controller stepping min(cap, gain * |goal - x|) along
    ``path`` would be, from the start until within the goal tolerance or the path's end."""
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    total = s[-1]
    out = [0.0]
    pos = 0.0
    for _ in range(100_000):
        x = np.array([np.interp(pos, s, path[:, k]) for k in range(3)])
        e = float(np.linalg.norm(goal - x))
        if e < cfg.tol or pos >= total:
            break
        pos = min(total, pos + min(cfg.max_cartesian_step, cfg.gain * e))
        out.append(pos)
    return np.asarray(out), s


RATE_WINDOW = 3
"""Samples per displacement window in `estimate_rate` (averages the noise of single samples)."""
RATE_QUANTILE = 0.25
"""`estimate_rate` takes this quantile of the per-sample ratios: steps slowed by a clamped joint
only raise the ratio, so a low quantile is the free steps' value."""


def estimate_rate(observations, simulator) -> float:
    """Recorded samples per controller step, pooled over ``observations`` (one recorder).

    Far from the goal (``gain * |goal - x| > 2 * max_cartesian_step``) the controller
    commands a step of exactly ``max_cartesian_step``, and a free (unclamped) step moves
    the end effector by about that much. At every such sample t of a reach's end-effector
    path (recorded, or FK of the joint trajectory) the ratio ``max_cartesian_step /
    (|x[t + w] - x[t]| / w)`` (w = `RATE_WINDOW` samples, to average out noise) estimates
    the rate; the file's rate is the `RATE_QUANTILE` quantile over all its reaches' samples
    (a step slowed by a clamped joint has a larger ratio, never a smaller one), snapped to the nearest integer
    when within `RATE_SNAP` of it, so a 1x recording is kept exactly as it is. A file with no
    sample that far from its goal falls back to walking each path with the controller's
    step law (`_walk`): rate = (L - 1) / (steps - 1), median over reaches.
    """
    cfg = _controller(simulator)
    w = RATE_WINDOW
    ratios, walked = [], []
    for o in observations:
        if o.length < 2:
            continue
        x = _ee_path(o, simulator)
        e = np.linalg.norm(o.goal.numpy() - x, axis=1)
        if o.length > w:
            d = np.linalg.norm(x[w:] - x[:-w], axis=1) / w
            far = cfg.gain * e > 2 * cfg.max_cartesian_step
            cruise = np.array([far[t: t + w + 1].all() for t in range(o.length - w)])
            ok = cruise & (d > 0)
            ratios += list(cfg.max_cartesian_step / d[ok])
        walk, _ = _walk(x, o.goal.numpy(), cfg)
        if walk.size >= 2:
            walked.append((o.length - 1) / (walk.size - 1))
    if ratios:
        r = float(np.quantile(ratios, RATE_QUANTILE))
    elif walked:
        r = float(np.median(walked))
    else:
        return 1.0
    k = max(1, round(r))
    return float(k) if abs(r - k) <= RATE_SNAP * k else r


def _interp_rows(x: np.ndarray, t_old: np.ndarray, t_new: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(t_new, t_old, x[:, k]) for k in range(x.shape[1])], axis=1)


def resample_to_controller(observation: Observation, simulator, *, mode: str = "time",
                           rate: float = 1.0) -> Observation:
    """``observation`` resampled to the controller's step.

    mode "time": linear interpolation in normalised time to round((L - 1) / rate) + 1
    samples (``rate`` recorded samples per controller step; at rate 1 the observation is
    returned unchanged). mode "arclength": the samples where a controller stepping
    ``min(max_cartesian_step, gain * |goal - x|)`` along the recorded end-effector path
    would be (joint values interpolated at the same path positions); at rate 1 unchanged.
    The start (first sample) is kept exactly.
    """
    if not isinstance(observation, Observation):
        raise TypeError(f"observation: expected an Observation, got {type(observation).__name__}")
    if mode not in RESAMPLE_MODES:
        raise ValueError(f"mode: expected one of {RESAMPLE_MODES}, got {mode!r}")
    if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not math.isfinite(rate) or rate <= 0:
        raise ValueError(f"rate: expected a number > 0, got {rate!r}")
    o = observation
    L = o.length
    if rate == 1.0 or L < 2:
        return o
    if mode == "time":
        t_old = np.arange(L, dtype=np.float64)
        n_new = max(2, int(round((L - 1) / rate)) + 1)
        t_new = np.linspace(0.0, L - 1.0, n_new)
    else:
        walk, s = _walk(_ee_path(o, simulator), o.goal.numpy(), _controller(simulator))
        if walk.size < 2:
            return o
        t_old, t_new = s, walk
        keep = np.r_[True, np.diff(s) > 0]  # a path that stands still has repeated arc lengths
        t_old = s[keep]
    sel = slice(None) if mode == "time" else keep
    q = None if o.q is None else torch.from_numpy(_interp_rows(o.q.numpy()[sel], t_old, t_new))
    ee = None if o.ee is None else torch.from_numpy(_interp_rows(o.ee.numpy()[sel], t_old, t_new))
    if q is not None:
        q[0] = o.q[0]
    return Observation(o.start.clone(), o.goal.clone(), q, ee)
