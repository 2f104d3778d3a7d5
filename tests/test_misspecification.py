"""The reproduction check (issue 33): p-values uniform when the observation is exchangeable with
the posterior's replicates, small when the model cannot produce the reach, Holm by hand, and
every reason not to check stated."""

import numpy as np
import pytest
import torch
from scipy import stats

from camo_sbi.diagnostics.misspecification import (
    check_reproduction,
    column_text,
    holm,
    onset_share,
    verdict_lines,
)
from camo_sbi.inference.result import PosteriorResult
from camo_sbi.priors import BoxPrior
from camo_sbi.scenarios.reaching import observe
from camo_sbi.task import Task
from tests.toy_sim import ToySimulator

GOALS = torch.tensor([[0.9, 0.9, 0.0], [0.9, -0.3, 0.0], [-0.2, 0.8, 0.0]], dtype=torch.float64)


def _draws(rng, n):
    """A distribution of limits whose upper bounds bind on the goals: hi ~ U(0.3, 0.7), lo = -1."""
    th = np.empty((n, 4))
    th[:, 0::2] = -1.0
    th[:, 1::2] = rng.uniform(0.3, 0.7, size=(n, 2))
    return th


def _task(sim, theta, goals=GOALS, observations=None):
    obs = observe(sim, torch.as_tensor(theta), goals) if observations is None else observations
    return Task(name="toy", subject="s", simulator=sim, prior=BoxPrior(sim.bounds, sim.start), observations=obs,
                test_starts=None, test_goals=None, true_theta=torch.as_tensor(theta))


def _result(samples):
    s = np.asarray(samples, dtype=np.float64)
    return PosteriorResult("toy-posterior", s, None, s.mean(axis=0), 0, 0.0, 1)


def test_holm_by_hand():
    # sorted 0.01, 0.02, 0.04, 0.5 -> 4*0.01, 3*0.02, 2*0.04, 1*0.5 (monotone), in input order
    np.testing.assert_allclose(holm([0.04, 0.01, 0.5, 0.02]), [0.08, 0.04, 0.5, 0.06], atol=1e-12)
    np.testing.assert_allclose(holm([0.3, 0.2]), [0.4, 0.4], atol=1e-12)  # step-down keeps monotonicity


@pytest.mark.parametrize("statistic", ["onset", "path"])
def test_p_values_uniform_when_the_truth_is_one_more_posterior_draw(statistic):
    """The truth drawn from the very distribution the posterior draws come from: the observed
    reach is exchangeable with its replicates, so each reach's p-value is U(0, 1) (KS, 60
    independent recordings, first and second reach each), for both statistics."""
    sim = ToySimulator(n=2, max_steps=30, step=0.1)
    rng = np.random.default_rng(0)
    p0, p1 = [], []
    for r in range(60):
        truth = _draws(rng, 1)[0]
        c = check_reproduction(_task(sim, truth), _result(_draws(rng, 2000)), seed=r, n_draws=99,
                               statistic=statistic)
        assert c.checked
        p0.append(c.p_reach[0])
        p1.append(c.p_reach[1])
    for p in (p0, p1):
        assert stats.kstest(p, "uniform").pvalue > 0.01
    # and the recording's flag rate is within binomial reach of its nominal level (<= 5%)
    assert np.mean(np.array(p0) < 0.05) <= 0.15


def test_a_reach_the_model_cannot_produce_is_flagged():
    """A via-point detour (the toy robot only moves straight) is flagged with the smallest p."""
    from camo_sbi.task import Observation

    sim = ToySimulator(n=2, max_steps=30, step=0.1)
    rng = np.random.default_rng(1)
    truth = _draws(rng, 1)[0]
    exact = observe(sim, torch.as_tensor(truth), GOALS)
    o = exact[0]
    bump = torch.zeros_like(o.ee)
    L = o.ee.shape[0]
    bump[:, 1] = 0.3 * torch.sin(torch.linspace(0, np.pi, L, dtype=torch.float64))  # lift then place
    detour = Observation(o.start, o.goal, o.q, o.ee + bump)
    c = check_reproduction(_task(sim, truth, observations=(detour, *exact[1:])), _result(_draws(rng, 2000)),
                           seed=3, statistic="path")  # 399 draws: the smallest p is 1/400, Holm over 3 reaches 3/400
    assert c.flagged and c.flagged_reaches == [0]
    assert c.p_reach[0] <= 1 / 400 + 1e-12
    (line,) = verdict_lines(c)
    assert line.startswith("toy-posterior: the model does not reproduce reach 0 (p < 0.01")
    assert line.endswith("read these limits with care")
    assert column_text(c).startswith("not reproduced: reach 0")


def test_onset_share_by_hand():
    path = torch.tensor([[0.0, 0.0], [0.1, 0.0], [0.5, 0.0], [0.6, 0.0]], dtype=torch.float64)
    assert onset_share(path) == pytest.approx(0.1 / 0.4)
    assert onset_share(path[:1]) == 1.0 and onset_share(torch.zeros(5, 3)) == 1.0


