"""Issue 23: how many reaches a restriction touches, the informative goal design, reachability
scores and the claims that mark few binding reaches. Hand computations on the toy point robot."""

import math

import numpy as np
import pandas as pd
import pytest
import torch

from camo_sbi.evaluation.claims import binding_line, informative_claims, mark_few_reaches
from camo_sbi.evaluation.metrics import reachability_metrics
from camo_sbi.scenarios.reaching import (
    binding_fraction,
    binding_reaches,
    informative_test_goals,
    make_reaching_task,
    nominal_workspace_goals,
    task_binding_metrics,
)
from camo_sbi.simulators.base import Trajectories
from tests.toy_sim import ToySimulator

NOMINAL = torch.tensor([-1.0, 1.0, -1.0, 1.0], dtype=torch.float64)
TRUTH = torch.tensor([-1.0, 0.5, -1.0, 1.0], dtype=torch.float64)  # x0 <= 0.5: one restricted bound
START = torch.zeros(2, dtype=torch.float64)


def _goals(*x0):
    return torch.tensor([[x, 0.0, 0.0] for x in x0], dtype=torch.float64)


def test_binding_reaches_against_a_hand_computation():
    """The point robot moves straight to its goal, clamped at x0 = 0.5. Relaxing the bound to 1
    moves a reach by (goal - 0.5) if its goal lies beyond 0.5: 0.3 m, 2 mm (binds), 0.5 mm (does
    not: below 1 mm), and 0 for the goals inside the restriction."""
    sim = ToySimulator(2, max_steps=30)
    goals = _goals(0.3, 0.8, 0.5005, 0.502, -0.9)
    hit = binding_reaches(sim, TRUTH, NOMINAL, START, goals)
    assert hit.tolist() == [False, True, False, True, False]
    assert binding_fraction(sim, TRUTH, NOMINAL, START, goals) == pytest.approx(2 / 5)
    # a looser tolerance (1 cm) keeps only the 0.3 m move
    assert binding_reaches(sim, TRUTH, NOMINAL, START, goals, tol_m=1e-2).tolist() == [False, True, False, False,
                                                                                      False]
    per = binding_reaches(sim, TRUTH, NOMINAL, START, goals, per_bound=True)
    assert per.shape == (4, 5)
    assert per[1].tolist() == hit.tolist() and not per[[0, 2, 3]].any()  # only the restricted bound binds
    # no restriction: nothing binds
    assert not binding_reaches(sim, NOMINAL, NOMINAL, START, goals).any()


def test_binding_reaches_bad_input_names_the_argument():
    sim = ToySimulator(2)
    with pytest.raises(ValueError, match="goals"):
        binding_reaches(sim, TRUTH, NOMINAL, START, torch.zeros(3, 2))
    with pytest.raises(ValueError, match="tol_m"):
        binding_reaches(sim, TRUTH, NOMINAL, START, _goals(0.1), tol_m=0.0)
    with pytest.raises(ValueError, match="nominal_theta"):
        binding_reaches(sim, TRUTH, NOMINAL[:3], START, _goals(0.1))


def test_task_binding_metrics_counts_test_and_training_reaches():
    sim = ToySimulator(2, max_steps=30)
    task = make_reaching_task(sim, TRUTH, n_train=4, n_test=6, seed=0, workspace="nominal")
    got = task_binding_metrics(task)
    train = torch.stack([o.goal for o in task.observations])
    want_test = (task.test_goals[:, 0] > 0.5 + 1e-3).to(torch.float64)  # hand rule of the toy (x1 never binds)
    want_train = (train[:, 0] > 0.5 + 1e-3).to(torch.float64)
    assert got["binding_test_fraction"] == pytest.approx(float(want_test.mean()))
    assert got["binding_test_reaches"] == float(want_test.sum())
    assert got["binding_train_fraction"] == pytest.approx(float(want_train.mean()))
    assert got["binding_test_bound_min_fraction"] == pytest.approx(float(want_test.mean()))  # one restricted bound


