"""The generated human model: URDF validity, anthropometry, range of motion, FK, reach, profiles."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import pybullet as p
import pytest
import pytorch_kinematics as pk
import torch

from camo_sbi._validation import check_theta
from camo_sbi.simulators import IMPAIRED_PROFILES, human, impaired_limits, sample_goals
from camo_sbi.simulators.human import (
    DEFAULT_START_DEG,
    END_EFFECTOR,
    JOINT_NAMES,
    ImpairmentProfile,
    anthropometry,
    default_start,
    human_urdf,
    normative_bounds,
)
from tests._fk_check import assert_fk_matches_pybullet

EXPECTED_NAMES = [
    "torso_flexion",
    "torso_rotation",
    "shoulder_flexion",
    "shoulder_abduction",
    "shoulder_rotation",
    "elbow_flexion",
    "forearm_pronation",
    "wrist_flexion",
    "wrist_deviation",
]
# AAOS normative range of motion, degrees, signed as documented in human.py.
EXPECTED_ROM_DEG = [
    (-25, 80),  # trunk extension 25 / flexion 80
    (-45, 45),  # trunk axial rotation
    (-60, 180),  # shoulder extension / flexion
    (-30, 180),  # shoulder adduction / abduction
    (-90, 70),  # shoulder external / internal rotation
    (0, 150),  # elbow
    (-80, 80),  # supination / pronation
    (-70, 80),  # wrist extension / flexion
    (-30, 20),  # ulnar / radial deviation
]


@pytest.fixture(scope="module")
def sim():
    return human()


def _deg(**angles) -> torch.Tensor:
    """(9,) radians with the named joints set (degrees), others 0."""
    q = torch.zeros(9, dtype=torch.float64)
    for name, v in angles.items():
        q[JOINT_NAMES.index(name)] = math.radians(v)
    return q


class _Bullet:
    """A private pybullet DIRECT client holding the full URDF (visuals, collisions, inertials)."""

    def __init__(self, urdf_text: str):
        self.cid = p.connect(p.DIRECT)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "human.urdf"
            path.write_text(urdf_text)
            self.body = p.loadURDF(str(path), useFixedBase=True, physicsClientId=self.cid)
        n = p.getNumJoints(self.body, physicsClientId=self.cid)
        infos = [p.getJointInfo(self.body, i, physicsClientId=self.cid) for i in range(n)]
        self.movable = [i for i, info in enumerate(infos) if info[2] == p.JOINT_REVOLUTE]
        self.movable_names = [infos[i][1].decode() for i in self.movable]
        self.limits = np.array([(infos[i][8], infos[i][9]) for i in self.movable])
        assert any(info[12].decode() == END_EFFECTOR for info in infos)

    def close(self):
        p.disconnect(self.cid)


# ----------------------------------------------------------------------------- URDF


@pytest.mark.parametrize("sex", ["male", "female"])
def test_urdf_loads_in_pybullet_and_pytorch_kinematics(sex):
    text = human_urdf(1.68, sex)
    chain = pk.build_serial_chain_from_urdf(text.encode(), END_EFFECTOR)
    assert chain.get_joint_parameter_names() == EXPECTED_NAMES
    assert "<mesh" not in text
    bullet = _Bullet(text)
    try:
        assert bullet.movable_names == EXPECTED_NAMES
        np.testing.assert_allclose(bullet.limits, np.radians(EXPECTED_ROM_DEG), atol=1e-12)
        masses = [p.getDynamicsInfo(bullet.body, i, physicsClientId=bullet.cid)[0] for i in bullet.movable]
        assert all(m > 0 for m in masses)
    finally:
        bullet.close()


def test_simulator_joints_bounds_and_start(sim):
    assert sim.joint_names == EXPECTED_NAMES
    assert sim.n_joints == 9
    expected = torch.tensor(np.radians(EXPECTED_ROM_DEG), dtype=sim.bounds.dtype)
    torch.testing.assert_close(sim.bounds, expected, atol=1e-12, rtol=0)
    torch.testing.assert_close(normative_bounds(), expected, atol=1e-12, rtol=0)
    start = sim.start.to(torch.float64)
    torch.testing.assert_close(start, default_start(), atol=1e-12, rtol=0)
    assert bool(((start > expected[:, 0]) & (start < expected[:, 1])).all())
    # arm hanging slightly forward: hand in front of the hip, below the shoulder, right side
    a = anthropometry()
    hand = sim.forward_kinematics(start)
    assert 0.1 < float(hand[0]) < 0.5
    assert a.hip_height < float(hand[2]) < a.hip_height + a.trunk
    assert float(hand[1]) < 0


# ------------------------------------------------------------------ anthropometry


def _reach_from_shoulder(sim, a) -> float:
    """Shoulder-to-hand distance with the arm straight (shoulder flexion 90 deg)."""
    hand = sim.forward_kinematics(_deg(shoulder_flexion=90).to(sim.bounds.dtype))
    return float(torch.linalg.vector_norm(hand.to(torch.float64) - torch.tensor(a.shoulder_position, dtype=torch.float64)))


def test_segment_lengths_scale_with_height_and_sex():
    reach = {}
    for sex in ("male", "female"):
        for height in (1.5, 1.75, 2.0):
            a = anthropometry(height, sex)
            s = human(height, sex)
            reach[sex, height] = _reach_from_shoulder(s, a)
            assert reach[sex, height] == pytest.approx(a.arm_reach, abs=1e-9)
            # zero posture: arm hanging straight down from the shoulder
            zero = s.forward_kinematics(torch.zeros(9, dtype=s.bounds.dtype)).to(torch.float64)
            sx, sy, sz = a.shoulder_position
            torch.testing.assert_close(zero, torch.tensor([sx, sy, sz - a.arm_reach], dtype=torch.float64), atol=1e-9, rtol=0)
    # de Leva / Drillis-Contini fractions
    m, f = anthropometry(1.75, "male"), anthropometry(1.75, "female")
    assert (m.upper_arm, m.forearm, m.hand) == pytest.approx((0.162 * 1.75, 0.155 * 1.75, 0.108 * 1.75))
    assert (f.upper_arm, f.forearm, f.hand) == pytest.approx((0.159 * 1.75, 0.152 * 1.75, 0.098 * 1.75))
    assert m.shoulder_position == pytest.approx((0.0, -0.105 * 1.75, 0.818 * 1.75))
    # reach proportional to height; women have shorter relative segments
    for sex in ("male", "female"):
        assert reach[sex, 2.0] / reach[sex, 1.5] == pytest.approx(2.0 / 1.5, rel=1e-9)
    assert reach["female", 1.75] < reach["male", 1.75]
    assert 0.60 <= reach["male", 1.75] <= 0.65


@pytest.mark.parametrize(
    ("angles", "direction"),
    [
        ({"shoulder_flexion": 90}, (1, 0, 0)),  # flexion raises the arm forward
        ({"shoulder_flexion": -60}, (-1, 0, 0)),  # extension moves it backward
        ({"shoulder_abduction": 90}, (0, -1, 0)),  # abduction: out to the right
        ({"elbow_flexion": 90}, (1, 0, 0)),  # forearm forward
        ({"elbow_flexion": 90, "shoulder_rotation": 70}, (0, 1, 0)),  # internal rotation: medial
        ({"elbow_flexion": 90, "shoulder_rotation": -90}, (0, -1, 0)),  # external: lateral
        ({"elbow_flexion": 90, "torso_rotation": 45}, (0, 1, 0)),  # trunk turns left
        ({"elbow_flexion": 90, "wrist_flexion": 80}, (0, 1, 0)),  # palm faces medially
        ({"elbow_flexion": 90, "wrist_deviation": 20}, (0, 0, 1)),  # thumb up: radial is up
        ({"elbow_flexion": 90, "forearm_pronation": 80, "wrist_flexion": 80}, (0, 0, -1)),  # palm down
    ],
)
def test_sign_conventions(sim, angles, direction):
    """Positive angles move the hand the way the docstring says (relative to the reference)."""
    reference = {"elbow_flexion": 90} if len(angles) > 1 else {}  # forearm forward first
    q0 = _deg(**reference).to(sim.bounds.dtype)
    q1 = _deg(**angles).to(sim.bounds.dtype)
    move = (sim.forward_kinematics(q1) - sim.forward_kinematics(q0)).to(torch.float64)
    cosine = float(move @ torch.tensor(direction, dtype=torch.float64)) / float(move.norm())
    assert cosine > 0.6, (angles, move)


def test_torso_flexion_tilts_the_shoulder_forward(sim):
    a = anthropometry()
    hand = sim.forward_kinematics(_deg(torso_flexion=80, shoulder_flexion=90).to(sim.bounds.dtype))
    c, s = math.cos(math.radians(80)), math.sin(math.radians(80))
    shoulder = torch.tensor([a.trunk * s, -a.shoulder_offset, a.hip_height + a.trunk * c], dtype=torch.float64)
    expected = shoulder + a.arm_reach * torch.tensor([c, 0.0, -s], dtype=torch.float64)  # arm along the trunk's normal
    torch.testing.assert_close(hand.to(torch.float64), expected, atol=1e-9, rtol=0)


# ------------------------------------------------------------------------ FK vs pybullet


@pytest.mark.parametrize(("height", "sex"), [(1.75, "male"), (1.62, "female")])
def test_fk_matches_pybullet(height, sex):
    """pk FK and the numba kernel FK vs pybullet's worldLinkFramePosition (measured ~1e-7 m)."""
    err = assert_fk_matches_pybullet(human(height, sex), n=128, seed=7, atol=1e-5)
    print(f"human FK max error vs pybullet ({sex}, {height} m): {err:.2e} m")


