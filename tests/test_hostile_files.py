"""Issue 36, the file readers: hostile or damaged files end in ONE line naming the file, key or
flag (exit 2), or run and warn, quickly; never a traceback, a hang or another exception type.

The BVH cases are in tests/test_mocap.py (next to the BVH writer); the random-bytes tests of
every reader are in tests/test_fuzz_readers.py.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from camo_sbi._files import MAX_DEPTH, parse_json, parse_toml, read_json, read_text, read_toml
from camo_sbi.experiments.cli import main
from tests import test_infer_cli
from tests.test_infer_cli import DATA, LIMITS, MODEL

DEEP_JSON = "[" * 100_000
DEEP_TOML = "a = " + "[" * 5000 + "]" * 5000 + "\n"
sim = test_infer_cli.sim  # the arm7 model fixture
TINY_COMPARE = ["compare", *MODEL, "--methods", "naive", "--budgets", "20", "--seeds", "1", "--tasks", "1"]

pytestmark = pytest.mark.timeout(120)


def _exit_2(argv, capsys) -> str:
    """Run the CLI expecting exit 2 with one line on stderr; returns that line without its prefix."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and len(err) == 1 and err[0].startswith("camo-sbi: error: "), err
    return err[0].removeprefix("camo-sbi: error: ")


# ----------------------------------------------------------------------------- the one reader


def test_the_helper_names_the_file_for_every_failure(tmp_path):
    p = tmp_path / "x.json"
    p.write_text(DEEP_JSON)
    with pytest.raises(ValueError, match=rf"^--flag {re.escape(str(p))}: invalid JSON \(nested more than 64 "):
        read_json(p, f"--flag {p}")
    p.write_text("[" * (MAX_DEPTH + 1) + "]" * (MAX_DEPTH + 1))  # parses, but deeper than allowed
    with pytest.raises(ValueError, match=rf"^{re.escape(str(p))}: nested more than {MAX_DEPTH} levels deep$"):
        read_json(p)
    p.write_text("[" * MAX_DEPTH + "]" * MAX_DEPTH)
    assert read_json(p) is not None
    p.write_bytes(b"\xef\xbb\xbf{\"a\": 1}")  # a byte-order mark (Excel, Notepad)
    assert read_json(p) == {"a": 1}
    p.write_bytes(b'{"a": "\xff\xfe"}')
    with pytest.raises(ValueError, match=r": not a UTF-8 text file \(byte 7 is b'\\xff'\)$"):
        read_json(p)
    with pytest.raises(ValueError, match=r"x\.json: more than the 3 bytes|x\.json: [\d,]+ bytes, more than the 3 "):
        read_text(p, max_bytes=3)
    with pytest.raises(ValueError, match=r"nope\.json: cannot read \(No such file or directory\)$"):
        read_json(tmp_path / "nope.json")
    with pytest.raises(ValueError, match=r"dir: cannot read \(Is a directory\)$"):
        read_json(tmp_path, "dir")
    t = tmp_path / "s.toml"
    t.write_text(DEEP_TOML)
    with pytest.raises(ValueError, match=r"s\.toml: invalid TOML \(nested more than 64 levels deep\)$"):
        read_toml(t)
    with pytest.raises(ValueError, match=r"^lbl: invalid JSON \(Expecting value: line 1 column 1 \(char 0\)\)$"):
        parse_json("", "lbl")
    with pytest.raises(ValueError, match=r"^lbl: invalid TOML \(.*\)$"):
        parse_toml("a = = 1\n\n\n", "lbl")


# ----------------------------------------------------------------------------- every JSON/TOML flag


