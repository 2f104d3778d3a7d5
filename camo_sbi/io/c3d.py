"""C3D motion-capture files (Vicon, Qualisys, OptiTrack exports): the only ezc3d import.

`read_c3d` returns the end-effector marker's track (the mean of several markers when more
than one is named) in metres (units from the file's ``POINT:UNITS``), with each frame's time
in seconds (``POINT:RATE``), split into reaches at the frames where a named marker is missing
(a gap in the recording separates two reaches). The lab frame is kept: `camo_sbi.io.frames`
maps it to the model's base.

A damaged C3D can crash ezc3d (a segmentation fault in its C++ parser: a few flipped bytes in the
parameter section do it) or make it allocate without bound. So every file is first opened by
ezc3d in a child process (`_probe`: no torch, an address-space limit that grows with the
file's size, `PROBE_MEMORY_BYTES` and up, and a time limit, `PROBE_TIMEOUT_S` and up); only a
file that opens there is read in this process. A crash, a timeout or an error there is a
ValueError naming the file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["UNITS", "c3d_events", "c3d_subject_height", "read_c3d", "read_c3d_points", "write_c3d_points"]

UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}

PROBE_TIMEOUT_S = 20
"""The child's time limit is this plus one second per 10 MB of file (ezc3d reads ~10 MB/s)."""
PROBE_MEMORY_BYTES = 512 << 20
"""The child's address-space limit is this plus `PROBE_BYTES_PER_FILE_BYTE` times the file's size
(a 12.8 MB file reads within 256 MiB: a damaged parameter section that asks for more fails there,
in ~3 s, instead of filling this process's memory)."""
PROBE_BYTES_PER_FILE_BYTE = 32
_PROBE = ("import sys\n"
          "try:\n"
          "    import resource\n"
          "    resource.setrlimit(resource.RLIMIT_AS, (int(sys.argv[2]), int(sys.argv[2])))\n"
          "except (ImportError, ValueError, OSError):\n"  # a system without RLIMIT_AS: no memory limit
          "    pass\n"
          "import ezc3d\n"
          "ezc3d.c3d(sys.argv[1])\n")


def _probe(path: Path) -> None:
    """Open ``path`` with ezc3d in a child process first; ValueError naming it when that crashes,
    runs out of memory or time, or fails."""
    import subprocess
    import sys

    try:
        size = path.stat().st_size
        limit = PROBE_MEMORY_BYTES + PROBE_BYTES_PER_FILE_BYTE * size
        timeout = PROBE_TIMEOUT_S + size / 1e7
        r = subprocess.run([sys.executable, "-I", "-c", _PROBE, str(path), str(limit)],
                           capture_output=True, timeout=timeout, text=True, errors="replace",
                           stdin=subprocess.DEVNULL)
    except OSError as exc:
        raise ValueError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except subprocess.TimeoutExpired:
        raise ValueError(f"{path}: cannot read as C3D (the reader took more than {timeout:.3g} s on it: a "
                         f"damaged file?)") from None
    if r.returncode < 0:
        raise ValueError(f"{path}: cannot read as C3D (the C3D reader crashed on it, signal {-r.returncode}: a "
                         f"damaged file)")
    if r.returncode != 0:
        last = (r.stderr.strip().splitlines() or [f"exit status {r.returncode}"])[-1]
        raise ValueError(f"{path}: cannot read as C3D ({' '.join(last.split())[:200]})")


def _param(c3d, group: str, name: str, path: Path):
    try:
        return c3d["parameters"][group][name]["value"]
    except KeyError:
        raise ValueError(f"{path}: parameter {group}:{name} is missing (not a C3D point file?)") from None