def test_nominal_workspace_goals_span_the_nominal_limits_not_the_true_ones():
    sim = ToySimulator(2)
    g = nominal_workspace_goals(sim, 400, 1)
    assert g.shape == (400, 3) and g.dtype == torch.float64
    assert float(g[:, 0].max()) > 0.9 and float(g[:, 0].min()) < -0.9  # beyond the subject's 0.5
    torch.testing.assert_close(nominal_workspace_goals(sim, 400, 1), g, rtol=0, atol=0)  # seeded


@pytest.mark.parametrize("n", [5, 20])
def test_informative_test_goals_bind_on_at_least_half(n):
    """The toy subject binds on 25% of the nominal workspace (x0 > 0.5): the quota keeps at least
    ceil(n/2) binding goals; a subject binding everywhere gets the plain draw unchanged."""
    sim = ToySimulator(2, max_steps=30)
    g = informative_test_goals(sim, TRUTH, n, torch.Generator().manual_seed(2), START)
    assert g.shape == (n, 3)
    hit = binding_reaches(sim, TRUTH, NOMINAL, START, g)
    assert int(hit.sum()) >= math.ceil(n / 2)
    tight = torch.tensor([-1.0, 1e-3, -1.0, 1.0], dtype=torch.float64)  # x0 <= 0: ~half bind
    plain = nominal_workspace_goals(sim, 2 * n, torch.Generator().manual_seed(3))
    got = informative_test_goals(sim, tight, n, torch.Generator().manual_seed(3), START, min_binding=0.0)
    torch.testing.assert_close(got, plain[:n], rtol=0, atol=0)
    with pytest.raises(ValueError, match="min_binding"):
        informative_test_goals(sim, TRUTH, n, 0, START, min_binding=1.5)


def _traj(reached):
    b = len(reached)
    return Trajectories(torch.zeros(b, 2, 2), torch.zeros(b, 2, 3), torch.full((b,), 2), torch.tensor(reached))


def test_reachability_metrics_hand_computation():
    true = _traj([True, True, False, False, True])
    pred = _traj([True, False, True, False, True])  # tp 2, fn 1, fp 1, tn 1
    got = reachability_metrics(true, pred)
    assert got["reachability_precision"] == pytest.approx(2 / 3)
    assert got["reachability_recall"] == pytest.approx(2 / 3)
    assert got["reachability_f1"] == pytest.approx(2 / 3)
    assert got["reachability_accuracy"] == pytest.approx(3 / 5)
    none = reachability_metrics(_traj([False, False]), _traj([False, False]))  # nothing claimed, nothing missed
    assert none["reachability_precision"] == 1.0 and none["reachability_recall"] == 1.0


def _table(values: dict, binding_reaches_per_run) -> pd.DataFrame:
    rows = []
    for run, count in enumerate(binding_reaches_per_run):
        for method, (cart, bind) in values.items():
            for metric, v in (("cartesian_error_mm", cart[run]), ("limit_error_binding_deg", bind[run]),
                              ("binding_test_reaches", count), ("binding_test_fraction", count / 20)):
                rows.append({"run": run, "method": method, "n_tasks": 10, "metric": metric, "value": v,
                             "status": "ok"})
    return pd.DataFrame(rows)


def test_informative_claims_and_the_few_reaches_mark():
    rng = np.random.default_rng(0)
    n = 12
    base = rng.uniform(20, 30, n)
    df = _table({"camo-js": (base - 10, base - 8), "naive": (base, base), "nominal": (base + 5, base + 40),
                 "oracle": (0 * base, 0 * base)}, [12] * n)
    claims = informative_claims(df)
    assert set(claims.method) == {"camo-js"} and set(claims.baseline) == {"naive", "nominal"}
    assert len(claims) == 4 and claims.holds.all()
    assert not claims.few_reaches.any() and (claims.binding_test_reaches_min == 12).all()
    worse = _table({"camo-js": (base + 3, base + 3), "naive": (base, base), "nominal": (base, base)}, [12] * n)
    assert not informative_claims(worse).holds.any()
    few = mark_few_reaches(claims, _table({"naive": (base, base)}, [12] * (n - 1) + [2]))
    assert few.few_reaches.all() and (few.binding_test_reaches_min == 2).all()
    unknown = mark_few_reaches(claims, df[df.metric != "binding_test_reaches"])
    assert not unknown.few_reaches.any() and unknown.binding_test_reaches_min.isna().all()
    line = binding_line(_table({"naive": (base, base)}, [12] * (n - 1) + [2]))
    assert "fewest 2 reaches" in line and "1 run(s) with < 3" in line


