"""`camo-sbi simulate-observations` then `camo-sbi infer` on a user URDF (tests/data/arm7.urdf), and
the shared model options (--urdf / --limits) on compare and reproduce panda."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from camo_sbi.experiments.cli import main
from camo_sbi.experiments.models import ModelSpec, load_limits
from camo_sbi.io.recordings import load_recordings
from camo_sbi.io.schema import K_SIGMA
from tests.test_recordings import csv_to_degrees

DATA = Path(__file__).parent / "data"
START = "0,0.4,0,-1.1,0,0.7,0"
MODEL = ["--urdf", str(DATA / "arm7.urdf"), "--ee", "tool", "--start", START]
LIMITS = ["--limits", str(DATA / "arm7_limits.json")]
JOINTS = ["base_yaw", "shoulder", "upper_roll", "elbow", "fore_roll", "wrist_pitch", "flange_roll"]
NOISE = ["--noise-joint-deg", "0.3", "--noise-ee-mm", "1.5"]
NPE_TINY = {"max_epochs": 3, "num_transforms": 1, "hidden_features": 8, "training_batch_size": 20,
            "n_posterior_samples": 200, "is_rounds": 1}
ABC_TINY = {"population_size": 20, "max_populations": 3}
PNG = "data:image/png;base64,"


def _exit_2(argv, capsys) -> str:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    return err[-1]


@pytest.fixture(scope="module")
def sim():
    return ModelSpec(kind="urdf", urdf=str(DATA / "arm7.urdf"), ee="tool",
                     start=tuple(float(v) for v in START.split(","))).build()


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "reaches.csv"
    assert main(["simulate-observations", *MODEL, *LIMITS, "--reaches", "4", "--seed", "2", *NOISE,
                 "--out", str(path)]) == 0
    return path


@pytest.fixture(scope="module")
def inferred(recording, tmp_path_factory):
    out = tmp_path_factory.mktemp("infer")
    goals = out.parent / "goals.csv"
    goals.write_text("goal_x,goal_y,goal_z\n0.25,0.15,0.75\n-0.1,0.3,0.7\n")
    argv = ["infer", "--observations", str(recording), *MODEL, "--methods", "camo,naive,nominal,npe",
            "--budget", "100", "--seed", "0", *NOISE, "--config", f"npe={json.dumps(NPE_TINY)}",
            "--predict-goals", str(goals), "--out", str(out)]
    assert main(argv) == 0
    return out, pd.read_csv(out / "limits.csv")


def test_simulate_observations_writes_the_recording_format(recording, sim):
    header = recording.read_text().splitlines()[0].split(",")
    assert header == ["reach", "step", "goal_x", "goal_y", "goal_z", *JOINTS, "ee_x", "ee_y", "ee_z"]
    obs = load_recordings(recording, sim, resample=None, noise=load_noise())
    assert len(obs) == 4
    # the recorded values are noisy: not on the simulator's exact trajectory
    fk = sim.forward_kinematics(obs[0].q)
    assert float((fk - obs[0].ee).abs().max()) > 1e-4


def load_noise():
    from camo_sbi.task import NoiseModel

    return NoiseModel(joint_deg=0.3, ee_mm=1.5)


def test_simulate_observations_same_seed_same_file(recording, tmp_path):
    again = tmp_path / "again.csv"
    assert main(["simulate-observations", *MODEL, *LIMITS, "--reaches", "4", "--seed", "2", *NOISE,
                 "--out", str(again)]) == 0
    assert again.read_bytes() == recording.read_bytes()


def test_rate_multiplier_writes_more_samples(recording, tmp_path, sim):
    fast = tmp_path / "fast.csv"
    assert main(["simulate-observations", *MODEL, *LIMITS, "--reaches", "4", "--seed", "2", "--rate-multiplier",
                 "3", "--out", str(fast)]) == 0
    slow = load_recordings(recording, sim, resample=None, noise=load_noise())
    quick = load_recordings(fast, sim, resample=None)
    assert [o.length for o in quick] == [3 * (o.length - 1) + 1 for o in slow]
    assert [o.length for o in load_recordings(fast, sim)] == [o.length for o in slow]  # resampled back


def test_infer_limits_table_has_every_joint_and_bound(inferred, sim):
    out, df = inferred
    assert list(df.columns) == ["method", "joint", "bound", "estimate_rad", "estimate_deg", "observed_min_deg",
                                "observed_max_deg", "median_deg", "lower_90_deg", "upper_90_deg", "identifiability",
                                "margin_deg", "reaches_at_bound", "exercised", "calibration",
                                "untouched_coverage_90", "untouched_calibration", "clipped_samples",
                                "beyond_range", "status", "model_check"]
    assert set(df.method) == {"camo", "naive", "nominal", "npe"}
    assert (df.clipped_samples == 0).all() and df.beyond_range.isna().all()  # nothing went past the model's range
    for _, g in df.groupby("method"):
        assert sorted(zip(g.joint, g.bound, strict=True)) == sorted((j, b) for j in JOINTS
                                                                     for b in ("lower", "upper"))
    np.testing.assert_allclose(df.estimate_deg, np.degrees(df.estimate_rad))
    assert (df.lower_90_deg <= df.upper_90_deg + 1e-9).all()
    b = sim.bounds.numpy()
    for _, r in df.iterrows():
        j = JOINTS.index(r.joint)
        assert b[j, 0] - 1e-9 <= r.estimate_rad <= b[j, 1] + 1e-9


def test_limits_csv_median_identifiability_exercised_calibration(inferred, sim, recording):
    """median inside the 90% interval; identifiability = 90% width / the prior's 90% width (the
    prior split at the reaches' starts); exercised = the recorded extreme within the margin (2 deg
    + 4 sigma) of the estimate (recomputed here from the file); naive's exercised is empty (its
    estimate is the recorded extreme); the README's calibration verdict per method."""
    out, df = inferred
    assert ((df.lower_90_deg <= df.median_deg + 1e-9) & (df.median_deg <= df.upper_90_deg + 1e-9)).all()
    obs = load_recordings(recording, sim, noise=load_noise())
    starts = np.stack([o.start.numpy() for o in obs])
    b = sim.bounds.numpy()
    prior_w = np.empty(2 * len(JOINTS))
    prior_w[0::2] = starts.min(axis=0) - b[:, 0]
    prior_w[1::2] = b[:, 1] - starts.max(axis=0)
    for m in ("camo", "npe"):
        g = df[df.method == m]
        width = np.radians(g.upper_90_deg - g.lower_90_deg).to_numpy()
        np.testing.assert_allclose(g.identifiability, width / (0.9 * prior_w), rtol=1e-9)
    assert df[df.method.isin(["naive", "nominal"])].identifiability.isna().all()
    lo = np.stack([o.q.numpy().min(axis=0) for o in obs])
    hi = np.stack([o.q.numpy().max(axis=0) for o in obs])
    allow = np.radians(2.0) + K_SIGMA * np.radians(0.3) + 1e-6
    nominal = df[df.method == "nominal"]
    expect = np.empty(2 * len(JOINTS), bool)
    expect[0::2] = np.abs(lo.min(axis=0) - b[:, 0]) <= allow
    expect[1::2] = np.abs(hi.max(axis=0) - b[:, 1]) <= allow
    assert nominal.exercised.tolist() == expect.tolist() and not expect.all()
    np.testing.assert_allclose(nominal.observed_min_deg.to_numpy()[0::2], np.degrees(lo.min(axis=0)))
    np.testing.assert_allclose(nominal.observed_max_deg.to_numpy()[1::2], np.degrees(hi.max(axis=0)))
    assert df[df.method == "naive"].exercised.isna().all()
    verdict = dict(zip(df.method, df.calibration, strict=True))
    assert verdict["camo"] == "not calibrated on this model (panda: over-confident; human: mildly over-confident)"
    assert verdict["npe"].startswith("not calibrated on this model (panda: calibrated")