def _check_complete(path: Path, c3d) -> int | None:
    """ValueError when the file holds fewer frames than its header declares (a cut-off file:
    ezc3d reads what is there and quietly shrinks its header to match). The frame count, data
    start and counts of the header's first 24 bytes are read here; the sample size comes from
    POINT:SCALE (negative: 4-byte floats, else 2-byte integers)."""
    import struct

    try:
        with open(path, "rb") as fh:
            head, proc = fh.read(512), b""
            size = os.fstat(fh.fileno()).st_size
            if head:  # the processor type: byte 4 of the parameter section (its block is byte 1)
                fh.seek(max(head[0] - 1, 0) * 512 + 3)
                proc = fh.read(1)
    except OSError as exc:
        raise ValueError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if len(head) < 24 or not proc:
        raise ValueError(f"{path}: cut off inside its header ({size} bytes)")
    endian = ">" if proc[0] == 86 else "<"  # 84 Intel, 85 DEC (little-endian integers), 86 MIPS
    _, n_points, n_analog, first, last, _, _, _, data_block = struct.unpack(f"{endian}9H", head[:18])
    if last < first or data_block < 1:
        return None
    scale = np.asarray(_param(c3d, "POINT", "SCALE", path), dtype=np.float64).reshape(-1)
    sample = 4 if scale.size and scale[0] < 0 else 2
    frame_bytes = (4 * n_points + n_analog) * sample
    if frame_bytes == 0:
        return None
    declared = last - first + 1
    held = max(size - (data_block - 1) * 512, 0) // frame_bytes
    if held < declared and last != 0xFFFF:  # 65535: a long trial keeps its count in its parameters
        raise ValueError(f"{path}: its header declares {declared} frames but the file holds {held} complete ones "
                         f"({size:,} bytes; cut off?)")
    return max(size - (data_block - 1) * 512 - 511, 0) // frame_bytes  # frames held beyond any block padding


def read_c3d(path, ee_markers, extra_markers=()) -> dict:
    """{"time" (F,), "reach" (F,), "ee" (F, 3) [m], "frames" (F,), "markers" {name: (3,) mean lab
    position [m]} for ``extra_markers``, "units": the file's unit, "warnings": [str], "events"} for the
    frames where every end-effector marker is present; reaches are runs of such frames (>= 2 frames).
    A warning says when the file holds more frames than its header declares (and ezc3d reads)."""
    path = Path(path)
    c3d = _open(path)
    held = _check_complete(path, c3d)
    labels, unit, rate, pts = _points(c3d, path)  # pts: (3, markers, frames) in metres

    def column(name: str, flag: str) -> np.ndarray:
        if name not in labels:
            raise ValueError(f"{flag}: marker {name!r} is not in {path} (its markers: {', '.join(labels)})")
        return pts[:, labels.index(name), :].T  # (F, 3)

    if not ee_markers:
        raise ValueError(f"--ee-marker: a C3D recording needs the end-effector marker(s) (its markers: "
                         f"{', '.join(labels)})")
    tracks = np.stack([column(m, "--ee-marker") for m in ee_markers])  # (k, F, 3)
    present = np.isfinite(tracks).all(axis=(0, 2)) & ~(tracks == 0).all(axis=(0, 2))
    ee = tracks.mean(axis=0)
    first = int(c3d["header"]["points"]["first_frame"])
    frame_no = np.arange(ee.shape[0]) + first
    run_id = np.cumsum(np.r_[True, ~present[:-1]] & present)  # a new reach after every gap
    keep = present.copy()
    for r in np.unique(run_id[present]):
        if (present & (run_id == r)).sum() < 2:
            keep &= run_id != r
    if not keep.any():
        raise ValueError(f"--ee-marker: marker(s) {', '.join(ee_markers)} of {path} have no run of two or more "
                         f"frames")
    reach = np.unique(run_id[keep], return_inverse=True)[1]
    markers = {}
    for m in extra_markers:
        x = column(m, "--frame-from-markers")
        ok = np.isfinite(x).all(axis=1) & ~(x == 0).all(axis=1)
        if not ok.any():
            raise ValueError(f"--frame-from-markers: marker {m!r} is never visible in {path}")
        markers[m] = x[ok].mean(axis=0)
    warnings = []
    if held is not None and held > pts.shape[2]:
        warnings.append(f"{path}: holds data for {held:,} frames but its header declares {pts.shape[2]:,} (a 16-bit "
                        f"count stops at 65,535): only those {pts.shape[2]:,} were read")
    return {"time": frame_no[keep] / rate, "reach": reach.astype(np.float64), "ee": ee[keep],
            "frames": frame_no[keep], "markers": markers, "units": unit, "warnings": warnings,
            "events": c3d_events(c3d)}


def c3d_events(c3d) -> list[tuple[float, str, str]]:
    """The file's events as (time [s], label, context), from EVENT:TIMES (minutes, seconds rows),
    EVENT:LABELS and EVENT:CONTEXTS; [] when the file has none."""
    try:
        group = c3d["parameters"]["EVENT"]
        times = np.asarray(group["TIMES"]["value"], dtype=np.float64)
    except KeyError:
        return []
    if times.size == 0:
        return []
    times = times.reshape(2, -1) if times.ndim == 1 else times
    labels = [str(v).strip() for v in group.get("LABELS", {}).get("value", [])]
    contexts = [str(v).strip() for v in group.get("CONTEXTS", {}).get("value", [])]
    n = times.shape[1]
    labels += [""] * (n - len(labels))
    contexts += [""] * (n - len(contexts))
    return [(float(times[0, k] * 60.0 + times[1, k]), labels[k], contexts[k]) for k in range(n)
            if np.isfinite(times[:, k]).all()]


