"""The human model's joint angles from an upper-limb marker set, after the ISB recommendations.

    angles = isb_joint_angles(markers, side="right")   # {ISB landmark: (F, 3) lab positions [m]}
                                                        # -> (F, 9) radians, JOINT_NAMES order

Landmarks (Wu G et al. (2005) "ISB recommendation on definitions of joint coordinate systems of
various joints for the reporting of human joint motion - Part II: shoulder, elbow, wrist and
hand", J Biomech 38:981-992), named in a map file (``--marker-map MAP.json``,
``{"IJ": "<the file's label>", ...}``):

    thorax    IJ (incisura jugularis), PX (xiphoid process), C7, T8 (spinous processes)
    shoulder  AC (acromioclavicular joint; the glenohumeral centre's estimate, below)
    humerus   EL, EM (lateral and medial epicondyles)
    forearm   RS, US (radial and ulnar styloids)
    hand      MC2, MC5 (heads of the 2nd and 5th metacarpals)

SC, AA, TS and AI (the clavicle's and scapula's) may be in the map; this computation does not
use them (`NEEDED` lists the ones it needs; a missing one is one error naming it).

The hand's measured track (`HAND_TRACK`): the mean of the wrist's and the hand's landmarks
(RS, US, MC2, MC5) in the lab frame. ``--reaches auto`` cuts a marker session by its speed: it
carries only the markers' own noise, where the model's forward kinematics of the computed angles
carries the angles' estimation error through the arm's lever.

Segment frames (each right-handed, in the lab frame), as Wu et al. define them and then
relabelled to the model's axes (x forward, y left, z up/proximal at the anatomical posture):

* thorax: Y_t from the midpoint of PX and T8 to the midpoint of IJ and C7; Z_t normal to the
  plane of IJ, C7 and that lower midpoint, pointing right; X_t = Y_t x Z_t (forward). The model's
  torso frame is [X_t, -Z_t, Y_t].
* glenohumeral centre GH: AC displaced `GH_BELOW_AC_M` along -Y_t (inferiorly). A fixed offset
  (as gait-lab upper-limb models do, e.g. Rab et al. 2002 with a fraction of the bi-acromial
  distance); no regression from the scapula landmarks. Its error bends the shoulder angles.
* humerus: z from the elbow centre (EL, EM midpoint) to GH; y along EM - EL made normal to z
  (medial = left for a right arm); x = y x z (Wu's first humerus option: the plane of GH, EL, EM).
* forearm: z from the wrist centre (RS, US midpoint) to the elbow centre; x along RS - US made
  normal to z (the thumb side, forward with the forearm in mid-position); y = z x x. ISB's
  forearm frame is the same plane turned 90 deg (ISB's neutral is supinated): the model's zero
  is the mid-position, thumb forward.
* hand: z from the MC2, MC5 midpoint to the wrist centre; x along MC2 - MC5 normal to z.

The model's angles (`camo_sbi.simulators.human`; `camo-sbi describe --model human`) are the
decomposition of the relative rotations in the model's own axis sequences, not ISB's clinical
sequences (the humerus-thorax Y-X-Y, for one):

    base -> thorax      R = R_y(torso_flexion) R_z(torso_rotation)            (residual: lateral bend)
    thorax -> humerus   R = R_-y(shoulder_flexion) R_-x(shoulder_abduction) R_z(shoulder_rotation)
    humerus -> forearm  R = R_-y(elbow_flexion) R_z(forearm_pronation)        (residual: carrying angle)
    forearm -> hand     R = R_x(wrist_flexion) R_-y(wrist_deviation)

The base frame: lab z up (the C3D convention of Vicon and Qualisys; `UP` otherwise), x the
thorax's median forward azimuth about the vertical over the recording. The arm's angles
are relative to the thorax, so the trunk's own motion is taken out of them; the trunk's motion
is in torso_flexion (the thorax's forward tilt from the vertical) and torso_rotation (its heading
relative to the recording's median heading). Left arm (``side="left"``): every landmark is
mirrored across the thorax's sagittal plane first, so the right-arm model holds it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["GH_BELOW_AC_M", "HAND_TRACK", "LANDMARKS", "NEEDED", "UP", "isb_joint_angles", "load_marker_map",
           "model_landmarks", "segment_frames"]

LANDMARKS = ("IJ", "PX", "C7", "T8", "SC", "AC", "AA", "TS", "AI", "EL", "EM", "RS", "US", "MC2", "MC5")
"""The ISB landmark names a ``--marker-map`` may use."""
NEEDED = ("IJ", "PX", "C7", "T8", "AC", "EL", "EM", "RS", "US", "MC2", "MC5")
"""The landmarks `isb_joint_angles` needs."""
HAND_TRACK = ("RS", "US", "MC2", "MC5")
"""The landmarks (all in `NEEDED`) whose mean is the hand's measured track (``--reaches auto``)."""
GH_BELOW_AC_M = 0.06
"""The glenohumeral centre's fixed offset below the AC landmark along the thorax's long axis [m]."""
UP = np.array([0.0, 0.0, 1.0])
"""The lab's vertical."""


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def _frame_zx(z: np.ndarray, x_hint: np.ndarray) -> np.ndarray:
    """(F, 3, 3) rotation with columns [x, y, z]: z along ``z``, x along ``x_hint`` made normal to z."""
    z = _unit(z)
    x = _unit(x_hint - np.sum(x_hint * z, axis=-1, keepdims=True) * z)
    return np.stack([x, np.cross(z, x), z], axis=-1)