def test_infer_point_methods_and_their_values(inferred, sim, recording):
    out, df = inferred
    for m in ("naive", "nominal"):
        g = df[df.method == m]
        np.testing.assert_allclose(g.lower_90_deg, g.estimate_deg)
        np.testing.assert_allclose(g.upper_90_deg, g.estimate_deg)
    nominal = df[df.method == "nominal"].estimate_rad.to_numpy()
    np.testing.assert_allclose(nominal, sim.bounds.numpy().reshape(-1))
    # naive = observed min/max: inside the true limits up to the noise (K_SIGMA sigma)
    truth = load_limits(DATA / "arm7_limits.json", sim).numpy().reshape(-1)
    naive = df[df.method == "naive"].estimate_rad.to_numpy()
    tol = K_SIGMA * np.radians(0.3)
    assert (naive[0::2] >= truth[0::2] - tol).all() and (naive[1::2] <= truth[1::2] + tol).all()
    # with joint noise naive takes the min/max of each reach median-filtered over 3 samples
    from camo_sbi.inference.naive import median3

    obs = load_recordings(recording, sim, noise=load_noise())
    q = np.concatenate([median3(o.q).numpy() for o in obs])
    np.testing.assert_allclose(naive[0::2], q.min(axis=0))
    np.testing.assert_allclose(naive[1::2], q.max(axis=0))


