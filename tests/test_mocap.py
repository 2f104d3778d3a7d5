"""Motion-capture recordings: C3D files (markers in mm, in a lab frame), frames, --goal final.

The C3D files are written here with ezc3d from the toolkit's own simulated reaches on
tests/data/arm7.urdf, in millimetres, in a lab frame where the model's base sits at
(1.2, -0.4, 0.8) m, rotated 90 degrees about z.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from camo_sbi.experiments.cli import main
from camo_sbi.experiments.models import load_limits
from camo_sbi.experiments.simulate import simulate_recordings
from camo_sbi.io.frames import frame_from_markers, load_frame
from camo_sbi.io.recordings import load_recording
from camo_sbi.io.schema import save_recordings
from camo_sbi.task import Observation
from tests import test_infer_cli
from tests.test_infer_cli import DATA, MODEL

ezc3d = pytest.importorskip("ezc3d")
sim = test_infer_cli.sim  # the arm7 model fixture

SHIFT = np.array([1.2, -0.4, 0.8])
RZ90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
BASE_MARKERS = {"BASE_A": [0.3, 0.0, 0.0], "BASE_B": [0.0, 0.3, 0.0], "BASE_C": [0.0, 0.0, 0.3]}


def to_lab(p: np.ndarray) -> np.ndarray:
    """Model base frame -> lab frame (the base at SHIFT, rotated 90 deg about z)."""
    return np.asarray(p) @ RZ90.T + SHIFT


def write_c3d(path: Path, observations, *, gap: int = 5, rate: float = 100.0, ee_name: str = "TOOL",
              split_marker: float | None = None) -> Path:
    """Reaches one after another, ``gap`` missing frames between them; markers in mm, lab frame.
    ``split_marker``: the end effector is also the mean of TOOL_L and TOOL_R, +-this many m apart in x."""
    frames = []
    for o in observations:
        frames.append(to_lab(o.ee.numpy()))
        frames.append(np.full((gap, 3), np.nan))
    ee = np.concatenate(frames[:-1])  # (F, 3) metres, lab
    labels = [ee_name, *BASE_MARKERS]
    tracks = [ee] + [np.broadcast_to(to_lab(np.array(v)), ee.shape) for v in BASE_MARKERS.values()]
    if split_marker is not None:
        labels += ["TOOL_L", "TOOL_R"]
        tracks += [ee + [split_marker, 0, 0], ee - [split_marker, 0, 0]]
    pts = np.ones((4, len(labels), ee.shape[0]))
    for k, t in enumerate(tracks):
        pts[:3, k, :] = t.T * 1000.0
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(labels)
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    c["data"]["points"] = pts
    c.write(str(path))
    return path


def write_frame(path: Path, quaternion: bool = False) -> Path:
    """The lab -> model transform: p_model = RZ90^T (p_lab - SHIFT)."""
    r = RZ90.T
    t = -r @ SHIFT
    rot = {"quaternion": [np.cos(-np.pi / 4), 0.0, 0.0, np.sin(-np.pi / 4)]} if quaternion else {"rotation": r.tolist()}
    path.write_text(json.dumps({**rot, "translation": t.tolist()}))
    return path


@pytest.fixture(scope="module")
def reaches(sim):
    theta = load_limits(DATA / "arm7_limits.json", sim).reshape(-1)
    obs = simulate_recordings(sim, theta, 4, seed=5)
    return tuple(Observation(o.start, o.ee[-1], None, o.ee) for o in obs)  # free reaching: goal = last sample


def _assert_same(a, b, atol):
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert x.length == y.length
        np.testing.assert_allclose(x.ee.numpy(), y.ee.numpy(), atol=atol)
        np.testing.assert_allclose(x.goal.numpy(), y.goal.numpy(), atol=atol)
        np.testing.assert_allclose(x.start.numpy(), y.start.numpy(), atol=1e-9)


def test_frame_file_matrix_and_quaternion_agree(tmp_path):
    a = load_frame(write_frame(tmp_path / "m.json"))
    b = load_frame(write_frame(tmp_path / "q.json", quaternion=True))
    np.testing.assert_allclose(a.rotation, b.rotation, atol=1e-12)
    p = np.array([[0.3, -0.2, 0.5]])
    np.testing.assert_allclose(a.apply(to_lab(p)), p, atol=1e-12)


@pytest.mark.parametrize("content, needle", [
    ({"rotation": np.eye(3).tolist()}, "key 'translation' is missing"),
    ({"rotation": (2 * np.eye(3)).tolist(), "translation": [0, 0, 0]}, "key 'rotation': not a rotation"),
    ({"rotation": np.diag([1, 1, -1]).tolist(), "translation": [0, 0, 0]}, "key 'rotation': not a rotation"),
    ({"quaternion": [1, 1, 0, 0], "translation": [0, 0, 0]}, "key 'quaternion': [w, x, y, z] must have norm 1"),
    ({"translation": [0, 0, 0]}, "give exactly one of 'rotation'"),
    ({"rotation": np.eye(3).tolist(), "translation": [0, 0], "x": 1}, "key 'x' is unknown"),
])
def test_bad_frame_files_name_the_key(tmp_path, content, needle):
    path = tmp_path / "frame.json"
    path.write_text(json.dumps(content))
    with pytest.raises(ValueError) as exc:
        load_frame(path)
    assert str(exc.value).startswith(f"--frame {path}: ") and needle in str(exc.value)


def test_frame_from_markers_recovers_the_transform():
    lab = {k: to_lab(np.array(v)) for k, v in BASE_MARKERS.items()}
    f = frame_from_markers(lab, {k: np.array(v) for k, v in BASE_MARKERS.items()})
    np.testing.assert_allclose(f.rotation, RZ90.T, atol=1e-12)
    np.testing.assert_allclose(f.translation, -RZ90.T @ SHIFT, atol=1e-12)
    assert f.residual_m < 1e-12
    with pytest.raises(ValueError, match="^--frame-from-markers: the markers .* are collinear"):
        frame_from_markers({"A": np.zeros(3), "B": np.ones(3), "C": 2 * np.ones(3)},
                           {"A": np.zeros(3), "B": np.ones(3), "C": 2 * np.ones(3)})


def test_c3d_in_mm_in_a_lab_frame_loads_as_the_model_frame_csv(tmp_path, sim, reaches):
    c3d = write_c3d(tmp_path / "session.c3d", reaches, split_marker=0.02)
    csv = save_recordings(tmp_path / "model.csv", reaches, sim)
    ref = load_recording(csv, sim).observations
    frame = load_frame(write_frame(tmp_path / "frame.json"))
    for kwargs in ({"frame": frame, "ee_markers": ["TOOL"]},
                   {"frame_markers": {k: np.array(v) for k, v in BASE_MARKERS.items()}, "ee_markers": ["TOOL"]},
                   {"frame": frame, "ee_markers": ["TOOL_L", "TOOL_R"]}):
        rec = load_recording(c3d, sim, goal="final", **kwargs)
        _assert_same(rec.observations, ref, atol=1e-5)  # float32 millimetres in the file
        assert rec.info["ee_units"] == "mm (POINT:UNITS)" and rec.warnings == ()
    assert load_recording(c3d, sim, goal="final", frame_markers={k: np.array(v) for k, v in BASE_MARKERS.items()},
                          ee_markers=["TOOL"]).info["frame_residual_mm"] < 0.01


def test_c3d_errors_name_the_flag_or_file(tmp_path, sim, reaches):
    c3d = write_c3d(tmp_path / "s.c3d", reaches)
    with pytest.raises(ValueError, match=r"^--ee-marker: marker 'HAND' is not in .*s\.c3d \(its markers: TOOL, "):
        load_recording(c3d, sim, goal="final", ee_markers=["HAND"])
    with pytest.raises(ValueError, match=r"^--ee-units: a C3D file's units come from its POINT:UNITS"):
        load_recording(c3d, sim, goal="final", ee_markers=["TOOL"], ee_units="mm")
    with pytest.raises(ValueError, match=r"^.*s\.c3d: column 'goal_x' is missing .*--goal final"):
        load_recording(c3d, sim, ee_markers=["TOOL"])
    fake = tmp_path / "fake.c3d"
    fake.write_bytes(b"\x00garbage" * 50)
    with pytest.raises(ValueError, match=r"^.*fake\.c3d: cannot read as C3D"):
        load_recording(fake, sim, goal="final", ee_markers=["TOOL"])


@pytest.mark.slow  # in the slow tier for the default tier's 4-minute budget (issue 28)
def test_infer_c3d_with_frame_and_goal_final_matches_the_model_frame_csv(tmp_path, sim, reaches, capsys):
    """Done-when of issue 27: the C3D (mm, lab frame shifted and rotated) with --ee-marker, --frame and
    --goal final gives limits within 2 degrees of the same reaches as a model-frame CSV."""
    c3d = write_c3d(tmp_path / "session.c3d", reaches)
    frame = write_frame(tmp_path / "frame.json", quaternion=True)
    csv = save_recordings(tmp_path / "model.csv", reaches, sim)
    common = [*MODEL, "--methods", "camo,nominal", "--budget", "100", "--seed", "0", "--noise-ee-mm", "1"]
    assert main(["infer", "--observations", str(c3d), "--ee-marker", "TOOL", "--frame", str(frame), "--goal",
                 "final", *common, "--out", str(tmp_path / "a")]) == 0
    assert main(["infer", "--observations", str(csv), *common, "--out", str(tmp_path / "b")]) == 0
    a = pd.read_csv(tmp_path / "a" / "limits.csv")
    b = pd.read_csv(tmp_path / "b" / "limits.csv")
    assert len(a) == len(b) == 2 * 2 * sim.n_joints
    assert float(np.abs(a.estimate_deg - b.estimate_deg).max()) < 2.0
    cfg = json.loads((tmp_path / "a" / "config.json").read_text())
    assert cfg["ee_units"] == "mm (POINT:UNITS)" and cfg["goal"] == "final"


# ----------------------------------------------------------------------------- BVH


BVH_CHANNELS = ("Zrotation", "Yrotation")  # the mapped channel of each joint: first and last of the ZXY order


def write_bvh(path: Path, observations, joints, *, signs, offsets, dt: float = 0.01) -> tuple[Path, dict]:
    """A BVH chain of one BVH joint per model joint (CHANNELS Z X Y, degrees), the reaches one after
    another, and its mapping file (model angle = sign * channel + offset)."""
    lines = ["HIERARCHY"]
    for k, _ in enumerate(joints):
        kind = "ROOT" if k == 0 else "JOINT"
        lines += ["  " * k + f"{kind} B{k}", "  " * k + "{", "  " * k + "  OFFSET 0 0.1 0",
                  "  " * k + "  CHANNELS 3 Zrotation Xrotation Yrotation"]
    lines += ["  " * len(joints) + "End Site", "  " * len(joints) + "{", "  " * len(joints) + "  OFFSET 0 0.1 0",
              "  " * len(joints) + "}"]
    lines += ["  " * k + "}" for k in reversed(range(len(joints)))]
    q = np.concatenate([o.q.numpy() for o in observations])
    lines += ["MOTION", f"Frames: {q.shape[0]}", f"Frame Time: {dt}"]
    for row in q:
        vals = []
        for k, v in enumerate(row):
            ch = (np.degrees(v) - offsets[k]) / signs[k]
            z, y = (ch, 0.0) if BVH_CHANNELS[k % 2] == "Zrotation" else (0.0, ch)
            vals += [z, 0.0, y]
        lines.append(" ".join(f"{v:.6f}" for v in vals))
    path.write_text("\n".join(lines) + "\n")
    ends = np.cumsum([o.length for o in observations])
    mapping = {"joints": {j: {"bvh": f"B{k}", "channel": BVH_CHANNELS[k % 2], "sign": signs[k],
                              "offset_deg": offsets[k]} for k, j in enumerate(joints)},
               "reaches": [[int(a), int(b) - 1] for a, b in zip(np.r_[0, ends[:-1]], ends, strict=True)]}
    map_path = path.with_suffix(".json")
    map_path.write_text(json.dumps(mapping))
    return path, mapping


def test_bvh_with_a_mapping_file_loads_as_the_joint_csv(tmp_path, sim):
    theta = load_limits(DATA / "arm7_limits.json", sim).reshape(-1)
    obs = tuple(Observation(o.start, sim.forward_kinematics(o.q[-1]).double(), o.q, None)
                for o in simulate_recordings(sim, theta, 3, seed=6))
    signs = [1, -1, 1, 1, -1, 1, 1]
    offsets = [0.0, 0.0, 10.0, 0.0, 0.0, -5.0, 0.0]
    bvh, _ = write_bvh(tmp_path / "arm.bvh", obs, list(sim.joint_names), signs=signs, offsets=offsets)
    rec = load_recording(bvh, sim, goal="final", bvh_map=bvh.with_suffix(".json"), resample=None)
    assert len(rec.observations) == 3
    for got, want in zip(rec.observations, obs, strict=True):
        np.testing.assert_allclose(got.q.numpy(), want.q.numpy(), atol=1e-6)  # 6 decimals of a degree
        np.testing.assert_allclose(got.goal.numpy(), want.goal.numpy(), atol=1e-6)
    with pytest.raises(ValueError, match=r"^--bvh-map: a BVH file .* needs the mapping"):
        load_recording(bvh, sim, goal="final")
    bad = json.loads(bvh.with_suffix(".json").read_text())
    bad["joints"]["elbow"]["bvh"] = "Forearm"
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match=r"^--bvh-map .*bad\.json: joint 'elbow': BVH joint 'Forearm' is not in"):
        load_recording(bvh, sim, goal="final", bvh_map=tmp_path / "bad.json")
    del bad["joints"]["elbow"]
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match=r"^--bvh-map .*bad\.json: joint 'elbow' is missing"):
        load_recording(bvh, sim, goal="final", bvh_map=tmp_path / "bad.json")


def _bvh_rows(path: Path, rows: np.ndarray, order: str = "Zrotation Xrotation Yrotation") -> Path:
    """A two-joint BVH (B0 with a position and three rotation channels, B1 with three) holding ``rows``."""
    text = ["HIERARCHY", "ROOT B0", "{", "  OFFSET 0 0 0", f"  CHANNELS 6 Xposition Yposition Zposition {order}",
            "  JOINT B1", "  {", "    OFFSET 0 0.3 0", f"    CHANNELS 3 {order}", "    End Site", "    {",
            "      OFFSET 0 0.2 0", "    }", "  }", "}", "MOTION", f"Frames: {len(rows)}", "Frame Time: 0.02"]
    path.write_text("\n".join(text + [" ".join(f"{v:.6f}" for v in r) for r in rows]) + "\n")
    return path


@pytest.mark.parametrize("order", ["Zrotation Xrotation Yrotation", "Xrotation Yrotation Zrotation",
                                   "Yrotation Zrotation Xrotation"])
def test_bvh_parser_reads_the_channels_bvhio_reads(tmp_path, order):
    """On complete files with angles inside (-90, 90) degrees (where an Euler triple is unique) our
    parser's channel values equal bvhio's per-frame rotation decomposed in the channel order (the
    reader used before issue 36), to 1e-4 degrees (bvhio works in float32)."""
    with __import__("warnings").catch_warnings():
        __import__("warnings").simplefilter("ignore")
        bvhio = pytest.importorskip("bvhio")
    from camo_sbi.io.bvh import parse_bvh

    rng = np.random.default_rng(3)
    rows = np.c_[rng.uniform(-1, 1, (40, 3)), rng.uniform(-85, 85, (40, 6))]
    path = _bvh_rows(tmp_path / "a.bvh", rows, order)
    got = parse_bvh(path)
    assert got.channels["B1"] == tuple(order.split()) and got.column == {"B0": 0, "B1": 6}
    assert got.frame_time == 0.02 and got.motion.shape == (40, 9)
    ref = bvhio.readAsBvh(str(path))
    for joint, first in (("B0", 3), ("B1", 6)):
        bj = ref.Root if joint == "B0" else ref.Root.Children[0]
        axes = [c for c in bj.Channels if c.endswith("rotation")]
        euler = np.array([list(k.getEuler(order="".join(c[0] for c in axes)[::-1], extrinsic=True))
                          for k in bj.Keyframes])
        for i, c in enumerate(axes):
            np.testing.assert_allclose(got.motion[:, first + i], euler[:, "XYZ".index(c[0])], atol=1e-4)
    np.testing.assert_allclose(got.motion, np.round(rows, 6), atol=1e-12)  # the file's own numbers


def test_bvh_keeps_a_middle_channel_beyond_90_degrees(tmp_path):
    """An elbow at 120 degrees in the middle channel: the value written (bvhio's Euler round trip
    gave 60, an equivalent rotation but not the joint angle)."""
    from camo_sbi.io.bvh import parse_bvh

    path = _bvh_rows(tmp_path / "a.bvh", np.array([[0, 0, 0, 10, 120, 5, 0, 0, 0], [0, 0, 0, 10, 30, 5, 0, 0, 0]]))
    np.testing.assert_allclose(parse_bvh(path).motion[:, 4], [120.0, 30.0])


def _cut(good: str, case: str) -> str:
    lines = good.splitlines()
    motion = lines.index("MOTION")
    return {"empty": "", "blank": "\n\n  \n", "cut_at_a_line": "\n".join(lines[:-10]) + "\n",
            "cut_in_a_row": good[: len(good) - 25],
            "no_motion": "\n".join(lines[:motion]) + "\n",
            "cut_in_the_hierarchy": "\n".join(lines[:5]) + "\n",
            "more_frames_declared": good.replace(lines[motion + 1], "Frames: 100000000000"),
            "fewer_frames_declared": good.replace(lines[motion + 1], "Frames: 3"),
            "nan_in_a_row": good.replace(lines[-1], " ".join(["nan"] * len(lines[-1].split()))),
            "word_in_a_row": good.replace(lines[-2], " ".join(["x"] * len(lines[-2].split()))),
            "short_row": good.replace(lines[-3], lines[-3].rsplit(" ", 1)[0]),
            "unbalanced_braces": good.replace("End Site", "JOINT Z\n{\nOFFSET 0 0 0\nCHANNELS 1 Xrotation", 1),
            "binary": "\x00\xff\xfe" * 100}[case]


@pytest.fixture(scope="module")
def joint_reaches(sim):
    theta = load_limits(DATA / "arm7_limits.json", sim).reshape(-1)
    return tuple(Observation(o.start, sim.forward_kinematics(o.q[-1]).double(), o.q, None)
                 for o in simulate_recordings(sim, theta, 2, seed=6))


@pytest.mark.timeout(60)
@pytest.mark.parametrize("case, needle", [
    ("empty", "is empty"), ("blank", "is empty"),
    ("cut_at_a_line", r"line \d+: 'Frames: \d+' declares \d+ motion rows but the file holds \d+ \(cut off\?\)"),
    ("cut_in_a_row", r"line \d+: a motion row needs 21 values \(one per channel\), found 1?\d"),
    ("no_motion", "end of file: the file ends where MOTION should follow"),
    ("cut_in_the_hierarchy", "end of file: the file ends where"),
    ("more_frames_declared", r"line \d+: 'Frames: 100000000000' declares 100000000000 motion rows but the file holds"),
    ("fewer_frames_declared", r"line \d+: 'Frames: 3' declares 3 motion rows but the file holds"),
    ("nan_in_a_row", r"line \d+: a motion row needs 21 finite numbers"),
    ("word_in_a_row", r"line \d+: a motion row needs 21 finite numbers"),
    ("short_row", r"line \d+: a motion row needs 21 values \(one per channel\), found 20"),
    ("unbalanced_braces", r"line \d+: expected JOINT, End Site or }, found"),
    ("binary", "not a UTF-8 text file"),
])
def test_damaged_bvh_is_refused_naming_the_file_and_line(tmp_path, sim, joint_reaches, case, needle):
    """Issue 36: an empty, cut-off or inconsistent BVH hung forever inside bvhio's parser."""
    good, _ = write_bvh(tmp_path / "good.bvh", joint_reaches, list(sim.joint_names), signs=[1] * 7,
                        offsets=[0.0] * 7)
    bad = tmp_path / f"{case}.bvh"
    bad.write_bytes(_cut(good.read_text(), case).encode("latin-1"))
    with pytest.raises(ValueError, match=rf"^{re.escape(str(bad))}: ({needle})"):
        load_recording(bad, sim, goal="final", bvh_map=good.with_suffix(".json"))


