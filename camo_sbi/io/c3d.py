"""C3D motion-capture files (Vicon, Qualisys, OptiTrack exports): the only ezc3d import.

`read_c3d` returns the end-effector marker's track (the mean of several markers when more
than one is named) in metres (units from the file's ``POINT:UNITS``), with each frame's time
in seconds (``POINT:RATE``), split into reaches at the frames where a named marker is missing
(a gap in the recording separates two reaches). The lab frame is kept: `camo_sbi.io.frames`
maps it to the model's base.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["UNITS", "c3d_events", "read_c3d"]

UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}


def _param(c3d, group: str, name: str, path: Path):
    try:
        return c3d["parameters"][group][name]["value"]
    except KeyError:
        raise ValueError(f"{path}: parameter {group}:{name} is missing (not a C3D point file?)") from None


def read_c3d(path, ee_markers, extra_markers=()) -> dict:
    """{"time" (F,), "reach" (F,), "ee" (F, 3) [m], "frames" (F,), "markers" {name: (3,) mean lab
    position [m]} for ``extra_markers``, "units": the file's unit} for the frames where every
    end-effector marker is present; reaches are runs of such frames (>= 2 frames)."""
    import ezc3d

    path = Path(path)
    try:
        c3d = ezc3d.c3d(str(path))
    except (OSError, RuntimeError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read as C3D ({exc})") from None
    labels = [str(s).strip() for s in _param(c3d, "POINT", "LABELS", path)]
    units_v = _param(c3d, "POINT", "UNITS", path)
    unit = str(units_v[0]).strip().lower() if len(units_v) else ""
    if unit not in UNITS:
        raise ValueError(f"{path}: parameter POINT:UNITS is {unit!r}; expected one of {', '.join(UNITS)}")
    rate = float(np.asarray(_param(c3d, "POINT", "RATE", path)).reshape(-1)[0])
    if not (np.isfinite(rate) and rate > 0):
        raise ValueError(f"{path}: parameter POINT:RATE is {rate!r}; expected a frame rate > 0")
    pts = np.asarray(c3d["data"]["points"], dtype=np.float64)[:3] * UNITS[unit]  # (3, markers, frames)

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
    return {"time": frame_no[keep] / rate, "reach": reach.astype(np.float64), "ee": ee[keep],
            "frames": frame_no[keep], "markers": markers, "units": unit, "events": c3d_events(c3d)}


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
