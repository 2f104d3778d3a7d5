"""BVH joint-angle recordings (animation, HRI and motion-capture exports), read by a strict parser.

A BVH file holds, per frame, each skeleton joint's rotation channels (degrees). A small JSON
mapping file (``--bvh-map``) says which channel is which model joint::

    {"joints": {"<model joint>": {"bvh": "<BVH joint>", "channel": "Xrotation",
                                  "sign": -1, "offset_deg": 0.0}, ...},
     "reaches": [[0, 120], [121, 260]]}

Every actuated joint of the model needs an entry (``sign`` defaults to 1, ``offset_deg`` to
0): model angle = sign * channel + offset. ``reaches`` lists inclusive frame ranges, one per
reach (default: the whole file is one reach); they may not overlap. The mapped channel's value is
read as written in the file (degrees), whatever the joint's rotation order.

`parse_bvh` reads the file itself, one line after another (no recursion, no loop that can
outlast the file): an empty or cut-off file, a missing MOTION section, or fewer (or more)
motion rows than ``Frames:`` declares is a ValueError naming the file and the line. (bvhio,
used before, loops forever at the end of such files, and its Euler round trip returned 60
degrees for a middle channel of 120.)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from camo_sbi._files import read_json, read_text

__all__ = ["MAX_BVH_BYTES", "BvhFile", "bvh_sources", "load_bvh_map", "parse_bvh", "read_bvh"]

_AXES = {"Xrotation": 0, "Yrotation": 1, "Zrotation": 2}
_CHANNELS = {*_AXES, "Xposition", "Yposition", "Zposition"}
MAX_BVH_BYTES = 1 << 30
"""A BVH file larger than 1 GiB is refused (200,000 frames of 60 channels are ~120 MB)."""
_MAX_DEPTH = 256  # nesting of JOINTs (a human skeleton: ~10)


def load_bvh_map(path, joint_names, flag: str = "--bvh-map") -> dict:
    """The mapping file ``path`` checked against the model's ``joint_names``."""
    path = Path(path)
    data = read_json(path, f"{flag} {path}")
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
        order = sorted(range(len(reaches)), key=lambda i: reaches[i][0])
        for i, j in zip(order, order[1:], strict=False):
            if reaches[j][0] <= reaches[i][1]:
                raise ValueError(f"{flag} {path}: 'reaches' {i} {reaches[i]} and {j} {reaches[j]} overlap (frames "
                                 f"{reaches[j][0]}-{min(reaches[i][1], reaches[j][1])} would count twice); give each "
                                 "frame to one reach")
    return {"joints": joints, "reaches": reaches, "path": str(path)}


@dataclass(frozen=True)
class BvhFile:
    """A parsed BVH file: ``channels[joint]`` its channel names, ``column[joint]`` the first of its
    columns in ``motion`` (F, C) (values as written: degrees, file units), ``frame_time`` seconds."""

    channels: dict[str, tuple[str, ...]]
    column: dict[str, int]
    motion: np.ndarray
    frame_time: float


def _lines(path: Path):
    """(line number, tokens) of the non-blank lines of ``path`` (ValueError naming it)."""
    text = read_text(path, str(path), max_bytes=MAX_BVH_BYTES)
    return [(k + 1, s.split()) for k, s in enumerate(text.splitlines()) if s.strip()]


