"""A synthetic upper-limb lab session with known joint angles and known reaches (C3D, map, .mot).

    files = synthetic_session("runs/lab", seed=0)
    # files["c3d"]: ISB landmarks (Plug-in-Gait-like labels, mm, 100 Hz, lab frame turned 30 deg
    #               about z and shifted), PROCESSING:Height, one event at each reach's start
    # files["map"]: the marker map (ISB landmark -> label) for --marker-map
    # files["mot"]: the true joint angles as an OpenSim .mot (degrees)
    # files["truth"]: truth.csv, each movement's true start and end [s]

The person is the human model (1.75 m, male): it rests at the model's start posture, reaches
to ``reaches`` postures drawn uniformly inside `TARGET_RANGE_DEG` and back, each movement a
minimum-jerk interpolation of the joint angles (durations and rests drawn from the
seeded generator, see `synthetic_session`). The
landmarks are placed on its links by its own forward kinematics (`camo_sbi.io.isb.model_landmarks`)
and get ``noise_mm`` of Gaussian noise per coordinate. The data come from the very model the
methods assume (no misspecification beyond the noise).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["MARKER_LABELS", "TARGET_RANGE_DEG", "synthetic_session"]

MARKER_LABELS = {"IJ": "CLAV", "PX": "STRN", "C7": "C7", "T8": "T10", "AC": "RSHO", "EL": "RELB", "EM": "RMEP",
                 "RS": "RWRA", "US": "RWRB", "MC2": "RFIN", "MC5": "RMT5"}
"""The file's labels of the ISB landmarks (Plug-in-Gait-like; T10 stands in for T8)."""
TARGET_RANGE_DEG = {
    "torso_flexion": (-5, 20), "torso_rotation": (-15, 15), "shoulder_flexion": (10, 100),
    "shoulder_abduction": (0, 60), "shoulder_rotation": (-40, 40), "elbow_flexion": (20, 120),
    "forearm_pronation": (-50, 50), "wrist_flexion": (-30, 30), "wrist_deviation": (-20, 10),
}


def synthetic_session(out, *, seed: int = 0, reaches: int = 4, noise_mm: float = 1.0, rate: float = 100.0,
                      height_m: float = 1.75) -> dict[str, Path]:
    """Write the session's files into the directory ``out`` (see the module docstring)."""
    import pandas as pd

    from camo_sbi._io import atomic_write_text
    from camo_sbi.io.c3d import write_c3d_points
    from camo_sbi.io.isb import model_landmarks
    from camo_sbi.simulators.human import JOINT_NAMES, anthropometry, default_start, human

    if reaches < 1:
        raise ValueError(f"reaches: expected >= 1, got {reaches}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    sim = human(height_m, "male")
    rest = default_start().numpy()
    lo, hi = (np.radians([TARGET_RANGE_DEG[j][i] for j in JOINT_NAMES]) for i in (0, 1))
    postures = [rest]
    for _ in range(reaches):
        postures += [rng.uniform(lo, hi), rest]
    plan, cur = [], 0.6
    for q0, q1 in zip(postures[:-1], postures[1:], strict=True):
        dur = rng.uniform(0.7, 1.2)
        plan.append((cur, cur + dur, q0, q1))
        cur += dur + rng.uniform(0.4, 0.8)
    time = np.arange(0.0, cur + 0.2, 1.0 / rate)
    q = np.tile(rest, (time.size, 1))
    for a, b, q0, q1 in plan:
        tau = np.clip((time - a) / (b - a), 0.0, 1.0)
        s = 10 * tau**3 - 15 * tau**4 + 6 * tau**5
        m = time >= a
        q[m] = q0 + s[m, None] * (q1 - q0)
    marks = model_landmarks(sim, q, anthropometry(height_m, "male"))
    c, sn = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    lab = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
    points = {MARKER_LABELS[k]: v @ lab.T + np.array([0.8, -0.5, 0.0]) + rng.normal(0.0, noise_mm / 1000.0, v.shape)
              for k, v in marks.items()}
    c3d = write_c3d_points(out / "session.c3d", points, rate, events=[(a, "Reach", "Right") for a, _, _, _ in plan],
                           height_m=height_m)
    mapping = atomic_write_text(out / "map.json", json.dumps(MARKER_LABELS, indent=1))
    lines = ["session", "version=1", f"nRows={time.size}", f"nColumns={len(JOINT_NAMES) + 1}", "inDegrees=yes",
             "endheader", "\t".join(["time", *JOINT_NAMES])]
    lines += ["\t".join([f"{t:.4f}", *(f"{v:.6f}" for v in np.degrees(row))]) for t, row in zip(time, q, strict=True)]
    mot = atomic_write_text(out / "session.mot", "\n".join(lines) + "\n")
    truth = atomic_write_text(out / "truth.csv", pd.DataFrame(
        [{"movement": k, "start_s": a, "end_s": b} for k, (a, b, _, _) in enumerate(plan)]).to_csv(index=False))
    return {"c3d": c3d, "map": mapping, "mot": mot, "truth": truth}