def test_deeply_nested_json_in_every_flag_exits_2_naming_it(tmp_path, capsys):
    """Issue 36: 100,000 '[' ended in a RecursionError traceback (exit 1) in each of these."""
    deep = tmp_path / "deep.json"
    deep.write_text(DEEP_JSON)
    c3d = ["infer", "--observations", str(DATA / "session.c3d"), "--ee-marker", "TOOL", "--goal", "final", *MODEL,
           "--methods", "naive", "--out", str(tmp_path / "o")]
    nested = "invalid JSON (nested more than 64 levels deep)"
    assert _exit_2([*TINY_COMPARE, "--limits", str(deep), "--out", str(tmp_path / "a")], capsys) == \
        f"--limits: {deep}: {nested}"
    assert _exit_2([*c3d, "--frame", str(deep)], capsys) == f"--frame {deep}: {nested}"
    (tmp_path / "x.bvh").write_text("HIERARCHY\n")  # the map is read first
    assert _exit_2(["infer", "--observations", str(tmp_path / "x.bvh"), "--bvh-map", str(deep), *c3d[5:]],
                   capsys) == \
        f"--bvh-map {deep}: {nested}"
    assert _exit_2([*TINY_COMPARE, *LIMITS, "--config", f"naive={DEEP_JSON}", "--out", str(tmp_path / "b")],
                   capsys) == f"--config: naive: {nested}"
    out = tmp_path / "planted"
    out.mkdir()
    (out / "manifest.json").write_text(DEEP_JSON)
    assert _exit_2([*TINY_COMPARE, *LIMITS, "--out", str(out)], capsys) == \
        f"--out {out}: its manifest.json is unreadable (manifest.json: {nested}); use a new --out"


def test_deeply_nested_study_toml_exits_2_naming_the_file(tmp_path, capsys):
    study = tmp_path / "deep.toml"
    study.write_text(DEEP_TOML)
    assert _exit_2(["run", str(study), "--out", str(tmp_path / "o")], capsys) == \
        f"{study}: invalid TOML (nested more than 64 levels deep)"
    study.write_bytes(b"name = \"\xff\"\n")
    assert _exit_2(["run", str(study), "--out", str(tmp_path / "o")], capsys) == \
        f"{study}: not a UTF-8 text file (byte 8 is b'\\xff')"


def test_binary_limits_file_exits_2_naming_it(tmp_path, capsys):
    """Issue 36: exit 2 with only "'utf-8' codec can't decode ...", naming no file."""
    limits = tmp_path / "limits.json"
    limits.write_bytes(bytes(range(256)) * 8)
    line = _exit_2([*TINY_COMPARE, "--limits", str(limits), "--out", str(tmp_path / "o")], capsys)
    assert line == f"--limits: {limits}: not a UTF-8 text file (byte 128 is b'\\x80')"
    assert json.loads(json.dumps(line)) == line  # one plain line


def test_store_and_output_records_with_deep_json_are_treated_as_damaged(tmp_path):
    """Files the toolkit writes itself (cell integrity records, output records, NPE metadata)
    read through the same helper: a planted deep record is 'unreadable', never a RecursionError."""
    from camo_sbi.experiments import outputs
    from camo_sbi.experiments.store import ResultStore

    store = ResultStore(tmp_path / "run")
    store.put("k", [{"a": 1.0}])
    assert store.problem("k") is None
    store._record_path("k").write_text(DEEP_JSON)
    assert store.problem("k").startswith("unreadable integrity record (ValueError: record: invalid JSON (nested")
    (tmp_path / "run" / outputs.RECORD).write_text(DEEP_JSON)
    assert outputs._load(tmp_path / "run") == {}


# ----------------------------------------------------------------------------- C3D, frames, URDF


