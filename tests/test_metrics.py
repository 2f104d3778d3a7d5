"""The evaluation metrics: hand computations, padding invariance, the authors' formula, limit errors."""

import math

import numpy as np
import pytest
import torch

from camo_sbi.evaluation import catalog
from camo_sbi.evaluation.metrics import (
    binding_bounds,
    cartesian_error_mm,
    eq2_cartesian,
    eq2_joint,
    joint_error_deg,
    limit_errors,
    prediction_metrics,
    reference_cartesian,
    reference_joint,
)
from camo_sbi.priors import BoxPrior
from camo_sbi.simulators import Trajectories
from camo_sbi.task import predict


def _traj(q, ee, length):
    q = torch.as_tensor(q, dtype=torch.float64)
    ee = torch.as_tensor(ee, dtype=torch.float64)
    return Trajectories(q, ee, torch.as_tensor(length), torch.ones(q.shape[0], dtype=torch.bool))


# two reaches, T = 4, n = 2 joints. Reach 0: true stops after 2 points, pred after 3;
# reach 1: both run 4 points. The padding (steps >= length) is deliberately GARBAGE, so a
# metric that reads it would be caught.
G = 99.0
Q_TRUE = [[[0, 0], [1, 1], [G, G], [G, G]], [[0, 0], [0, 0], [0, 0], [0, 0]]]
Q_PRED = [[[0, 0], [1, 2], [2, 2], [G, G]], [[0, 0], [3, 4], [3, 4], [0, 0]]]
EE_TRUE = [[[0, 0, 0], [1, 0, 0], [G, G, G], [G, G, G]], [[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]]]
EE_PRED = [[[0, 0, 0], [1, 0, 0], [1, 2, 2], [G, G, G]], [[0, 0, 0], [0, 3, 4], [0, 3, 4], [0, 0, 0]]]


def _pair():
    return _traj(Q_TRUE, EE_TRUE, [2, 4]), _traj(Q_PRED, EE_PRED, [3, 4])


def test_cartesian_error_mm_hand_computed():
    true, pred = _pair()
    # reach 0: 3 steps (the longer valid length); true holds (1,0,0) at step 2:
    #   distances 0, 0, |(1,0,0)-(1,2,2)| = sqrt(8)  -> mean sqrt(8)/3 m
    # reach 1: 4 steps: 0, 5, 5, 0 -> mean 2.5 m
    expected = torch.tensor([1000 * math.sqrt(8) / 3, 2500.0], dtype=torch.float64)
    torch.testing.assert_close(cartesian_error_mm(true, pred), expected)
    torch.testing.assert_close(cartesian_error_mm(pred, true), expected)  # symmetric


def test_joint_error_deg_hand_computed():
    true, pred = _pair()
    # reach 0 (3 steps, true holds (1,1)): |0|+|0| -> 0; |0|+|1| -> 0.5; |1|+|1| -> 1 -> mean 0.5 rad
    # reach 1 (4 steps): 0; (3+4)/2 = 3.5; 3.5; 0 -> mean 1.75 rad
    expected = torch.rad2deg(torch.tensor([0.5, 1.75], dtype=torch.float64))
    torch.testing.assert_close(joint_error_deg(true, pred), expected)


def test_eq2_and_reference_hand_computed_on_fixed_horizon_arrays():
    # fixed horizon: every point counts (no early stop), T = 3, n = 2
    q_true = [[[0, 0], [1, 1], [2, 2]]]
    q_pred = [[[0, 0], [1, 2], [5, 6]]]
    ee_true = [[[0, 0, 0], [1, 0, 0], [1, 1, 0]]]
    ee_pred = [[[0, 0, 0], [1, 0, 0], [1, 1, 2]]]
    true, pred = _traj(q_true, ee_true, [3]), _traj(q_pred, ee_pred, [3])
    # Eq. 2: sqrt(sum of squares): joint 0 + 1 + 9 + 16 = 26; Cartesian 4
    torch.testing.assert_close(eq2_joint(true, pred), torch.tensor([math.sqrt(26)], dtype=torch.float64))
    torch.testing.assert_close(eq2_cartesian(true, pred), torch.tensor([2.0], dtype=torch.float64))
    # the authors' formula: np.sum(np.linalg.norm(true - pred, axis=0)) on the (T, D) arrays
    for f, t, p in ((reference_joint, q_true, q_pred), (reference_cartesian, ee_true, ee_pred)):
        want = float(np.sum(np.linalg.norm(np.array(t[0]) - np.array(p[0]), axis=0)))
        assert float(f(true, pred)[0]) == pytest.approx(want, rel=1e-12)
    # by hand: joint axis 0: sqrt(0 + 0 + 9) = 3; axis 1: sqrt(0 + 1 + 16) = sqrt(17)
    assert float(reference_joint(true, pred)[0]) == pytest.approx(3 + math.sqrt(17))


