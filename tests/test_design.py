"""Active design (camo_sbi.design): the criterion on a 1-joint arm whose most informative goal is
known analytically, invariance to candidate order, seeds, counted simulations, refusals."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from camo_sbi.design import next_goal, rank_goals
from camo_sbi.experiments.cli import main
from camo_sbi.inference.result import PosteriorResult
from camo_sbi.priors import BoxPrior
from camo_sbi.simulators import from_urdf
from camo_sbi.task import Task

R = 0.5
ARM1 = f"""<robot name="arm1">
  <link name="base"/><link name="link1"/><link name="tool"/>
  <joint name="yaw" type="revolute"><parent link="base"/><child link="link1"/><origin xyz="0 0 0"/>
    <axis xyz="0 0 1"/><limit lower="-2.5" upper="2.5" effort="1" velocity="1"/></joint>
  <joint name="tip" type="fixed"><parent link="link1"/><child link="tool"/><origin xyz="{R} 0 0"/></joint>
</robot>"""  # a 1-joint planar arm of radius R: the goal at angle a is (R cos a, R sin a, 0)
HI_SPREAD = (0.8, 1.2)  # the posterior over the restricted upper bound


@pytest.fixture(scope="module")
def arm():
    return from_urdf(ARM1, "tool", start=[0.0])


def _goal(angle):
    return [R * math.cos(angle), R * math.sin(angle), 0.0]


@pytest.fixture(scope="module")
def toy(arm):
    """A posterior that knows lo = -2.5 and spreads hi uniformly over HI_SPREAD."""
    task = Task("arm1", "toy", arm, BoxPrior(arm.bounds, torch.tensor([0.0])), ())
    hi = np.linspace(*HI_SPREAD, 101)
    samples = np.stack([np.full_like(hi, -2.5), hi], axis=1)
    result = PosteriorResult("toy", samples, None, samples.mean(0), 0, 0.0, 0)
    return task, result


ANGLES = [-1.5, 0.0, 0.5, 1.0, 1.3]  # inside every draw's limits x3, within the spread, just beyond it


def test_arm_reaches_its_goals(arm):
    traj = arm.simulate(torch.tensor([[-2.5, 2.5]] * len(ANGLES)), torch.tensor([_goal(a) for a in ANGLES]))
    assert bool(traj.reached.all())
    traj = arm.simulate(torch.tensor([[-2.5, 1.0]]), torch.tensor([_goal(1.3)]))
    assert not bool(traj.reached[0]) and abs(float(traj.q[0, -1, 0]) - 1.0) < 1e-6  # clamped at the bound


@pytest.mark.parametrize("criterion", ["variance", "eig"])
def test_goal_just_beyond_the_bound_ranks_first(toy, criterion):
    task, result = toy
    cands = torch.tensor([_goal(a) for a in ANGLES])
    info = rank_goals(task, result, cands, seed=0, budget=len(ANGLES) * 100, criterion=criterion)
    assert info.status == "ok" and info.n_draws == 100 and info.n_simulations == 500
    assert list(info.index[:2]) == [4, 3]  # beyond the spread first, then within it
    by_angle = dict(zip(info.index.tolist(), info.scores.tolist(), strict=True))
    # goals inside every draw: ~0 (the controller's pull toward mid-range moves their end points by µm)
    assert max(by_angle[i] for i in range(3)) < 1e-3 * by_angle[4]
    if criterion == "variance":
        # beyond the spread every draw stops at its own bound: the whole variance of hi is resolved
        # (up to the arc's curvature and the 1 mm resolution)
        resampled = result.resample(100, np.random.default_rng(0))
        assert by_angle[4] == pytest.approx(resampled[:, 1].var(ddof=1), rel=0.02)
    else:
        assert by_angle[4] <= math.log(100) + 1e-9


def test_ranking_is_invariant_to_candidate_order_and_seeded(toy):
    task, result = toy
    cands = torch.tensor([_goal(a) for a in ANGLES])
    perm = [3, 0, 4, 2, 1]
    a = rank_goals(task, result, cands, seed=3, budget=500)
    b = rank_goals(task, result, cands[perm], seed=3, budget=500)
    np.testing.assert_allclose(a.goals, b.goals)
    np.testing.assert_allclose(a.scores, b.scores)
    assert [perm[i] for i in b.index] == a.index.tolist()
    c = rank_goals(task, result, cands, seed=3, budget=500)
    np.testing.assert_array_equal(a.scores, c.scores)
    goal, info = next_goal(task, result, cands, seed=3, budget=500)
    assert goal.shape == (3,) and torch.allclose(goal, cands[4].double())


def test_a_point_estimate_is_refused_and_no_spread_is_a_fallback(toy):
    task, result = toy
    cands = torch.tensor([_goal(a) for a in ANGLES])
    point = PosteriorResult("naive", np.array([[-2.5, 1.0]]), None, np.array([-2.5, 1.0]), 0, 0.0, 1)
    with pytest.raises(ValueError, match="^result: method 'naive'"):
        rank_goals(task, point, cands, seed=0, budget=500)
    with pytest.raises(ValueError, match="^budget:"):
        rank_goals(task, result, cands, seed=0, budget=9)
    with pytest.raises(ValueError, match="^candidates:"):
        rank_goals(task, result, cands[:, :2], seed=0, budget=500)
    with pytest.raises(ValueError, match="^criterion:"):
        rank_goals(task, result, cands, seed=0, budget=500, criterion="bald")
    inside = rank_goals(task, result, cands[:3], seed=0, budget=300)
    assert inside.status.startswith("fallback: ")


DATA = Path(__file__).parent / "data"
MODEL = ["--urdf", str(DATA / "arm7.urdf"), "--ee", "tool", "--start", "0,0.4,0,-1.1,0,0.7,0"]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "reaches.csv"
    assert main(["simulate-observations", *MODEL, "--limits", str(DATA / "arm7_limits.json"), "--reaches", "4",
                 "--seed", "2", "--out", str(path)]) == 0
    return path


@pytest.mark.slow  # in the slow tier for the default tier's 4-minute budget (issue 28)
def test_infer_suggest_writes_ranked_next_goals(recording, tmp_path, capsys):
    argv = ["infer", "--observations", str(recording), *MODEL, "--methods", "naive,camo", "--budget", "50",
            "--seed", "0", "--suggest", "3"]
    assert main([*argv, "--out", str(tmp_path / "a")]) == 0
    printed = capsys.readouterr().out
    table = pd.read_csv(tmp_path / "a" / "next_goals.csv")
    assert list(table.columns[:5]) == ["rank", "goal_x", "goal_y", "goal_z", "score"]
    assert table["rank"].tolist() == [1, 2, 3] and set(table.method) == {"camo"}  # naive has no draws
    assert (np.diff(table.score) <= 0).all() and (table.score > 0).all()
    assert "next reaches" in printed and f"{table.goal_x[0]:.4g}" in printed
    assert main([*argv, "--out", str(tmp_path / "b")]) == 0  # same seed, same goals
    pd.testing.assert_frame_equal(table, pd.read_csv(tmp_path / "b" / "next_goals.csv"))


@pytest.mark.parametrize("extra, needle", [(["--methods", "naive,nominal", "--suggest", "2"], "--suggest: needs"),
                                           (["--methods", "camo", "--suggest", "-1"], "--suggest: must be")])
def test_infer_suggest_bad_options_exit_2(extra, needle, recording, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["infer", "--observations", str(recording), *MODEL, *extra, "--out", str(tmp_path)])
    assert exc.value.code == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith(f"camo-sbi: error: {needle}")


def test_reproduce_informative_active_design(tmp_path):
    """--design active runs to completion and counts the design's simulations."""
    from camo_sbi.experiments import reproduce_panda

    out = tmp_path / "active"
    argv = ["reproduce", "panda", "--setting", "informative", "--methods", "camo-seq", "--runs", "1",
            "--tasks", "3", "--test-goals", "6", "--samples", "200", "--seed", "1"]
    assert main([*argv, "--design", "active", "--out", str(out)]) == 0
    df = pd.read_csv(out / "results.csv")
    last = df[(df.n_tasks == 3) & (df.method == "camo-seq")].set_index("metric").value
    assert last["design_simulations"] == 2 * reproduce_panda.DESIGN_CANDIDATES * reproduce_panda.DESIGN_DRAWS
    assert last["design_fallbacks"] == 0 and last["design_method_simulations"] > 0
    assert last["binding_test_fraction"] >= 0.5 and "reachability_f1" in last and "limit_error_binding_deg" in last
    assert set(df.method) >= {"camo-seq", "naive", "nominal", "oracle"}


@pytest.mark.parametrize("extra, needle", [(["--setting", "toolkit"], "--design: active design needs"),
                                           (["--setting", "informative", "--design-method", "naive"],
                                            "--design-method: naive returns no posterior"),
                                           (["--setting", "informative", "--design-method", "camo-x"],
                                            "--design-method:")])
def test_active_design_bad_options_exit_2(extra, needle, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["reproduce", "panda", "--design", "active", *extra, "--runs", "1", "--out", str(tmp_path)])
    assert exc.value.code == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith(f"camo-sbi: error: {needle}")
