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
farther ones are an error, or (``out_of_range``, the CLI's ``--out-of-range``, `OUT_OF_RANGE_MODES`)
clipped onto the range with a warning per joint and the bound marked (``Recording.clipped``;
limits.csv's ``clipped_samples``). The default, "auto", clips the joint angles computed from
anatomical landmarks (``markers="isb"``: a person beyond the model's normative range is a
finding, not a file error) and refuses every other file (a BVH channel map's sign or offset, a
CSV's unit or a .mot's convention is the likelier cause there). ``degrees=True`` reads the revolute joint columns in degrees
(prismatic ones stay in metres). Joint values beyond the range that would fit it after a
degrees-to-radians conversion are reported as "use --degrees".

Lab recordings (`load_recording`):

* ``time`` (seconds) may replace ``step``: each reach is first interpolated onto a uniform
  grid at the file's median sample interval (jittered or dropped samples), then resampled to
  the controller's step like a step file.
* ``ee_units="mm"`` reads ee_* and goal_* in millimetres; positions more than `UNITS_FACTOR`
  times farther than the model reaches are refused, with a "use --ee-units mm" hint when they
  would fit in millimetres.
* ``frame`` (`camo_sbi.io.frames`) maps every position from the lab to the model's base;
  C3D files (`camo_sbi.io.c3d`) come through the same checks as CSV.
* ``goal="final"``: each reach's last end-effector position is its goal (free reaching).
* An end-effector-only reach that does not start where the model's start posture puts the
  end effector gets its start by IK of its first sample (`estimate_starts`), recorded in its
  `Observation.start`.
* Warnings (not errors), returned in `Recording.warnings` for the run summary and the
  report: goals out of the model's reach (distance measured against `reach_radius`), a
  systematic offset between ee_* and the FK of the joint columns (mean over the samples),
  a marker-frame fit residual above `OFFSET_WARN_M`.

A CSV is read as UTF-8 (a BOM is accepted); a binary file, a non-UTF-8 file, a field over
131,072 characters, or an .npz that is not a zip archive is one error naming the file.

Every error is a ValueError that starts with the file name and names the column and the
row: the CSV line number (the header is line 1), or the array index in an NPZ file.

Resampling (`resample_to_controller`): a recorder samples at its own rate, the controller
moves once per step. Before any distance is computed the loader resamples each reach to
the controller's step: the recorder's rate R (recorded samples per controller step) is
estimated from the whole file (`estimate_rate`) and, unless it is 1, each reach is
linearly interpolated in normalised time to round((L - 1) / R) + 1 samples (``"time"``,
the default), or re-walked along its path with the controller's step law
(``"arclength"``). See docs/user-guide/your-robot.md for the measurement behind the default.
"""

from __future__ import annotations

import csv
import io
import math
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from camo_sbi._io import atomic_write_bytes, atomic_write_text
from camo_sbi.io.frames import Frame, frame_from_markers
from camo_sbi.io.text import read_text
from camo_sbi.simulators.controller import ControllerConfig
from camo_sbi.task import NoiseModel, Observation

__all__ = ["BOUND_SLACK", "EE_COLUMNS", "EE_UNITS", "GOAL_COLUMNS", "GOAL_MODES", "K_SIGMA", "OUT_OF_RANGE_MODES", "RESAMPLE_MODES",
           "START_TOL_M", "Recording", "estimate_body_scale", "estimate_rate", "estimate_starts", "load_goals", "load_recording",
           "load_recordings", "reach_radius", "resample_to_controller", "save_recordings"]

REACH, STEP, TIME = "reach", "step", "time"
EE_UNITS = {"m": 1.0, "mm": 1e-3}
GOAL_MODES = ("columns", "final")
OFFSET_WARN_M = 0.005
"""A mean offset between ee_* and the FK of the joint columns (or a marker-frame RMS residual)
beyond this is a warning in the run summary and the report."""
UNITS_FACTOR = 10.0
"""A position this many times farther from the base than the model reaches is refused (with a
hint when it would fit in millimetres)."""
GOAL_COLUMNS = ("goal_x", "goal_y", "goal_z")
EE_COLUMNS = ("ee_x", "ee_y", "ee_z")
OUT_OF_RANGE_MODES = ("auto", "clip", "error")
"""``out_of_range``: "auto" (clip the ISB landmarks' angles, refuse other files), "clip", "error"."""
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
    sources: dict | None = None  # column -> where its values come from (a BVH channel and its map entry)

    def where(self, column: str, i: int) -> str:
        return f"{self.path}: column {column!r}, {self.row_word} {int(self.rows[i])}"


CSV_FIELD_LIMIT = 131_072
"""Python's csv module refuses longer fields; a recording's numbers are never that long."""


def _read_csv(path: Path) -> _Table:
    text = read_text(path, "a CSV recording")
    reader = csv.reader(io.StringIO(text, newline=""))
    header = None
    values: list[list[float]] = []
    lines: list[int] = []
    try:
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
                                     f"{cell.strip()[:40]!r}") from None
            values.append(parsed)
            lines.append(reader.line_num)
    except csv.Error as exc:
        why = (f"a field is longer than {CSV_FIELD_LIMIT:,} characters" if "field limit" in str(exc) else str(exc))
        raise ValueError(f"{path}: line {reader.line_num}: {why}: not a CSV recording") from None
    if header is None:
        raise ValueError(f"{path}: empty file (expected a header line and one row per sample)")
    if not values:
        raise ValueError(f"{path}: has a header but no samples")
    data = np.asarray(values, dtype=np.float64)
    return _Table(path, {c: data[:, i] for i, c in enumerate(header)}, np.asarray(lines), "line")


def _read_npz(path: Path) -> _Table:
    if not zipfile.is_zipfile(path):
        raise ValueError(f"{path}: cannot read as NPZ (not a zip archive of .npy arrays)")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: np.asarray(z[k]) for k in z.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{path}: cannot read as NPZ ({exc})") from None
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


def _read_c3d(path: Path, ee_markers, frame_markers) -> tuple[_Table, dict]:
    from camo_sbi.io.c3d import read_c3d

    d = read_c3d(path, ee_markers, list(frame_markers or ()))
    cols = {REACH: d["reach"], TIME: d["time"]}
    for k, c in enumerate(EE_COLUMNS):
        cols[c] = d["ee"][:, k]
    return _Table(path, cols, d["frames"], "frame"), d


def _read_c3d_isb(path: Path, simulator, markers: str, marker_map, side, ee_markers, frame_markers):
    """The human model's joint angles per frame from a C3D's ISB landmarks: (table, info dict)."""
    from camo_sbi.io.c3d import read_c3d_points
    from camo_sbi.io.isb import HAND_TRACK, NEEDED, isb_joint_angles, load_marker_map

    if markers != "isb":
        raise ValueError(f"--markers: expected isb (ISB upper-limb landmarks), got {markers!r}")
    if marker_map is None:
        raise ValueError("--marker-map: --markers isb needs the map from ISB landmarks to the file's marker labels "
                         '(JSON {"IJ": "<label>", ...})')
    if ee_markers or frame_markers:
        raise ValueError("--markers: isb computes joint angles in the thorax's frame; drop --ee-marker and "
                         "--frame-from-markers")
    from camo_sbi.simulators.human import JOINT_NAMES

    if tuple(simulator.joint_names) != JOINT_NAMES:
        raise ValueError(f"--markers: isb gives the human model's joint angles ({', '.join(JOINT_NAMES)}); use "
                         f"--model human")
    mapping = load_marker_map(marker_map)
    d = read_c3d_points(path, [mapping[k] for k in NEEDED])
    pts = {k: d["points"][mapping[k]] for k in NEEDED}
    present = np.all([np.isfinite(v).all(axis=1) for v in pts.values()], axis=0)
    if present.sum() < 2:
        lost = min(NEEDED, key=lambda k: np.isfinite(pts[k]).all(axis=1).sum())
        raise ValueError(f"--marker-map: {path} has fewer than two frames with every landmark (landmark {lost!r}, "
                         f"marker {mapping[lost]!r}, is seen least)")
    q = isb_joint_angles({k: v[present] for k, v in pts.items()}, side or "right")
    run_id = np.cumsum(np.r_[True, ~present[:-1]] & present)[present]  # a new reach after every gap
    cols = {REACH: np.unique(run_id, return_inverse=True)[1].astype(np.float64), TIME: d["time"][present],
            **{j: q[:, k] for k, j in enumerate(JOINT_NAMES)}}
    # the hand's measured track for --reaches auto: only the markers' noise, not the angles' error through FK
    d["hand_track"] = np.mean([pts[k][present] for k in HAND_TRACK], axis=0)
    d["hand_track_source"] = (f"the hand's markers: mean of {', '.join(mapping[k] for k in HAND_TRACK)} "
                              f"(ISB {', '.join(HAND_TRACK)}), lab frame")
    src = {j: {"what": "the ISB landmarks", "entry": f"--marker-map {marker_map} and --side {side or 'right'}; a "
                                                   f"person beyond the model's normative range: drop --out-of-range "
                                                   f"error (the default clips and marks the bound)"}
           for j in JOINT_NAMES}
    return _Table(path, cols, d["frames"][present], "frame", sources=src), d


def _layout(table: _Table, joint_names: list[str], goal: str = "columns") -> tuple[bool, bool]:
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


def _reaches(table: _Table, goal: str = "columns") -> list[np.ndarray]:
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


def _joint_values(table: _Table, simulator, degrees: bool, noise: NoiseModel,
                  clip_warnings: list | None = None, clipped: list | None = None, why: str = "clip") -> np.ndarray:
    """(rows, n) joint values in radians, checked against the model's range and clipped within noise.
    With ``clip_warnings`` (a list; ``out_of_range`` "clip", or "auto" on the ISB landmarks' angles:
    ``why`` names it) values beyond the range are clipped onto it too, one warning per joint (how
    many samples, by how much at most, which frames) appended to the list, and one row per bound
    ({"joint", "bound", "samples", "beyond"}: the most beyond, degrees or metres) appended to ``clipped``."""
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


def _check_ee_matches_fk(table: _Table, simulator, q: np.ndarray, ee: np.ndarray, noise: NoiseModel) -> str | None:
    """With both spaces recorded, the model's FK of the joint values must land near ee_*: a file
    recorded at another link than ``--ee`` (or for another robot) is refused, not inferred on.
    Returns a warning when the mean of ee_* - FK (a systematic offset: a marker placed off the
    end effector, or a frame a little off) exceeds `OFFSET_WARN_M`, else None."""
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
    off = (ee - fk).mean(axis=0)
    if float(np.linalg.norm(off)) > OFFSET_WARN_M:
        return (f"{table.path}: ee_x, ee_y, ee_z lie a systematic {np.linalg.norm(off) * 1000:.1f} mm from the model's "
                f"end effector at the recorded joint values (mean offset ({off[0] * 1000:.1f}, {off[1] * 1000:.1f}, "
                f"{off[2] * 1000:.1f}) mm over {ee.shape[0]} samples): a marker off the end effector, or a frame a "
                f"little off?")
    return None


REACH_SAMPLES = 4096
REACH_MARGIN = 0.02
"""A goal farther from the base than (1 + REACH_MARGIN) x the farthest sampled end-effector
position (plus 1 cm) is reported as out of reach."""


def reach_radius(simulator) -> float:
    """The farthest distance from the base origin of the end effector over `REACH_SAMPLES`
    postures uniform in the model's range (fixed seed), and the start posture [m]."""
    b = simulator.bounds.to(torch.float64).numpy()
    q = np.random.default_rng(0).uniform(b[:, 0], b[:, 1], size=(REACH_SAMPLES, b.shape[0]))
    q = np.vstack([q, np.asarray(simulator.start, dtype=np.float64)[None]])
    fk = simulator.forward_kinematics(torch.from_numpy(q)).to(torch.float64).numpy()
    return float(np.linalg.norm(fk, axis=1).max())


def _check_units(table: _Table, radius: float, ee_units: str, frame: Frame | None = None) -> None:
    """Positions far beyond the model's reach: with a hint when they would fit in millimetres.
    ``ee_units`` "file": the file states its units (C3D), so no --ee-units hint; ``frame``: the
    transform applied to the positions, named in the message."""
    for c in (*EE_COLUMNS, *GOAL_COLUMNS):
        if c not in table.columns:
            continue
        a = np.abs(table.columns[c])
        i = int(np.argmax(a))
        if a[i] > UNITS_FACTOR * max(radius, 0.05):
            if ee_units == "file":
                hint = (" check the frame (--frame, --frame-from-markers) and the end-effector marker "
                        "(--ee-marker); the units come from the file's POINT:UNITS")
            elif ee_units == "m" and a[i] / 1000 <= 2 * radius:
                hint = " the positions look like millimetres: use --ee-units mm"
            else:
                hint = " check the units (--ee-units) and the frame (--frame)"
            after = f" after the transform of {frame.source}" if frame is not None else ""
            raise ValueError(f"{table.where(c, i)}{after}: {table.columns[c][i]:.6g} m is {a[i] / radius:.3g}x as far "
                             f"as the model reaches ({radius:.3g} m from the base);{hint}")


IK_ITERATIONS = 300
IK_DAMPING = 0.02
IK_MAX_STEP = 0.2
IK_PROGRESS_MIN = 200
"""From this many reaches on, the start-posture IK shows a progress bar and logs its estimated time."""

MAX_REACHES = 2000
"""A recording with more reaches is refused unless ``max_reaches`` (``--max-reaches``) allows it:
every reach is a task of every method (``--budget`` simulations each) and an IK problem."""


def _fk_numpy(simulator):
    """q (B, n) float64 -> end-effector positions (B, 3): the simulator's numba kernel when it has
    one (agrees with the reference FK to 1e-12 m, tests/test_simulators.py; thousands of times
    faster than pytorch_kinematics on a batch), else its reference `forward_kinematics`."""
    spec = getattr(simulator, "spec", None)
    if spec is not None and getattr(simulator, "backend", "torch") != "torch":
        from camo_sbi.simulators.kernel import kernel_fk

        return lambda q: kernel_fk(spec, np.ascontiguousarray(q, dtype=np.float64))
    return lambda q: simulator.forward_kinematics(torch.from_numpy(q)).to(torch.float64).numpy()


def estimate_starts(simulator, targets, initial, bounds=None) -> tuple[np.ndarray, np.ndarray]:
    """Start postures whose end effector is at ``targets`` (R, 3): damped least squares from
    ``initial`` (n,) within ``bounds`` (default: the model's range), with a null-space pull
    back towards ``initial`` (the posture nearest the model's start that reaches the point).
    Returns (postures (R, n), residual distances (R,) [m]).

    From `IK_PROGRESS_MIN` reaches on, a progress bar counts the iterations and the time of all
    `IK_ITERATIONS` (an upper bound: it stops when every reach is solved), measured on the first
    iteration, is logged (a warning above a minute)."""
    import logging
    import time

    from tqdm import tqdm

    fk_numpy = _fk_numpy(simulator)
    b = (simulator.bounds if bounds is None else torch.as_tensor(bounds)).to(torch.float64).numpy()
    x_t = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    q0 = np.asarray(initial, dtype=np.float64)
    n, r = q0.shape[0], x_t.shape[0]
    q = np.broadcast_to(q0, (r, n)).copy()
    eps = 1e-6
    eye = np.eye(n)
    big = r >= IK_PROGRESS_MIN
    bar = tqdm(total=IK_ITERATIONS, desc=f"start postures (IK of {r} reaches)", unit="it", disable=not big,
               leave=False)
    fk_numpy(q[:1])  # loads (or compiles) the kernel before the timing
    t0 = time.perf_counter()
    for it in range(IK_ITERATIONS):
        if it == 1 and big:
            total = (time.perf_counter() - t0) * IK_ITERATIONS
            logging.getLogger(__name__).log(
                logging.WARNING if total > 60 else logging.INFO,
                "start postures: IK of %d reaches (their first end-effector samples), about %.3g s at most "
                "(%d iterations, measured on the first)", r, total, IK_ITERATIONS)
        bar.update(1)
        pert = np.concatenate([q[:, None, :], q[:, None, :] + eps * eye[None]], axis=1)  # (r, n+1, n)
        fk = fk_numpy(pert.reshape(-1, n)).reshape(r, n + 1, 3)
        x = fk[:, 0]
        e = x_t - x
        if float(np.linalg.norm(e, axis=1).max()) < 1e-6:
            break
        jac = np.transpose(fk[:, 1:] - x[:, None], (0, 2, 1)) / eps  # (r, 3, n)
        jjt = jac @ np.transpose(jac, (0, 2, 1)) + IK_DAMPING ** 2 * np.eye(3)
        dq = np.einsum("rjn,rj->rn", jac, np.linalg.solve(jjt, e[..., None])[..., 0])
        pinv = np.transpose(jac, (0, 2, 1)) @ np.linalg.inv(jjt)  # (r, n, 3)
        null = eye[None] - pinv @ jac
        dq += 0.1 * np.einsum("rnm,rm->rn", null, q0[None] - q)
        step = np.abs(dq).max(axis=1, keepdims=True)
        dq *= np.minimum(1.0, IK_MAX_STEP / np.maximum(step, 1e-12))
        q = np.clip(q + dq, b[:, 0], b[:, 1])
    bar.close()
    return q, np.linalg.norm(x_t - fk_numpy(q), axis=1)


def _uniform_in_time(t: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(times, new times) of a reach resampled on a uniform grid of step ``dt`` from its first sample."""
    n = max(2, int(round((t[-1] - t[0]) / dt)) + 1)
    return t, np.minimum(t[0] + dt * np.arange(n), t[-1])


@dataclass(frozen=True)
class Recording:
    """A loaded recording: its reaches, the warnings to show in the run summary and the report, and
    what the loader did (``info``: units, frame and its residual, starts, goals, rate, offsets)."""

    observations: tuple[Observation, ...]
    warnings: tuple[str, ...] = ()
    info: dict = field(default_factory=dict)
    scale: float = 1.0  # the body's segment-length scale (body_scale="free"), else 1
    segments: tuple[dict, ...] = ()  # reaches found by --reaches (reaches.csv rows), else ()
    speed: dict | None = None  # {"time", "speed", "cuts": [(t0, t1)], "rule"} for the report's speed figure
    clipped: tuple[dict, ...] = ()  # bounds the recording went past, clipped: {"joint", "bound", "samples", "beyond"}


BODY_SCALE_RANGE = (0.85, 1.15)
BODY_SCALE_BOOTSTRAP = 200
BODY_SCALE_WARN = 0.01
"""A body more than 1% larger or smaller than the model (its 90% interval excluding 1) is warned."""


def estimate_body_scale(simulator, q: np.ndarray, ee: np.ndarray, reaches) -> tuple[float, float, float]:
    """The segment-length scale s of a recorded body: least squares of ``ee`` on s * FK(q) (every
    segment s times as long moves the end effector to exactly s * FK(q) in the base frame,
    `KinematicSimulator.scaled`), with a 90% interval from a bootstrap over the reaches (fixed
    seed). Returns (s, lower, upper)."""
    fk = simulator.forward_kinematics(torch.from_numpy(q)).to(torch.float64).numpy()
    num = np.array([float((ee[i] * fk[i]).sum()) for i in reaches])
    den = np.array([float((fk[i] * fk[i]).sum()) for i in reaches])
    s = float(num.sum() / den.sum())
    rng = np.random.default_rng(0)
    boot = []
    for _ in range(BODY_SCALE_BOOTSTRAP):
        k = rng.integers(0, len(reaches), len(reaches))
        boot.append(num[k].sum() / den[k].sum())
    lo, hi = np.quantile(boot, [0.05, 0.95])
    return s, float(lo), float(hi)


def _hint_body_scale(table: _Table, simulator, q, ee, reaches, noise) -> None:
    """A recording that does not fit the model but fits a body of another size: say so."""
    try:
        _check_ee_matches_fk(table, simulator, q, ee, noise)
    except ValueError as exc:
        s, _, _ = estimate_body_scale(simulator, q, ee, reaches)
        if abs(s - 1) > 0.01 and BODY_SCALE_RANGE[0] <= s <= BODY_SCALE_RANGE[1] and hasattr(simulator, "scaled"):
            try:
                _check_ee_matches_fk(table, simulator.scaled(s), q, ee, noise)
            except ValueError:
                raise exc from None
            raise ValueError(f"{exc} The recording fits a body {s:.3f} times the model's size: use --body-scale "
                             f"free") from None
        raise


def _resegment(table: _Table, simulator, spec: str, side, events, has_q: bool, has_ee: bool, degrees: bool,
               noise: NoiseModel, clip: bool = False, track: tuple[np.ndarray, str] | None = None):
    """The table cut into the reaches ``spec`` finds (`camo_sbi.io.segment`): (the table of the
    reaches' rows with new reach ids, the reaches.csv rows, the speed figure's data). ``track``:
    (an (F, 3) measured hand path [m], row for row with the table; what it is): the hand speed and
    the cuts come from it instead of the end-effector columns or the forward kinematics (a marker
    session's hand markers); the start and goal positions stay the model's."""
    from camo_sbi.io.segment import (
        events_segments,
        hand_speed,
        parse_reaches,
        ranges_segments,
        rule_text,
        segment_by_speed,
    )

    kind, ranges = parse_reaches(spec)
    if TIME not in table.columns:
        raise ValueError(f"--reaches: {table.path} has no time (a C3D, a BVH, or a CSV/NPZ with a 'time' column "
                         f"in seconds); with a step column give the reach column instead")
    t = table.columns[TIME]
    if has_ee:
        hand = np.stack([table.columns[c] for c in EE_COLUMNS], axis=1)
    else:
        q = _joint_values(table, simulator, degrees, noise, [] if clip else None)  # warned when loaded
        hand = simulator.forward_kinematics(torch.from_numpy(q)).to(torch.float64).numpy()
    source = "end-effector track" if has_ee else "forward kinematics of the joint angles"
    moving = hand
    if track is not None:
        moving, source = np.asarray(track[0], dtype=np.float64), str(track[1])
        if moving.shape != hand.shape:
            raise ValueError(f"track: expected shape {hand.shape} (one hand position per row of {table.path}), got "
                             f"{moving.shape}")
    # the file's own runs (C3D gaps, a CSV's reach ids): speed is computed within each, never across a gap
    rid = table.columns[REACH]
    starts = np.flatnonzero(np.r_[True, rid[1:] != rid[:-1]])
    runs = list(zip(starts, np.r_[starts[1:], rid.shape[0]], strict=True))
    speed = np.zeros(t.shape[0])
    for a, b in runs:
        speed[a:b] = hand_speed(t[a:b], moving[a:b])
    what = str(table.path)
    if kind == "frames":
        segs = ranges_segments(table.rows, ranges, what)
        rule = "explicit frame ranges (--reaches)"
    elif kind == "events":
        if events is None:
            raise ValueError(f"--reaches: events come from a C3D file's EVENT group; {table.path} is not a C3D file")
        segs = events_segments(t, events, side, what)
        rule = f"the file's events{'' if side is None else f' (context {side} or General)'}"
    else:
        segs = []
        for a, b in runs:
            segs += [type(g)(g.first + a, g.last + a, g.rule, g.peak_speed)
                     for g in segment_by_speed(t[a:b], speed[a:b], moving[a:b])]
        rule = rule_text(track=source)
    if not segs:
        raise ValueError(f"--reaches: {spec} found no reach in {table.path} (rule: {rule}); give frame ranges "
                         f"(--reaches 0-120,121-260)")
    keep = np.concatenate([np.arange(g.first, g.last + 1) for g in segs])
    new_rid = np.concatenate([np.full(g.last - g.first + 1, k, dtype=np.float64) for k, g in enumerate(segs)])
    cols = {c: a[keep] for c, a in table.columns.items()}
    cols[REACH] = new_rid
    out = _Table(table.path, cols, table.rows[keep], table.row_word, table.sources)
    rows = []
    for k, g in enumerate(segs):
        peak = g.peak_speed if np.isfinite(g.peak_speed) else float(speed[g.first: g.last + 1].max())
        rows.append({"reach": k, "first_frame": int(table.rows[g.first]), "last_frame": int(table.rows[g.last]),
                     "start_s": round(float(t[g.first]), 4), "end_s": round(float(t[g.last]), 4),
                     "duration_s": round(float(t[g.last] - t[g.first]), 4), "peak_speed_m_s": round(peak, 4),
                     **{f"start_{c}": round(float(v), 5) for c, v in zip("xyz", hand[g.first], strict=True)},
                     **{f"goal_{c}": round(float(v), 5) for c, v in zip("xyz", hand[g.last], strict=True)},
                     "rule": g.rule, **({"hand_track": source} if kind == "auto" else {})})
    fig = {"time": t, "speed": speed, "cuts": [(float(t[g.first]), float(t[g.last])) for g in segs], "rule": rule,
           "source": source}
    return out, tuple(rows), fig


def load_recordings(path, simulator, **kwargs) -> tuple[Observation, ...]:
    """The observed reaches in ``path``: `load_recording` (same arguments) without its warnings."""
    return load_recording(path, simulator, **kwargs).observations


def load_recording(path, simulator, *, degrees: bool = False, noise: NoiseModel | None = None,
                   start=None, resample: str | None = "time", rate: float | None = None,
                   ee_units: str | None = None, goal: str = "columns", frame: Frame | None = None,
                   ee_markers=None, frame_markers: dict | None = None, body_scale: str = "fixed",
                   bvh_map=None, max_reaches: int | None = MAX_REACHES, reaches: str | None = None, side: str | None = None,
                   markers: str | None = None, marker_map=None, out_of_range: str = "auto") -> Recording:
    """The observed reaches in the recording file ``path`` (CSV, .npz or .c3d), for ``simulator``.

    Args:
        path: a CSV file (one row per sample, header line), an .npz file (the same names as
            1-D arrays), or a C3D motion-capture file (``ee_markers`` name the end effector);
            the schema is in the module docstring.
        simulator: the body model; its joint names name the joint columns, its range bounds them.
        degrees: the revolute joint columns are in degrees.
        noise: the `NoiseModel` of the recording (the tolerance beyond the model's range).
        start: (n,) the model's start posture (default: the model's); an end-effector-only
            reach that starts elsewhere gets its start by IK from it (`estimate_starts`).
        resample: "time" (default), "arclength" or None (no resampling): see
            `resample_to_controller`.
        rate: recorded samples per controller step (default: estimated from the file with
            `estimate_rate`).
        ee_units: "m" (default) or "mm": the unit of ee_* and goal_* (a C3D file's own
            ``POINT:UNITS`` is used instead).
        goal: "columns" (goal_* columns) or "final" (each reach's last end-effector position).
        frame: a `Frame` (lab -> model base) applied to every position.
        ee_markers: the C3D end-effector marker(s) (their mean).
        frame_markers: {C3D marker: (3,) model-frame position}: the frame estimated from these
            markers (`frame_from_markers`) instead of ``frame``.
        bvh_map: a BVH file's mapping file (`camo_sbi.io.bvh`: BVH channels -> model joints,
            signs, offsets, reach frame ranges); a .bvh ``path`` needs it.
        reaches: None (the file's own reaches: its reach column, C3D gaps, the BVH map's ranges),
            or ``--reaches``: "auto" (hand speed, `camo_sbi.io.segment`), "events" (the C3D
            file's events) or frame ranges "0-120,121-260"; the file needs time. Each reach's
            goal is then where it ends (unless the file has goal columns); ``Recording.segments``
            lists the reaches found and ``Recording.speed`` the hand speed with the cuts.
        side: "right" or "left": the recorded arm (``markers="isb"``: a left arm is mirrored onto
            the right-arm model) and the events' context for ``reaches="events"``.
        markers: "isb": a C3D's joint angles from its anatomical landmarks (`camo_sbi.io.isb`),
            named by ``marker_map`` (a JSON file {ISB landmark: the file's label}); the model
            must be the human model. Frames missing a landmark separate reaches.
        out_of_range: what a joint value beyond the model's range by more than the noise
            allowance does. "error": an error naming it (file, frame or line, joint, what to
            check). "clip": it is clipped onto the range with a warning per joint, and the bound
            is listed in ``Recording.clipped`` (the bound's estimate is then the model's range,
            not the person's: limits.csv and the limits table mark it). "auto" (default): "clip"
            for the joint angles of ``markers="isb"`` (a person beyond the model's normative
            range), "error" for every other file (BVH, CSV, NPZ, .mot: there a channel map, a
            unit or a sign convention is the likelier cause).
        body_scale: "fixed" (the model's body) or "free": the segment-length scale s of the
            recorded body is estimated from the joint and end-effector columns
            (`estimate_body_scale`) and ``Recording.scale`` holds it; the checks use the
            scaled body (``simulator.scaled(s)``), as the caller should.
        max_reaches: refuse a recording of more reaches (ValueError naming ``--max-reaches``);
            None: no limit. Default `MAX_REACHES`.

    Returns:
        A `Recording`: one `Observation` per reach, in file order (float64), the warnings
        (out-of-reach goals, a systematic ee offset) and ``info``.

    Raises:
        ValueError: starting with the file name (or the flag) and naming the column and the CSV
            line (the header is line 1), NPZ row or C3D frame, for every malformed file.
    """
    noise = NoiseModel() if noise is None else noise
    if not isinstance(noise, NoiseModel):
        raise TypeError(f"noise: expected a NoiseModel, got {type(noise).__name__}")
    if resample is not None and resample not in RESAMPLE_MODES:
        raise ValueError(f"resample: expected one of {RESAMPLE_MODES} or None, got {resample!r}")
    if ee_units is not None and ee_units not in EE_UNITS:
        raise ValueError(f"ee_units: expected one of {tuple(EE_UNITS)}, got {ee_units!r}")
    if goal not in GOAL_MODES:
        raise ValueError(f"goal: expected one of {GOAL_MODES}, got {goal!r}")
    if max_reaches is not None and (isinstance(max_reaches, bool) or not isinstance(max_reaches, int)
                                    or max_reaches < 1):
        raise ValueError(f"--max-reaches: expected a whole number >= 1, got {max_reaches!r}")
    if out_of_range not in OUT_OF_RANGE_MODES:
        raise ValueError(f"out_of_range: expected one of {OUT_OF_RANGE_MODES}, got {out_of_range!r}")
    clip = out_of_range == "clip" or (out_of_range == "auto" and markers is not None)
    if body_scale not in ("fixed", "free"):
        raise ValueError(f"body_scale: expected 'fixed' or 'free', got {body_scale!r}")
    path = Path(path)
    info: dict = {"goal": goal}
    warns: list[str] = []
    events = None
    track = None  # a measured hand path for --reaches auto (a marker session's hand markers)
    if path.suffix.lower() == ".c3d":
        if ee_units is not None:
            raise ValueError(f"--ee-units: a C3D file's units come from its POINT:UNITS ({path}); drop --ee-units")
        if not path.is_file():
            raise ValueError(f"{path}: no such file")
        if markers is not None:
            table, c3d = _read_c3d_isb(path, simulator, markers, marker_map, side, ee_markers, frame_markers)
            track = (c3d["hand_track"], c3d["hand_track_source"])
            info["joint_angles"] = (f"ISB landmarks ({marker_map}), {side or 'right'} arm, relative to the "
                                    f"thorax (camo_sbi.io.isb)")
        else:
            table, c3d = _read_c3d(path, ee_markers, frame_markers)
            info["ee_marker"] = "+".join(ee_markers)
        events = c3d.get("events", [])
        info["ee_units"] = f"{c3d['units']} (POINT:UNITS)"
        warns.extend(c3d.get("warnings", []))
        if frame_markers:
            frame = frame_from_markers(c3d["markers"], frame_markers)
    elif path.suffix.lower() == ".bvh":
        from camo_sbi.io.bvh import bvh_sources, load_bvh_map, read_bvh

        if bvh_map is None:
            raise ValueError(f"--bvh-map: a BVH file ({path}) needs the mapping from its channels to the model's "
                             f"joints (see docs/user-guide/motion-capture.md)")
        if not path.is_file():
            raise ValueError(f"{path}: no such file")
        if degrees:
            raise ValueError(f"--degrees: a BVH file's channels are in degrees and read as such ({path}); drop "
                             f"--degrees")
        mapping = load_bvh_map(bvh_map, list(simulator.joint_names))
        d = read_bvh(path, mapping)
        frames = d.pop("frames")
        table = _Table(path, d, frames, "frame", sources=bvh_sources(mapping))
        info["bvh_map"] = str(bvh_map)
    elif path.suffix.lower() in (".mot", ".sto"):
        from camo_sbi.io.mot import read_mot

        if markers is not None or ee_markers:
            raise ValueError(f"--markers: only a C3D file has markers ({path})")
        if not path.is_file():
            raise ValueError(f"{path}: no such file")
        if degrees:
            raise ValueError(f"--degrees: an OpenSim file says its unit itself (inDegrees); drop --degrees ({path})")
        d = read_mot(path, list(simulator.joint_names))
        table = _Table(path, {REACH: np.zeros(d["time"].shape[0]), TIME: d["time"], **d["columns"]}, d["frames"],
                       "line")
        info["joint_angles"] = f"OpenSim {path.suffix} ({'degrees' if d['in_degrees'] else 'radians'})"
        if d["skipped"]:
            info["skipped_columns"] = ", ".join(d["skipped"])
    else:
        if markers is not None:
            raise ValueError(f"--markers: only a C3D file has markers ({path})")
        if ee_markers:
            raise ValueError(f"--ee-marker: only a C3D file has markers ({path})")
        if frame_markers:
            raise ValueError(f"--frame-from-markers: only a C3D file has markers ({path})")
        table = _read(path)
        info["ee_units"] = ee_units or "m"
        scale = EE_UNITS[ee_units or "m"]
        if scale != 1.0:
            for c in (*EE_COLUMNS, *GOAL_COLUMNS):
                if c in table.columns:
                    table.columns[c] = table.columns[c] * scale
    names = list(simulator.joint_names)
    angles_only = markers is not None or path.suffix.lower() in (".mot", ".sto")  # formats without goals
    if (reaches is not None or angles_only) and goal == "columns" and not any(c in table.columns for c in GOAL_COLUMNS):
        goal = info["goal"] = "final"  # reaches found in a stream: each ends at its goal
    has_q, has_ee = _layout(table, names, goal)
    if frame is not None:
        for cols in (EE_COLUMNS, GOAL_COLUMNS):
            if cols[0] in table.columns:
                p = frame.apply(np.stack([table.columns[c] for c in cols], axis=1))
                for k, c in enumerate(cols):
                    table.columns[c] = p[:, k]
        info["frame"] = frame.source
        if math.isfinite(frame.residual_m):
            info["frame_residual_mm"] = round(frame.residual_m * 1000, 2)
            if frame.residual_m > OFFSET_WARN_M:
                warns.append(f"--frame-from-markers: the markers lie {frame.residual_m * 1000:.1f} mm (RMS) from "
                             f"their model positions after the best rigid transform: check the marker positions")
    radius = reach_radius(simulator)
    _check_units(table, radius, "file" if path.suffix.lower() == ".c3d" else ee_units or "m", frame)
    segments, speed = (), None
    if reaches is not None:
        if path.suffix.lower() == ".bvh" and table.columns.get(REACH) is not None and \
                np.unique(table.columns[REACH]).size > 1:
            raise ValueError(f"--reaches: the --bvh-map file lists reaches already ({bvh_map}); give one or the other")
        table, segments, speed = _resegment(table, simulator, reaches, side, events, has_q, has_ee, degrees, noise,
                                            clip=clip, track=track)
        info["reaches"] = f"{len(segments)} found ({speed['rule']})"
    reaches = _reaches(table, goal)
    if max_reaches is not None and len(reaches) > max_reaches:
        raise ValueError(f"--max-reaches: {path} holds {len(reaches):,} reaches, more than {max_reaches:,}: every "
                         f"reach is a task of every method (--budget simulations each) and, when the recording "
                         f"has no joint columns, an IK problem; give --max-reaches {len(reaches)} to run them all")
    clipped: list[dict] = []
    q_all = _joint_values(table, simulator, degrees, noise, warns if clip else None, clipped, out_of_range) \
        if has_q else None
    ee_all = np.stack([table.columns[c] for c in EE_COLUMNS], axis=1) if has_ee else None
    if goal == "final":
        last = np.array([i[-1] for i in reaches])
        ends = (ee_all[last] if has_ee else
                simulator.forward_kinematics(torch.from_numpy(q_all[last])).to(torch.float64).numpy())
        goal_all = np.zeros((table.rows.shape[0], 3))
        for idx, g in zip(reaches, ends, strict=True):
            goal_all[idx] = g
    else:
        goal_all = np.stack([table.columns[c] for c in GOAL_COLUMNS], axis=1)
    starts = None
    if not has_q:
        s = simulator.start if start is None else start
        s = np.asarray(torch.as_tensor(s, dtype=torch.float64).numpy(), dtype=np.float64)
        if s.shape != (simulator.n_joints,):
            raise ValueError(f"start: expected shape ({simulator.n_joints},), got {tuple(s.shape)}")
        ee0 = simulator.forward_kinematics(torch.from_numpy(s)).to(torch.float64).numpy()
        tol = START_TOL_M + K_SIGMA * math.sqrt(3) * noise.sigma("cartesian")
        first = ee_all[[i[0] for i in reaches]]
        at_start = np.linalg.norm(first - ee0, axis=1) <= tol
        starts = np.broadcast_to(s, (len(reaches), s.shape[0])).copy()
        if not at_start.all():
            moved = np.flatnonzero(~at_start)
            q_ik, resid = estimate_starts(simulator, first[moved], s)
            for k, i in enumerate(moved):
                if resid[k] > tol:
                    row = reaches[i][0]
                    raise ValueError(f"{table.where('ee_x', row)}: reach {int(table.columns[REACH][row])} starts "
                                     f"{resid[k] * 1000:.1f} mm from any posture the model reaches (IK from the start "
                                     f"posture; tolerance {tol * 1000:.1f} mm): check the units (--ee-units), the "
                                     f"frame (--frame) and the end effector (--ee)")
            starts[moved] = q_ik
            info["ik_residual_mm"] = round(float(resid.max()) * 1000, 3)
        info["starts"] = (f"{int((~at_start).sum())} of {len(reaches)} estimated by IK of the first sample "
                          f"(the others at the start posture)" if not at_start.all() else "the start posture")
    else:
        info["starts"] = "observed (first row of each reach)"
    scale = 1.0
    if body_scale == "free":
        if not (has_q and has_ee):
            raise ValueError(f"--body-scale: free estimates the body's size from the joint and the end-effector "
                             f"columns together; {path} has only {'joint' if has_q else 'end-effector'} columns")
        scale, lo, hi = estimate_body_scale(simulator, q_all, ee_all, reaches)
        if not BODY_SCALE_RANGE[0] <= scale <= BODY_SCALE_RANGE[1]:
            raise ValueError(f"--body-scale: the recorded body is {scale:.3f} times the model's, outside "
                             f"[{BODY_SCALE_RANGE[0]}, {BODY_SCALE_RANGE[1]}]: another model (--urdf, --height)?")
        info["body_scale"] = round(scale, 4)
        info["body_scale_90"] = [round(lo, 4), round(hi, 4)]
        simulator = simulator.scaled(scale)
    if has_q and has_ee:
        if body_scale == "fixed":
            _hint_body_scale(table, simulator, q_all, ee_all, reaches, noise)
            s_fit, s_lo, s_hi = estimate_body_scale(simulator, q_all, ee_all, reaches)
            if abs(s_fit - 1) > BODY_SCALE_WARN and not s_lo <= 1.0 <= s_hi:
                warns.append(f"{table.path}: the recording fits a body {s_fit:.3f} times the model's size (90% "
                             f"interval {s_lo:.3f}-{s_hi:.3f}): the limits of the model's body will be off; "
                             f"use --body-scale free")
        w = _check_ee_matches_fk(table, simulator, q_all, ee_all, noise)
        if w:
            warns.append(w)
    gnorm = np.linalg.norm(goal_all[[i[0] for i in reaches]], axis=1)
    far = np.flatnonzero(gnorm > radius * (1 + REACH_MARGIN) + 0.01)
    if far.size:
        k = int(far[np.argmax(gnorm[far])])
        warns.append(f"{table.where(GOAL_COLUMNS[0] if goal != 'final' else EE_COLUMNS[0], reaches[k][0])}: "
                     f"{far.size} of {len(reaches)} goals out of the model's reach: reach "
                     f"{int(table.columns[REACH][reaches[k][0]])}'s goal is {gnorm[k]:.3f} m from the base, "
                     f"{gnorm[k] - radius:.3f} m beyond the farthest point the model reaches ({radius:.3f} m over "
                     f"{REACH_SAMPLES} sampled postures)")
    timed = TIME in table.columns
    if timed:
        dts = np.concatenate([np.diff(table.columns[TIME][i]) for i in reaches])
        dt = float(np.median(dts))
        info["sample_interval_s"] = dt
    obs = []
    for r, idx in enumerate(reaches):
        q = q_all[idx].copy() if has_q else None
        ee = ee_all[idx].copy() if has_ee else None
        if timed:
            t_old, t_new = _uniform_in_time(table.columns[TIME][idx], dt)
            q = None if q is None else np.vstack([q[:1], _interp_rows(q, t_old, t_new)[1:]])
            ee = None if ee is None else _interp_rows(ee, t_old, t_new)
        q = None if q is None else torch.from_numpy(q)
        st = q[0].clone() if has_q else torch.from_numpy(starts[r].copy())
        ee = None if ee is None else torch.from_numpy(ee)
        obs.append(Observation(st, torch.from_numpy(goal_all[idx[0]].copy()), q, ee))
    obs = tuple(obs)
    if resample is None:
        return Recording(obs, tuple(warns), info, scale, segments, speed, tuple(clipped))
    r = estimate_rate(obs, simulator) if rate is None else float(rate)
    if not (math.isfinite(r) and r > 0):
        raise ValueError(f"rate: expected a number > 0, got {rate!r}")
    info["rate"] = round(r, 4)
    return Recording(tuple(resample_to_controller(o, simulator, mode=resample, rate=r) for o in obs),
                     tuple(warns), info, scale, segments, speed, tuple(clipped))


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
                         f"posture or none; the model's joints: {', '.join(names)})")
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
