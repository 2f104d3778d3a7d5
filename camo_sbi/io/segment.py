"""Reaches found in a continuous recording: by hand speed, by the file's events, or by frame ranges.

``--reaches`` (any recording with time: C3D, BVH, a CSV/NPZ with a ``time`` column)::

    auto                  segmentation by hand speed (`segment_by_speed`, thresholds below)
    events                the C3D file's own events (EVENT:TIMES / LABELS / CONTEXTS): each
                          reach runs from one event of the side's context (or "General") to the next
    0-120,121-260         explicit inclusive frame ranges (the file's frame numbers)

Hand speed (`hand_speed`): the hand's path (the end-effector track, or the model's forward
kinematics of the joint angles) low-pass filtered with a zero-phase 2nd-order Butterworth at
`CUTOFF_HZ` (6 Hz, the usual choice for upper-limb kinematics), differentiated by central
differences.

Rule "speed" (`segment_by_speed`), with these stated thresholds:

1. a movement is a run of samples whose speed exceeds `ACTIVE_SPEED` (0.05 m/s) and whose
   peak exceeds `MIN_PEAK_SPEED` (0.15 m/s);
2. walking back from the peak, its start is where the speed has fallen below
   max(`ONSET_FRACTION` (5%) x the peak, `NOISE_FACTOR` (1.5) x the median speed of the
   samples not in any run, i.e. the noise's speed at rest), moved on to the speed's local
   minimum there; its end likewise after the peak (never into the neighbouring movement);
3. movements shorter than `MIN_DURATION_S` are dropped; two movements whose cuts
   overlap are merged (a pause of less than a sample).

How close the cuts come to the true ones is measured in docs/guide/lab_session.md.

Each reach's goal is where the hand is at its end (free reaching), its start posture its
first sample. The outward reach and the return to rest are both reaches (the return's goal is
the rest position): the rule does not guess which is which, and ``reaches.csv`` lists both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ACTIVE_SPEED", "CUTOFF_HZ", "MIN_DURATION_S", "MIN_PEAK_SPEED", "ONSET_FRACTION", "Segment",
           "events_segments", "hand_speed", "parse_reaches", "ranges_segments", "segment_by_speed"]

CUTOFF_HZ = 6.0
ACTIVE_SPEED = 0.05
MIN_PEAK_SPEED = 0.15
ONSET_FRACTION = 0.05
MIN_DURATION_S = 0.15
NOISE_FACTOR = 1.5


@dataclass(frozen=True)
class Segment:
    """One reach: sample indices [first, last] (inclusive) into the recording, and how it was found."""

    first: int
    last: int
    rule: str
    peak_speed: float = float("nan")


def parse_reaches(text) -> tuple[str, list[tuple[int, int]] | None]:
    """``--reaches``: ("auto" | "events" | "frames", [(first, last), ...] for "frames")."""
    if text is None:
        return "", None
    t = str(text).strip().lower()
    if t in ("auto", "events"):
        return t, None
    ranges = []
    for part in t.split(","):
        a, sep, b = part.strip().partition("-")
        try:
            lo, hi = int(a), int(b)
        except ValueError:
            raise ValueError(f"--reaches: expected auto, events or frame ranges like 0-120,121-260, got "
                             f"{text!r}") from None
        if not sep or lo < 0 or hi <= lo:
            raise ValueError(f"--reaches: frame range {part.strip()!r} must be FIRST-LAST with 0 <= FIRST < LAST")
        ranges.append((lo, hi))
    if not ranges:
        raise ValueError("--reaches: give auto, events or frame ranges")
    for (a0, b0), (a1, _) in zip(ranges, ranges[1:], strict=False):
        if a1 <= b0:
            raise ValueError(f"--reaches: frame ranges must be in order and not overlap ({a0}-{b0} then {a1}-...)")
    return "frames", ranges


def hand_speed(time: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """(F,) speed [m/s] of the (F, 3) path sampled at ``time`` [s]: 6 Hz zero-phase low-pass, then
    central differences (the filter is skipped for fewer than 16 samples or a rate under 15 Hz)."""
    from scipy.signal import butter, filtfilt

    t = np.asarray(time, dtype=np.float64)
    x = np.asarray(pos, dtype=np.float64)
    if t.shape[0] < 3:
        return np.zeros(t.shape[0])
    dt = float(np.median(np.diff(t)))
    rate = 1.0 / dt
    if x.shape[0] >= 16 and rate > 2.5 * CUTOFF_HZ:
        b, a = butter(2, CUTOFF_HZ / (0.5 * rate))
        x = filtfilt(b, a, x, axis=0, padlen=min(3 * max(len(a), len(b)), x.shape[0] - 1))
    v = np.gradient(x, t, axis=0)
    return np.linalg.norm(v, axis=1)


def segment_by_speed(time: np.ndarray, speed: np.ndarray) -> list[Segment]:
    """The movements of a speed profile by the rule of the module docstring (sample indices)."""
    t = np.asarray(time, dtype=np.float64)
    s = np.asarray(speed, dtype=np.float64)
    active = s > ACTIVE_SPEED
    edges = np.flatnonzero(np.diff(np.r_[0, active.astype(np.int8), 0]))
    runs = [(int(a), int(b) - 1) for a, b in zip(edges[0::2], edges[1::2], strict=True)]
    runs = [(a, b) for a, b in runs if s[a: b + 1].max() > MIN_PEAK_SPEED]
    still = ~active
    floor_speed = float(np.median(s[still])) if still.any() else 0.0  # the noise's speed at rest
    out: list[Segment] = []
    for k, (a, b) in enumerate(runs):
        peak_i = a + int(np.argmax(s[a: b + 1]))
        thr = max(ONSET_FRACTION * s[peak_i], NOISE_FACTOR * floor_speed)
        floor = out[-1].last if out else 0  # never cut into the previous reach
        ceil = runs[k + 1][0] if k + 1 < len(runs) else s.shape[0] - 1
        i = _edge(t, s, peak_i, floor, thr, -1)
        j = _edge(t, s, peak_i, ceil, thr, +1)
        if out and i <= out[-1].last:  # overlapping cuts: one movement
            prev = out.pop()
            seg = Segment(prev.first, j, "speed", max(prev.peak_speed, float(s[peak_i])))
        else:
            seg = Segment(i, j, "speed", float(s[peak_i]))
        out.append(seg)
    return [g for g in out if t[g.last] - t[g.first] >= MIN_DURATION_S]


def _crossing(t: np.ndarray, s: np.ndarray, peak_i: int, stop: int, level: float, step: int) -> float | None:
    """The time (linear interpolation) where the speed, walking from the peak towards ``stop``,
    first falls below ``level`` (None: it does not)."""
    i = peak_i
    while i != stop and s[i] >= level:
        i += step
    if s[i] >= level:
        return None
    k = i - step  # the last sample above the level
    frac = (s[k] - level) / (s[k] - s[i]) if s[k] != s[i] else 0.0
    return float(t[k] + frac * (t[i] - t[k]))


def _edge(t: np.ndarray, s: np.ndarray, peak_i: int, stop: int, thr: float, step: int) -> int:
    """A movement's first (step -1) or last (step +1) sample: walking from the peak towards
    ``stop``, past the last sample whose speed is at or above ``thr``, on to the speed's local
    minimum (or ``stop``)."""
    i = peak_i
    while i != stop and s[i + step] >= thr:
        i += step
    while i != stop and s[i + step] < s[i]:  # on to the speed's minimum: the hand at rest, up to the noise
        i += step
    return i


def ranges_segments(frames: np.ndarray, ranges: list[tuple[int, int]], what: str) -> list[Segment]:
    """Segments of explicit inclusive frame ranges (``frames``: the file's frame number per sample)."""
    f = np.asarray(frames)
    out = []
    for a, b in ranges:
        idx = np.flatnonzero((f >= a) & (f <= b))
        if idx.size < 2:
            raise ValueError(f"--reaches: frames {a}-{b} hold fewer than two samples of {what} (its frames: "
                             f"{int(f.min())}-{int(f.max())})")
        out.append(Segment(int(idx[0]), int(idx[-1]), f"frames {a}-{b}"))
    return out


def events_segments(time: np.ndarray, events: list[tuple[float, str, str]], side: str | None,
                    what: str) -> list[Segment]:
    """Segments between consecutive events (``(time [s], label, context)``) of the context ``side``
    ("Right"/"Left", case-insensitive) or "General"; every context when ``side`` is None."""
    t = np.asarray(time, dtype=np.float64)
    keep = sorted((e for e in events if side is None or e[2].strip().lower() in (side.lower(), "general", "")),
                  key=lambda e: e[0])
    if len(keep) < 2:
        have = ", ".join(f"{lab} ({ctx}) {tt:.3f} s" for tt, lab, ctx in events) or "none"
        raise ValueError(f"--reaches: events needs two or more events{'' if side is None else f' of side {side}'} "
                         f"in {what} (it has: {have})")
    out = []
    for (t0, l0, _), (t1, l1, _) in zip(keep, keep[1:], strict=False):
        idx = np.flatnonzero((t >= t0 - 1e-9) & (t <= t1 + 1e-9))
        if idx.size >= 2:
            out.append(Segment(int(idx[0]), int(idx[-1]), f"events {l0} {t0:.3f} s .. {l1} {t1:.3f} s"))
    if not out:
        raise ValueError(f"--reaches: no two events of {what} enclose two or more samples")
    return out
