"""The recording format: loader round trips, every bad-file case, resampling to the controller's step.

All on tests/data/arm7.urdf, a 7-DOF arm that is neither the Panda nor the human model.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch

from camo_sbi.experiments.models import ModelSpec, load_limits
from camo_sbi.experiments.simulate import simulate_recordings
from camo_sbi.io.recordings import load_goals, load_recording, load_recordings
from camo_sbi.io.resample import estimate_rate, resample_to_controller
from camo_sbi.io.schema import K_SIGMA, save_recordings
from camo_sbi.task import NoiseModel, Observation

DATA = Path(__file__).parent / "data"
ARM7 = DATA / "arm7.urdf"
ARM7_LIMITS = DATA / "arm7_limits.json"
ARM7_START = (0.0, 0.4, 0.0, -1.1, 0.0, 0.7, 0.0)


@pytest.fixture(scope="module")
def sim():
    return ModelSpec(kind="urdf", urdf=str(ARM7), ee="tool", start=ARM7_START).build()


@pytest.fixture(scope="module")
def theta(sim):
    return load_limits(ARM7_LIMITS, sim).reshape(-1)


@pytest.fixture(scope="module")
def exact(sim, theta):
    """Four exact (noise-free) 1x reaches."""
    return simulate_recordings(sim, theta, 4, seed=3)


@pytest.fixture
def csv_file(tmp_path, sim, exact):
    return save_recordings(tmp_path / "rec.csv", exact, sim)


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines()


def _write(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n")
    return path


def _edit(path: Path, line_no: int, column: str, value: str) -> Path:
    """Set ``column`` on CSV line ``line_no`` (1-based, header = 1) to ``value``."""
    lines = _lines(path)
    header = lines[0].split(",")
    cells = lines[line_no - 1].split(",")
    cells[header.index(column)] = value
    lines[line_no - 1] = ",".join(cells)
    return _write(path, lines)


def _drop_column(path: Path, column: str) -> Path:
    lines = _lines(path)
    k = lines[0].split(",").index(column)
    return _write(path, [",".join(c for i, c in enumerate(line.split(",")) if i != k) for line in lines])


def _rename_column(path: Path, old: str, new: str) -> Path:
    lines = _lines(path)
    lines[0] = ",".join(new if c == old else c for c in lines[0].split(","))
    return _write(path, lines)


def _err(path: Path, rest: str) -> str:
    """The loader's messages start with the file name."""
    return "^" + re.escape(f"{path}: ") + rest


# ----------------------------------------------------------------------------- round trips


def test_csv_round_trip_is_exact(csv_file, sim, exact):
    obs = load_recordings(csv_file, sim, resample=None)
    assert len(obs) == len(exact)
    for a, b in zip(obs, exact, strict=True):
        assert torch.equal(a.q, b.q) and torch.equal(a.ee, b.ee) and torch.equal(a.goal, b.goal)
        assert torch.equal(a.start, b.q[0])


def test_header_names_the_model_joints(csv_file, sim):
    assert _lines(csv_file)[0].split(",") == ["reach", "step", "goal_x", "goal_y", "goal_z", *sim.joint_names,
                                              "ee_x", "ee_y", "ee_z"]


def test_npz_round_trip_is_exact(tmp_path, sim, exact):
    path = save_recordings(tmp_path / "rec.npz", exact, sim)
    obs = load_recordings(path, sim, resample=None)
    for a, b in zip(obs, exact, strict=True):
        assert torch.equal(a.q, b.q) and torch.equal(a.ee, b.ee)


def test_joint_only_and_ee_only_files(tmp_path, sim, exact):
    q_only = tuple(Observation(o.start, o.goal, o.q, None) for o in exact)
    ee_only = tuple(Observation(o.start, o.goal, None, o.ee) for o in exact)
    a = load_recordings(save_recordings(tmp_path / "q.csv", q_only, sim), sim, resample=None)
    b = load_recordings(save_recordings(tmp_path / "ee.csv", ee_only, sim), sim, resample=None)
    assert all(o.spaces == ("joint",) for o in a)
    assert all(o.spaces == ("cartesian",) for o in b)
    # an end-effector-only recording starts at the model's start posture
    assert all(torch.equal(o.start, sim.start) for o in b)


