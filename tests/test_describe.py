"""`camo-sbi describe`: the joint table, the frames, the figure; the human model's sign
conventions (JOINT_SIGNS) checked against its forward kinematics; "joint missing" errors list
every joint the model expects."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest

from camo_sbi.experiments.cli import main
from camo_sbi.experiments.describe import joint_table
from camo_sbi.experiments.models import load_limits
from camo_sbi.simulators.human import JOINT_NAMES, JOINT_SIGNS, human


@pytest.fixture(scope="module")
def body():
    return human(1.75, "male")


def test_describe_human_prints_table_and_writes_figure(tmp_path, capsys):
    assert main(["describe", "--model", "human", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "x forward (anterior), y to the person's left, z up" in out
    assert "RIGHT arm" in out and "'right_hand_tip'" in out
    assert "joint order (the columns of a recording, --start, --limits): " + ", ".join(JOINT_NAMES) in out
    for pos, neg in JOINT_SIGNS.values():
        assert pos in out and neg in out
    t = pd.read_csv(tmp_path / "human_joints.csv")
    assert list(t["joint"]) == list(JOINT_NAMES)
    assert list(t["axis_base_frame"]) == ["+y", "+z", "-y", "-x", "+z", "-y", "+z", "+x", "-y"]
    row = t.set_index("joint").loc["shoulder_rotation"]
    assert (row["lower"], row["upper"], row["positive"]) == (-90.0, 70.0, "internal rotation")
    png = (tmp_path / "human_model.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000


def test_describe_urdf_uses_the_right_hand_rule(tmp_path, capsys):
    assert main(["describe", "--urdf", "tests/data/arm7.urdf", "--ee", "tool", "--out", str(tmp_path)]) == 0
    t = pd.read_csv(tmp_path / "arm7_joints.csv")
    assert t["positive"].str.startswith("right-hand rotation about").all()


def _tip(body, **deg):
    q = np.array([math.radians(deg.get(j, 0.0)) for j in JOINT_NAMES])
    return body.spec.fk_numpy(q)


def _frame(body, joint: str, **deg):
    q = np.array([math.radians(deg.get(j, 0.0)) for j in JOINT_NAMES])
    frames, _ = body.spec.joint_frames(q)
    return frames[JOINT_NAMES.index(joint)]


@pytest.mark.parametrize("joint, pose, axis, sign", [
    ("torso_flexion", {"shoulder_flexion": 90.0}, 0, +1),        # the trunk (and the raised arm) bends forward
    ("torso_rotation", {}, 0, +1),                               # turning left brings the right arm forward
    ("shoulder_flexion", {}, 0, +1),                             # arm raised forward
    ("shoulder_abduction", {}, 1, -1),                           # right arm away from the body (-y)
    ("shoulder_rotation", {"elbow_flexion": 90.0}, 1, +1),       # forearm swings medially (+y): internal
    ("elbow_flexion", {}, 0, +1),                                # hand comes forward
    ("wrist_flexion", {}, 1, +1),                                # palm faces +y (medially): palmar flexion
    ("wrist_deviation", {}, 0, +1),                              # thumb forward (+x): radial deviation
])
def test_human_positive_directions_follow_the_kinematics(body, joint, pose, axis, sign):
    before = _tip(body, **pose)
    after = _tip(body, **{**pose, joint: 20.0})
    assert sign * (after[axis] - before[axis]) > 0.01


def test_pronation_turns_the_palm_backward(body):
    # the hand's palm normal is +y of its frame at the zero posture (thumb +x)
    palm0 = _frame(body, "wrist_deviation")[:3, :3] @ np.array([0.0, 1.0, 0.0])
    palm = _frame(body, "wrist_deviation", forearm_pronation=60.0)[:3, :3] @ np.array([0.0, 1.0, 0.0])
    np.testing.assert_allclose(palm0, [0, 1, 0], atol=1e-9)
    assert palm[0] < -0.8  # faces backward (-x) with the arm hanging: pronation


def test_joint_table_matches_the_chain(body):
    t = joint_table(body, "human")
    frames, _ = body.spec.joint_frames(np.zeros(9))
    np.testing.assert_allclose(t[["centre_x_m", "centre_y_m", "centre_z_m"]].to_numpy(), frames[:, :3, 3], atol=1e-4)
    np.testing.assert_allclose(t["start"], [0, 0, 15, 10, 0, 40, 0, 0, 0], atol=1e-9)


def test_missing_joint_error_lists_every_joint(body, tmp_path):
    path = tmp_path / "limits.json"
    path.write_text(json.dumps({"torso_flexion": [-10, 10]}))
    with pytest.raises(ValueError, match="joint 'torso_rotation' is missing") as err:
        load_limits(path, body, degrees=True)
    assert ", ".join(JOINT_NAMES) in str(err.value)