def _frame_zy(z: np.ndarray, y_hint: np.ndarray) -> np.ndarray:
    """(F, 3, 3) rotation with columns [x, y, z]: z along ``z``, y along ``y_hint`` made normal to z."""
    z = _unit(z)
    y = _unit(y_hint - np.sum(y_hint * z, axis=-1, keepdims=True) * z)
    return np.stack([np.cross(y, z), y, z], axis=-1)


def segment_frames(m: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """{"thorax", "humerus", "forearm", "hand": (F, 3, 3) rotations in the model's axes; "GH":
    (F, 3)} from the landmarks ``m`` (each (F, 3), lab frame, a right arm)."""
    top = 0.5 * (m["IJ"] + m["C7"])
    low = 0.5 * (m["PX"] + m["T8"])
    y_t = _unit(top - low)
    z_t = _unit(np.cross(m["IJ"] - low, m["C7"] - low))  # IJ forward, C7 back: the normal points right
    x_t = np.cross(y_t, z_t)
    thorax = np.stack([x_t, -z_t, y_t], axis=-1)
    gh = m["AC"] - GH_BELOW_AC_M * y_t
    elbow = 0.5 * (m["EL"] + m["EM"])
    wrist = 0.5 * (m["RS"] + m["US"])
    knuckles = 0.5 * (m["MC2"] + m["MC5"])
    return {"thorax": thorax, "GH": gh,
            "humerus": _frame_zy(gh - elbow, m["EM"] - m["EL"]),
            "forearm": _frame_zx(elbow - wrist, m["RS"] - m["US"]),
            "hand": _frame_zx(wrist - knuckles, m["MC2"] - m["MC5"])}


def _rel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("fji,fjk->fik", a, b)  # a^T b


def _yxz(r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """r = R_y(a) R_x(b) R_z(c) -> (a, b, c)."""
    b = np.arcsin(np.clip(-r[:, 1, 2], -1.0, 1.0))
    a = np.arctan2(r[:, 0, 2], r[:, 2, 2])
    c = np.arctan2(r[:, 1, 0], r[:, 1, 1])
    return a, b, c


def _xyz(r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """r = R_x(a) R_y(b) R_z(c) -> (a, b, c)."""
    b = np.arcsin(np.clip(r[:, 0, 2], -1.0, 1.0))
    a = np.arctan2(-r[:, 1, 2], r[:, 2, 2])
    c = np.arctan2(-r[:, 0, 1], r[:, 0, 0])
    return a, b, c


def _mirror(m: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Every landmark reflected across the thorax's sagittal plane (per frame): a left arm as a right."""
    low = 0.5 * (m["PX"] + m["T8"])
    n = _unit(np.cross(m["IJ"] - low, m["C7"] - low))  # the sagittal plane's normal, through `low`
    return {k: v - 2.0 * np.sum((v - low) * n, axis=-1, keepdims=True) * n for k, v in m.items()}


def isb_joint_angles(markers: dict[str, np.ndarray], side: str = "right", *,
                     heading: np.ndarray | None = None) -> np.ndarray:
    """(F, 9) the human model's joint angles [rad] (`JOINT_NAMES` order) from the landmarks.

    Args:
        markers: {ISB landmark: (F, 3) lab positions [m]} with every name of `NEEDED`.
        side: "right" or "left" (mirrored onto the right-arm model).
        heading: (3,) the base frame's forward direction in the lab (default: the thorax's
            median forward direction over the frames, projected on the floor).

    Raises:
        ValueError naming the landmark that is missing, or ``side``.
    """
    if side not in ("right", "left"):
        raise ValueError(f"side: expected 'right' or 'left', got {side!r}")
    missing = [k for k in NEEDED if k not in markers]
    if missing:
        raise ValueError(f"--marker-map: landmark {missing[0]!r} is missing (the ISB joint angles need "
                         f"{', '.join(NEEDED)})")
    m = {k: np.asarray(markers[k], dtype=np.float64) for k in NEEDED}
    if side == "left":
        m = _mirror(m)
    f = segment_frames(m)
    fwd = f["thorax"][:, :, 0] if heading is None else np.asarray(heading, float).reshape(1, 3)
    ang = np.arctan2(fwd[:, 1], fwd[:, 0])  # the forward direction's azimuth about the lab's z
    ref = np.arctan2(np.sin(ang).mean(), np.cos(ang).mean())
    a0 = ref + float(np.median(np.angle(np.exp(1j * (ang - ref)))))  # the median azimuth
    h = np.array([np.cos(a0), np.sin(a0), 0.0])
    base = np.stack([h, np.cross(UP, h), UP], axis=-1)[None]  # x forward, y left, z up
    base = np.broadcast_to(base, f["thorax"].shape)
    tf, _, tr = _yxz(_rel(base, f["thorax"]))
    sf, sa, sr = _yxz(_rel(f["thorax"], f["humerus"]))  # R_y(-flexion) R_x(-abduction) R_z(rotation)
    ef, _, pr = _yxz(_rel(f["humerus"], f["forearm"]))  # R_y(-elbow) [R_x(carrying)] R_z(pronation)
    wf, wd, _ = _xyz(_rel(f["forearm"], f["hand"]))  # R_x(wrist flexion) R_y(-deviation)
    return np.stack([tf, tr, -sf, -sa, sr, -ef, pr, wf, -wd], axis=-1)


def load_marker_map(path, flag: str = "--marker-map") -> dict[str, str]:
    """{ISB landmark: the file's marker label} from a JSON object; every landmark `NEEDED` must be
    there (one error naming the first missing one), no key outside `LANDMARKS`."""
    from camo_sbi.io.frames import read_json_object

    path, data = read_json_object(path, flag)
    unknown = [k for k in data if k not in LANDMARKS]
    if unknown:
        raise ValueError(f"{flag} {path}: key {unknown[0]!r} is not an ISB landmark ({', '.join(LANDMARKS)})")
    bad = [k for k, v in data.items() if not isinstance(v, str) or not v.strip()]
    if bad:
        raise ValueError(f"{flag} {path}: landmark {bad[0]!r}: expected the file's marker label (a string)")
    missing = [k for k in NEEDED if k not in data]
    if missing:
        raise ValueError(f"{flag} {path}: landmark {missing[0]!r} is missing (the ISB joint angles need "
                         f"{', '.join(NEEDED)})")
    return {k: v.strip() for k, v in data.items()}


def model_landmarks(sim, q, anthro) -> dict[str, np.ndarray]:
    """The landmarks of `NEEDED` placed on the human model's links at postures ``q`` (F, 9) [rad],
    in its base frame (z up), for synthetic sessions: the thorax's on the torso link (IJ and C7
    above PX and T8 in its sagittal plane), AC `GH_BELOW_AC_M` above the shoulder joint centre,
    the epicondyles 8 cm apart across the elbow axis, the styloids 6 cm apart across the wrist
    (thumb side forward at the zero posture), the metacarpal heads 7 cm apart 0.45 hand lengths
    distal to the wrist. ``anthro``: the model's `camo_sbi.simulators.human.Anthropometry`."""
    spec = sim.spec
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    frames, tip = spec.joint_frames(q)

    def link(k):  # the pose of the link joint k moves: the next joint's frame without its origin
        if k + 1 < spec.n_joints:
            return frames[:, k + 1] @ np.linalg.inv(spec.origins[k + 1])
        return tip @ np.linalg.inv(spec.tip)

    T, Lu, Lf, Lh = anthro.trunk, anthro.upper_arm, anthro.forearm, anthro.hand
    sho = np.array([0.0, -anthro.shoulder_offset, T])
    local = {
        1: {"IJ": [0.07, 0.0, T + 0.02], "C7": [-0.09, 0.0, T + 0.07], "PX": [0.10, 0.0, T - 0.16],
            "T8": [-0.12, 0.0, T - 0.14], "AC": sho + [0.0, 0.0, GH_BELOW_AC_M]},
        4: {"EL": [0.0, -0.04, -Lu], "EM": [0.0, 0.04, -Lu]},
        6: {"RS": [0.03, 0.0, -Lf], "US": [-0.03, 0.0, -Lf]},
        8: {"MC2": [0.035, 0.0, -0.45 * Lh], "MC5": [-0.035, 0.0, -0.45 * Lh]},
    }
    out = {}
    for k, names in local.items():
        pose = link(k)
        for name, p in names.items():
            out[name] = (pose @ np.r_[np.asarray(p, dtype=np.float64), 1.0])[:, :3]
    return {k: out[k] for k in NEEDED}