def csv_to_degrees(lines: list[str], joints) -> list[str]:
    """CSV lines with the ``joints`` columns converted from radians to degrees."""
    header = lines[0].split(",")
    cols = [header.index(j) for j in joints]
    out = [lines[0]]
    for line in lines[1:]:
        cells = line.split(",")
        for k in cols:
            cells[k] = repr(float(np.degrees(float(cells[k]))))
        out.append(",".join(cells))
    return out


def test_degrees_flag_reads_degrees(tmp_path, sim, exact):
    path = save_recordings(tmp_path / "rad.csv", exact, sim)
    deg = _write(tmp_path / "deg.csv", csv_to_degrees(_lines(path), sim.joint_names))
    obs = load_recordings(deg, sim, degrees=True, resample=None)
    for a, b in zip(obs, exact, strict=True):
        torch.testing.assert_close(a.q, b.q, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match=_err(deg, r"column '.+', line \d+: .*use --degrees")):
        load_recordings(deg, sim)


def test_values_beyond_range_within_noise_are_clipped(tmp_path, sim, csv_file):
    hi = float(sim.bounds[6, 1])  # flange_roll upper bound
    sigma = NoiseModel(joint_deg=1.0).sigma("joint")
    _edit(csv_file, 3, "flange_roll", repr(hi + 0.5 * K_SIGMA * sigma))
    obs = load_recordings(csv_file, sim, noise=NoiseModel(joint_deg=1.0), resample=None)
    assert float(obs[0].q[1, 6]) == hi
    with pytest.raises(ValueError, match=_err(csv_file, r"column 'flange_roll', line 3: .*outside the model's range")):
        load_recordings(csv_file, sim, resample=None)  # no noise: no allowance


# ----------------------------------------------------------------------------- bad files


def test_missing_goal_column(csv_file, sim):
    _drop_column(csv_file, "goal_y")
    with pytest.raises(ValueError, match=_err(csv_file, "column 'goal_y' is missing")):
        load_recordings(csv_file, sim)


def test_unknown_joint_column(csv_file, sim):
    _rename_column(csv_file, "elbow", "elbow_joint")
    with pytest.raises(ValueError, match=_err(csv_file, "column 'elbow_joint' is unknown: not a joint of the model")):
        load_recordings(csv_file, sim)


def test_missing_joint_column(csv_file, sim):
    _drop_column(csv_file, "elbow")
    with pytest.raises(ValueError, match=_err(csv_file, "column 'elbow' is missing")):
        load_recordings(csv_file, sim)


def test_partial_ee_columns(csv_file, sim):
    _drop_column(csv_file, "ee_z")
    with pytest.raises(ValueError, match=_err(csv_file, "column 'ee_z' is missing")):
        load_recordings(csv_file, sim)


def test_nan_names_column_and_line(csv_file, sim):
    _edit(csv_file, 5, "shoulder", "nan")
    with pytest.raises(ValueError, match=_err(csv_file, "column 'shoulder', line 5: NaN")):
        load_recordings(csv_file, sim)


def test_empty_cell_and_text_cell(csv_file, sim):
    _edit(csv_file, 4, "ee_x", "abc")
    with pytest.raises(ValueError, match=_err(csv_file, "column 'ee_x', line 4: not a number: 'abc'")):
        load_recordings(csv_file, sim)
    _edit(csv_file, 4, "ee_x", "")
    with pytest.raises(ValueError, match=_err(csv_file, "column 'ee_x', line 4: not a number")):
        load_recordings(csv_file, sim)


def test_wrong_field_count(csv_file, sim):
    lines = _lines(csv_file)
    lines[6] += ",1.0"
    _write(csv_file, lines)
    with pytest.raises(ValueError, match=_err(csv_file, "line 7: has")):
        load_recordings(csv_file, sim)


def test_non_increasing_step(csv_file, sim):
    _edit(csv_file, 4, "step", "1")  # line 3 has step 1
    with pytest.raises(ValueError, match=_err(csv_file, "column 'step', line 4: step 1 does not increase")):
        load_recordings(csv_file, sim)


def test_non_integer_ids(csv_file, sim):
    _edit(csv_file, 3, "step", "1.5")
    with pytest.raises(ValueError, match=_err(csv_file, r"column 'step', line 3: expected an integer")):
        load_recordings(csv_file, sim)


def test_single_sample_reach(csv_file, sim, exact):
    lines = _lines(csv_file)
    first = exact[0].length  # lines 2 .. first + 1 are reach 0
    lines = lines[:2] + lines[first + 1:]  # reach 0 keeps only its start
    _write(csv_file, lines)
    with pytest.raises(ValueError, match=_err(csv_file, "column 'step', line 2: reach 0 has a single sample")):
        load_recordings(csv_file, sim)


