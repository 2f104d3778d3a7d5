"""The numbers of docs/guide/lab_session.md: cut accuracy of --reaches auto, ISB joint-angle error,
and naive limits from markers vs from the .mot of the same synthetic session.

    PYTHONPATH=. .venv/bin/python docs/studies/lab_session_measurements.py
"""

from __future__ import annotations

import tempfile

import numpy as np

from camo_sbi.experiments.lab_session import synthetic_session
from camo_sbi.inference.naive import median3
from camo_sbi.io.isb import isb_joint_angles, model_landmarks
from camo_sbi.io.recordings import load_recording
from camo_sbi.io.segment import hand_speed, segment_by_speed
from camo_sbi.simulators.human import JOINT_NAMES, anthropometry, human
from camo_sbi.task import NoiseModel
from tests.test_isb import _postures
from tests.test_segment import minimum_jerk_session


def cuts(n_sessions: int = 30, rate: float = 100.0, noise_m: float = 0.001) -> None:
    errs, found, total = [], 0, 0
    for seed in range(n_sessions):
        rng = np.random.default_rng(100 + seed)
        rest = np.array([0.2, -0.2, 0.9])
        targets = rest + rng.uniform([0.1, -0.1, 0.0], [0.35, 0.25, 0.35], size=(5, 3))
        points = np.vstack([np.vstack([rest, t]) for t in targets] + [rest])
        time, x, truth = minimum_jerk_session(points, seed, rate=rate, noise_m=noise_m)
        segs = segment_by_speed(time, hand_speed(time, x), x)
        total += len(truth)
        if len(segs) == len(truth):
            found += len(truth)
            errs += [[time[g.first] - a, time[g.last] - b] for g, (a, b) in zip(segs, truth, strict=True)]
    e = np.abs(np.asarray(errs)) * 1000
    print(f"cuts, {n_sessions} sessions at {rate:g} Hz, noise {noise_m * 1000:g} mm: {found}/{total} movements found; "
          f"mean error start {np.mean(np.asarray(errs)[:, 0]) * 1000:+.1f} ms, end "
          f"{np.mean(np.asarray(errs)[:, 1]) * 1000:+.1f} ms; |error| median {np.median(e):.0f} ms, "
          f"within 50 ms {np.mean(e <= 50) * 100:.1f}%, max {e.max():.0f} ms")


def cuts_markers(n_sessions: int = 10, rate: float = 100.0, noise_mm: float = 1.0, first_seed: int = 0) -> None:
    """--reaches auto on the synthetic marker session (ISB landmarks, 1 mm noise; the hand speed of the
    hand markers RS, US, MC2, MC5, as load_recording cuts a marker session)."""
    import pandas as pd

    body = human(1.75, "male")
    errs, found, total = [], 0, 0
    for seed in range(first_seed, first_seed + n_sessions):
        with tempfile.TemporaryDirectory() as d:
            f = synthetic_session(d, seed=seed, reaches=4, noise_mm=noise_mm, rate=rate)
            rec = load_recording(f["c3d"], body, markers="isb", marker_map=f["map"], reaches="auto", resample=None,
                                 noise=NoiseModel(joint_deg=1.0))
            truth = pd.read_csv(f["truth"])
        total += len(truth)
        if len(rec.segments) == len(truth):
            found += len(truth)
            errs += [[r["start_s"] - a, r["end_s"] - b] for r, (a, b) in
                     zip(rec.segments, truth[["start_s", "end_s"]].to_numpy(), strict=True)]
    e = np.abs(np.asarray(errs)) * 1000
    print(f"cuts on the marker session, seeds {first_seed}-{first_seed + n_sessions - 1} at {rate:g} Hz, noise "
          f"{noise_mm:g} mm: {found}/{total} movements found; mean error start "
          f"{np.mean(np.asarray(errs)[:, 0]) * 1000:+.1f} ms, end {np.mean(np.asarray(errs)[:, 1]) * 1000:+.1f} ms; "
          f"|error| median {np.median(e):.0f} ms, within 50 ms {np.mean(e <= 50) * 100:.1f}%, max {e.max():.0f} ms")


def isb(seeds=(1, 2), n: int = 500) -> None:
    body = human(1.75, "male")
    for seed in seeds:
        q = _postures(n, seed)
        rng = np.random.default_rng(10 + seed)
        m = {k: v + rng.normal(0, 0.001, v.shape) for k, v in model_landmarks(body, q, anthropometry()).items()}
        got = isb_joint_angles(m, heading=np.array([1.0, 0.0, 0.0]))
        rms = np.degrees(np.sqrt(np.mean((got - q) ** 2, axis=0)))
        print(f"ISB angles, seed {seed}, {n} postures, 1 mm noise: RMS [deg] "
              + ", ".join(f"{j} {r:.2f}" for j, r in zip(JOINT_NAMES, rms, strict=True)))


def mot_vs_markers(seeds=(0, 1), noise_mm: float = 1.0) -> None:
    body = human(1.75, "male")
    for seed in seeds:
        with tempfile.TemporaryDirectory() as d:
            f = synthetic_session(d, seed=seed, reaches=4, noise_mm=noise_mm)
            kw = {"reaches": "auto", "resample": None, "noise": NoiseModel(joint_deg=1.0)}
            a = load_recording(f["c3d"], body, markers="isb", marker_map=f["map"], **kw)
            b = load_recording(f["mot"], body, **kw)
        # naive's estimate: the min/max of each reach median-filtered over 3 samples (camo_sbi.inference.naive)
        ra = [np.degrees(np.concatenate([median3(o.q).numpy() for o in r.observations])) for r in (a, b)]
        diff = np.abs(np.stack([ra[0].min(0) - ra[1].min(0), ra[0].max(0) - ra[1].max(0)]))
        print(f"naive (median-3 min/max) from markers ({noise_mm:g} mm noise) vs from the true .mot, seed {seed}: "
              f"{len(a.observations)} vs {len(b.observations)} reaches; |difference| max {diff.max():.2f} deg, "
              f"mean {diff.mean():.2f} deg, bounds over 1 deg: {int((diff > 1).sum())} of {diff.size}")


if __name__ == "__main__":
    cuts()
    cuts(rate=200.0)
    cuts_markers()
    cuts_markers(rate=200.0)
    cuts_markers(40, first_seed=10)  # seeds the tests do not use
    cuts_markers(40, rate=200.0, first_seed=10)
    isb()
    mot_vs_markers()
    mot_vs_markers(noise_mm=0.0)