# --------------------------------------------------------------------------- reaching


def test_reaches_most_goals_inside_full_bounds(sim):
    """Default controller, full range of motion, goals = FK of uniform postures in the bounds.

    Measured: 0.86 of 2000 goals (male 1.75 m) and 0.86 (female 1.62 m); the misses are
    mostly goals above/behind the shoulder, where the null-space pull towards mid-range
    (27.5 deg trunk flexion, 60 deg shoulder flexion) fights the task.
    """
    n = 500
    goals = sample_goals(sim, sim.bounds, n, 11)
    traj = sim.simulate(sim.bounds.reshape(1, -1), goals)
    rate = float(traj.reached.double().mean())
    print(f"human reach rate to goals inside the full bounds: {rate:.3f}")
    assert rate >= 0.8
    lo, hi = sim.bounds[:, 0], sim.bounds[:, 1]
    assert bool(((traj.q >= lo - 1e-9) & (traj.q <= hi + 1e-9)).all())
    final = traj.ee[torch.arange(n), traj.length - 1]
    dist = torch.linalg.vector_norm(final - goals, dim=-1)
    assert bool((dist[traj.reached] < sim.config.tol).all())


def test_arm_only_subset_of_joints():
    arm = EXPECTED_NAMES[2:]
    s = human(joints=arm)
    assert s.joint_names == arm
    torch.testing.assert_close(s.start, default_start()[2:])
    theta = impaired_limits(s, "frozen_shoulder")
    assert theta.shape == (14,)
    torch.testing.assert_close(theta, impaired_limits(human(), "frozen_shoulder")[4:])