def test_goal_not_constant_within_reach(csv_file, sim):
    _edit(csv_file, 6, "goal_z", "0.123")
    with pytest.raises(ValueError, match=_err(csv_file, "column 'goal_z', line 6: the goal changes within reach 0")):
        load_recordings(csv_file, sim)


def test_reach_rows_must_be_consecutive(csv_file, sim, exact):
    last = 1 + sum(o.length for o in exact)  # the last line of the file
    _edit(csv_file, last, "reach", "0")
    with pytest.raises(ValueError, match=_err(csv_file, f"column 'reach', line {last}: reach 0 continues here")):
        load_recordings(csv_file, sim)


def test_value_beyond_model_range(csv_file, sim):
    _edit(csv_file, 3, "elbow", "0.9")  # the URDF allows [-2.4, 0.3]; 0.9 is no degrees value either
    with pytest.raises(ValueError, match=_err(csv_file, r"column 'elbow', line 3: 0.9 lies outside the model's "
                                                        r"range \[-2.4, 0.3\] rad by more than 4 noise sigma")):
        load_recordings(csv_file, sim)


def test_ee_must_match_the_joints_forward_kinematics(csv_file, sim, exact):
    line = 2 + exact[0].length + 3  # reach 1, its fourth sample
    value = float(_lines(csv_file)[line - 1].split(",")[-3])
    _edit(csv_file, line, "ee_x", repr(value + 0.03))
    with pytest.raises(ValueError, match=_err(csv_file, rf"column 'ee_x', line {line}: the model's end effector "
                                                        r"at this row's joint values is 30.0 mm from")):
        load_recordings(csv_file, sim)
    load_recordings(csv_file, sim, noise=NoiseModel(ee_mm=10.0))  # within the noise allowance


def test_ee_only_reaches_from_other_starts_get_their_start_by_ik(tmp_path, sim, theta):
    """Five reaches from five start postures, end-effector columns only: each start is estimated
    (IK of the first sample within the model's range) and lands on the first sample."""
    from camo_sbi.scenarios.reaching import observe, reachable_goals

    gen = torch.Generator().manual_seed(1)
    base = torch.tensor(ARM7_START, dtype=torch.float64)
    lo, hi = theta[0::2], theta[1::2]
    starts = torch.stack([torch.clamp(base + 0.3 * (2 * torch.rand(7, generator=gen, dtype=torch.float64) - 1),
                                      lo + 0.05, hi - 0.05) for _ in range(5)])
    goals = reachable_goals(sim, theta, 5, gen)
    obs = observe(sim, theta, goals, starts)
    path = save_recordings(tmp_path / "ee.csv", tuple(Observation(o.start, o.goal, None, o.ee) for o in obs), sim)
    rec = load_recording(path, sim, resample=None)
    got = torch.stack([o.start for o in rec.observations])
    fk = sim.forward_kinematics(got).to(torch.float64)
    first = torch.stack([o.ee[0] for o in rec.observations])
    assert float((fk - first).norm(dim=1).max()) < 1e-4
    assert float((got - starts).abs().max()) > 0.05  # not the model's start: each reach has its own
    assert "5 of 5 estimated by IK" in rec.info["starts"]


def test_ee_only_start_out_of_reach_is_refused(tmp_path, sim, exact):
    moved = tuple(Observation(o.start, o.goal, None, o.ee + torch.tensor([2.0, 0.0, 0.0], dtype=torch.float64))
                  for o in exact)
    path = save_recordings(tmp_path / "ee.csv", moved, sim)
    with pytest.raises(ValueError, match=_err(path, r"column 'ee_x', line 2: reach 0 starts .* mm from any posture "
                                                    r"the model reaches .*--ee-units")):
        load_recordings(path, sim)


# ----------------------------------------------------------------------------- hostile and foreign files


def test_utf8_bom_is_accepted(csv_file, sim, exact):
    csv_file.write_bytes(b"\xef\xbb\xbf" + csv_file.read_bytes())
    obs = load_recordings(csv_file, sim, resample=None)
    assert torch.equal(obs[0].q, exact[0].q)