def _points(c3d, path: Path) -> tuple[list[str], str, float, np.ndarray]:
    """(labels, unit, rate [Hz], (3, markers, frames) positions in metres) of an opened C3D."""
    labels = [str(s).strip() for s in _param(c3d, "POINT", "LABELS", path)]
    units_v = _param(c3d, "POINT", "UNITS", path)
    unit = str(units_v[0]).strip().lower() if len(units_v) else ""
    if unit not in UNITS:
        raise ValueError(f"{path}: parameter POINT:UNITS is {unit!r}; expected one of {', '.join(UNITS)}")
    rate = float(np.asarray(_param(c3d, "POINT", "RATE", path)).reshape(-1)[0])
    if not (np.isfinite(rate) and rate > 0):
        raise ValueError(f"{path}: parameter POINT:RATE is {rate!r}; expected a frame rate > 0")
    return labels, unit, rate, np.asarray(c3d["data"]["points"], dtype=np.float64)[:3] * UNITS[unit]


def _open(path: Path):
    """The C3D file ``path`` opened by ezc3d, after a probe in a child process (`_probe`: a file
    that crashes or exhausts ezc3d is refused naming it, never taking this process down)."""
    import ezc3d

    if not path.is_file():
        raise ValueError(f"{path}: no such file")
    _probe(path)
    try:
        return ezc3d.c3d(str(path))
    except (OSError, RuntimeError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read as C3D ({exc})") from None


def read_c3d_points(path, labels, flag: str = "--marker-map") -> dict:
    """{"time" (F,), "frames" (F,), "points" {label: (F, 3) [m], NaN where the marker is missing},
    "units", "events"} for the markers ``labels`` (each must be in the file: ValueError naming
    ``flag``, the label and the file's markers)."""
    path = Path(path)
    c3d = _open(path)
    _check_complete(path, c3d)
    names, unit, rate, pts = _points(c3d, path)
    out = {}
    for lab in labels:
        if lab not in names:
            raise ValueError(f"{flag}: marker {lab!r} is not in {path} (its markers: {', '.join(names)})")
        x = pts[:, names.index(lab), :].T.copy()
        x[~np.isfinite(x).all(axis=1) | (x == 0).all(axis=1)] = np.nan  # a missing marker: NaN or zeros
        out[lab] = x
    first = int(c3d["header"]["points"]["first_frame"])
    frames = np.arange(pts.shape[2]) + first
    return {"time": frames / rate, "frames": frames, "points": out, "units": unit, "events": c3d_events(c3d)}


def c3d_subject_height(path) -> float | None:
    """The subject's standing height [m] from PROCESSING:Height (Vicon's, millimetres when above
    3, else metres), or None when the file has none."""
    c3d = _open(Path(path))
    try:
        v = np.asarray(c3d["parameters"]["PROCESSING"]["Height"]["value"], dtype=np.float64).reshape(-1)
    except (KeyError, TypeError, ValueError):
        return None
    if v.size == 0 or not np.isfinite(v[0]) or v[0] <= 0:
        return None
    return float(v[0] / 1000.0 if v[0] > 3.0 else v[0])


def write_c3d_points(path, points: dict, rate: float, *, events=(), height_m: float | None = None) -> Path:
    """A C3D file of marker tracks ``points`` {label: (F, 3) metres, NaN = missing} written in mm
    at ``rate`` Hz, with ``events`` [(time [s], label, context)] and PROCESSING:Height [mm]."""
    import ezc3d

    labels = list(points)
    n = next(iter(points.values())).shape[0]
    pts = np.ones((4, len(labels), n))
    for k, lab in enumerate(labels):
        x = np.asarray(points[lab], dtype=np.float64) * 1000.0
        pts[:3, k, :] = np.where(np.isfinite(x), x, 0.0).T  # a missing marker is written as zeros
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(rate)]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(labels)
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    c["data"]["points"] = pts
    for t, label, context in events:
        c.add_event([0, float(t)], context=context, label=label)
    if height_m is not None:
        c.add_parameter("PROCESSING", "Height", [float(height_m) * 1000.0])
    path = Path(path)
    c.write(str(path))
    return path
