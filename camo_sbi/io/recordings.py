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

Resampling to the controller's step (`camo_sbi.io.resample`): the recorder's rate is estimated
from the whole file (`estimate_rate`) and each reach is interpolated to the controller's step
(`resample_to_controller`).

The loader's parts: the schema and its checks (`camo_sbi.io.schema`), the format dispatch
(`camo_sbi.io.formats`), the model's geometry (`camo_sbi.io.geometry`: reach, units, FK, IK
of the starts, body scale) and the resampling (`camo_sbi.io.resample`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from camo_sbi.io.formats import EE_UNITS, read_csv_or_npz, read_recording_table
from camo_sbi.io.frames import Frame
from camo_sbi.io.geometry import (
    BODY_SCALE_RANGE,
    BODY_SCALE_WARN,
    OFFSET_WARN_M,
    REACH_MARGIN,
    REACH_SAMPLES,
    START_TOL_M,
    check_ee_matches_fk,
    check_units,
    estimate_body_scale,
    estimate_starts,
    hint_body_scale,
    reach_radius,
)
from camo_sbi.io.resample import (
    RESAMPLE_MODES,
    estimate_rate,
    interp_rows,
    resample_to_controller,
    uniform_in_time,
)
from camo_sbi.io.schema import (
    EE_COLUMNS,
    GOAL_COLUMNS,
    K_SIGMA,
    REACH,
    TIME,
    Table,
    check_layout,
    joint_values,
    reach_rows,
)
from camo_sbi.task import NoiseModel, Observation

__all__ = ["GOAL_MODES", "MAX_REACHES", "OUT_OF_RANGE_MODES", "Recording", "load_goals", "load_recording",
           "load_recordings"]

GOAL_MODES = ("columns", "final")
OUT_OF_RANGE_MODES = ("auto", "clip", "error")
"""``out_of_range``: "auto" (clip the ISB landmarks' angles, refuse other files), "clip", "error"."""

MAX_REACHES = 2000
"""A recording with more reaches is refused unless ``max_reaches`` (``--max-reaches``) allows it:
every reach is a task of every method (``--budget`` simulations each) and an IK problem."""


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


def _resegment(table: Table, simulator, spec: str, side, events, has_q: bool, has_ee: bool, degrees: bool,
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
        q = joint_values(table, simulator, degrees, noise, [] if clip else None)  # warned when loaded
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
    out = Table(table.path, cols, table.rows[keep], table.row_word, table.sources)
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
    table, events, track, frame = read_recording_table(
        path, simulator, degrees=degrees, ee_units=ee_units, markers=markers, marker_map=marker_map, side=side,
        ee_markers=ee_markers, frame_markers=frame_markers, bvh_map=bvh_map, frame=frame, info=info, warns=warns)
    names = list(simulator.joint_names)
    angles_only = markers is not None or path.suffix.lower() in (".mot", ".sto")  # formats without goals
    if (reaches is not None or angles_only) and goal == "columns" and not any(c in table.columns for c in GOAL_COLUMNS):
        goal = info["goal"] = "final"  # reaches found in a stream: each ends at its goal
    has_q, has_ee = check_layout(table, names, goal)
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
    check_units(table, radius, "file" if path.suffix.lower() == ".c3d" else ee_units or "m", frame)
    segments, speed = (), None
    if reaches is not None:
        if path.suffix.lower() == ".bvh" and table.columns.get(REACH) is not None and \
                np.unique(table.columns[REACH]).size > 1:
            raise ValueError(f"--reaches: the --bvh-map file lists reaches already ({bvh_map}); give one or the other")
        table, segments, speed = _resegment(table, simulator, reaches, side, events, has_q, has_ee, degrees, noise,
                                            clip=clip, track=track)
        info["reaches"] = f"{len(segments)} found ({speed['rule']})"
    reaches = reach_rows(table, goal)
    if max_reaches is not None and len(reaches) > max_reaches:
        raise ValueError(f"--max-reaches: {path} holds {len(reaches):,} reaches, more than {max_reaches:,}: every "
                         f"reach is a task of every method (--budget simulations each) and, when the recording "
                         f"has no joint columns, an IK problem; give --max-reaches {len(reaches)} to run them all")
    clipped: list[dict] = []
    q_all = joint_values(table, simulator, degrees, noise, warns if clip else None, clipped, out_of_range) \
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
            hint_body_scale(table, simulator, q_all, ee_all, reaches, noise)
            s_fit, s_lo, s_hi = estimate_body_scale(simulator, q_all, ee_all, reaches)
            if abs(s_fit - 1) > BODY_SCALE_WARN and not s_lo <= 1.0 <= s_hi:
                warns.append(f"{table.path}: the recording fits a body {s_fit:.3f} times the model's size (90% "
                             f"interval {s_lo:.3f}-{s_hi:.3f}): the limits of the model's body will be off; "
                             f"use --body-scale free")
        w = check_ee_matches_fk(table, simulator, q_all, ee_all, noise)
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
            t_old, t_new = uniform_in_time(table.columns[TIME][idx], dt)
            q = None if q is None else np.vstack([q[:1], interp_rows(q, t_old, t_new)[1:]])
            ee = None if ee is None else interp_rows(ee, t_old, t_new)
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


def load_goals(path, simulator, *, degrees: bool = False, noise: NoiseModel | None = None):
    """Goals to predict, from a CSV/NPZ with ``goal_x, goal_y, goal_z`` and optionally the start
    posture's joint columns (named as the model's joints; all of them or none).

    Returns (goals (M, 3) float64, starts (M, n) float64 or None). Errors name the file, the
    column and the line, as `load_recordings` does.
    """
    noise = NoiseModel() if noise is None else noise
    table = read_csv_or_npz(path)
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
    starts = torch.from_numpy(joint_values(table, simulator, degrees, noise)) if has_q else None
    return goals, starts