def test_binary_oversized_and_non_zip_files_name_the_file(tmp_path, sim):
    binary = tmp_path / "bin.csv"
    binary.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(ValueError, match=_err(binary, "is a binary file")):
        load_recordings(binary, sim)
    latin = tmp_path / "latin.csv"
    latin.write_bytes(b"reach,step,goal_x\n\xff\xfe,1,2\n")
    with pytest.raises(ValueError, match=_err(latin, "is not UTF-8 text")):
        load_recordings(latin, sim)
    huge = tmp_path / "huge.csv"
    huge.write_text('reach,step\n"' + "1" * 140_000 + '",0\n')
    with pytest.raises(ValueError, match=_err(huge, "line 2: a field is longer than 131,072 characters")):
        load_recordings(huge, sim)
    fake = tmp_path / "fake.npz"
    fake.write_bytes(b"not a zip at all" * 10)
    with pytest.raises(ValueError, match=_err(fake, r"cannot read as NPZ \(not a zip")):
        load_recordings(fake, sim)


def test_millimetres_get_a_hint_and_load_with_ee_units_mm(tmp_path, sim, exact):
    ee = tuple(Observation(o.start, o.goal * 1000, None, o.ee * 1000) for o in exact)
    path = save_recordings(tmp_path / "mm.csv", ee, sim)
    with pytest.raises(ValueError, match=_err(path, r"column 'ee_x', line \d+: -?[\d.]+ m is \d+x as far as "
                                                    r"the model reaches .* look like millimetres: "
                                                    r"use --ee-units mm")):
        load_recordings(path, sim)
    obs = load_recordings(path, sim, ee_units="mm", resample=None)
    assert torch.allclose(obs[0].ee, exact[0].ee, atol=1e-12)


def test_time_column_in_seconds_replaces_step(tmp_path, sim, exact):
    """A ``time`` column (seconds, jittered) with ``--ee-units mm``: each reach is put on a uniform
    grid at the file's median interval, then resampled as a step file is."""
    ref = save_recordings(tmp_path / "ref.csv", exact, sim)
    lines = _lines(ref)
    header = lines[0].split(",")
    out = ["reach,time," + ",".join(header[2:])]
    rng = np.random.default_rng(0)
    for line in lines[1:]:
        c = line.split(",")
        t = int(c[1]) * 0.01 + (rng.uniform(-0.001, 0.001) if int(c[1]) else 0.0)
        vals = [float(v) for v in c[2:]]
        vals = [v * 1000 if h.startswith(("goal_", "ee_")) else v for h, v in zip(header[2:], vals, strict=True)]
        out.append(",".join([c[0], repr(t)] + [repr(v) for v in vals]))
    path = _write(tmp_path / "timed.csv", out)
    rec = load_recording(path, sim, ee_units="mm")
    assert [o.length for o in rec.observations] == [o.length for o in exact]
    assert rec.info["sample_interval_s"] == pytest.approx(0.01, abs=2e-4)
    for o, e in zip(rec.observations, exact, strict=True):
        assert float((o.ee - e.ee).abs().max()) < 5e-3  # the jitter (1 ms of a 10 ms step) moves samples < 5 mm
    both = _write(tmp_path / "both.csv", [out[0].replace("reach,time", "reach,step,time")]
                  + [line.replace(",", ",0,", 1) for line in out[1:]])
    with pytest.raises(ValueError, match=_err(both, "column 'time': give step or time, not both")):
        load_recordings(both, sim)


def test_out_of_reach_goal_and_systematic_offset_are_warned(csv_file, sim, exact):
    lines = _lines(csv_file)
    header = lines[0].split(",")
    cells = [line.split(",") for line in lines]
    for row in cells[1:]:
        if row[0] == "1":
            for c in ("goal_x", "goal_y", "goal_z"):
                row[header.index(c)] = "5.0"
        row[header.index("ee_x")] = repr(float(row[header.index("ee_x")]) + 0.02)
    _write(csv_file, [",".join(r) for r in cells])
    rec = load_recording(csv_file, sim, resample=None, noise=NoiseModel(ee_mm=5.0))  # 2 cm: within the noise
    text = "\n".join(rec.warnings)
    assert re.search(r"1 of 4 goals out of the model's reach: reach 1's goal is 8.660 m from the base", text)
    assert re.search(r"a systematic 20.0 mm from the model's end effector", text)
    clean = load_recording(save_recordings(csv_file.parent / "clean.csv", exact, sim), sim, resample=None)
    assert clean.warnings == ()