def test_reference_matches_the_formula_on_random_arrays():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(5, 21, 7)), rng.normal(size=(5, 21, 7))
    e, f = rng.normal(size=(5, 21, 3)), rng.normal(size=(5, 21, 3))
    true, pred = _traj(a, e, [21] * 5), _traj(b, f, [21] * 5)
    want_j = [np.sum(np.linalg.norm(a[i] - b[i], axis=0)) for i in range(5)]
    want_c = [np.sum(np.linalg.norm(e[i] - f[i], axis=0)) for i in range(5)]
    np.testing.assert_allclose(reference_joint(true, pred).numpy(), want_j, rtol=1e-12)
    np.testing.assert_allclose(reference_cartesian(true, pred).numpy(), want_c, rtol=1e-12)
    agg = prediction_metrics(true, pred)
    assert list(agg) == [m.name for m in catalog.METRICS if m.group == "prediction"]
    assert agg["reference_joint"] == pytest.approx(sum(want_j))  # summed over the test goals
    assert agg["eq2_joint"] == pytest.approx(sum(np.sqrt(((a - b) ** 2).sum(axis=(1, 2)))))
    assert agg["cartesian_error_mm"] == pytest.approx(float(cartesian_error_mm(true, pred).mean()))


def test_metrics_reject_mismatched_pairs():
    true, pred = _pair()
    with pytest.raises(ValueError, match="^pred:"):
        cartesian_error_mm(true, pred[:1])
    with pytest.raises(TypeError, match="^pred:"):
        joint_error_deg(true, "x")


def test_cartesian_error_does_not_change_with_max_steps(panda_sim):
    """For reaches that converge, padding beyond both lengths is never counted."""
    from camo_sbi.experiments.subjects import subject_theta
    from camo_sbi.scenarios.reaching import make_reaching_task

    theta = subject_theta(panda_sim, "panda", "elbow_restricted")
    task = make_reaching_task(panda_sim, theta, n_train=1, n_test=8, seed=4)
    wrong = task.prior.outer_theta()
    values = {}
    for T in (100, 300):
        sim = panda_sim.with_config(max_steps=T)
        true = predict(sim, theta, task.test_starts, task.test_goals)
        pred = predict(sim, wrong, task.test_starts, task.test_goals)
        assert int(true.length.max()) < 100 and int(pred.length.max()) < 100  # both converged
        values[T] = (cartesian_error_mm(true, pred), joint_error_deg(true, pred), eq2_cartesian(true, pred))
    torch.testing.assert_close(values[100][0], values[300][0], rtol=0, atol=1e-12)
    torch.testing.assert_close(values[100][1], values[300][1], rtol=0, atol=1e-12)
    assert float(values[100][0].max()) > 0  # the check is not vacuous
    # Eq. 2 on fixed-horizon arrays grows with the horizon by construction (documented)
    assert bool((values[300][2] >= values[100][2]).all()) and float((values[300][2] - values[100][2]).max()) > 0


def test_limit_errors_hand_computed():
    prior = BoxPrior(torch.tensor([[-1.0, 1.0], [-2.0, 2.0]]), torch.zeros(2), fixed={1: (-1.5, 1.5)})
    truth = torch.tensor([-0.5, 0.5, -1.5, 1.5])
    est = truth + torch.tensor([0.1, -0.3, 0.0, 0.0])
    binding = np.array([True, False, True, True])  # fixed coordinates never count
    out = limit_errors(est, truth, prior, binding)
    assert out["limit_error_deg"] == pytest.approx(math.degrees(0.2))
    assert out["limit_error_binding_deg"] == pytest.approx(math.degrees(0.1))
    assert out["limit_error_free_deg"] == pytest.approx(math.degrees(0.3))
    assert set(limit_errors(est, truth, prior)) == {"limit_error_deg"}
    # an empty group is left out, never NaN
    assert "limit_error_binding_deg" not in limit_errors(est, truth, prior, np.zeros(4, dtype=bool))


def test_binding_bounds_are_the_restricted_bounds_that_change_test_reaches(panda_sim):
    from camo_sbi.experiments.subjects import subject_theta
    from camo_sbi.scenarios.reaching import make_reaching_task

    theta = subject_theta(panda_sim, "panda", "shoulder_restricted")
    task = make_reaching_task(panda_sim, theta, n_train=1, n_test=10, seed=0)
    b = binding_bounds(panda_sim, theta, task.test_starts, task.test_goals, task.prior)
    outer = task.prior.outer_theta()
    restricted = (theta - outer).abs().numpy() > 1e-12
    assert b.dtype == bool and b.shape == (14,)
    assert not (b & ~restricted).any()  # a bound at its full range never binds
    assert b.any()
    # a binding bound, relaxed alone, changes a true test trajectory; a non-binding one does not
    true = predict(panda_sim, theta, task.test_starts, task.test_goals)
    for c in np.flatnonzero(restricted):
        relaxed = theta.clone()
        relaxed[c] = outer[c]
        moved = float((predict(panda_sim, relaxed, task.test_starts, task.test_goals).q - true.q).abs().max())
        assert (moved > 1e-3) == bool(b[c]), c