@pytest.mark.timeout(60)
def test_empty_bvh_exits_2_from_the_cli(tmp_path, capsys):
    (tmp_path / "e.bvh").touch()
    (tmp_path / "map.json").write_text(json.dumps({"joints": {}}))
    with pytest.raises(SystemExit) as exc:
        main(["infer", "--observations", str(tmp_path / "e.bvh"), "--bvh-map", str(tmp_path / "map.json"),
              "--goal", "final", *MODEL, "--methods", "naive", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and len(err) == 1 and err[0].startswith("camo-sbi: error: ")
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").glob("limits.csv"))


def test_overlapping_bvh_reaches_are_refused_naming_them(tmp_path, sim):
    from camo_sbi.io.bvh import load_bvh_map

    joints = {j: {"bvh": f"B{k}", "channel": "Zrotation"} for k, j in enumerate(sim.joint_names)}
    path = tmp_path / "map.json"
    path.write_text(json.dumps({"joints": joints, "reaches": [[50, 60], [0, 30], [10, 40]]}))
    with pytest.raises(ValueError, match=rf"^--bvh-map {path}: 'reaches' 1 \[0, 30\] and 2 \[10, 40\] overlap "
                                         r"\(frames 10-30 would count twice\)"):
        load_bvh_map(path, list(sim.joint_names))
    path.write_text(json.dumps({"joints": joints, "reaches": [[0, 30], [31, 40]]}))  # adjacent: fine
    assert load_bvh_map(path, list(sim.joint_names))["reaches"] == [[0, 30], [31, 40]]


def test_the_readme_session_c3d(tmp_path, sim, capsys):
    """README "From a motion-capture session": tests/data/session.c3d with its frame file, or with
    the frame fitted from its base markers, loads the same 8 reaches; infer runs on it."""
    from camo_sbi.io.frames import load_marker_positions

    c3d = DATA / "session.c3d"
    a = load_recording(c3d, sim, goal="final", ee_markers=["TOOL"], frame=load_frame(DATA / "session_frame.json"),
                       noise=None)
    names = ["BASE_A", "BASE_B", "BASE_C"]
    b = load_recording(c3d, sim, goal="final", ee_markers=["TOOL"],
                       frame_markers=load_marker_positions(DATA / "session_markers.json", names))
    assert len(a.observations) == 8 and b.info["frame_residual_mm"] < 0.01
    _assert_same(a.observations, b.observations, atol=1e-5)
    assert main(["infer", "--observations", str(c3d), "--ee-marker", "TOOL", "--frame-from-markers", ",".join(names),
                 "--marker-positions", str(DATA / "session_markers.json"), "--goal", "final", *MODEL,
                 "--noise-ee-mm", "1", "--methods", "nominal", "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert "limits [deg], lower .. upper" in out and "base_yaw" in out