def test_empty_and_missing_files(tmp_path, sim):
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    with pytest.raises(ValueError, match=_err(empty, "empty file")):
        load_recordings(empty, sim)
    header_only = _write(tmp_path / "header.csv", ["reach,step,goal_x,goal_y,goal_z,ee_x,ee_y,ee_z"])
    with pytest.raises(ValueError, match=_err(header_only, "has a header but no samples")):
        load_recordings(header_only, sim)
    with pytest.raises(ValueError, match=_err(tmp_path / "nope.csv", "no such file")):
        load_recordings(tmp_path / "nope.csv", sim)


def test_npz_errors_name_the_row(tmp_path, sim, exact):
    path = save_recordings(tmp_path / "rec.npz", exact, sim)
    with np.load(path) as z:
        arrays = {k: z[k].copy() for k in z.files}
    arrays["wrist_pitch"][7] = np.nan
    np.savez(path, **arrays)
    with pytest.raises(ValueError, match=_err(path, "column 'wrist_pitch', row 7: NaN")):
        load_recordings(path, sim)


def test_predict_goals_file(tmp_path, sim):
    good = _write(tmp_path / "goals.csv", ["goal_x,goal_y,goal_z", "0.3,0.1,0.6", "0.2,-0.2,0.7"])
    goals, starts = load_goals(good, sim)
    assert goals.shape == (2, 3) and starts is None
    bad = _write(tmp_path / "bad.csv", ["goal_x,goal_y", "0.3,0.1"])
    with pytest.raises(ValueError, match=_err(bad, "column 'goal_z' is missing")):
        load_goals(bad, sim)


# ----------------------------------------------------------------------------- resampling


def test_resampling_is_the_identity_at_1x(csv_file, sim, exact):
    o = exact[0]
    assert resample_to_controller(o, sim, mode="time", rate=1.0) is o
    assert resample_to_controller(o, sim, mode="arclength", rate=1.0) is o
    assert estimate_rate(exact, sim) == 1.0
    loaded = load_recordings(csv_file, sim)  # resampling on by default: the rate is estimated as 1
    for a, b in zip(loaded, exact, strict=True):
        assert torch.equal(a.q, b.q) and torch.equal(a.ee, b.ee)


@pytest.mark.parametrize("rate", [2, 3])
def test_faster_recording_resampled_back_matches_1x(tmp_path, sim, theta, exact, rate):
    """A 3x (2x) recording written by simulate_recordings loads back as the 1x one: its rate is
    estimated exactly and time resampling hits the 1x samples (tolerance 1e-9, interpolation only)."""
    fast = simulate_recordings(sim, theta, 4, seed=3, rate_multiplier=rate)
    assert [o.length for o in fast] == [rate * (o.length - 1) + 1 for o in exact]
    path = save_recordings(tmp_path / "fast.csv", fast, sim)
    assert estimate_rate(fast, sim) == rate
    back = load_recordings(path, sim)
    raw = load_recordings(path, sim, resample=None)
    for a, b, r in zip(back, exact, raw, strict=True):
        assert a.length == b.length and r.length > b.length
        torch.testing.assert_close(a.q, b.q, rtol=0, atol=1e-9)
        torch.testing.assert_close(a.ee, b.ee, rtol=0, atol=1e-9)


def test_noisy_3x_recording_rate_is_estimated(sim, theta, exact):
    noise = NoiseModel(joint_deg=0.3, ee_mm=2.0)
    fast = simulate_recordings(sim, theta, 4, seed=3, noise=noise, rate_multiplier=3)
    assert estimate_rate(fast, sim) == 3.0
    back = [resample_to_controller(o, sim, rate=3.0) for o in fast]
    assert [o.length for o in back] == [o.length for o in exact]
    # the samples kept are the noisy ones at the 1x times: within 5 sigma of the exact ones
    err = max(float((a.ee - b.ee).abs().max()) for a, b in zip(back, exact, strict=True))
    assert err < 5 * noise.sigma("cartesian")


def test_arclength_mode_walks_the_controller_step(sim, exact, theta):
    fast = simulate_recordings(sim, theta, 4, seed=3, rate_multiplier=3)
    cfg = sim.config
    for o in fast:
        r = resample_to_controller(o, sim, mode="arclength", rate=3.0)
        assert torch.equal(r.q[0], o.q[0]) and torch.equal(r.start, o.start)
        steps = (r.ee[1:] - r.ee[:-1]).norm(dim=1)
        assert float(steps.max()) <= cfg.max_cartesian_step + 1e-9  # a chord is never longer than its arc
        assert r.length < o.length
