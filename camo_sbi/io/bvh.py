"""BVH joint-angle recordings (animation, HRI and motion-capture exports): the only bvhio import.

A BVH file holds, per frame, each skeleton joint's rotation channels (degrees). A small JSON
mapping file (``--bvh-map``) says which channel is which model joint::

    {"joints": {"<model joint>": {"bvh": "<BVH joint>", "channel": "Xrotation",
                                  "sign": -1, "offset_deg": 0.0}, ...},
     "reaches": [[0, 120], [121, 260]]}

Every actuated joint of the model needs an entry (``sign`` defaults to 1, ``offset_deg`` to
0): model angle = sign * channel + offset. ``reaches`` lists inclusive frame ranges, one per
reach (default: the whole file is one reach). Each frame's channel values are recovered from
bvhio's per-frame rotation in the joint's own channel order, so any rotation order works.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["bvh_sources", "load_bvh_map", "read_bvh"]

_AXES = {"Xrotation": 0, "Yrotation": 1, "Zrotation": 2}


def load_bvh_map(path, joint_names, flag: str = "--bvh-map") -> dict:
    """The mapping file ``path`` checked against the model's ``joint_names``."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))
    except OSError as exc:
        raise ValueError(f"{flag} {path}: cannot read ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise ValueError(f"{flag} {path}: not a JSON file ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("joints"), dict):
        raise ValueError(f"{flag} {path}: expected a JSON object with a 'joints' object (model joint -> BVH channel)")
    joints = {}
    for j in joint_names:
        e = data["joints"].get(j)
        if not isinstance(e, dict) or not isinstance(e.get("bvh"), str):
            missing = [k for k in joint_names if not isinstance(data["joints"].get(k), dict)]
            raise ValueError(f"{flag} {path}: joint {j!r} is missing (every model joint needs "
                             f'{{"bvh": NAME, "channel": "Xrotation|Yrotation|Zrotation"}}; the model\'s joints, '
                             f"in order: {', '.join(joint_names)}; missing: {', '.join(missing)})")
        if e.get("channel") not in _AXES:
            raise ValueError(f"{flag} {path}: joint {j!r}: channel {e.get('channel')!r} is not one of {', '.join(_AXES)}")
        sign, off = e.get("sign", 1), e.get("offset_deg", 0.0)
        if sign not in (1, -1) or isinstance(sign, bool):
            raise ValueError(f"{flag} {path}: joint {j!r}: sign must be 1 or -1, got {sign!r}")
        if isinstance(off, bool) or not isinstance(off, (int, float)) or not np.isfinite(off):
            raise ValueError(f"{flag} {path}: joint {j!r}: offset_deg must be a number, got {off!r}")
        joints[j] = {"bvh": e["bvh"], "channel": e["channel"], "sign": int(sign), "offset_deg": float(off)}
    extra = sorted(set(data["joints"]) - set(joint_names))
    if extra:
        raise ValueError(f"{flag} {path}: joint {extra[0]!r} is not a joint of the model ({', '.join(joint_names)})")
    reaches = data.get("reaches")
    if reaches is not None:
        ok = isinstance(reaches, list) and all(isinstance(r, list) and len(r) == 2 and all(
            isinstance(v, int) and not isinstance(v, bool) for v in r) and 0 <= r[0] < r[1] for r in reaches)
        if not ok or not reaches:
            raise ValueError(f"{flag} {path}: 'reaches' must be a list of [first, last] frame numbers (first < last)")
    return {"joints": joints, "reaches": reaches, "path": str(path)}


def bvh_sources(mapping: dict) -> dict:
    """{model joint: {"what": "BVH channel J.Xrotation", "entry": "--bvh-map FILE entry 'joint' (sign s,
    offset_deg o)", "raw": model angle [rad] -> the channel's value [deg]}} for error messages."""
    out = {}
    for j, e in mapping["joints"].items():
        out[j] = {"what": f"BVH channel {e['bvh']}.{e['channel']}",
                  "entry": f"--bvh-map {mapping['path']} entry {j!r} (sign {e['sign']}, offset_deg {e['offset_deg']:g}: "
                           f"its channel, sign and offset_deg)",
                  "raw": lambda v, s=e["sign"], o=e["offset_deg"]: (float(np.degrees(v)) - o) / s}
    return out


def read_bvh(path, mapping: dict) -> dict:
    """{"time" (F,), "reach" (F,), "frames" (F,), <model joint>: (F,) radians} of the frames
    that belong to a reach."""
    import warnings

    with warnings.catch_warnings():  # bvhio's own `import glm` (PyGLM's PendingDeprecationWarning)
        warnings.simplefilter("ignore", PendingDeprecationWarning)
        import bvhio

    path = Path(path)
    try:
        bvh = bvhio.readAsBvh(str(path))
    except Exception as exc:  # bvhio raises bare Exceptions and IndexErrors on malformed files  # noqa: BLE001
        raise ValueError(f"{path}: cannot read as BVH ({type(exc).__name__}: {exc})") from None
    by_name = {}
    stack = [bvh.Root]
    while stack:
        j = stack.pop()
        by_name[j.Name] = j
        stack.extend(j.Children)
    n = int(bvh.FrameCount)
    dt = float(bvh.FrameTime)
    if n < 2 or not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"{path}: has {n} frames of {dt!r} s; a reach needs two or more frames")
    cols = {}
    for model_joint, e in mapping["joints"].items():
        bj = by_name.get(e["bvh"])
        if bj is None:
            raise ValueError(f"--bvh-map {mapping['path']}: joint {model_joint!r}: BVH joint {e['bvh']!r} is not in "
                             f"{path} (its joints: {', '.join(by_name)})")
        chans = [c for c in bj.Channels if c in _AXES]
        if e["channel"] not in chans:
            raise ValueError(f"--bvh-map {mapping['path']}: joint {model_joint!r}: BVH joint {e['bvh']!r} has no "
                             f"{e['channel']} channel (it has: {', '.join(bj.Channels)})")
        order = "".join(c[0] for c in chans)[::-1]  # intrinsic channel order = reversed extrinsic order
        axis = _AXES[e["channel"]]
        deg = np.array([float(k.getEuler(order=order, extrinsic=True)[axis]) for k in bj.Keyframes[:n]])
        cols[model_joint] = np.radians(e["sign"] * deg + e["offset_deg"])
    ranges = mapping["reaches"] or [[0, n - 1]]
    frames, reach = [], []
    for r, (a, b) in enumerate(ranges):
        if b >= n:
            raise ValueError(f"--bvh-map {mapping['path']}: reach {r}: frame {b} is past the last frame of {path} "
                             f"({n - 1})")
        frames.append(np.arange(a, b + 1))
        reach.append(np.full(b - a + 1, r, dtype=np.float64))
    idx = np.concatenate(frames)
    return {"time": idx * dt, "reach": np.concatenate(reach), "frames": idx,
            **{k: v[idx] for k, v in cols.items()}}
