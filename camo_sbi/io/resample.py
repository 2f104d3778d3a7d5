"""Resampling a recording to the controller's step (`resample_to_controller`), and the recorder's
rate (`estimate_rate`).

A recorder samples at its own rate, the controller moves once per step. Before any distance is
computed the loader (`camo_sbi.io.recordings.load_recording`) resamples each reach to the
controller's step: the recorder's rate R (recorded samples per controller step) is estimated
from the whole file (`estimate_rate`) and, unless it is 1, each reach is linearly interpolated
in normalised time to round((L - 1) / R) + 1 samples (``"time"``, the default), or re-walked
along its path with the controller's step law (``"arclength"``). See
docs/user-guide/your-robot.md for the measurement behind the default. A file with a ``time``
column is first put on a uniform grid (`uniform_in_time`).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from camo_sbi.simulators.controller import ControllerConfig
from camo_sbi.task import Observation

__all__ = ["RESAMPLE_MODES", "estimate_rate", "interp_rows", "resample_to_controller", "uniform_in_time"]

RESAMPLE_MODES = ("time", "arclength")
RATE_SNAP = 0.15
"""An estimated rate within this relative distance of an integer is taken as that integer."""

def _controller(simulator) -> ControllerConfig:
    cfg = getattr(simulator, "config", None)
    return cfg if isinstance(cfg, ControllerConfig) else ControllerConfig()



def uniform_in_time(t: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(times, new times) of a reach resampled on a uniform grid of step ``dt`` from its first sample."""
    n = max(2, int(round((t[-1] - t[0]) / dt)) + 1)
    return t, np.minimum(t[0] + dt * np.arange(n), t[-1])


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


def interp_rows(x: np.ndarray, t_old: np.ndarray, t_new: np.ndarray) -> np.ndarray:
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
    q = None if o.q is None else torch.from_numpy(interp_rows(o.q.numpy()[sel], t_old, t_new))
    ee = None if o.ee is None else torch.from_numpy(interp_rows(o.ee.numpy()[sel], t_old, t_new))
    if q is not None:
        q[0] = o.q[0]
    return Observation(o.start.clone(), o.goal.clone(), q, ee)
