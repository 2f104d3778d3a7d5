"""The format dispatch of the recording loader: a file read into a `Table` by its format (C3D,
BVH, OpenSim .mot/.sto, else CSV or NPZ: `read_recording_table`), with the checks of the options
each format refuses. A CSV is read as UTF-8 (a BOM is accepted); a binary file, a non-UTF-8 file,
a field over `CSV_FIELD_LIMIT` characters, or an .npz that is not a zip archive is one error
naming the file.
"""

from __future__ import annotations

import csv
import io
import zipfile
from pathlib import Path

import numpy as np

from camo_sbi.io.frames import Frame, frame_from_markers
from camo_sbi.io.schema import EE_COLUMNS, GOAL_COLUMNS, REACH, TIME, Table
from camo_sbi.io.text import read_text

__all__ = ["CSV_FIELD_LIMIT", "EE_UNITS", "c3d_isb_table", "c3d_table", "read_csv", "read_csv_or_npz", "read_npz",
           "read_recording_table"]

EE_UNITS = {"m": 1.0, "mm": 1e-3}


CSV_FIELD_LIMIT = 131_072
"""Python's csv module refuses longer fields; a recording's numbers are never that long."""


def read_csv(path: Path) -> Table:
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
    return Table(path, {c: data[:, i] for i, c in enumerate(header)}, np.asarray(lines), "line")


def read_npz(path: Path) -> Table:
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
    return Table(path, {k: a.astype(np.float64) for k, a in arrays.items()}, np.arange(n), "row")


def c3d_table(path: Path, ee_markers, frame_markers) -> tuple[Table, dict]:
    from camo_sbi.io.c3d import read_c3d

    d = read_c3d(path, ee_markers, list(frame_markers or ()))
    cols = {REACH: d["reach"], TIME: d["time"]}
    for k, c in enumerate(EE_COLUMNS):
        cols[c] = d["ee"][:, k]
    return Table(path, cols, d["frames"], "frame"), d


def c3d_isb_table(path: Path, simulator, markers: str, marker_map, side, ee_markers, frame_markers):
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
    return Table(path, cols, d["frames"][present], "frame", sources=src), d


def read_csv_or_npz(path) -> Table:
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such file")
    return read_npz(path) if path.suffix.lower() == ".npz" else read_csv(path)


def read_recording_table(path: Path, simulator, *, degrees: bool, ee_units: str | None, markers: str | None,
                         marker_map, side: str | None, ee_markers, frame_markers: dict | None, bvh_map,
                         frame: Frame | None, info: dict, warns: list[str]):
    """The recording file ``path`` as a `Table`, by its format (`load_recording`'s arguments);
    ``info`` and ``warns`` receive what the reader did and found. Returns (table, the C3D file's
    events or None, a measured hand track (positions, what it is) or None, the frame: ``frame``,
    or the one fitted to ``frame_markers`` in a C3D file)."""
    events = None
    track = None  # a measured hand path for --reaches auto (a marker session's hand markers)
    if path.suffix.lower() == ".c3d":
        if ee_units is not None:
            raise ValueError(f"--ee-units: a C3D file's units come from its POINT:UNITS ({path}); drop --ee-units")
        if not path.is_file():
            raise ValueError(f"{path}: no such file")
        if markers is not None:
            table, c3d = c3d_isb_table(path, simulator, markers, marker_map, side, ee_markers, frame_markers)
            track = (c3d["hand_track"], c3d["hand_track_source"])
            info["joint_angles"] = (f"ISB landmarks ({marker_map}), {side or 'right'} arm, relative to the "
                                    f"thorax (camo_sbi.io.isb)")
        else:
            table, c3d = c3d_table(path, ee_markers, frame_markers)
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
        table = Table(path, d, frames, "frame", sources=bvh_sources(mapping))
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
        table = Table(path, {REACH: np.zeros(d["time"].shape[0]), TIME: d["time"], **d["columns"]}, d["frames"],
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
        table = read_csv_or_npz(path)
        info["ee_units"] = ee_units or "m"
        scale = EE_UNITS[ee_units or "m"]
        if scale != 1.0:
            for c in (*EE_COLUMNS, *GOAL_COLUMNS):
                if c in table.columns:
                    table.columns[c] = table.columns[c] * scale
    return table, events, track, frame
