"""A 9-DOF human model (torso + right arm) generated as URDF text, with impairment profiles.

Why one module of ~700 lines: the anthropometric tables (segment ratios, masses, ranges of
motion, impairment profiles with their sources) and the URDF writer that uses them are one
definition of the model; most of the length is data with its references.

The model stands for the person in the paper's human-robot collaboration scenario
(CAMO, section V-B: "9 Degrees of Freedom in total -- 7 in the right arm, and 2 in the
torso"). The URDF is written by `human_urdf` from a height and a sex; it uses primitive
shapes only (boxes, cylinders, spheres) with segment masses and inertias, so it loads in
pybullet as well as in pytorch_kinematics. `human` builds a `KinematicSimulator` on it.

Frames
------
Right-handed, x forward (anterior), y to the person's left, z up (ROS REP-103).
The root link ``base`` is fixed, at the FLOOR directly under the mid-point of the hip
joint centres; it carries the legs and the pelvis. Placing the base at the world origin
therefore makes the chain's coordinates world coordinates (z = height above the floor).
The end effector is ``right_hand_tip`` (`END_EFFECTOR`): a point on the hand's long axis
half a hand length (0.054 H male, 0.049 H female) distal to the wrist joint centre, i.e.
close to the third metacarpal head (de Leva's WJC-MET3 = 0.050 H / 0.045 H), the centre
of a power grasp.

Joints, base to tip, and sign conventions (angle 0 = anatomical standing posture with
the arm hanging at the side, palm facing the thigh, thumb forward)
----------------------------------------------------------------------------------------
1. ``torso_flexion``      axis +y at the mid-hip point. + = forward bend (flexion),
                          - = backward bend (extension). Lumps hip and lumbar flexion.
2. ``torso_rotation``     axis +z along the trunk. + = turn to the left, - = to the right.
3. ``shoulder_flexion``   axis -y at the right shoulder joint centre. + = flexion (arm
                          raised forward), - = extension (arm moved backward).
4. ``shoulder_abduction`` axis -x (after flexion). + = abduction (arm raised sideways,
                          away from the body), - = adduction (across the body).
5. ``shoulder_rotation``  axis +z along the upper arm (pointing proximally).
                          + = internal rotation, - = external rotation.
6. ``elbow_flexion``      axis -y at the elbow joint centre. + = flexion; 0 = fully
                          extended.
7. ``forearm_pronation``  axis +z along the forearm (pointing proximally). 0 = mid-position
                          (thumb forward, as in goniometry); + = pronation, - = supination.
8. ``wrist_flexion``      axis +x at the wrist joint centre. + = palmar flexion,
                          - = dorsal extension.
9. ``wrist_deviation``    axis -y (after wrist flexion). + = radial deviation (towards the
                          thumb), - = ulnar deviation.

Anthropometry (fractions of standing height H)
----------------------------------------------
* upper arm (shoulder to elbow joint centre): 0.162 H male, 0.159 H female;
  forearm (elbow to wrist joint centre): 0.155 H / 0.152 H
  -- de Leva P. (1996) "Adjustments to Zatsiorsky-Seluyanov's segment inertia
  parameters", J Biomech 29(9):1223-1230, Table 4 (281.7 / 268.9 mm of 1741 mm for
  men, 275.1 / 264.3 mm of 1735 mm for women).
* hand (wrist joint centre to middle fingertip): 0.108 H male (Drillis R, Contini R
  (1966) "Body segment parameters", Rep. 1166-03, New York University, as tabulated in
  Winter DA (2009) "Biomechanics and Motor Control of Human Movement", 4th ed., Fig. 4.1);
  0.098 H female = 0.108 H scaled by de Leva's female/male ratio of relative WJC-MET3
  lengths ((78.0/1735) / (86.2/1741) = 0.908).
* mid-hip joint centre 0.530 H above the floor; shoulder joint centres 0.818 H, i.e. a
  trunk (hip joint centre to shoulder joint centre height) of 0.288 H -- Drillis & Contini
  (1966) / Winter (2009) Fig. 4.1 (for comparison: de Leva's suprasternale to mid-hip
  length is 0.305 H, and the shoulder joint centre lies a few cm below the suprasternale).
* shoulder joint centre separation 0.21 H (right shoulder 0.105 H to the right of the
  mid-sagittal plane): biacromial breadth of ~0.23 H (Drillis & Contini, ANSUR) minus
  ~2 cm per side from the acromion to the glenohumeral centre. Same ratio for both sexes.
* segment masses (fractions of body mass, de Leva 1996 Table 4) and, unless given,
  body mass from de Leva's reference subjects' body-mass index (73.0 kg at 1.741 m ->
  24.1 kg m^-2 male; 61.9 kg at 1.735 m -> 20.6 kg m^-2 female). Inertias are those of
  the primitives used as collision shapes (kinematics do not depend on them).

With H = 1.75 m (male) the arm from the shoulder to ``right_hand_tip`` measures
(0.162 + 0.155 + 0.054) H = 0.649 m; the shoulder is at 1.43 m and the hip at 0.93 m.

Range of motion (`NORMATIVE_ROM_DEG`, put into the URDF ``<limit>``)
------------------------------------------------------------------
American Academy of Orthopaedic Surgeons normative values (AAOS (1965) "Joint Motion:
Method of Measuring and Recording"; Greene WB, Heckman JD (eds.) (1994) "The Clinical
Measurement of Joint Motion", AAOS, Rosemont IL), consistent with the healthy reference
values of Soucie JM et al. (2011) "Range of motion measurements: reference values and a
database for comparison studies", Haemophilia 17(3):500-507:

* thoracolumbar flexion 80 deg, extension 25 deg, axial rotation 45 deg each way;
* shoulder flexion 180, extension 60, abduction 180, adduction 30 (our choice: cross-body
  adduction from the side is blocked by the trunk, reported values span 30-50 deg; we
  take the lower end as the model has no self-collision), internal rotation 70,
  external rotation 90;
* elbow flexion 150, extension 0 (no hyperextension);
* forearm pronation 80, supination 80;
* wrist flexion 80, extension 70, radial deviation 20, ulnar deviation 30.

The default start (`DEFAULT_START_DEG`) is the arm hanging slightly forward with the
elbow bent: shoulder flexion 15, abduction 10, elbow flexion 40 deg, all else 0. It lies
inside the full bounds and inside every profile of `IMPAIRED_PROFILES`.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np
import torch

from camo_sbi._validation import as_tensor, check_finite, check_positive_float
from camo_sbi.simulators.simulator import KinematicSimulator, from_urdf

__all__ = [
    "Anthropometry",
    "DEFAULT_START_DEG",
    "END_EFFECTOR",
    "IMPAIRED_PROFILES",
    "ImpairmentProfile",
    "JOINT_NAMES",
    "JOINT_SIGNS",
    "NORMATIVE_ROM_DEG",
    "anthropometry",
    "default_start",
    "human",
    "human_urdf",
    "impaired_limits",
    "normative_bounds",
]

JOINT_NAMES: tuple[str, ...] = (
    "torso_flexion",
    "torso_rotation",
    "shoulder_flexion",
    "shoulder_abduction",
    "shoulder_rotation",
    "elbow_flexion",
    "forearm_pronation",
    "wrist_flexion",
    "wrist_deviation",
)
"""Movable joints, base to tip (the simulator's joint order)."""

JOINT_SIGNS: Mapping[str, tuple[str, str]] = MappingProxyType(
    {
        "torso_flexion": ("forward bend (flexion)", "backward bend (extension)"),
        "torso_rotation": ("trunk turns to the left", "trunk turns to the right"),
        "shoulder_flexion": ("arm raised forward (flexion)", "arm moved backward (extension)"),
        "shoulder_abduction": ("arm raised sideways, away from the body (abduction)",
                               "arm across the body (adduction)"),
        "shoulder_rotation": ("internal rotation", "external rotation"),
        "elbow_flexion": ("elbow flexion (0 = fully extended)", "hyperextension (outside the range)"),
        "forearm_pronation": ("pronation (palm turns backward / down)", "supination (palm turns forward / up)"),
        "wrist_flexion": ("palmar flexion", "dorsal extension"),
        "wrist_deviation": ("radial deviation (towards the thumb)", "ulnar deviation (towards the little finger)"),
    }
)
"""Per joint, what a positive and a negative angle mean (the module docstring's conventions;
checked against the forward kinematics by tests/test_describe.py)."""

END_EFFECTOR = "right_hand_tip"
"""End-effector link: half a hand length distal to the wrist joint centre."""

NORMATIVE_ROM_DEG: Mapping[str, tuple[float, float]] = MappingProxyType(
    {
        "torso_flexion": (-25.0, 80.0),  # extension 25, flexion 80 (AAOS thoracolumbar)
        "torso_rotation": (-45.0, 45.0),  # right / left axial rotation 45 each
        "shoulder_flexion": (-60.0, 180.0),  # extension 60, flexion 180
        "shoulder_abduction": (-30.0, 180.0),  # adduction 30 (our choice), abduction 180
        "shoulder_rotation": (-90.0, 70.0),  # external 90, internal 70
        "elbow_flexion": (0.0, 150.0),  # full extension 0, flexion 150
        "forearm_pronation": (-80.0, 80.0),  # supination 80, pronation 80
        "wrist_flexion": (-70.0, 80.0),  # extension 70, flexion 80
        "wrist_deviation": (-30.0, 20.0),  # ulnar 30, radial 20
    }
)
"""Full range of motion [lo, hi] in degrees per joint (AAOS; signs as in the module doc)."""

DEFAULT_START_DEG: Mapping[str, float] = MappingProxyType(
    {
        "torso_flexion": 0.0,
        "torso_rotation": 0.0,
        "shoulder_flexion": 15.0,
        "shoulder_abduction": 10.0,
        "shoulder_rotation": 0.0,
        "elbow_flexion": 40.0,
        "forearm_pronation": 0.0,
        "wrist_flexion": 0.0,
        "wrist_deviation": 0.0,
    }
)
"""Default start posture in degrees: arm hanging slightly forward, elbow bent."""

_SEXES = ("male", "female")
_HEIGHT_RANGE_M = (0.5, 2.5)

# Fractions of stature H (see module docstring for the sources).
_SEGMENT_FRACTIONS = {
    "male": {"upper_arm": 0.162, "forearm": 0.155, "hand": 0.108},
    "female": {"upper_arm": 0.159, "forearm": 0.152, "hand": 0.098},
}
_HIP_HEIGHT = 0.530  # mid-hip joint centre above the floor (Drillis & Contini)
_TRUNK = 0.288  # shoulder joint centre above hip joint centre (0.818 H - 0.530 H)
_SHOULDER_SEPARATION = 0.21  # between the two shoulder joint centres
_HIP_SEPARATION = 0.10  # between the two hip joint centres (legs' visuals only)

# de Leva (1996) Table 4 segment masses (fraction of body mass), male / female.
_MASS_FRACTIONS = {
    "male": {"head": 0.0694, "trunk": 0.4346, "upper_trunk": 0.1596, "middle_trunk": 0.1633,
             "lower_trunk": 0.1117, "upper_arm": 0.0271, "forearm": 0.0162, "hand": 0.0061,
             "thigh": 0.1416, "shank": 0.0433, "foot": 0.0137},
    "female": {"head": 0.0668, "trunk": 0.4257, "upper_trunk": 0.1545, "middle_trunk": 0.1465,
               "lower_trunk": 0.1247, "upper_arm": 0.0255, "forearm": 0.0138, "hand": 0.0056,
               "thigh": 0.1478, "shank": 0.0481, "foot": 0.0129},
}
# de Leva's reference subjects: 73.0 kg / 1.741 m (male), 61.9 kg / 1.735 m (female).
_REFERENCE_BMI = {"male": 73.0 / 1.741**2, "female": 61.9 / 1.735**2}


# --------------------------------------------------------------------------------------
# Anthropometry
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Anthropometry:
    """Segment dimensions (metres) and masses (kg) of one generated model.

    Attributes:
        height_m: standing height H.
        sex: "male" or "female".
        mass_kg: body mass.
        hip_height: mid-hip joint centre above the floor (0.530 H).
        trunk: shoulder joint centre above the hip joint centre (0.288 H).
        shoulder_offset: right shoulder joint centre to the mid-sagittal plane (0.105 H).
        upper_arm, forearm, hand: joint-centre based segment lengths (hand: wrist to
            middle fingertip).
    """

    height_m: float
    sex: str
    mass_kg: float
    hip_height: float
    trunk: float
    shoulder_offset: float
    upper_arm: float
    forearm: float
    hand: float

    @property
    def tip_offset(self) -> float:
        """Wrist joint centre to ``right_hand_tip`` (half the hand length)."""
        return 0.5 * self.hand

    @property
    def arm_reach(self) -> float:
        """Shoulder joint centre to ``right_hand_tip`` with the arm straight."""
        return self.upper_arm + self.forearm + self.tip_offset

    @property
    def shoulder_position(self) -> tuple[float, float, float]:
        """Right shoulder joint centre in the base frame at the zero posture."""
        return (0.0, -self.shoulder_offset, self.hip_height + self.trunk)


def _check_height(height_m) -> float:
    if isinstance(height_m, bool) or not isinstance(height_m, numbers.Real):
        raise ValueError(f"height_m: expected a real number of metres, got {height_m!r}")
    h = check_positive_float(height_m, "height_m")
    lo, hi = _HEIGHT_RANGE_M
    if not lo <= h <= hi:
        raise ValueError(f"height_m: expected a standing height in metres within [{lo}, {hi}], got {h}")
    return h


def _check_sex(sex) -> str:
    s = sex.strip().lower() if isinstance(sex, str) else None
    if s not in _SEXES:
        raise ValueError(f"sex: expected one of {list(_SEXES)}, got {sex!r}")
    return s


def anthropometry(height_m: float = 1.75, sex: str = "male", mass_kg: float | None = None) -> Anthropometry:
    """Segment lengths/masses for a standing height (m) and sex (see the module docstring)."""
    h = _check_height(height_m)
    s = _check_sex(sex)
    if mass_kg is None:
        m = _REFERENCE_BMI[s] * h * h
    else:
        m = check_positive_float(mass_kg, "mass_kg")
        if not 10.0 <= m <= 400.0:
            raise ValueError(f"mass_kg: expected a body mass within [10, 400] kg, got {m}")
    f = _SEGMENT_FRACTIONS[s]
    return Anthropometry(
        height_m=h,
        sex=s,
        mass_kg=m,
        hip_height=_HIP_HEIGHT * h,
        trunk=_TRUNK * h,
        shoulder_offset=0.5 * _SHOULDER_SEPARATION * h,
        upper_arm=f["upper_arm"] * h,
        forearm=f["forearm"] * h,
        hand=f["hand"] * h,
    )


def normative_bounds(dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """(9, 2) full range of motion [lo, hi] in radians, in `JOINT_NAMES` order."""
    return torch.tensor([[math.radians(v) for v in NORMATIVE_ROM_DEG[j]] for j in JOINT_NAMES], dtype=dtype)


def default_start(dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """(9,) default start posture in radians, in `JOINT_NAMES` order."""
    return torch.tensor([math.radians(DEFAULT_START_DEG[j]) for j in JOINT_NAMES], dtype=dtype)


# --------------------------------------------------------------------------------------
# URDF generation
# --------------------------------------------------------------------------------------


def _f(x: float) -> str:
    """Shortest round-trip text of a float (exact limits in the URDF)."""
    x = float(x)
    return repr(0.0 if x == 0 else x)


def _vec(v) -> str:
    return " ".join(_f(x) for x in v)


@dataclass
class _Shape:
    """A primitive placed in a link frame (axis-aligned), for visual, collision, inertia."""

    kind: str  # "box" (size xyz), "cylinder" (radius, length along z), "sphere" (radius)
    dims: tuple[float, ...]
    xyz: tuple[float, float, float]
    mass: float
    material: str
    collide: bool = True

    def geometry(self) -> str:
        if self.kind == "box":
            return f'<box size="{_vec(self.dims)}"/>'
        if self.kind == "cylinder":
            return f'<cylinder radius="{_f(self.dims[0])}" length="{_f(self.dims[1])}"/>'
        return f'<sphere radius="{_f(self.dims[0])}"/>'

    def principal_inertia(self) -> np.ndarray:
        m = self.mass
        if self.kind == "box":
            a, b, c = self.dims
            return m / 12.0 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
        if self.kind == "cylinder":
            r, L = self.dims
            t = m * (3 * r * r + L * L) / 12.0
            return np.array([t, t, 0.5 * m * r * r])
        r = self.dims[0]
        return np.full(3, 0.4 * m * r * r)


def _link(name: str, shapes: list[_Shape], *, virtual_mass: float = 0.0) -> str:
    """A <link> with visuals, collisions and the combined inertial of ``shapes``."""
    parts = [s for s in shapes if s.mass > 0]
    if parts:
        masses = np.array([s.mass for s in parts])
        pos = np.array([s.xyz for s in parts], dtype=float)
        mass = float(masses.sum())
        com = (masses[:, None] * pos).sum(0) / mass
        inertia = np.zeros((3, 3))
        for s, p in zip(parts, pos, strict=True):
            d = p - com
            inertia += np.diag(s.principal_inertia()) + s.mass * (d @ d * np.eye(3) - np.outer(d, d))
    else:  # a virtual link between two coincident joints: tiny point-like inertial
        mass, com = virtual_mass, np.zeros(3)
        inertia = np.eye(3) * virtual_mass * 1e-4
    lines = [f'  <link name="{name}">']
    lines.append(
        f'    <inertial><origin xyz="{_vec(com)}" rpy="0 0 0"/><mass value="{_f(mass)}"/>'
        f'<inertia ixx="{_f(inertia[0, 0])}" ixy="{_f(inertia[0, 1])}" ixz="{_f(inertia[0, 2])}" '
        f'iyy="{_f(inertia[1, 1])}" iyz="{_f(inertia[1, 2])}" izz="{_f(inertia[2, 2])}"/></inertial>'
    )
    for s in shapes:
        origin = f'<origin xyz="{_vec(s.xyz)}" rpy="0 0 0"/>'
        lines.append(
            f"    <visual>{origin}<geometry>{s.geometry()}</geometry>"
            f'<material name="{s.material}"/></visual>'
        )
        if s.collide:
            lines.append(f"    <collision>{origin}<geometry>{s.geometry()}</geometry></collision>")
    lines.append("  </link>")
    return "\n".join(lines)


def _revolute(name: str, parent: str, child: str, xyz, axis, limit_deg) -> str:
    lo, hi = (math.radians(v) for v in limit_deg)
    return (
        f'  <joint name="{name}" type="revolute">\n'
        f'    <parent link="{parent}"/><child link="{child}"/>\n'
        f'    <origin xyz="{_vec(xyz)}" rpy="0 0 0"/><axis xyz="{_vec(axis)}"/>\n'
        f'    <limit lower="{_f(lo)}" upper="{_f(hi)}" effort="100.0" velocity="3.0"/>\n'
        f"  </joint>"
    )


def _fixed(name: str, parent: str, child: str, xyz) -> str:
    return (
        f'  <joint name="{name}" type="fixed">\n'
        f'    <parent link="{parent}"/><child link="{child}"/>\n'
        f'    <origin xyz="{_vec(xyz)}" rpy="0 0 0"/>\n'
        f"  </joint>"
    )


_MATERIALS = {
    "skin": (0.87, 0.72, 0.60, 1.0),
    "shirt": (0.25, 0.42, 0.70, 1.0),
    "trousers": (0.30, 0.30, 0.35, 1.0),
    "hair": (0.25, 0.18, 0.12, 1.0),
    "marker": (0.90, 0.15, 0.15, 1.0),
}


def human_urdf(height_m: float = 1.75, sex: str = "male", *, mass_kg: float | None = None) -> str:
    """URDF text of the 9-DOF torso + right-arm model (see the module docstring).

    Args:
        height_m: standing height in metres, within [0.5, 2.5].
        sex: "male" or "female" (case-insensitive); selects the segment-length and
            segment-mass fractions.
        mass_kg: body mass; default from de Leva's reference body-mass index for ``sex``.

    Returns:
        URDF text; root link ``base`` at the floor under the pelvis, end-effector link
        `END_EFFECTOR`, movable joints `JOINT_NAMES` with `NORMATIVE_ROM_DEG` limits.
    """
    a = anthropometry(height_m, sex, mass_kg)
    H, M, mf = a.height_m, a.mass_kg, _MASS_FRACTIONS[a.sex]
    hip, trunk, sho = a.hip_height, a.trunk, a.shoulder_offset
    Lu, Lf, Lh = a.upper_arm, a.forearm, a.hand
    leg_mass = (mf["thigh"] + mf["shank"] + mf["foot"]) * M
    arm_mass = (mf["upper_arm"] + mf["forearm"] + mf["hand"]) * M
    virtual = 1e-3 * M  # small mass of the virtual links between coincident joints

    # Base: legs (visual and collision) and pelvis, frame on the floor under the mid-hip.
    leg_r = 0.035 * H
    base = [
        _Shape("cylinder", (leg_r, hip), (0.0, side * 0.5 * _HIP_SEPARATION * H, 0.5 * hip),
               0.5 * leg_mass, "trousers")
        for side in (1.0, -1.0)
    ]
    base.append(_Shape("box", (0.11 * H, 0.19 * H, 0.07 * H), (0.0, 0.0, hip), mf["lower_trunk"] * M,
                       "trousers"))
    # Torso (frame at the mid-hip joint centre): trunk, neck, head and the hanging left arm.
    trunk_bottom, trunk_top = 0.035 * H, trunk + 0.03 * H
    head_r = 0.057 * H
    torso = [
        _Shape("box", (0.11 * H, 0.18 * H, trunk_top - trunk_bottom),
               (0.0, 0.0, 0.5 * (trunk_top + trunk_bottom)), (mf["upper_trunk"] + mf["middle_trunk"]) * M,
               "shirt"),
        _Shape("cylinder", (0.028 * H, 0.08 * H), (0.0, 0.0, trunk_top + 0.03 * H), 0.0, "skin",
               collide=False),
        _Shape("sphere", (head_r,), (0.0, 0.0, trunk + (1.0 - _HIP_HEIGHT - _TRUNK) * H - head_r),
               mf["head"] * M, "skin"),
        _Shape("cylinder", (0.025 * H, Lu + Lf + Lh), (0.0, sho, trunk - 0.5 * (Lu + Lf + Lh)),
               arm_mass, "skin"),
    ]
    upper_arm = [_Shape("cylinder", (0.026 * H, Lu), (0.0, 0.0, -0.5 * Lu), mf["upper_arm"] * M, "shirt")]
    forearm = [_Shape("cylinder", (0.02 * H, Lf), (0.0, 0.0, -0.5 * Lf), mf["forearm"] * M, "skin")]
    # Hand in the neutral forearm posture: thumb forward (+x), palm facing medially (+y).
    hand = [
        _Shape("box", (0.05 * H, 0.017 * H, Lh), (0.0, 0.0, -0.5 * Lh), mf["hand"] * M, "skin"),
        _Shape("box", (0.012 * H, 0.012 * H, 0.35 * Lh), (0.031 * H, 0.004 * H, -0.3 * Lh), 0.0, "skin",
               collide=False),
    ]
    tip = [_Shape("sphere", (0.006 * H,), (0.0, 0.0, 0.0), 0.0, "marker", collide=False)]

    rom = NORMATIVE_ROM_DEG
    body = [
        _link("base", base),
        _revolute("torso_flexion", "base", "lumbar", (0, 0, hip), (0, 1, 0), rom["torso_flexion"]),
        _link("lumbar", [], virtual_mass=virtual),
        _revolute("torso_rotation", "lumbar", "torso", (0, 0, 0), (0, 0, 1), rom["torso_rotation"]),
        _link("torso", torso),
        _revolute("shoulder_flexion", "torso", "right_shoulder_flexion_link", (0, -sho, trunk), (0, -1, 0),
                  rom["shoulder_flexion"]),
        _link("right_shoulder_flexion_link", [], virtual_mass=virtual),
        _revolute("shoulder_abduction", "right_shoulder_flexion_link", "right_shoulder_abduction_link",
                  (0, 0, 0), (-1, 0, 0), rom["shoulder_abduction"]),
        _link("right_shoulder_abduction_link", [], virtual_mass=virtual),
        _revolute("shoulder_rotation", "right_shoulder_abduction_link", "right_upper_arm", (0, 0, 0),
                  (0, 0, 1), rom["shoulder_rotation"]),
        _link("right_upper_arm", upper_arm),
        _revolute("elbow_flexion", "right_upper_arm", "right_elbow_link", (0, 0, -Lu), (0, -1, 0),
                  rom["elbow_flexion"]),
        _link("right_elbow_link", [], virtual_mass=virtual),
        _revolute("forearm_pronation", "right_elbow_link", "right_forearm", (0, 0, 0), (0, 0, 1),
                  rom["forearm_pronation"]),
        _link("right_forearm", forearm),
        _revolute("wrist_flexion", "right_forearm", "right_wrist_link", (0, 0, -Lf), (1, 0, 0),
                  rom["wrist_flexion"]),
        _link("right_wrist_link", [], virtual_mass=virtual),
        _revolute("wrist_deviation", "right_wrist_link", "right_hand", (0, 0, 0), (0, -1, 0),
                  rom["wrist_deviation"]),
        _link("right_hand", hand),
        _fixed("right_hand_tip_joint", "right_hand", END_EFFECTOR, (0, 0, -a.tip_offset)),
        _link(END_EFFECTOR, tip, virtual_mass=virtual),
    ]
    materials = [
        f'  <material name="{k}"><color rgba="{_vec(v)}"/></material>' for k, v in _MATERIALS.items()
    ]
    header = (
        '<?xml version="1.0"?>\n'
        f"<!-- camo_sbi human model: torso + right arm, 9 DOF; H = {H:.3f} m, {a.sex}, "
        f"{M:.1f} kg. Generated by camo_sbi.simulators.human.human_urdf. -->\n"
        f'<robot name="human_{a.sex}_{round(H * 1000)}mm">'
    )
    return "\n".join([header, *materials, *body, "</robot>"]) + "\n"


# --------------------------------------------------------------------------------------
# Simulator
# --------------------------------------------------------------------------------------


def human(height_m: float = 1.75, sex: str = "male", *, mass_kg: float | None = None,
          **kwargs) -> KinematicSimulator:
    """The 9-DOF human torso + right arm as a `KinematicSimulator`.

    Args:
        height_m: standing height in metres, within [0.5, 2.5].
        sex: "male" or "female".
        mass_kg: body mass (inertials only; kinematics do not depend on it).
        **kwargs: forwarded to `from_urdf` (``controller=``, ``backend=``, ``start=``,
            ``joints=``). ``start`` defaults to `default_start` (restricted to ``joints``
            when a subset of joint names is given).

    Returns:
        Simulator whose ``bounds`` are the normative ranges (`NORMATIVE_ROM_DEG`, radians),
        ``joint_names`` `JOINT_NAMES`, end effector `END_EFFECTOR`, base frame on the floor.
    """
    urdf = human_urdf(height_m, sex, mass_kg=mass_kg)
    if kwargs.get("start") is None:
        start = default_start()
        joints = kwargs.get("joints")
        if joints is not None and all(isinstance(j, str) for j in joints):
            unknown = [j for j in joints if j not in JOINT_NAMES]
            if unknown:
                raise ValueError(f"joints: unknown joint names {unknown}; known: {list(JOINT_NAMES)}")
            start = start[[JOINT_NAMES.index(j) for j in joints]]
        kwargs["start"] = start
    return from_urdf(urdf, END_EFFECTOR, **kwargs)


# --------------------------------------------------------------------------------------
# Impairment profiles
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ImpairmentProfile:
    """A range-of-motion deficit: per-joint [lo, hi] overrides in degrees.

    Attributes:
        name: short identifier (key of `IMPAIRED_PROFILES`).
        limits_deg: joint name -> (lo, hi) in degrees, same signs as `NORMATIVE_ROM_DEG`;
            joints not listed keep their full range.
        rationale: clinical picture the numbers represent.
        source: references the values are based on.
    """

    name: str
    limits_deg: Mapping[str, tuple[float, float]] = field(hash=False)
    rationale: str = ""
    source: str = ""

    def __post_init__(self):
        clean = {}
        for joint, lim in dict(self.limits_deg).items():
            if joint not in JOINT_NAMES:
                raise ValueError(f"limits_deg: unknown joint {joint!r}; known: {list(JOINT_NAMES)}")
            lo, hi = (float(v) for v in lim)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ValueError(f"limits_deg: {joint} needs finite lo <= hi, got {lim!r}")
            clean[joint] = (lo, hi)
        object.__setattr__(self, "limits_deg", MappingProxyType(clean))


IMPAIRED_PROFILES: Mapping[str, ImpairmentProfile] = MappingProxyType(
    {
        p.name: p
        for p in (
            ImpairmentProfile(
                "frozen_shoulder",
                {
                    "shoulder_flexion": (-35.0, 95.0),
                    "shoulder_abduction": (-20.0, 80.0),
                    "shoulder_rotation": (-25.0, 40.0),
                },
                rationale=(
                    "Adhesive capsulitis (frozen phase), capsular pattern: external rotation lost "
                    "most (90 -> 25 deg), then abduction (180 -> 80) and flexion (180 -> 95), "
                    "internal rotation and extension lost less."
                ),
                source=(
                    "Zuckerman JD, Rokito A (2011) Frozen shoulder: a consensus definition, "
                    "J Shoulder Elbow Surg 20(2):322-325; Kelley MJ et al. (2013) Shoulder pain "
                    "and mobility deficits: adhesive capsulitis, J Orthop Sports Phys Ther "
                    "43(5):A1-A31."
                ),
            ),
            ImpairmentProfile(
                "elbow_flexion_contracture",
                {"elbow_flexion": (35.0, 120.0)},
                rationale=(
                    "Post-traumatic elbow stiffness: 35 deg extension deficit and flexion "
                    "limited to 120 deg, an arc narrower than the 30-130 deg needed for most "
                    "activities of daily living."
                ),
                source=(
                    "Morrey BF, Askew LJ, Chao EY (1981) A biomechanical study of normal "
                    "functional elbow motion, J Bone Joint Surg Am 63(6):872-877; Sardelli M "
                    "et al. (2011) Functional elbow range of motion for contemporary tasks, "
                    "J Bone Joint Surg Am 93(5):471-477."
                ),
            ),
            ImpairmentProfile(
                "restricted_wrist",
                {"wrist_flexion": (-30.0, 30.0), "wrist_deviation": (-10.0, 10.0)},
                rationale=(
                    "Stiff wrist after a distal radius fracture: flexion and extension 30 deg "
                    "each, radial and ulnar deviation 10 deg each, below the functional wrist "
                    "range of motion."
                ),
                source=(
                    "Ryu J et al. (1991) Functional ranges of motion of the wrist joint, J Hand "
                    "Surg Am 16(3):409-419; Palmer AK et al. (1985) Functional wrist motion: a "
                    "biomechanical study, J Hand Surg Am 10(1):39-46."
                ),
            ),
            ImpairmentProfile(
                "hemiparesis_mild",
                {
                    "shoulder_flexion": (-40.0, 120.0),
                    "shoulder_abduction": (-30.0, 90.0),
                    "shoulder_rotation": (-30.0, 70.0),
                    "elbow_flexion": (15.0, 140.0),
                    "forearm_pronation": (-30.0, 80.0),
                    "wrist_flexion": (-30.0, 80.0),
                },
                rationale=(
                    "Mild post-stroke hemiparesis with flexor hypertonia/contractures: reduced "
                    "shoulder elevation and external rotation, incomplete elbow extension, "
                    "limited supination and wrist extension. Illustrative values, not a cohort "
                    "mean."
                ),
                source=(
                    "Kwah LK et al. (2012) Half of the adults who present to hospital with "
                    "stroke develop at least one contracture within six months, J Physiother "
                    "58(1):41-47; Sukal TM, Ellis MD, Dewald JPA (2007) Shoulder "
                    "abduction-induced reductions in reaching work area following hemiparetic "
                    "stroke, Exp Brain Res 183(2):215-223."
                ),
            ),
        )
    }
)
"""Named range-of-motion deficits (degrees). Every profile contains `DEFAULT_START_DEG`."""


def _resolve_profile(profile) -> ImpairmentProfile:
    if isinstance(profile, ImpairmentProfile):
        return profile
    if isinstance(profile, str) and profile in IMPAIRED_PROFILES:
        return IMPAIRED_PROFILES[profile]
    raise ValueError(
        f"profile: unknown impairment profile {profile!r}; known: {sorted(IMPAIRED_PROFILES)}"
    )


def impaired_limits(sim_or_bounds, profile: str | ImpairmentProfile) -> torch.Tensor:
    """Theta vector (2n,) = [lo_1, hi_1, ..., lo_n, hi_n] (radians) of an impaired person.

    Args:
        sim_or_bounds: a simulator (uses its ``bounds``, ``joint_names`` and ``start``)
            or full bounds, (n, 2) or (2n,), in `JOINT_NAMES` order (start =
            `default_start`). Joints not named by the profile keep these bounds.
        profile: a key of `IMPAIRED_PROFILES` or an `ImpairmentProfile`.

    Returns:
        (2n,) tensor, dtype/device of the bounds; each overridden range is intersected with
        the full bounds.

    Raises:
        ValueError naming ``profile`` if it is unknown, if an overridden range does not
        overlap the full bounds, or if the start posture falls outside the result.
    """
    prof = _resolve_profile(profile)
    if hasattr(sim_or_bounds, "bounds") and hasattr(sim_or_bounds, "joint_names"):
        bounds = as_tensor(sim_or_bounds.bounds, "sim_or_bounds.bounds")
        names = list(sim_or_bounds.joint_names)
        start = getattr(sim_or_bounds, "start", None)
        start = None if start is None else as_tensor(start, "sim_or_bounds.start").to(bounds)
    else:
        bounds = as_tensor(sim_or_bounds, "sim_or_bounds")
        names = list(JOINT_NAMES)
        start = default_start(dtype=bounds.dtype).to(bounds.device)
    if bounds.dim() == 1 and bounds.shape[0] % 2 == 0:
        bounds = bounds.reshape(-1, 2)
    if bounds.dim() != 2 or bounds.shape[1] != 2 or bounds.shape[0] != len(names):
        raise ValueError(
            f"sim_or_bounds: expected bounds of shape ({len(names)}, 2) or ({2 * len(names)},), "
            f"got {tuple(bounds.shape)}"
        )
    check_finite(bounds, "sim_or_bounds")
    if start is not None and start.shape != (len(names),):
        raise ValueError(f"sim_or_bounds: start has shape {tuple(start.shape)}, expected ({len(names)},)")

    limits = bounds.clone()
    for joint, (lo_deg, hi_deg) in prof.limits_deg.items():
        if joint not in names:  # e.g. a simulator built on a subset of the joints
            continue
        i = names.index(joint)
        lo = max(math.radians(lo_deg), float(bounds[i, 0]))
        hi = min(math.radians(hi_deg), float(bounds[i, 1]))
        if lo > hi:
            raise ValueError(
                f"profile: {prof.name!r} range for {joint} [{lo_deg}, {hi_deg}] deg does not "
                f"overlap the full bounds"
            )
        limits[i, 0], limits[i, 1] = lo, hi
    if start is not None:
        outside = (start < limits[:, 0] - 1e-9) | (start > limits[:, 1] + 1e-9)
        if bool(outside.any()):
            bad = [names[i] for i in torch.nonzero(outside).flatten().tolist()]
            raise ValueError(
                f"profile: {prof.name!r} excludes the start posture at joints {bad}; choose a "
                f"profile whose ranges contain the start"
            )
    return limits.reshape(-1)