def test_c3d_cut_off_is_refused_against_its_header(tmp_path, capsys):
    """Issue 36: half of a C3D ran with exit 0 on the frames left, without a warning (ezc3d reads
    what is there and shrinks its header to match)."""
    data = (DATA / "session.c3d").read_bytes()
    for cut in (len(data) // 2, len(data) - 200):
        half = tmp_path / f"cut{cut}.c3d"
        half.write_bytes(data[:cut])
        line = _exit_2(["infer", "--observations", str(half), "--ee-marker", "TOOL", "--frame",
                        str(DATA / "session_frame.json"), "--goal", "final", *MODEL, "--methods", "nominal",
                        "--out", str(tmp_path / "o")], capsys)
        assert re.fullmatch(rf"{re.escape(str(half))}: its header declares 278 frames but the file holds \d+ "
                            rf"complete ones \([\d,]+ bytes; cut off\?\)", line), line
    whole = tmp_path / "whole.c3d"
    whole.write_bytes(data + b"\0" * 100)  # padding after the data is fine
    from camo_sbi.io.c3d import read_c3d

    assert len(read_c3d(whole, ["TOOL"])["time"]) == len(read_c3d(DATA / "session.c3d", ["TOOL"])["time"])


def test_c3d_with_analog_channels_is_checked_with_its_analog_bytes(tmp_path):
    """The frame size counts the analog samples (3 channels at 10 per frame here): a file cut by
    one frame's worth is refused, the complete one reads."""
    ezc3d = pytest.importorskip("ezc3d")
    from camo_sbi.io.c3d import read_c3d

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [100.0]
    c["parameters"]["POINT"]["LABELS"]["value"] = ("TOOL", "B")
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    c["parameters"]["ANALOG"]["RATE"]["value"] = [1000.0]
    c["parameters"]["ANALOG"]["LABELS"]["value"] = ("F1", "F2", "F3")
    c["data"]["points"] = np.ones((4, 2, 50))
    c["data"]["analogs"] = np.ones((1, 3, 500))
    path = tmp_path / "an.c3d"
    c.write(str(path))
    assert len(read_c3d(path, ["TOOL"])["time"]) == 50
    frame_bytes = (4 * 2 + 3 * 10) * 4
    data = path.read_bytes()
    end = 3 * 512 + 50 * frame_bytes  # the data block starts at block 4 (ezc3d's layout, checked below)
    assert len(data) >= end and data[8 * 2:9 * 2] == (4).to_bytes(2, "little")
    (tmp_path / "cut.c3d").write_bytes(data[:end - frame_bytes])
    with pytest.raises(ValueError, match=r"cut\.c3d: its header declares 50 frames but the file holds 49 complete"):
        read_c3d(tmp_path / "cut.c3d", ["TOOL"])


def test_c3d_far_away_gets_no_ee_units_hint(tmp_path, capsys):
    """Issue 36: a C3D 1000 m away was told "use --ee-units mm", which a C3D refuses."""
    ezc3d = pytest.importorskip("ezc3d")
    c = ezc3d.c3d(str(DATA / "session.c3d"))
    pts = np.array(c["data"]["points"])
    pts[0] += 1e6  # +1000 m in x (the file is in mm)
    c["data"]["points"] = pts
    far = tmp_path / "far.c3d"
    c.write(str(far))
    line = _exit_2(["infer", "--observations", str(far), "--ee-marker", "TOOL", "--goal", "final", *MODEL,
                    "--methods", "nominal", "--out", str(tmp_path / "o")], capsys)
    assert line.startswith(f"{far}: column 'ee_x', frame ") and "--ee-units" not in line
    assert "check the frame (--frame, --frame-from-markers)" in line and "POINT:UNITS" in line
    assert re.search(r": 100\d\.\d+ m is \d+(\.\d+)?x as far as the model reaches", line), line


def test_frame_translation_of_1e308_is_refused_naming_the_frame_file(tmp_path, capsys):
    """Issue 36: printed a 330-digit number and blamed the C3D's column."""
    frame = json.loads((DATA / "session_frame.json").read_text())
    path = tmp_path / "frame.json"
    path.write_text(json.dumps({**frame, "translation": [1e308, 0, 0]}))
    line = _exit_2(["infer", "--observations", str(DATA / "session.c3d"), "--ee-marker", "TOOL", "--frame", str(path),
                    "--goal", "final", *MODEL, "--methods", "nominal", "--out", str(tmp_path / "o")], capsys)
    assert line == (f"--frame {path}: key 'translation': 1e+308 m is farther than 1000 m from the lab's origin; "
                    "the translation is in metres")
    path.write_text(json.dumps({**frame, "translation": [frame["translation"][0] + 999, *frame["translation"][1:]]}))
    line = _exit_2(["infer", "--observations", str(DATA / "session.c3d"), "--ee-marker", "TOOL", "--frame", str(path),
                    "--goal", "final", *MODEL, "--methods", "nominal", "--out", str(tmp_path / "o")], capsys)
    assert f"after the transform of {path}: 99" in line and len(line) < 400, line  # names the frame file


def test_a_non_urdf_file_is_never_echoed(tmp_path, capsys):
    """Issue 36: a study's urdf = "../../../../etc/passwd" printed the file's first 200 characters."""
    secret = tmp_path / "secret.txt"
    secret.write_text("root:x:0:0:SECRET-LINE\n" * 50)
    line = _exit_2(["compare", "--urdf", str(secret), "--ee", "tool", *LIMITS, "--methods", "naive", "--budgets", "20",
                    "--seeds", "1", "--tasks", "1", "--out", str(tmp_path / "o")], capsys)
    assert line == f"--urdf: {secret}: urdf: not a URDF (no <robot> element in its 1,150 characters)"
    study = tmp_path / "s.toml"
    study.write_text(f'methods = ["naive"]\nbudgets = [20]\nseeds = 1\ntasks = 1\n[[model]]\nurdf = "{secret}"\n'
                     'ee = "tool"\n')
    assert "SECRET" not in _exit_2(["run", str(study), "--out", str(tmp_path / "o2")], capsys)
    secret.write_bytes(b"\x89PNG\r\n" + bytes(range(256)))
    line = _exit_2(["compare", "--urdf", str(secret), "--ee", "tool", *LIMITS, "--methods", "naive", "--budgets", "20",
                    "--seeds", "1", "--tasks", "1", "--out", str(tmp_path / "o")], capsys)
    assert line == f"--urdf: {secret}: not a UTF-8 text file (byte 0 is b'\\x89')"


# ----------------------------------------------------------------------------- large recordings


def test_start_posture_ik_on_the_kernel_equals_the_reference_fk(sim, monkeypatch, caplog):
    """The IK of the start postures runs on the numba kernel's FK (a 141-reach C3D: 84.6 s -> 4.1 s on
    the shared 2-core machine); its postures equal those of the pytorch_kinematics reference FK
    to 1e-9 rad over 40 iterations (the two FKs agree to 1e-12 m). From IK_PROGRESS_MIN reaches it logs its time."""
    import logging

    import torch

    from camo_sbi.io import geometry

    rng = np.random.default_rng(4)
    q_true = sim.start.double().numpy() + rng.uniform(-0.2, 0.2, size=(4, sim.n_joints))  # near the start
    targets = sim.forward_kinematics(torch.from_numpy(q_true)).to(torch.float64).numpy()
    monkeypatch.setattr(geometry, "IK_PROGRESS_MIN", 2)
    monkeypatch.setattr(geometry, "IK_ITERATIONS", 40)  # the reference FK is slow: 40 of the 300 iterations
    with caplog.at_level(logging.INFO, logger="camo_sbi.io.geometry"):
        q_kernel, res_kernel = geometry.estimate_starts(sim, targets, sim.start)
    assert re.search(r"start postures: IK of 4 reaches .*about [\d.e+-]+ s at most", caplog.text), caplog.text
    monkeypatch.setattr(geometry, "_fk_numpy", lambda s: (
        lambda q: s.forward_kinematics(torch.from_numpy(q)).to(torch.float64).numpy()))
    q_ref, res_ref = geometry.estimate_starts(sim, targets, sim.start)
    np.testing.assert_allclose(q_kernel, q_ref, atol=1e-9)
    np.testing.assert_allclose(res_kernel, res_ref, atol=1e-9)
    assert res_kernel.max() < 0.2 * np.linalg.norm(targets - sim.forward_kinematics(sim.start).double().numpy(),
                                                     axis=1).max()  # it moved towards the targets


def test_more_reaches_than_max_reaches_are_refused_naming_the_flag(tmp_path, sim, capsys):
    """Issue 36: a 200,000-frame C3D sat silent for 240 s in the start-posture IK."""
    from camo_sbi.io.frames import load_frame
    from camo_sbi.io.recordings import MAX_REACHES, load_recording

    args = {"goal": "final", "ee_markers": ["TOOL"], "frame": load_frame(DATA / "session_frame.json")}
    with pytest.raises(ValueError, match=r"^--max-reaches: .*session\.c3d holds 8 reaches, more than 5: .* give "
                                         r"--max-reaches 8 to run them all$"):
        load_recording(DATA / "session.c3d", sim, max_reaches=5, **args)
    assert len(load_recording(DATA / "session.c3d", sim, max_reaches=8, **args).observations) == 8
    assert MAX_REACHES >= 1000
    with pytest.raises(ValueError, match=r"^--max-reaches: expected a whole number >= 1, got 0$"):
        load_recording(DATA / "session.c3d", sim, max_reaches=0, **args)
    line = _exit_2(["infer", "--observations", str(DATA / "session.c3d"), "--ee-marker", "TOOL", "--frame",
                    str(DATA / "session_frame.json"), "--goal", "final", *MODEL, "--methods", "nominal",
                    "--max-reaches", "7", "--out", str(tmp_path / "o")], capsys)
    assert line.startswith("--max-reaches: ") and "holds 8 reaches, more than 7" in line


def test_a_c3d_that_crashes_ezc3d_is_refused_and_this_process_lives_on(tmp_path, monkeypatch):
    """Four bytes of session.c3d's parameter section, changed as a fuzzer did, made ezc3d 1.7
    segfault (exit 139, the whole command gone): the file is opened in a child process first."""
    from camo_sbi.io import c3d

    data = bytearray((DATA / "session.c3d").read_bytes())
    for pos, value in ((655, 0o114), (717, 0o112), (1036, 0o364), (1252, 0o106)):  # cmp -l: 1-based
        data[pos - 1] = value
    bad = tmp_path / "bad.c3d"
    bad.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=rf"^{re.escape(str(bad))}: (cannot read as C3D|parameter|its header)"):
        c3d.read_c3d(bad, ["TOOL"])
    monkeypatch.setattr(c3d, "_PROBE", "import os, signal\nos.kill(os.getpid(), signal.SIGSEGV)\n")
    with pytest.raises(ValueError, match=rf"^{re.escape(str(bad))}: cannot read as C3D \(the C3D reader crashed on "
                                         r"it, signal 11: a damaged file\)$"):
        c3d.read_c3d(bad, ["TOOL"])
    monkeypatch.setattr(c3d, "_PROBE", "import time\ntime.sleep(30)\n")
    monkeypatch.setattr(c3d, "PROBE_TIMEOUT_S", 0.5)
    with pytest.raises(ValueError, match=r"cannot read as C3D \(the reader took more than 0.50\d s on it"):
        c3d.read_c3d(bad, ["TOOL"])