# ------------------------------------------------------------------ touched bounds (issue 23 item 4)


def test_touched_bounds_finds_a_clamped_joint_and_only_it():
    """x0 is clamped at 0.5 while x1 still moves toward its goal: hi_0 is touched, read as 0.5
    exactly; a reach inside the limits touches nothing (it stops at its goal)."""
    from camo_sbi.inference.touched import touched_bounds
    from camo_sbi.scenarios.reaching import observe

    sim = ToySimulator(2, max_steps=30)
    far = observe(sim, TRUTH, torch.tensor([[0.8, 0.9, 0.0]], dtype=torch.float64))
    touched, ext = touched_bounds([o.q for o in far])
    assert touched.tolist() == [False, True, False, False] and ext[1] == 0.5
    near = observe(sim, TRUTH, torch.tensor([[0.3, -0.4, 0.0]], dtype=torch.float64))
    assert not touched_bounds([o.q for o in near])[0].any()
    # the arm at rest at the extreme (no other joint moving) is not evidence of a limit
    rest = torch.tensor([[0.0, 0.0], [0.2, 0.1], [0.2, 0.1], [0.2, 0.1]], dtype=torch.float64)
    assert not touched_bounds([rest])[0].any()
    # a joint that never leaves its start while the other moves is at both its extremes: not touched
    still = torch.tensor([[0.0, 0.0], [0.0, 0.1], [0.0, 0.2], [0.0, 0.3]], dtype=torch.float64)
    assert touched_bounds([still])[0].tolist() == [False, False, False, False]


def test_with_touched_replaces_only_touched_bounds():
    from camo_sbi.inference.result import PosteriorResult
    from camo_sbi.inference.touched import with_touched
    from camo_sbi.priors import BoxPrior
    from camo_sbi.scenarios.reaching import observe

    sim = ToySimulator(2, max_steps=30)
    obs = observe(sim, TRUTH, torch.tensor([[0.8, 0.9, 0.0]], dtype=torch.float64))
    samples = np.tile([-0.9, 0.7, -0.8, 0.95], (5, 1))
    res = PosteriorResult("camo", samples, None, samples[0].copy(), 10, 0.0, 1)
    out = with_touched(res, obs, BoxPrior(sim.bounds, sim.start))
    assert out.estimate.tolist() == [-0.9, 0.5, -0.8, 0.95] and (out.samples[:, 1] == 0.5).all()
    assert res.estimate[1] == 0.7  # the input is not changed


def test_simulate_observations_says_how_many_reaches_bind(tmp_path, capsys):
    """The synthetic recording's own count, checked against binding_reaches on the written file."""
    import json
    from pathlib import Path

    from camo_sbi.experiments.cli import main
    from camo_sbi.experiments.models import ModelSpec
    from camo_sbi.io.recordings import load_recordings

    data = Path(__file__).parent / "data"
    start = "0,0.4,0,-1.1,0,0.7,0"
    out = tmp_path / "r.csv"
    assert main(["simulate-observations", "--urdf", str(data / "arm7.urdf"), "--ee", "tool", "--start", start,
                 "--limits", str(data / "arm7_limits.json"), "--reaches", "5", "--seed", "1", "--out", str(out)]) == 0
    line = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("binding_train_fraction")]
    assert len(line) == 1
    sim = ModelSpec(kind="urdf", urdf=str(data / "arm7.urdf"), ee="tool",
                    start=tuple(float(v) for v in start.split(","))).build()
    limits = json.loads((data / "arm7_limits.json").read_text())
    truth = torch.tensor([v for j in sim.joint_names for v in limits[j]], dtype=torch.float64)
    obs = load_recordings(out, sim, resample=None)
    hit = binding_reaches(sim, truth, sim.bounds.reshape(-1), torch.stack([o.start for o in obs]),
                          torch.stack([o.goal for o in obs]))
    assert f": {int(hit.sum())} of 5 reaches move" in line[0]