def parse_bvh(path) -> BvhFile:
    """The hierarchy and motion of the BVH file ``path``, checked line by line (see the module
    docstring): ValueError ``<path>: line N: ...`` on anything that is not a complete BVH file."""
    path = Path(path)
    lines = _lines(path)
    if not lines:
        raise ValueError(f"{path}: is empty (a BVH file starts with HIERARCHY)")
    pos = 0

    def fail(msg: str, k: int | None = None):
        k = pos if k is None else k
        where = f"line {lines[k][0]}" if k < len(lines) else "end of file"
        raise ValueError(f"{path}: {where}: {msg}")

    def take(first: str, what: str) -> list[str]:
        nonlocal pos
        if pos >= len(lines):
            fail(f"the file ends where {what} should follow (cut off?)")
        toks = lines[pos][1]
        if toks[0] != first:
            fail(f"expected {what}, found {' '.join(toks)[:60]!r}")
        pos += 1
        return toks

    def numbers(toks: list[str], n: int, what: str, k: int | None = None) -> list[float]:
        try:
            vals = [float(v) for v in toks]
        except ValueError:
            vals = []
        if len(vals) != n or not all(np.isfinite(vals)):
            fail(f"{what} needs {n} finite numbers, found {' '.join(toks)[:60]!r}", pos - 1 if k is None else k)
        return vals

    take("HIERARCHY", "HIERARCHY")
    channels: dict[str, tuple[str, ...]] = {}
    column: dict[str, int] = {}
    n_cols = 0
    opened = 0  # open joints ({ ... } blocks of ROOT/JOINT)
    kind = "ROOT"
    while True:
        toks = take(kind, f"{kind} <name>" if kind == "ROOT" else "JOINT, End Site or }")
        name = " ".join(toks[1:])
        if not name:
            fail(f"{kind} has no name", pos - 1)
        if name in channels:
            fail(f"joint {name!r} is defined twice", pos - 1)
        take("{", "{")
        opened += 1
        if opened > _MAX_DEPTH:
            fail(f"joints nested more than {_MAX_DEPTH} deep")
        numbers(take("OFFSET", "OFFSET x y z")[1:], 3, "OFFSET")
        ch = take("CHANNELS", "CHANNELS <count> <names>")
        if len(ch) < 2 or not ch[1].isdigit() or int(ch[1]) != len(ch) - 2:
            fail("CHANNELS needs its count followed by that many channel names", pos - 1)
        bad = [c for c in ch[2:] if c not in _CHANNELS]
        if bad or len(set(ch[2:])) != len(ch) - 2:
            fail(f"channel {(bad or ch[2:])[0]!r} is unknown or repeated (expected {', '.join(sorted(_CHANNELS))})",
                 pos - 1)
        channels[name], column[name] = tuple(ch[2:]), n_cols
        n_cols += len(ch) - 2
        while pos < len(lines) and lines[pos][1][0] in ("End", "}"):  # end sites and closed joints
            if lines[pos][1][0] == "End":
                pos += 1
                take("{", "{")
                numbers(take("OFFSET", "OFFSET x y z")[1:], 3, "OFFSET")
                take("}", "}")
            else:
                pos += 1
                opened -= 1
                if opened == 0:
                    break
        if opened == 0:
            break
        kind = "JOINT"
    take("MOTION", "MOTION")
    toks = take("Frames:", "Frames: <count>")
    if len(toks) != 2 or not toks[1].isdigit():
        fail(f"expected 'Frames: <count>', found {' '.join(toks)[:60]!r}", pos - 1)
    n = int(toks[1])
    toks = take("Frame", "Frame Time: <seconds>")
    if len(toks) != 3 or toks[1] != "Time:":
        fail(f"expected 'Frame Time: <seconds>', found {' '.join(toks)[:60]!r}", pos - 1)
    dt = numbers(toks[2:], 1, "Frame Time")[0]
    rows = lines[pos:]
    if len(rows) != n:
        fail(f"'Frames: {n}' declares {n} motion rows but the file holds {len(rows)}"
             + (" (cut off?)" if len(rows) < n else ""), pos - 1)
    for k, (_, toks) in enumerate(rows):
        if len(toks) != n_cols:
            fail(f"a motion row needs {n_cols} values (one per channel), found {len(toks)}", pos + k)
    try:
        motion = np.array([toks for _, toks in rows], dtype=np.float64).reshape(n, n_cols)
        bad = np.flatnonzero(~np.isfinite(motion).all(axis=1))
    except ValueError:  # a token that is not a number: find its row
        bad = [k for k, (_, toks) in enumerate(rows) if not _numbers_ok(toks)]
    if len(bad):
        numbers(rows[bad[0]][1], n_cols, "a motion row", pos + int(bad[0]))
    return BvhFile(channels, column, motion, dt)


def _numbers_ok(toks: list[str]) -> bool:
    try:
        return all(np.isfinite([float(v) for v in toks]))
    except ValueError:
        return False


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
    path = Path(path)
    bvh = parse_bvh(path)
    n, dt = bvh.motion.shape[0], bvh.frame_time
    if n < 2 or not dt > 0:
        raise ValueError(f"{path}: has {n} frames of {dt!r} s; a reach needs two or more frames")
    cols = {}
    for model_joint, e in mapping["joints"].items():
        chans = bvh.channels.get(e["bvh"])
        if chans is None:
            raise ValueError(f"--bvh-map {mapping['path']}: joint {model_joint!r}: BVH joint {e['bvh']!r} is not in "
                             f"{path} (its joints: {', '.join(bvh.channels)})")
        if e["channel"] not in chans:
            raise ValueError(f"--bvh-map {mapping['path']}: joint {model_joint!r}: BVH joint {e['bvh']!r} has no "
                             f"{e['channel']} channel (it has: {', '.join(chans)})")
        deg = bvh.motion[:, bvh.column[e["bvh"]] + chans.index(e["channel"])]
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
