"""Reaches found in a continuous recording: by hand speed, by the file's events, or by frame ranges.

``--reaches`` (any recording with time: C3D, BVH, a CSV/NPZ with a ``time`` column)::

    auto                  segmentation by hand speed (`segment_by_speed`, thresholds below)
    events                the C3D file's own events (EVENT:TIMES / LABELS / CONTEXTS): each
                          reach runs from one event of the side's context (or "General") to the next
    0-120,121-260         explicit inclusive frame ranges (the file's frame numbers)

Hand speed (`hand_speed`): the hand's path low-pass filtered with a zero-phase 2nd-order
Butterworth at `CUTOFF_HZ` (6 Hz, the usual choice for upper-limb kinematics), differentiated by
central differences. The path comes as directly from the recording as it allows: the end-effector
track (a C3D's ``--ee-marker``, a CSV's ee_* columns); for a marker session (``--markers isb``) the mean of the
wrist's and hand's landmarks (`camo_sbi.io.isb.HAND_TRACK`), which carries only the markers' own
noise, where the model's forward kinematics of the computed joint angles would add the angles'
estimation error through the arm's lever; the forward kinematics only for joint angles without
markers (BVH, ``.mot``, a CSV's joint columns). ``reaches.csv`` (column ``hand_track``) and the
rule's text name the path used.

Rule "speed" (`segment_by_speed`), with these stated thresholds, in two passes:

1. a movement is a run of samples whose speed exceeds `ACTIVE_SPEED` (0.05 m/s) and whose
   peak exceeds `MIN_PEAK_SPEED` (0.15 m/s);
2. first cuts: walking back from the peak, its start is where the speed has fallen below
   max(`ONSET_FRACTION` (5%) x the peak, `NOISE_FACTOR` (1.5) x the median speed of the
   samples not in any run, i.e. the noise's speed at rest), moved on to the speed's local
   minimum there; its end likewise after the peak (never into the neighbouring movement);
3. movements shorter than `MIN_DURATION_S` between their first-pass cuts are dropped; two
   movements whose first-pass cuts overlap are merged (a pause of less than a sample);
4. each cut refined from the hand's position (`refine_cut`; when the path is given, as
   ``--reaches auto`` does): the rest position is the median of the low-passed positions at
   rest beside the movement (speed under `ACTIVE_SPEED`, at most `REST_WINDOW_S` away); the
   displacement from it towards the position at peak speed, from that rest up to `FIT_FRACTION`
   (10%) of the movement's amplitude, is fitted by least squares with d(t) = c max(t - t0, 0)^3,
   a smooth start from rest (zero velocity and acceleration at t0; the initial phase as a cubic
   power of time, as in Botzer & Karniel 2009's onset regression); the cut is the sample nearest
   t0 (the end likewise, in reversed time). With fewer than `MIN_REST_SAMPLES` samples at rest
   beside it (no pause between two movements) a cut keeps its first-pass place.

Why the second pass: a threshold on speed cannot place a smooth start, whose speed stays under
the noise's for a while; the first pass's cut then lands wherever the noise puts the local
minimum. The fit uses every sample of the rise up to `FIT_FRACTION` of the amplitude, where the
displacement stands clear of the noise, and extrapolates the start. The reasoning with numbers,
and how close the cuts come to the true ones: docs/guide/lab_session.md.

Each reach's goal is where the hand is at its end (free reaching), its start posture its
first sample. The outward reach and the return to rest are both reaches (the return's goal is
the rest position): the rule does not guess which is which, and ``reaches.csv`` lists both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ACTIVE_SPEED", "CUTOFF_HZ", "FIT_FRACTION", "MIN_DURATION_S", "MIN_PEAK_SPEED", "MIN_REST_SAMPLES",
           "NOISE_FACTOR", "ONSET_FRACTION", "REST_WINDOW_S", "Segment", "events_segments", "hand_speed", "lowpass",
           "parse_reaches", "ranges_segments", "refine_cut", "rule_text", "segment_by_speed"]

CUTOFF_HZ = 6.0
ACTIVE_SPEED = 0.05
MIN_PEAK_SPEED = 0.15
ONSET_FRACTION = 0.05
MIN_DURATION_S = 0.15
NOISE_FACTOR = 1.5
FIT_FRACTION = 0.10
REST_WINDOW_S = 0.5
MIN_REST_SAMPLES = 3


def rule_text(refined: bool = True, track: str | None = None) -> str:
    """The rule "speed" in one line (reaches.csv's run settings, the report); ``track``: which hand
    path the speed came from (the end-effector track, the hand's markers, the forward kinematics)."""
    first = (f"hand speed: {CUTOFF_HZ:g} Hz low-pass; movement = speed > {ACTIVE_SPEED:g} m/s with a peak > "
             f"{MIN_PEAK_SPEED:g} m/s; first cuts where the speed falls below max({ONSET_FRACTION:g} x peak, "
             f"{NOISE_FACTOR:g} x the speed at rest), then on to its local minimum")
    second = (f"; refined by the start (end) of a cubic fitted to the displacement from the rest position up to "
              f"{FIT_FRACTION:g} of the amplitude") if refined else ""
    return f"{first}{second}; at least {MIN_DURATION_S:g} s" + ("" if track is None else f"; hand track: {track}")


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


def lowpass(time: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """The (F, 3) path sampled at ``time`` [s] through the 6 Hz zero-phase low-pass (unchanged for
    fewer than 16 samples or a rate under 15 Hz)."""
    from scipy.signal import butter, filtfilt

    t = np.asarray(time, dtype=np.float64)
    x = np.asarray(pos, dtype=np.float64)
    if t.shape[0] < 3:
        return x
    rate = 1.0 / float(np.median(np.diff(t)))
    if x.shape[0] >= 16 and rate > 2.5 * CUTOFF_HZ:
        b, a = butter(2, CUTOFF_HZ / (0.5 * rate))
        x = filtfilt(b, a, x, axis=0, padlen=min(3 * max(len(a), len(b)), x.shape[0] - 1))
    return x


def hand_speed(time: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """(F,) speed [m/s] of the (F, 3) path sampled at ``time`` [s]: 6 Hz zero-phase low-pass
    (`lowpass`), then central differences."""
    t = np.asarray(time, dtype=np.float64)
    if t.shape[0] < 3:
        return np.zeros(t.shape[0])
    v = np.gradient(lowpass(t, pos), t, axis=0)
    return np.linalg.norm(v, axis=1)


def segment_by_speed(time: np.ndarray, speed: np.ndarray, pos: np.ndarray | None = None) -> list[Segment]:
    """The movements of a speed profile by the rule of the module docstring (sample indices).
    ``pos``: the (F, 3) hand path the speed came from; with it every cut is refined (`refine_cut`),
    without it the cuts are the first pass's."""
    t = np.asarray(time, dtype=np.float64)
    s = np.asarray(speed, dtype=np.float64)
    if pos is not None:
        pos = np.asarray(pos, dtype=np.float64)
        if pos.ndim != 2 or pos.shape[0] != s.shape[0]:
            raise ValueError(f"pos: expected shape ({s.shape[0]}, 3) like speed, got {tuple(pos.shape)}")
    active = s > ACTIVE_SPEED
    edges = np.flatnonzero(np.diff(np.r_[0, active.astype(np.int8), 0]))
    runs = [(int(a), int(b) - 1) for a, b in zip(edges[0::2], edges[1::2], strict=True)]
    runs = [(a, b) for a, b in runs if s[a: b + 1].max() > MIN_PEAK_SPEED]
    still = ~active
    floor_speed = float(np.median(s[still])) if still.any() else 0.0  # the noise's speed at rest
    out: list[Segment] = []
    spans: list[tuple[int, int]] = []  # each movement's active samples (first and last run merged)
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
            spans[-1] = (spans[-1][0], b)
        else:
            seg = Segment(i, j, "speed", float(s[peak_i]))
            spans.append((a, b))
        out.append(seg)
    keep = [k for k, g in enumerate(out) if t[g.last] - t[g.first] >= MIN_DURATION_S]  # by the first pass's cuts
    out, spans = [out[k] for k in keep], [spans[k] for k in keep]
    if pos is not None and out:
        xf = lowpass(t, pos)
        refined = []
        for k, (g, (a, b)) in enumerate(zip(out, spans, strict=True)):
            peak_i = a + int(np.argmax(s[a: b + 1]))
            amp = float(np.linalg.norm(xf[g.last] - xf[g.first]))
            lo = spans[k - 1][1] + 1 if k else 0  # the rest between the previous movement and this one
            hi = spans[k + 1][0] - 1 if k + 1 < len(spans) else s.shape[0] - 1
            i = refine_cut(t, xf, active, peak_i, lo, a, amp, -1)
            j = refine_cut(t, xf, active, peak_i, hi, b, amp, +1)
            i = g.first if i is None else max(i, refined[-1].last + 1 if refined else 0)
            j = g.last if j is None else j
            refined.append(Segment(i, max(j, i + 1), g.rule, g.peak_speed))
        out = refined
    return out


def refine_cut(t: np.ndarray, xf: np.ndarray, active: np.ndarray, peak_i: int, stop: int, edge: int,
               amp: float, step: int) -> int | None:
    """A movement's start (``step`` -1) or end (+1) from the low-passed path ``xf`` (rule 3 of the
    module docstring): the sample nearest the t0 of d(t) = c max(t - t0, 0)^3 fitted to the
    displacement from the rest position, over the samples from the rest (between ``stop``, the
    neighbouring movement's side, and ``edge``, the movement's first or last active sample) up to
    `FIT_FRACTION` of ``amp``. None: too little rest beside it, or nothing to fit."""
    rest = np.arange(edge + step, stop + step, step) if (stop - edge) * step > 0 else np.zeros(0, dtype=int)
    rest = rest[np.abs(t[rest] - t[edge]) <= REST_WINDOW_S] if rest.size else rest
    rest = rest[~active[rest]] if rest.size else rest
    if rest.size < MIN_REST_SAMPLES or not np.isfinite(amp) or amp <= 0:
        return None
    x0 = np.median(xf[rest], axis=0)
    u = xf[peak_i] - x0
    n = float(np.linalg.norm(u))
    if n <= 0:
        return None
    far = int(rest[-1])  # from the rest's far side towards the peak
    idx = np.arange(far, peak_i + step, -step)
    d = (xf[idx] - x0) @ (u / n)
    over = np.flatnonzero(d > FIT_FRACTION * amp)
    m = int(over[0]) if over.size else d.size
    if m < MIN_REST_SAMPLES + 2:
        return None
    tt, d = -step * t[idx[:m]], d[:m]  # time running away from the rest: increasing
    grid = np.linspace(tt[0], tt[-1], int(min(10 * m, 2000)), endpoint=False)
    u3 = np.clip(tt[None, :] - grid[:, None], 0.0, None) ** 3
    den = (u3 * u3).sum(axis=1)
    num = (u3 * d[None, :]).sum(axis=1)
    sse = -np.where(den > 0, num * np.abs(num) / np.where(den > 0, den, 1.0), -np.inf)  # up to sum(d^2); c >= 0
    t0 = -step * float(grid[int(np.argmin(sse))])
    return int(np.argmin(np.abs(t - t0)))


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