def test_infer_posterior_interval_is_the_weighted_quantile(inferred):
    import arviz as az

    out, df = inferred
    idata = az.from_netcdf(out / "posteriors" / "npe.nc")
    assert list(idata.posterior.limits.coords["joint"].values) == JOINTS
    npe = df[df.method == "npe"]
    assert (npe.upper_90_deg - npe.lower_90_deg > 0).all()  # a posterior, not a point
    # the interval written is the one calibrate measures: its central 90% interval of the stored
    # weighted samples, by the one weighted quantile (camo_sbi.diagnostics.calibration uses it too)
    from camo_sbi.diagnostics.calibration import weighted_quantile

    cd = idata.constant_data
    samples = cd["weighted_samples"].values.reshape(cd["weights"].size, -1)
    lo, hi = np.degrees(weighted_quantile(samples, cd["weights"].values, [0.05, 0.95]))
    k = [2 * JOINTS.index(j) + (b == "upper") for j, b in zip(npe.joint, npe.bound, strict=True)]
    np.testing.assert_allclose(npe.lower_90_deg, lo[k], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(npe.upper_90_deg, hi[k], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(npe.median_deg, np.degrees(weighted_quantile(samples, cd["weights"].values, 0.5))[k],
                               rtol=1e-6, atol=1e-9)


def test_infer_writes_report_posteriors_and_predictions(inferred, sim):
    out, df = inferred
    html = (out / "report.html").read_text()
    assert html.count(PNG) == 5  # the limits figure, then one figure per reach
    first = html.index(PNG)
    assert html[first:].split('alt="', 1)[1].startswith("limits figure")  # the report opens with it
    assert "not exercised" in html
    assert "http://" not in html and "https://" not in html  # self-contained
    for m in ("camo", "naive", "nominal", "npe"):  # naive and nominal are point estimates: estimates/
        assert (out / ("estimates" if m in ("naive", "nominal") else "posteriors") / f"{m}.nc").is_file()
        pred = load_recordings(out / "predictions" / f"{m}.csv", sim, resample=None)
        assert len(pred) == 2
        np.testing.assert_allclose(pred[1].goal.numpy(), [-0.1, 0.3, 0.7])


@pytest.mark.slow  # in the slow tier for the default tier's 4-minute budget (issue 28)
def test_ee_only_recording(recording, tmp_path, sim, capsys):
    ee = tmp_path / "ee.csv"
    assert main(["simulate-observations", *MODEL, *LIMITS, "--reaches", "3", "--seed", "4", "--space",
                 "cartesian", "--noise-ee-mm", "1", "--out", str(ee)]) == 0
    out = tmp_path / "out"
    argv = ["infer", "--observations", str(ee), *MODEL, "--methods", "camo,camo-cs,naive,nominal,abc-smc,npe",
            "--budget", "60", "--noise-ee-mm", "1", "--config", f"npe={json.dumps(NPE_TINY)}",
            "--config", f"abc-smc={json.dumps(ABC_TINY)}", "--out", str(out)]
    capsys.readouterr()
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "naive: skipped (space: method 'naive' needs joint observations" in printed
    df = pd.read_csv(out / "limits.csv")
    assert set(df.method) == {"camo", "camo-cs", "nominal", "abc-smc", "npe"}
    assert len(df) == 5 * 2 * len(JOINTS)
    for m in ("naive", "camo-hull", "camo-js"):
        line = _exit_2(["infer", "--observations", str(ee), *MODEL, "--methods", m, "--out", str(tmp_path / m)],
                       capsys)
        assert line.startswith("camo-sbi: error: space: method") and "joint observations" in line


def test_oracle_is_skipped_on_recordings(recording, tmp_path, capsys):
    argv = ["infer", "--observations", str(recording), *MODEL, *NOISE, "--methods", "nominal,oracle", "--out",
            str(tmp_path / "o")]
    assert main(argv) == 0
    assert "oracle: skipped (needs the true limits" in capsys.readouterr().out
    # without its noise model the noisy recording's ee_* are too far from the FK of its joints
    without = [a for a in argv if a not in NOISE]
    line = _exit_2(without, capsys)
    assert line.startswith(f"camo-sbi: error: {recording}: column 'ee_x', line ") and "(--ee)" in line and "--noise-joint-deg 0" in line


def _csv_edit(src: Path, dst: Path, fn) -> Path:
    lines = src.read_text().splitlines()
    dst.write_text("\n".join(fn(lines)) + "\n")
    return dst


def test_bad_files_exit_2_naming_the_column(recording, tmp_path, capsys, sim):
    base = ["infer", *MODEL, "--methods", "naive", "--out", str(tmp_path / "x")]

    def drop_goals(lines):
        keep = [i for i, c in enumerate(lines[0].split(",")) if not c.startswith("goal_")]
        return [",".join(line.split(",")[i] for i in keep) for line in lines]

    f = _csv_edit(recording, tmp_path / "nogoal.csv", drop_goals)
    line = _exit_2([*base, "--observations", str(f)], capsys)
    assert line == f"camo-sbi: error: {f}: column 'goal_x' is missing " \
                   f"(a recording needs reach, step (or time in seconds), goal_x, goal_y, goal_z (or --goal final " \
                   f"for free reaching), then the joint columns and/or " \
                   f"ee_x, ee_y, ee_z)"
    f = _csv_edit(recording, tmp_path / "unknown.csv",
                  lambda lines: [lines[0].replace("wrist_pitch", "wrist_flex"), *lines[1:]])
    line = _exit_2([*base, "--observations", str(f)], capsys)
    assert line.startswith(f"camo-sbi: error: {f}: column 'wrist_flex' is unknown")

    f = _csv_edit(recording, tmp_path / "deg.csv", lambda lines: csv_to_degrees(lines, JOINTS))
    line = _exit_2([*base, "--observations", str(f), *NOISE], capsys)
    assert line.startswith(f"camo-sbi: error: {f}: column '") and "use --degrees" in line
    assert main([*base, "--observations", str(f), *NOISE, "--degrees"]) == 0


@pytest.mark.parametrize("extra, needle", [
    (["--methods", "nope"], "--methods: method: unknown method 'nope'"),
    (["--budget", "0"], "--budget: must be >= 1"),
    (["--noise-joint-deg", "-1"], "--noise-joint-deg: expected a finite number >= 0"),
    (["--space", "cartesian", "--methods", "nominal"], None),
    (["--config", "camo={\"keep_best\": 0.5}"], "--config: camo:"),
])
def test_infer_bad_options_exit_2(extra, needle, recording, tmp_path, capsys):
    # argparse keeps the last of a repeated option, so ``extra`` may override --methods
    argv = ["infer", "--observations", str(recording), *MODEL, *NOISE, "--methods", "camo", "--out",
            str(tmp_path / "y")]
    if needle is None:  # a recording with both spaces: --space cartesian is fine
        assert main([*argv, *extra]) == 0
        return
    line = _exit_2([*argv, *extra], capsys)
    assert line.startswith(f"camo-sbi: error: {needle}"), line


# ----------------------------------------------------------------------------- the model options


def _limits_file(tmp_path, **changes) -> Path:
    data = json.loads((DATA / "arm7_limits.json").read_text())
    for k, v in changes.items():
        if v is None:
            data.pop(k)
        else:
            data[k] = v
    path = tmp_path / "limits.json"
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize("changes, needle", [
    ({"wrist_flex": [0, 1]}, "unknown joint 'wrist_flex'"),
    ({"elbow": None}, "joint 'elbow' is missing"),
    ({"elbow": [-1.9, 0.9]}, "joint 'elbow': [-1.9, 0.9] rad lies outside the model's range [-2.4, 0.3]"),
    ({"shoulder": [0.5, 1.0]}, "joint 'shoulder': [0.5, 1] does not contain the start posture 0.4"),
    ({"shoulder": [1.0, 0.5]}, "joint 'shoulder': lo 1.0 > hi 0.5"),
    ({"shoulder": [0.1]}, "joint 'shoulder': expected [lo, hi]"),
])
def test_limits_file_is_checked(changes, needle, tmp_path, capsys):
    path = _limits_file(tmp_path, **changes)
    line = _exit_2(["simulate-observations", *MODEL, "--limits", str(path), "--out", str(tmp_path / "r.csv")],
                   capsys)
    assert line.startswith(f"camo-sbi: error: --limits: {path}: {needle}"), line


def test_limits_file_in_degrees(tmp_path, sim):
    data = json.loads((DATA / "arm7_limits.json").read_text())
    deg = tmp_path / "deg.json"
    deg.write_text(json.dumps({k: [float(np.degrees(v)) for v in p] for k, p in data.items()}))
    np.testing.assert_allclose(load_limits(deg, sim, degrees=True), load_limits(DATA / "arm7_limits.json", sim),
                               atol=1e-12)


@pytest.mark.parametrize("argv, needle", [
    (["--urdf", str(DATA / "arm7.urdf"), "--start", START], "--ee: --urdf needs the end-effector link name"),
    ([*MODEL[:2], "--ee", "nolink", "--start", START], "--ee: "),
    ([*MODEL, "--model", "panda"], "--model: give --model or --urdf, not both"),
    ([*MODEL[:4], "--start", "0,1"], "--start: "),
    (["--urdf", "missing.urdf", "--ee", "tool"], "--urdf: no such file missing.urdf"),
    (["--model", "panda", "--height", "1.7"], "--height: only with --model human"),
])
def test_model_options_exit_2(argv, needle, tmp_path, capsys):
    line = _exit_2(["demo", *argv, "--out", str(tmp_path)], capsys)
    assert line.startswith(f"camo-sbi: error: {needle}"), line


COMPARE = ["compare", *MODEL, *LIMITS, "--methods", "camo", "--budgets", "30", "--seeds", "2", "--tasks", "1",
           "--test-goals", "2", "--no-report"]


def _comparable(df: pd.DataFrame) -> pd.DataFrame:
    timings = ("wall_time", "compile_time", "import_time")  # differ between runs
    return df[~df.metric.isin(timings)].sort_values(list(df.columns[:7])).reset_index(drop=True)


@pytest.fixture(scope="module")
def compare_urdf(tmp_path_factory):
    out = tmp_path_factory.mktemp("compare") / "serial"
    assert main([*COMPARE, "--out", str(out)]) == 0
    return pd.read_csv(out / "results.csv")


def test_compare_on_a_urdf(compare_urdf, tmp_path, capsys):
    df = compare_urdf
    assert set(df.task) == {"arm7"} and set(df.subject) == {"arm7_limits"}
    assert {f"limit_error_deg_{j}" for j in JOINTS} <= set(df.metric)
    assert (df[(df.method == "oracle") & (df.metric == "cartesian_error_mm")].value == 0).all()
    assert _exit_2(["compare", *MODEL, "--out", str(tmp_path / "n")], capsys).startswith(
        "camo-sbi: error: --limits: a URDF model needs the subject's true limits")
    assert _exit_2([*COMPARE, "--out", str(tmp_path / "z"), "--subjects", "elbow_restricted"], capsys).startswith(
        "camo-sbi: error: --subjects: the --limits file is the subject")


# slow: worker processes that rebuild the URDF kernel (~30 s); --workers stays in the default run
# (test_cli.py::test_compare_parallel_workers_same_table)
@pytest.mark.slow
def test_compare_urdf_in_worker_processes_same_table(compare_urdf, tmp_path):
    """Spawned workers rebuild the URDF model from the cell's ModelSpec (path + sha256)."""
    out = tmp_path / "workers"
    assert main([*COMPARE, "--workers", "2", "--out", str(out)]) == 0
    pd.testing.assert_frame_equal(_comparable(pd.read_csv(out / "results.csv")), _comparable(compare_urdf))


def test_reproduce_panda_on_a_urdf(tmp_path):
    rep = tmp_path / "r"
    assert main(["reproduce", "panda", *MODEL, *LIMITS, "--runs", "1", "--tasks", "2", "--test-goals", "2",
                 "--samples", "40", "--methods", "camo-hull,naive,nominal,oracle", "--out", str(rep)]) == 0
    df = pd.read_csv(rep / "results.csv")
    assert set(df.model) == {"arm7"} and set(df.subject) == {"arm7_limits"}
    assert (df[(df.method == "oracle") & (df.metric == "cartesian_error_mm")].value == 0).all()


def test_urdf_changed_since_setup_is_refused(tmp_path):
    urdf = tmp_path / "arm.urdf"
    urdf.write_text((DATA / "arm7.urdf").read_text())
    spec = ModelSpec(kind="urdf", urdf=str(urdf), digest="0" * 64, ee="tool")
    with pytest.raises(ValueError, match="^--urdf: .* changed since the run was set up"):
        spec.build()


def test_reaches_from_different_starts(tmp_path, sim, capsys):
    """The prior splits at the first reach's start and is conditioned on every other start lying
    inside the limits, so every estimate contains every observed start."""
    import torch

    from camo_sbi.io.schema import save_recordings
    from camo_sbi.scenarios.reaching import observe, reachable_goals

    theta = load_limits(DATA / "arm7_limits.json", sim).reshape(-1)
    starts = torch.tensor([[0.0, 0.4, 0.0, -1.1, 0.0, 0.7, 0.0], [0.9, -0.4, 1.5, -0.4, 0.6, -1.0, 2.0],
                           [-1.0, 0.9, -2.0, -1.8, -0.8, 1.2, -2.5]], dtype=torch.float64)
    goals = reachable_goals(sim, theta, 3, torch.Generator().manual_seed(0))
    path = save_recordings(tmp_path / "starts.csv", observe(sim, theta, goals, starts), sim)
    out = tmp_path / "out"
    assert main(["infer", "--observations", str(path), *MODEL, "--methods", "camo,naive,nominal", "--budget",
                 "100", "--out", str(out)]) == 0
    df = pd.read_csv(out / "limits.csv")
    s = starts.numpy()
    for m, g in df.groupby("method"):
        est = g.estimate_rad.to_numpy()
        assert (est[0::2] <= s.min(axis=0) + 1e-9).all() and (est[1::2] >= s.max(axis=0) - 1e-9).all(), m


@pytest.mark.slow  # in the slow tier for the default tier's 4-minute budget (issue 28)
def test_ee_only_reaches_from_five_start_postures_are_inferred(tmp_path, sim, capsys):
    """Done-when of issue 27: end-effector-only reaches from 5 start postures. Each start is
    estimated by IK (starts.csv), and every method's limits contain every estimated start."""
    import torch

    from camo_sbi.io.schema import save_recordings
    from camo_sbi.scenarios.reaching import observe, reachable_goals
    from camo_sbi.task import Observation

    theta = load_limits(DATA / "arm7_limits.json", sim).reshape(-1)
    gen = torch.Generator().manual_seed(4)
    base = torch.tensor([float(v) for v in START.split(",")], dtype=torch.float64)
    starts = torch.stack([torch.clamp(base + 0.3 * (2 * torch.rand(7, generator=gen, dtype=torch.float64) - 1),
                                      theta[0::2] + 0.05, theta[1::2] - 0.05) for _ in range(5)])
    obs = observe(sim, theta, reachable_goals(sim, theta, 5, gen), starts)
    path = save_recordings(tmp_path / "ee5.csv", tuple(Observation(o.start, o.goal, None, o.ee) for o in obs), sim)
    out = tmp_path / "out"
    assert main(["infer", "--observations", str(path), *MODEL, "--methods", "camo,nominal", "--budget", "100",
                 "--noise-ee-mm", "1", "--out", str(out)]) == 0
    est = pd.read_csv(out / "starts.csv")
    assert len(est) == 5 and list(est.columns[:2]) == ["reach", "source"] and (est.source == "IK").all()
    q = torch.tensor(est[JOINTS].to_numpy())
    first = torch.stack([o.ee[0] for o in obs])
    assert float((sim.forward_kinematics(q).to(torch.float64) - first).norm(dim=1).max()) < 1e-3
    df = pd.read_csv(out / "limits.csv")
    for m, g in df.groupby("method"):
        e = g.estimate_rad.to_numpy()
        assert (e[0::2] <= q.numpy().min(axis=0) + 1e-6).all() and (e[1::2] >= q.numpy().max(axis=0) - 1e-6).all(), m


@pytest.mark.slow  # in the slow tier for the default tier's 4-minute budget (issue 28)
def test_infer_a_folder_of_subjects_writes_one_limits_csv(recording, tmp_path, capsys):
    """Done-when of issue 27: ``infer --observations DIR/`` (one subject per file) writes one
    combined limits.csv with a subject column, and one report."""
    folder = tmp_path / "session"
    folder.mkdir()
    (folder / "alice.csv").write_text(recording.read_text())
    assert main(["simulate-observations", *MODEL, *LIMITS, "--reaches", "3", "--seed", "9", *NOISE,
                 "--out", str(folder / "bob.npz")]) == 0
    (folder / "notes.txt").write_text("not a recording")
    out = tmp_path / "out"
    assert main(["infer", "--observations", str(folder), *MODEL, *NOISE, "--methods", "naive,nominal",
                 "--out", str(out)]) == 0
    df = pd.read_csv(out / "limits.csv")
    assert df.columns[0] == "subject" and sorted(set(df.subject)) == ["alice", "bob"]
    assert len(df) == 2 * 2 * 2 * len(JOINTS)
    alone = pd.read_csv(out / "subjects" / "alice" / "limits.csv")
    pd.testing.assert_frame_equal(df[df.subject == "alice"].drop(columns="subject").reset_index(drop=True), alone)
    html = (out / "report.html").read_text()
    assert html.count('alt="limits figure"') == 2 and 'href="subjects/bob/report.html"' in html
    (folder / "carol.csv").write_text("reach,step\n")
    line = _exit_2(["infer", "--observations", str(folder), *MODEL, *NOISE, "--methods", "naive", "--out",
                    str(tmp_path / "o2")], capsys)
    assert line.startswith(f"camo-sbi: error: {folder / 'carol.csv'}: has a header but no samples")
    assert not (tmp_path / "o2").exists()  # every file is checked before anything runs


@pytest.mark.slow  # in the slow tier for the default tier's 4-minute budget (issue 28)
def test_body_scale_free_on_a_body_5_percent_taller(tmp_path, sim, capsys):
    """Done-when of issue 27: recordings of a body 5% taller report s within 0.02 of 1.05; without
    --body-scale free the run warns that the body does not fit the model."""
    path = tmp_path / "tall.csv"
    assert main(["simulate-observations", *MODEL, *LIMITS, "--scale", "1.05", "--reaches", "5", "--seed", "1", *NOISE,
                 "--out", str(path)]) == 0
    assert _exit_2(["simulate-observations", *MODEL, *LIMITS, "--scale", "1.5", "--out", str(tmp_path / "x.csv")],
                   capsys) == "camo-sbi: error: --scale: must lie in [0.85, 1.15], got 1.5"
    assert main(["infer", "--observations", str(path), *MODEL, *NOISE, "--methods", "nominal", "--out",
                 str(tmp_path / "fixed")]) == 0
    assert re.search(r"warning: .*tall.csv: the recording fits a body 1.0[45]\d times the model's size .* use "
                     r"--body-scale free", capsys.readouterr().out)
    assert "the recording fits a body 1.0" in (tmp_path / "fixed" / "report.html").read_text()  # and the report
    out = tmp_path / "out"
    assert main(["infer", "--observations", str(path), *MODEL, *NOISE, "--body-scale", "free", "--methods",
                 "camo,naive,nominal", "--budget", "100", "--out", str(out)]) == 0
    cfg = json.loads((out / "config.json").read_text())
    assert abs(cfg["body_scale"] - 1.05) < 0.02
    lo, hi = cfg["body_scale_90"]
    assert lo <= cfg["body_scale"] <= hi and hi - lo < 0.02
    assert f"body scale s = {cfg['body_scale']:.3f}" in capsys.readouterr().out


def test_demo_and_calibrate_on_a_urdf(tmp_path):
    assert main(["demo", *MODEL, "--batch", "8", "--out", str(tmp_path / "demo")]) == 0
    assert (tmp_path / "demo" / "demo.png").stat().st_size > 1000
    out = tmp_path / "cal"
    assert main(["calibrate", *MODEL, "--methods", "camo,naive", "--subjects", "2", "--tasks", "1", "--budget",
                 "40", "--sbc-draws", "10", "--out", str(out)]) == 0
    cov = pd.read_csv(out / "coverage.csv")
    assert set(cov.task) == {"arm7"} and set(cov.method) == {"camo", "naive"}


@pytest.mark.slow  # in the slow tier for the default tier's 4-minute budget (issue 28)
def test_infer_with_an_amortized_estimator(recording, sim, tmp_path, capsys):
    """`infer --amortized FILE` runs npe-amortized on a recording whose reaches start at the
    model's start (0 simulations); an estimator that does not fit the recording (trained with
    another noise model; reaches chained from posture to posture, as `simulate-observations`
    writes them) is skipped with a note beside other methods, and refused, naming the reason,
    when it is the only method."""
    from camo_sbi.io.schema import save_recordings
    from camo_sbi.scenarios.reaching import make_reaching_task

    theta = load_limits(DATA / "arm7_limits.json", sim).reshape(-1)
    rec = save_recordings(tmp_path / "r.csv", make_reaching_task(sim, theta, n_train=3, n_test=1, seed=0).observations,
                          sim)
    clean, noisy = tmp_path / "clean.pt", tmp_path / "noisy.pt"
    tiny = ["--simulations", "300", "--max-epochs", "2"]
    assert main(["amortize", *MODEL, *tiny, "--out", str(clean)]) == 0
    assert main(["amortize", *MODEL, *tiny, *NOISE, "--out", str(noisy)]) == 0
    base = ["infer", "--observations", str(rec), *MODEL]
    out = tmp_path / "a"
    assert main([*base, "--methods", "naive,npe-amortized", "--amortized", str(clean), "--out", str(out)]) == 0
    df = pd.read_csv(out / "limits.csv")
    assert set(df.method) == {"naive", "npe-amortized"} and len(df) == 2 * 2 * len(JOINTS)
    assert (out / "posteriors" / "npe-amortized.nc").is_file()
    capsys.readouterr()
    assert main([*base, "--methods", "naive,npe-amortized", "--amortized", str(noisy), "--out",
                 str(tmp_path / "b")]) == 0
    assert "npe-amortized: skipped (task.noise:" in capsys.readouterr().out
    assert set(pd.read_csv(tmp_path / "b" / "limits.csv").method) == {"naive"}
    line = _exit_2([*base, "--methods", "npe-amortized", "--amortized", str(noisy), "--out", str(tmp_path / "c")],
                   capsys)
    assert line.startswith("camo-sbi: error: task.noise:")
    tall = save_recordings(tmp_path / "tall.csv", make_reaching_task(sim.scaled(1.05), theta, n_train=3, n_test=1,
                                                                      seed=0).observations, sim)
    assert main(["infer", "--observations", str(tall), *MODEL, "--methods", "naive,npe-amortized", "--amortized",
                 str(clean), "--body-scale", "free", "--out", str(tmp_path / "scaled")]) == 0
    assert "npe-amortized: skipped (trained on the model's own size" in capsys.readouterr().out
    line = _exit_2(["infer", "--observations", str(tall), *MODEL, "--methods", "npe-amortized", "--amortized",
                    str(clean), "--body-scale", "free", "--out", str(tmp_path / "scaled_alone")], capsys)
    assert line.startswith("camo-sbi: error: --body-scale: npe-amortized was trained on the model's own size")
    assert main(["infer", "--observations", str(rec), *MODEL, "--methods", "naive,npe-amortized", "--amortized",
                 str(clean), "--reach-model", "minimum-jerk", "--out", str(tmp_path / "mj")]) == 0
    assert "npe-amortized: skipped (trained on the controller's reaches, not on --reach-model minimum-jerk)" in \
        capsys.readouterr().out
    line = _exit_2([*base, "--methods", "npe-amortized", "--out", str(tmp_path / "d")], capsys)
    assert line.startswith("camo-sbi: error: --amortized: npe-amortized needs a trained estimator file")
    line = _exit_2([*base, "--methods", "npe-amortized", "--amortized", str(tmp_path / "missing.pt"), "--out",
                    str(tmp_path / "d")], capsys)
    assert line.startswith("camo-sbi: error: --amortized: estimator: no such file")
    chained = ["infer", "--observations", str(recording), *MODEL, *NOISE, "--methods", "naive,npe-amortized",
               "--amortized", str(noisy), "--out", str(tmp_path / "e")]
    assert main(chained) == 0
    assert "npe-amortized: skipped (task.prior: differs" in capsys.readouterr().out
