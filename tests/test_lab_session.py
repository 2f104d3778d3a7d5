"""A lab's session in (issue 34): a C3D of ISB landmarks -> the human model's joint angles ->
reaches found by hand speed -> limits; the same session's true angles as an OpenSim .mot give
the same naive limits; the .mot reader refuses malformed files naming the line."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

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


def _cuts(rec) -> np.ndarray:
    return np.array([[r["start_s"], r["end_s"]] for r in rec.segments])


@pytest.mark.parametrize("seed, rate", [(0, 100.0), (2, 100.0), (5, 100.0), (8, 100.0), (2, 200.0)])
def test_auto_reaches_on_the_marker_session_cut_within_50_ms(body, tmp_path, seed, rate):
    """The issue's done-when on the synthetic marker session (1 mm landmark noise, 4 reaches out and
    back): every movement found, every cut within 50 ms of the true start and end. The speed comes
    from the hand's markers (RS, US, MC2, MC5), named in reaches.csv's hand_track and the rule."""
    files = synthetic_session(tmp_path, seed=seed, reaches=4, noise_mm=1.0, rate=rate)
    rec = load_recording(files["c3d"], body, markers="isb", marker_map=files["map"], reaches="auto", resample=None,
                         noise=NoiseModel(joint_deg=1.0))
    truth = pd.read_csv(files["truth"])[["start_s", "end_s"]].to_numpy()
    got = _cuts(rec)
    assert got.shape == truth.shape == (8, 2)
    assert np.abs(got - truth).max() <= 0.050
    labels = ", ".join(MARKER_LABELS[k] for k in ("RS", "US", "MC2", "MC5"))
    assert {r["hand_track"] for r in rec.segments} == {rec.speed["source"]}
    assert f"mean of {labels} (ISB RS, US, MC2, MC5)" in rec.speed["source"]
    assert rec.speed["rule"].endswith(f"; hand track: {rec.speed['source']}")


def test_the_angles_forward_kinematics_would_miss_a_cut(body, tmp_path):
    """Why the hand's markers: on seed 2 the hand computed by forward kinematics from the ISB angles
    (the angles' error through the arm's lever) puts a cut more than 50 ms off with the same rule,
    where the markers' own track puts every cut within 50 ms (the test above)."""
    import torch

    from camo_sbi.io.segment import hand_speed, segment_by_speed

    files = synthetic_session(tmp_path, seed=2, reaches=4, noise_mm=1.0)
    whole = load_recording(files["c3d"], body, markers="isb", marker_map=files["map"], resample=None,
                           noise=NoiseModel(joint_deg=1.0))
    [obs] = whole.observations  # no gap in the landmarks: the whole trial, every frame
    t = np.arange(obs.q.shape[0]) / 100.0
    hand = body.forward_kinematics(obs.q.to(torch.float64)).to(torch.float64).numpy()
    segs = segment_by_speed(t, hand_speed(t, hand), hand)
    truth = pd.read_csv(files["truth"])[["start_s", "end_s"]].to_numpy()
    got = np.array([[t[g.first], t[g.last]] for g in segs])
    assert got.shape == truth.shape and np.abs(got - truth).max() > 0.050


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
    deviation goes past the model's 30 deg. By default (out_of_range "auto": angles from ISB
    landmarks) it is clipped onto the range with one loud warning naming the joint, the bound, how
    many samples and by how much, and the bound is listed in ``clipped``; "error" refuses it naming
    the joint, the frame and what to check (never --degrees); two reaches are found by hand speed."""
    rec = load_recording(REAL, body, markers="isb", marker_map=REAL_MAP, reaches="auto", resample=None,
                         noise=NoiseModel(joint_deg=1.0))
    assert len(rec.observations) == 2 and len(rec.segments) == 2
    assert [w.split(": ")[1] for w in rec.warnings] == ["wrist_deviation"]
    w = rec.warnings[0]
    assert "OUTSIDE THE MODEL'S RANGE [-30.0, 20.0] deg" in w and "below its lower bound -30.0 deg" in w
    assert "--out-of-range auto" in w and "--out-of-range error stops instead" in w
    [c] = rec.clipped
    assert (c["joint"], c["bound"]) == ("wrist_deviation", "lower") and c["samples"] > 100 and 15 < c["beyond"] < 30
    q = np.degrees(np.concatenate([o.q.numpy() for o in rec.observations]))
    assert q[:, JOINT_NAMES.index("wrist_deviation")].min() >= -30.0 - 1e-9  # clipped onto the range
    elbow = q[:, JOINT_NAMES.index("elbow_flexion")]
    assert elbow.min() < 20 and elbow.max() > 120  # the trial bends the elbow through most of its range
    clip = load_recording(REAL, body, markers="isb", marker_map=REAL_MAP, reaches="auto", resample=None,
                          noise=NoiseModel(joint_deg=1.0), out_of_range="clip")
    assert clip.clipped == rec.clipped and "--out-of-range clip" in clip.warnings[0]
    with pytest.raises(ValueError) as err:
        load_recording(REAL, body, markers="isb", marker_map=REAL_MAP, reaches="auto", resample=None,
                       out_of_range="error")
    msg = str(err.value)
    assert "the ISB landmarks give wrist_deviation = " in msg and "frame " in msg and "--degrees" not in msg
    with pytest.raises(ValueError, match=r"^out_of_range: expected one of \('auto', 'clip', 'error'\)"):
        load_recording(REAL, body, markers="isb", marker_map=REAL_MAP, out_of_range="warn")


def test_limits_table_marks_the_bounds_the_recording_went_past(body):
    """A clipped bound: limits.csv's clipped_samples and beyond_range on that bound's rows only,
    and "!" on it (observed and every method) in the wide table."""
    from camo_sbi.experiments.infer import _recorded_task
    from camo_sbi.experiments.infer_limits import WIDE_LIMITS_KEY, limits_table, wide_limits
    from camo_sbi.inference.registry import run_method

    rec = load_recording(REAL, body, markers="isb", marker_map=REAL_MAP, reaches="auto", resample=None,
                         noise=NoiseModel(joint_deg=1.0))
    task = _recorded_task(SimpleNamespace(name="human"), body, rec.observations, NoiseModel(joint_deg=1.0))
    table = limits_table({"naive": run_method("naive", task, budget=1, seed=0)}, body, task, rec.clipped)
    hit = (table.joint == "wrist_deviation") & (table.bound == "lower")
    assert (table.loc[hit, "clipped_samples"] == rec.clipped[0]["samples"]).all()
    assert table.loc[hit, "beyond_range"].iloc[0] == pytest.approx(rec.clipped[0]["beyond"])
    assert (table.loc[~hit, "clipped_samples"] == 0).all() and table.loc[~hit, "beyond_range"].isna().all()
    wide = wide_limits(table)
    assert wide.loc["wrist_deviation", "observed"].startswith("-30.0! .. ")
    assert wide.loc["wrist_deviation", "naive"].startswith("-30.0! .. ")
    assert "!" not in "".join(wide.drop(index="wrist_deviation").to_numpy().ravel())
    assert "! = the recording went past the model's range" in WIDE_LIMITS_KEY


@pytest.mark.slow
def test_the_done_when_command_on_the_real_session(tmp_path):
    """The issue's command on the real trial exactly as the done-when writes it (no --out-of-range:
    its wrist goes past the model's ulnar deviation, which the default clips and marks), small
    budgets: exit 0, two reaches, every method's rows, the clipped bound marked."""
    out = tmp_path / "out"
    npe = json.dumps({"max_epochs": 3, "num_transforms": 1, "hidden_features": 8, "training_batch_size": 20,
                      "n_posterior_samples": 200, "is_rounds": 1})
    assert main(["infer", "--observations", str(REAL), "--model", "human", "--markers", "isb", "--marker-map",
                 str(REAL_MAP), "--reaches", "auto", "--side", "right", "--methods",
                 "naive,camo-seq,camo-touched,npe", "--budget", "60", "--noise-joint-deg", "1", "--config",
                 f"npe={npe}", "--out", str(out)]) == 0
    assert len(pd.read_csv(out / "reaches.csv")) == 2
    limits = pd.read_csv(out / "limits.csv")
    assert set(limits.method) == {"naive", "camo-seq", "camo-touched", "npe"} and limits.observed_min_deg.notna().all()
    past = limits[limits.clipped_samples > 0]
    assert set(zip(past.joint, past.bound, strict=True)) == {("wrist_deviation", "lower")} and len(past) == 4
    assert "! = the recording went past" in (out / "report.html").read_text()