def test_a_reach_that_sets_off_from_rest_is_flagged_by_the_default_statistic():
    """The same straight path as the model's, retimed as a person moves (minimum jerk: speed 0
    at the start, a bell): the onset statistic (the default) flags it with the smallest p, and
    the warning says at what share of its peak speed it set off."""
    from camo_sbi.task import Observation

    sim = ToySimulator(n=2, max_steps=30, step=0.1)
    rng = np.random.default_rng(1)
    truth = _draws(rng, 1)[0]
    exact = observe(sim, torch.as_tensor(truth), GOALS)
    o = exact[0]
    D = 2 * o.ee.shape[0]
    tau = torch.arange(D + 1, dtype=torch.float64) / D
    s_ = 10 * tau ** 3 - 15 * tau ** 4 + 6 * tau ** 5  # minimum-jerk progress along the path
    ee = o.ee[0] + s_[:, None] * (o.ee[-1] - o.ee[0])
    q = o.q[0] + s_[:, None] * (o.q[-1] - o.q[0])
    slow = Observation(o.start, o.goal, q, ee)
    c = check_reproduction(_task(sim, truth, observations=(slow, *exact[1:])), _result(_draws(rng, 2000)), seed=3)
    assert c.statistic == "onset" and c.flagged and c.flagged_reaches == [0]
    assert c.p_reach[0] <= 1 / 400 + 1e-12
    assert c.onset_observed[0] < 0.05 and c.onset_replicates[0] > 0.9
    (line,) = verdict_lines(c)
    assert "sets off at 0% of its peak speed, the model's reaches at 100%" in line


def test_not_checked_says_why_and_bad_arguments_name_themselves():
    sim = ToySimulator(n=2)
    truth = _draws(np.random.default_rng(2), 1)[0]
    task = _task(sim, truth)
    point = check_reproduction(task, _result(truth[None]), seed=0)
    assert not point.checked and "point estimate" in point.status and not point.flagged
    assert column_text(point) == point.status and verdict_lines(point) == []
    failed = PosteriorResult("m", _draws(np.random.default_rng(0), 5), None, truth, 0, 0.0, 1,
                             status="failed: no draws")
    assert "failed" in check_reproduction(task, failed, seed=0).status
    for kwargs, name in (({"n_draws": 5}, "n_draws"), ({"test": "ks"}, "test"), ({"alpha": 2.0}, "alpha"),
                         ({"statistic": "dtw"}, "statistic"), ({"tolerance_mm": -1.0}, "tolerance_mm"),
                         ({"onset_tolerance": float("nan")}, "onset_tolerance"),
                         ({"prior_share": 1.5}, "prior_share")):
        with pytest.raises(ValueError, match=name):
            check_reproduction(task, _result(_draws(np.random.default_rng(0), 50)), seed=0, **kwargs)


@pytest.mark.slow
def test_infer_prints_the_verdict_per_reach_and_writes_it(tmp_path, capsys):
    """simulate-observations --generator via-point, then infer: the verdict per reach is printed,
    in config.json's warnings, in limits.csv's model_check column and at the top of the report."""
    import json
    from pathlib import Path

    import pandas as pd

    from camo_sbi.experiments.cli import main

    data = Path(__file__).parent / "data"
    model = ["--urdf", str(data / "arm7.urdf"), "--ee", "tool", "--start", "0,0.4,0,-1.1,0,0.7,0"]
    rec = tmp_path / "vp.csv"
    assert main(["simulate-observations", *model, "--limits", str(data / "arm7_limits.json"), "--reaches", "3",
                 "--generator", "via-point", "--out", str(rec)]) == 0
    out = tmp_path / "run"
    assert main(["infer", *model, "--observations", str(rec), "--methods", "camo-hull,naive", "--budget", "500",
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "model check" in printed and "per reach: 0 " in printed
    assert "the model does not reproduce reach" in printed
    cfg = json.loads((out / "config.json").read_text())
    assert any("does not reproduce reach" in w and w.endswith("read these limits with care") for w in cfg["warnings"])
    table = pd.read_csv(out / "limits.csv")
    assert set(table[table.method == "camo-hull"].model_check.str.split(":").str[0]) == {"not reproduced"}
    assert table[table.method == "naive"].model_check.str.startswith("not checked").all()
    html = (out / "report.html").read_text()
    assert html.index("Does the model reproduce the recording?") < html.index("Estimated limits")
    checks = pd.read_csv(out / "model_check.csv")
    hull = checks[checks.method == "camo-hull"]
    assert list(hull.reach) == [0, 1, 2] and set(hull.verdict) == {"not reproduced"}
    assert (hull.onset_model - hull.onset_observed > 0.4).all()  # set off from rest, the model near full speed
    assert (hull.predictive_error_mm > 0).all() and (hull.shape_error_mm > 0).all()


@pytest.mark.slow
def test_infer_with_the_minimum_jerk_reach_model_reproduces_minimum_jerk_reaches(tmp_path):
    """--reach-model minimum-jerk: every method conditions on, and is checked against, the
    human-like reach law; reaches from that law are then reproduced (onset test), while the
    controller flags them; config.json records the law."""
    import json
    from pathlib import Path

    import pandas as pd

    from camo_sbi.experiments.cli import main

    data = Path(__file__).parent / "data"
    model = ["--urdf", str(data / "arm7.urdf"), "--ee", "tool", "--start", "0,0.4,0,-1.1,0,0.7,0"]
    rec = tmp_path / "mj.csv"
    assert main(["simulate-observations", *model, "--limits", str(data / "arm7_limits.json"), "--reaches", "4",
                 "--generator", "minimum-jerk", "--noise-ee-mm", "2", "--seed", "3", "--out", str(rec)]) == 0
    verdicts = {}
    for law in ("controller", "minimum-jerk"):
        out = tmp_path / law
        assert main(["infer", *model, "--observations", str(rec), "--methods", "camo-hull", "--budget", "300",
                     "--noise-ee-mm", "2", "--reach-model", law, "--out", str(out)]) == 0
        assert json.loads((out / "config.json").read_text())["reach_model"] == law
        verdicts[law] = set(pd.read_csv(out / "model_check.csv").verdict)
    assert verdicts == {"controller": {"not reproduced"}, "minimum-jerk": {"reproduced"}}
