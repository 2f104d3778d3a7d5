"""Joint angles from markers (`camo_sbi.io.isb`): ISB landmarks placed on the human model's
segments by its own forward kinematics, 1 mm noise, give back the joint angles within 2 deg RMS
per joint; a left arm mirrored gives the same angles; a missing landmark is one error naming it."""

from __future__ import annotations

import numpy as np
import pytest

from camo_sbi.io.isb import NEEDED, isb_joint_angles, model_landmarks
from camo_sbi.simulators.human import JOINT_NAMES, anthropometry, human

ANGLE_RANGE_DEG = {  # away from the shoulder's Y-X-Z gimbal lock at +-90 deg of abduction
    "torso_flexion": (-10, 30), "torso_rotation": (-30, 30), "shoulder_flexion": (-30, 120),
    "shoulder_abduction": (-20, 75), "shoulder_rotation": (-60, 60), "elbow_flexion": (5, 140),
    "forearm_pronation": (-70, 70), "wrist_flexion": (-50, 50), "wrist_deviation": (-25, 15),
}


@pytest.fixture(scope="module")
def body():
    return human(1.75, "male")


def place_markers(body, q: np.ndarray, rng=None, noise_m: float = 0.0) -> dict[str, np.ndarray]:
    """ISB landmarks on the model's links at postures q (F, 9), in its base frame, plus noise."""
    m = model_landmarks(body, q, anthropometry(1.75, "male"))
    return m if rng is None else {k: v + rng.normal(0.0, noise_m, v.shape) for k, v in m.items()}


def _postures(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lo, hi = (np.array([ANGLE_RANGE_DEG[j][i] for j in JOINT_NAMES], float) for i in (0, 1))
    return np.radians(rng.uniform(lo, hi, size=(n, len(JOINT_NAMES))))


def test_exact_markers_give_the_exact_angles(body):
    q = _postures(200, 0)
    got = isb_joint_angles(place_markers(body, q), heading=np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(got, q, atol=1e-9)


@pytest.mark.parametrize("seed", [1, 2])
def test_one_mm_noise_recovers_angles_within_2_deg_rms(body, seed):
    """Two seeds, 500 postures each, 1 mm Gaussian noise on every landmark coordinate."""
    q = _postures(500, seed)
    m = place_markers(body, q, np.random.default_rng(10 + seed), 0.001)
    got = isb_joint_angles(m, heading=np.array([1.0, 0.0, 0.0]))
    rms = np.degrees(np.sqrt(np.mean((got - q) ** 2, axis=0)))
    assert (rms < 2.0).all(), dict(zip(JOINT_NAMES, np.round(rms, 2), strict=True))


def test_lab_frame_and_median_heading(body):
    """The lab rotated 70 deg about z and shifted: with the default heading (the thorax's median
    forward direction) torso_rotation is relative to the median heading, the rest unchanged."""
    q = _postures(201, 3)
    q[:, 1] -= np.median(q[:, 1])  # the median heading is straight ahead
    c, s = np.cos(np.radians(70)), np.sin(np.radians(70))
    r = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    m = {k: v @ r.T + [1.0, -2.0, 0.1] for k, v in place_markers(body, q).items()}
    got = isb_joint_angles(m)
    np.testing.assert_allclose(got, q, atol=np.radians(0.5))


def test_left_arm_is_mirrored_onto_the_model(body):
    q = _postures(50, 4)
    m = place_markers(body, q)
    # the same person's left arm: every landmark reflected across the sagittal plane (y -> -y)
    left = {k: v * [1.0, -1.0, 1.0] for k, v in m.items()}
    got = isb_joint_angles(left, side="left", heading=np.array([1.0, 0.0, 0.0]))
    expect = q.copy()
    expect[:, 1] *= -1  # the mirrored trunk turns the other way
    np.testing.assert_allclose(got, expect, atol=1e-9)


def test_missing_landmark_is_named(body):
    m = place_markers(body, _postures(3, 5))
    del m["EM"]
    with pytest.raises(ValueError, match=r"^--marker-map: landmark 'EM' is missing \(the ISB joint angles need "
                                         + ", ".join(NEEDED)):
        isb_joint_angles(m)
