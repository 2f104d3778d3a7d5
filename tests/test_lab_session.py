"""A lab's session in (issue 34): a C3D of ISB landmarks -> the human model's joint angles ->
reaches found by hand speed -> limits; the same session's true angles as an OpenSim .mot give
the same naive limits; the .mot reader refuses malformed files naming the line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from camo_sbi.experiments.cli import main
from camo_sbi.experiments.lab_session import MARKER_LABELS, synthetic_session
from camo_sbi.io.mot import read_mot
from camo_sbi.io.recordings import load_recording
from camo_sbi.simulators.human import JOINT_NAMES, human
from camo_sbi.task import NoiseModel

pytest.importorskip("ezc3d")


@pytest.fixture(scope="module")
def body():
    return human(1.75, "male")


@pytest.fixture(scope="module")
def exact(tmp_path_factory):
    return synthetic_session(tmp_path_factory.mktemp("exact"), seed=0, reaches=2, noise_mm=0.0)


def _ranges(rec) -> np.ndarray:
    q = np.concatenate([o.q.numpy() for o in rec.observations])
    return np.degrees(np.stack([q.min(axis=0), q.max(axis=0)], axis=1))


def test_markers_and_mot_give_the_same_session(body, exact):
    """Noise-free landmarks: the ISB pipeline's angles are the true ones, the same reaches are
    found in both files (cuts within one frame), and the observed ranges (naive's limits) agree
    within 1 deg."""
    a = load_recording(exact["c3d"], body, markers="isb", marker_map=exact["map"], reaches="auto", resample=None)
    b = load_recording(exact["mot"], body, reaches="auto", resample=None)
    assert len(a.observations) == len(b.observations) == 4  # out and back, twice
    ta = np.array([[r["start_s"], r["end_s"]] for r in a.segments])
    tb = np.array([[r["start_s"], r["end_s"]] for r in b.segments])
    np.testing.assert_allclose(ta, tb, atol=0.011)
    np.testing.assert_allclose(_ranges(a), _ranges(b), atol=1.0)
    truth = pd.read_csv(exact["truth"])
    np.testing.assert_allclose(ta, truth[["start_s", "end_s"]].to_numpy(), atol=0.1)
    assert a.info["goal"] == "final" and a.info["joint_angles"].startswith("ISB landmarks")


def test_missing_landmark_in_the_map_is_named(body, exact, tmp_path):
    m = dict(MARKER_LABELS)
    del m["US"]
    bad = tmp_path / "map.json"
    bad.write_text(json.dumps(m))
    with pytest.raises(ValueError, match=r"^--marker-map .*map\.json: landmark 'US' is missing"):
        load_recording(exact["c3d"], body, markers="isb", marker_map=bad)
    bad.write_text(json.dumps({**MARKER_LABELS, "US": "RWRX"}))
    with pytest.raises(ValueError, match=r"^--marker-map: marker 'RWRX' is not in .*session\.c3d \(its markers: "):
        load_recording(exact["c3d"], body, markers="isb", marker_map=bad)
    with pytest.raises(ValueError, match=r"^--marker-map: --markers isb needs the map"):
        load_recording(exact["c3d"], body, markers="isb")


def _mot(tmp_path, body_lines, header=("name", "version=1", "inDegrees=yes", "endheader")):
    p = tmp_path / "x.mot"
    p.write_text("\n".join([*header, "\t".join(["time", *JOINT_NAMES, "pelvis_tx"]), *body_lines]) + "\n")
    return p


def _row(t, v=1.0):
    return "\t".join([f"{t}", *([f"{v}"] * len(JOINT_NAMES)), "0.5"])


def test_mot_reader_reads_degrees_and_skips_other_columns(tmp_path):
    d = read_mot(_mot(tmp_path, [_row(0.0), _row(0.01, 2.0)]), list(JOINT_NAMES))
    np.testing.assert_allclose(d["columns"]["elbow_flexion"], np.radians([1.0, 2.0]))
    assert d["skipped"] == ["pelvis_tx"] and d["in_degrees"]
    d = read_mot(_mot(tmp_path, [_row(0.0), _row(0.01, 2.0)], header=("inDegrees=no", "endheader")),
                 list(JOINT_NAMES))
    np.testing.assert_allclose(d["columns"]["elbow_flexion"], [1.0, 2.0])


@pytest.mark.parametrize("header, rows, needle", [
    (("name", "inDegrees=yes"), [_row(0.0), _row(0.1)], "no 'endheader' line"),
    (("inDegrees=maybe", "endheader"), [_row(0.0), _row(0.1)], "inDegrees='maybe'; expected yes or no"),
    (("nRows=3", "endheader"), [_row(0.0), _row(0.1)], "header nRows=3 but the file has 2 rows"),
    (("endheader",), [_row(0.0), _row(0.0)], "column 'time', line 4: time 0 does not increase"),
    (("endheader",), [_row(0.0), _row(0.1).replace("1.0", "nan", 1)], "line 4: NaN or inf"),
    (("endheader",), [_row(0.0), _row(0.1) + "\t3"], "line 4: has 12 fields, the labels have 11"),
])
def test_mot_reader_refuses(tmp_path, header, rows, needle):
    with pytest.raises(ValueError, match=".*" + needle.replace("(", r"\(").replace(")", r"\)")):
        read_mot(_mot(tmp_path, rows, header=header), list(JOINT_NAMES))


def test_mot_missing_joint_lists_every_joint(tmp_path):
    p = tmp_path / "y.mot"
    p.write_text("endheader\ntime\televation\n0\t1\n0.1\t2\n")
    with pytest.raises(ValueError, match="column 'torso_flexion' is missing") as err:
        read_mot(p, list(JOINT_NAMES))
    assert ", ".join(JOINT_NAMES) in str(err.value)


@pytest.mark.slow
def test_the_done_when_command_on_a_synthetic_session(tmp_path):
    """The issue's command, on the synthetic session (1 mm noise; not a real recording): exit 0,
    reaches.csv lists the reaches, the joint-space methods run, limits.csv carries the observed
    range beside every estimate."""
    files = synthetic_session(tmp_path / "lab", seed=1, reaches=2, noise_mm=1.0)
    out = tmp_path / "out"
    npe = json.dumps({"max_epochs": 3, "num_transforms": 1, "hidden_features": 8, "training_batch_size": 20,
                      "n_posterior_samples": 200, "is_rounds": 1})
    assert main(["infer", "--observations", str(files["c3d"]), "--model", "human", "--markers", "isb",
                 "--marker-map", str(files["map"]), "--reaches", "auto", "--side", "right", "--methods",
                 "naive,camo-seq,camo-touched,npe", "--budget", "60", "--noise-joint-deg", "1",
                 "--config", f"npe={npe}", "--out", str(out)]) == 0
    reaches = pd.read_csv(out / "reaches.csv")
    assert len(reaches) == 4 and set(reaches.rule) == {"speed"}
    limits = pd.read_csv(out / "limits.csv")
    assert set(limits.method) == {"naive", "camo-seq", "camo-touched", "npe"}
    assert limits.observed_min_deg.notna().all() and limits.observed_max_deg.notna().all()


# ----------------------------------------------------------------------------- a real session


REAL = Path(__file__).parent / "data" / "pyomeca_shoulder.c3d"
REAL_MAP = REAL.with_name("pyomeca_shoulder_map.json")


def test_real_session_gives_joint_angles_and_reaches(body):
    """pyomeca's upper-limb trial (tests/data/pyomeca_shoulder.SOURCE.md): the wrist's ulnar
    deviation goes past the model's 30 deg, which is refused naming the joint, the frame and what
    to check (never --degrees), or clipped with a warning; two reaches are found by hand speed."""
    with pytest.raises(ValueError) as err:
        load_recording(REAL, body, markers="isb", marker_map=REAL_MAP, reaches="auto", resample=None)
    msg = str(err.value)
    assert "the ISB landmarks give wrist_deviation = " in msg and "frame " in msg and "--degrees" not in msg
    rec = load_recording(REAL, body, markers="isb", marker_map=REAL_MAP, reaches="auto", resample=None,
                         out_of_range="clip", noise=NoiseModel(joint_deg=1.0))
    assert len(rec.observations) == 2 and len(rec.segments) == 2
    assert [w.split(": ")[1] for w in rec.warnings] == ["wrist_deviation"]
    q = np.degrees(np.concatenate([o.q.numpy() for o in rec.observations]))
    elbow = q[:, JOINT_NAMES.index("elbow_flexion")]
    assert elbow.min() < 20 and elbow.max() > 120  # the trial bends the elbow through most of its range


@pytest.mark.slow
def test_the_done_when_command_on_the_real_session(tmp_path):
    """The issue's command on the real trial, with --out-of-range clip (its wrist goes past the
    model's ulnar deviation) and small budgets: exit 0, two reaches, every method's rows."""
    out = tmp_path / "out"
    npe = json.dumps({"max_epochs": 3, "num_transforms": 1, "hidden_features": 8, "training_batch_size": 20,
                      "n_posterior_samples": 200, "is_rounds": 1})
    assert main(["infer", "--observations", str(REAL), "--model", "human", "--markers", "isb", "--marker-map",
                 str(REAL_MAP), "--reaches", "auto", "--side", "right", "--out-of-range", "clip", "--methods",
                 "naive,camo-seq,camo-touched,npe", "--budget", "60", "--noise-joint-deg", "1", "--config",
                 f"npe={npe}", "--out", str(out)]) == 0
    assert len(pd.read_csv(out / "reaches.csv")) == 2
    limits = pd.read_csv(out / "limits.csv")
    assert set(limits.method) == {"naive", "camo-seq", "camo-touched", "npe"} and limits.observed_min_deg.notna().all()