def test_impaired_reaches_stay_within_profile(sim):
    theta = impaired_limits(sim, "frozen_shoulder")
    goals = sample_goals(sim, sim.bounds, 32, 3)  # many lie outside the impaired workspace
    traj = sim.simulate(theta, goals)
    lim = theta.reshape(-1, 2).to(traj.q.dtype)
    assert bool(((traj.q >= lim[:, 0] - 1e-6) & (traj.q <= lim[:, 1] + 1e-6)).all())


# --------------------------------------------------------------------------- profiles


@pytest.mark.parametrize("name", sorted(IMPAIRED_PROFILES))
def test_impaired_profiles_are_valid(sim, name):
    profile = IMPAIRED_PROFILES[name]
    assert profile.name == name and profile.rationale and profile.source
    theta = impaired_limits(sim, name)
    assert theta.shape == (18,)
    check_theta(theta, 9)
    lim = theta.reshape(9, 2)
    bounds = sim.bounds.to(theta.dtype)
    assert bool((lim[:, 0] >= bounds[:, 0] - 1e-12).all() and (lim[:, 1] <= bounds[:, 1] + 1e-12).all())
    start = sim.start.to(theta.dtype)
    assert bool(((start >= lim[:, 0]) & (start <= lim[:, 1])).all())
    for i, joint in enumerate(JOINT_NAMES):
        if joint in profile.limits_deg:
            lo, hi = profile.limits_deg[joint]
            assert float(lim[i, 1] - lim[i, 0]) < float(bounds[i, 1] - bounds[i, 0])
            assert (float(lim[i, 0]), float(lim[i, 1])) == pytest.approx((math.radians(lo), math.radians(hi)))
        else:
            torch.testing.assert_close(lim[i], bounds[i], atol=0, rtol=0)
    # the bounds-only entry point gives the same theta
    torch.testing.assert_close(impaired_limits(sim.bounds, name), theta)
    torch.testing.assert_close(impaired_limits(sim.bounds.reshape(-1), profile), theta)