def test_c3d_with_more_frames_than_its_16_bit_header_says_is_warned(tmp_path):
    """ezc3d writes 65,600 frames under a header count of 65,535 and reads back 65,535: the
    frames beyond are reported, not silently dropped."""
    ezc3d = pytest.importorskip("ezc3d")
    from camo_sbi.io.c3d import read_c3d

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [100.0]
    c["parameters"]["POINT"]["LABELS"]["value"] = ("TOOL",)
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    pts = np.ones((4, 1, 65_600))
    pts[0, 0] = np.arange(65_600) * 1e-3
    c["data"]["points"] = pts
    path = tmp_path / "long.c3d"
    c.write(str(path))
    d = read_c3d(path, ["TOOL"])
    assert len(d["time"]) == 65_535
    assert d["warnings"] == [f"{path}: holds data for 65,600 frames but its header declares 65,535 (a 16-bit count "
                             "stops at 65,535): only those 65,535 were read"]
    assert read_c3d(DATA / "session.c3d", ["TOOL"])["warnings"] == []


def test_a_urdf_parse_error_is_one_line(tmp_path, capsys):
    """Found by the slow fuzz test: a NUL byte in arm7.urdf gave lxml's two-line message."""
    text = (DATA / "arm7.urdf").read_bytes()
    bad = tmp_path / "nul.urdf"
    bad.write_bytes(text[:221] + b"\x00" + text[222:])
    line = _exit_2(["compare", "--urdf", str(bad), "--ee", "tool", *LIMITS, "--methods", "naive", "--budgets", "20",
                    "--seeds", "1", "--tasks", "1", "--out", str(tmp_path / "o")], capsys)
    assert line.startswith(f"--urdf: {bad}: urdf: cannot parse URDF (") and "Char 0x0" in line, line