def test_profile_values():
    deg = {k: v.limits_deg for k, v in IMPAIRED_PROFILES.items()}
    assert deg["frozen_shoulder"]["shoulder_flexion"][1] <= 100
    assert deg["frozen_shoulder"]["shoulder_abduction"][1] <= 90
    assert deg["frozen_shoulder"]["shoulder_rotation"][0] >= -30  # external rotation <= 30 deg
    assert deg["elbow_flexion_contracture"]["elbow_flexion"] == (35.0, 120.0)
    assert deg["restricted_wrist"]["wrist_flexion"] == (-30.0, 30.0)
    assert deg["restricted_wrist"]["wrist_deviation"] == (-10.0, 10.0)
    for limits in deg.values():
        for joint, (lo, hi) in limits.items():
            assert lo <= DEFAULT_START_DEG[joint] <= hi


def test_profile_errors(sim):
    with pytest.raises(ValueError, match="profile.*known.*frozen_shoulder"):
        impaired_limits(sim, "broken_everything")
    excludes_start = ImpairmentProfile("stiff_elbow", {"elbow_flexion": (90.0, 100.0)})
    with pytest.raises(ValueError, match="profile.*elbow_flexion"):
        impaired_limits(sim, excludes_start)
    with pytest.raises(ValueError, match="limits_deg"):
        ImpairmentProfile("bad", {"knee_flexion": (0.0, 10.0)})
    with pytest.raises(ValueError, match="limits_deg"):
        ImpairmentProfile("bad", {"elbow_flexion": (50.0, 10.0)})
    with pytest.raises(ValueError, match="sim_or_bounds"):
        impaired_limits(torch.zeros(5, 2), "frozen_shoulder")


# ------------------------------------------------------------------------ bad inputs


@pytest.mark.parametrize("sex", ["other", "", None, 1, "males"])
def test_bad_sex(sex):
    with pytest.raises(ValueError, match="sex"):
        human_urdf(1.75, sex)


@pytest.mark.parametrize("height", [0.0, -1.7, float("nan"), float("inf"), 0.3, 3.0, 175, "1.75", True])
def test_bad_height(height):
    with pytest.raises(ValueError, match="height_m"):
        human(height)


def test_sex_is_case_insensitive_and_mass_optional():
    assert human_urdf(1.6, "Female") == human_urdf(1.6, "female")
    with pytest.raises(ValueError, match="mass_kg"):
        human_urdf(1.6, "female", mass_kg=-3.0)
    heavy = human_urdf(1.6, "female", mass_kg=95.0)
    assert heavy != human_urdf(1.6, "female")
