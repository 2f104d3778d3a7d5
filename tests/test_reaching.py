"""Reaching tasks on the Panda: goals, observations and prediction (metrics: test_metrics.py)."""

import numpy as np
import pytest
import torch

from camo_sbi.evaluation.metrics import cartesian_error_mm, joint_error_deg
from camo_sbi.experiments.subjects import subject_names, subject_theta
from camo_sbi.priors import BoxPrior
from camo_sbi.scenarios.reaching import make_reaching_task, observe
from camo_sbi.simulators import sample_goals, theta_to_limits
from camo_sbi.task import Observation, Task, predict

TOL = 0.01  # the Panda controller's goal tolerance (ControllerConfig.tol)


@pytest.fixture(scope="module")
def sim():
    from tests.conftest import build_simulator

    return build_simulator("panda")


@pytest.fixture(scope="module")
def theta(sim):
    return subject_theta(sim, "panda", "mixed_restricted")


@pytest.fixture(scope="module")
def task(sim, theta):
    return make_reaching_task(sim, theta, n_train=6, n_test=5, seed=3, name="panda", subject="mixed")


def test_task_fields(task, sim, theta):
    assert isinstance(task, Task)
    assert task.name == "panda" and task.subject == "mixed" and task.n_joints == 7
    assert len(task.observations) == 6 and all(isinstance(o, Observation) for o in task.observations)
    assert task.test_goals.shape == (5, 3) and task.test_starts.shape == (5, 7)
    assert task.test_goals.dtype == torch.float64 and task.true_theta.dtype == torch.float64
    torch.testing.assert_close(task.true_theta, theta)
    assert torch.equal(task.test_starts, sim.start.expand(5, -1))
    for o in task.observations:
        assert torch.equal(o.start, sim.start)
        assert o.q.dtype == torch.float64 and o.ee.dtype == torch.float64
        assert o.q.shape[1] == 7 and o.ee.shape == (o.q.shape[0], 3)
        assert torch.equal(o.q[0], sim.start)  # the trajectory starts at the start posture
        assert o.trajectory("joint") is o.q and o.trajectory("cartesian") is o.ee
    # default prior: the full range split at the start
    ref = BoxPrior(sim.bounds, sim.start)
    assert torch.equal(task.prior.low, ref.low) and torch.equal(task.prior.high, ref.high)


def test_goals_are_fk_images_of_postures_inside_the_true_limits(task, sim, theta):
    """Train and test goals are FK(q) with q uniform inside the true limits (the documented construction)."""
    goals = sample_goals(sim, theta_to_limits(theta), 11, 3)
    train = torch.stack([o.goal for o in task.observations])
    torch.testing.assert_close(train, goals[:6], rtol=0, atol=0)
    torch.testing.assert_close(task.test_goals, goals[6:], rtol=0, atol=0)


@pytest.mark.parametrize("subject", ["shoulder_restricted", "elbow_restricted"])
def test_observed_reaches_reach_their_goals(sim, subject):
    """The subject reaches every training goal: the final end-effector is within the tolerance."""
    th = subject_theta(sim, "panda", subject)
    t = make_reaching_task(sim, th, n_train=10, n_test=1, seed=0)
    dist = [float((o.ee[-1] - o.goal).norm()) for o in t.observations]
    assert max(dist) < TOL, f"unreached training goals (final distance, m): {np.round(dist, 4).tolist()}"
    traj = sim.simulate(th.expand(10, -1), torch.stack([o.goal for o in t.observations]))
    assert bool(traj.reached.all())


def test_test_goals_distinct_from_train_goals(task):
    train = torch.stack([o.goal for o in task.observations])
    d = torch.cdist(task.test_goals, train)
    assert float(d.min()) > 1e-6
    # and no goal is repeated within either set
    assert torch.unique(train, dim=0).shape[0] == 6
    assert torch.unique(task.test_goals, dim=0).shape[0] == 5


def test_same_seed_identical_other_seed_differs(sim, theta, task):
    again = make_reaching_task(sim, theta, n_train=6, n_test=5, seed=3, name="panda", subject="mixed")
    for a, b in zip(task.observations, again.observations, strict=True):
        for f in ("start", "goal", "q", "ee"):
            assert torch.equal(getattr(a, f), getattr(b, f))
    assert torch.equal(task.test_goals, again.test_goals)
    other = make_reaching_task(sim, theta, n_train=6, n_test=5, seed=4)
    assert not torch.allclose(task.test_goals, other.test_goals)
    assert not torch.allclose(task.observations[0].goal, other.observations[0].goal)
    # a torch.Generator seeded the same way is equivalent to the int seed
    gen = torch.Generator().manual_seed(3)
    g = make_reaching_task(sim, theta, n_train=6, n_test=5, seed=gen)
    assert torch.equal(g.test_goals, task.test_goals)


def test_observations_inside_true_limits(task, theta):
    lim = theta_to_limits(theta)
    for o in task.observations:
        assert bool((o.q >= lim[:, 0] - 1e-9).all()) and bool((o.q <= lim[:, 1] + 1e-9).all())
    # the restricted joints matter: some observation moves at least one restricted joint
    moved = torch.stack([(o.q - o.q[0]).abs().max(0).values for o in task.observations]).max(0).values
    assert float(moved.max()) > 0.05


def test_observations_are_the_simulator_trajectories_trimmed(task, sim, theta):
    goals = torch.stack([o.goal for o in task.observations])
    traj = sim.simulate(theta.expand(6, -1), goals, sim.start)
    for i, o in enumerate(task.observations):
        L = int(traj.length[i])
        assert o.q.shape[0] == L
        assert torch.equal(o.q, traj.q[i, :L]) and torch.equal(o.ee, traj.ee[i, :L])


def test_predict_with_true_theta_reproduces_test_trajectories_exactly(task, sim, theta):
    m = task.test_goals.shape[0]
    true = sim.simulate(theta.expand(m, -1), task.test_goals, task.test_starts)
    pred = predict(sim, theta, task.test_starts, task.test_goals)
    for f in ("q", "ee", "length", "reached"):
        assert torch.equal(getattr(pred, f), getattr(true, f)), f
    assert torch.equal(cartesian_error_mm(true, pred), torch.zeros(m, dtype=torch.float64))
    assert torch.equal(joint_error_deg(true, pred), torch.zeros(m, dtype=torch.float64))
    # ... and the training observations too
    goals = torch.stack([o.goal for o in task.observations])
    starts = torch.stack([o.start for o in task.observations])
    p = predict(sim, theta, starts, goals)
    for i, o in enumerate(task.observations):
        assert torch.equal(p.q[i, : o.q.shape[0]], o.q)


def test_predict_with_wrong_theta_has_positive_error(task, sim, theta):
    m = task.test_goals.shape[0]
    true = sim.simulate(theta.expand(m, -1), task.test_goals, task.test_starts)
    full = task.prior.high.clone()
    full[0::2] = task.prior.low[0::2]  # the full range: the restrictions are gone
    pred = predict(sim, full, task.test_starts, task.test_goals)
    ce, je = cartesian_error_mm(true, pred), joint_error_deg(true, pred)
    assert ce.shape == (m,) and je.shape == (m,)
    assert bool((ce >= 0).all()) and bool((je >= 0).all())
    assert float(ce.sum()) > 0 and float(je.sum()) > 0
    # both errors vanish exactly on the goals whose trajectories coincide, and only there
    same = [bool(torch.equal(true.q[i], pred.q[i])) for i in range(m)]
    assert [float(je[i]) == 0.0 for i in range(m)] == same


def test_predict_widens_an_estimate_that_excludes_the_start(task, sim, theta):
    """An estimate whose interval misses the observed start is widened to contain it (documented)."""
    bad = theta.clone()
    j = 3
    bad[2 * j] = sim.start[j] + 0.1  # lo above the start
    bad[2 * j + 1] = sim.start[j] + 0.2
    pred = predict(sim, bad, task.test_starts, task.test_goals)
    widened = bad.clone()
    widened[2 * j] = sim.start[j]
    ref = sim.simulate(widened.expand(5, -1), task.test_goals, task.test_starts)
    assert torch.equal(pred.q, ref.q)


def test_observe_shapes_and_bad_goals(sim, theta):
    goals = sample_goals(sim, theta_to_limits(theta), 3, 0)
    obs = observe(sim, theta, goals)
    assert len(obs) == 3
    starts = sim.start.expand(3, -1).clone()
    obs2 = observe(sim, theta, goals, starts)  # per-goal starts give the same result as a shared start
    assert all(torch.equal(a.q, b.q) for a, b in zip(obs, obs2, strict=True))
    with pytest.raises(ValueError, match="goals"):
        observe(sim, theta, goals[0])
    with pytest.raises(ValueError, match="goals"):
        observe(sim, theta, goals[:, :2])
    with pytest.raises(ValueError, match="theta"):
        observe(sim, theta[:-1], goals)
    with pytest.raises(ValueError, match="space"):
        obs[0].trajectory("polar")


def test_make_reaching_task_bad_inputs(sim, theta):
    with pytest.raises(ValueError, match="n_train"):
        make_reaching_task(sim, theta, n_train=0, seed=0)
    with pytest.raises(TypeError, match="n_train"):
        make_reaching_task(sim, theta, n_train=2.0, seed=0)
    with pytest.raises(ValueError, match="n_test"):
        make_reaching_task(sim, theta, n_test=-1, seed=0)
    with pytest.raises(ValueError, match="true_theta"):
        make_reaching_task(sim, theta[:-2], seed=0)
    swapped = theta.clone()
    swapped[0], swapped[1] = theta[1], theta[0]
    with pytest.raises(ValueError, match="true_theta"):
        make_reaching_task(sim, swapped, seed=0)
    nan = theta.clone()
    nan[3] = float("nan")
    with pytest.raises(ValueError, match="true_theta"):
        make_reaching_task(sim, nan, seed=0)
    with pytest.raises(TypeError, match="true_theta"):
        make_reaching_task(sim, "limits", seed=0)
    outside = sim.start.clone()
    outside[0] = float(theta[1]) + 0.1  # beyond the true upper limit of joint 0
    with pytest.raises(ValueError, match="start"):
        make_reaching_task(sim, theta, start=outside, seed=0)
    with pytest.raises(TypeError, match="seed"):
        make_reaching_task(sim, theta, seed=1.5)
    with pytest.raises(TypeError, match="seed"):
        make_reaching_task(sim, theta, seed=None)


def test_predict_bad_goals(task, sim, theta):
    with pytest.raises(ValueError, match="goal"):
        predict(sim, theta, task.test_starts, task.test_goals[:, :2])
    with pytest.raises(ValueError, match="goal"):
        predict(sim, theta, task.test_starts, task.test_goals[:3])
    with pytest.raises(TypeError, match="goals"):
        predict(sim, theta, task.test_starts, "goals")


def test_predict_bad_theta_hat_names_theta_hat(task, sim, theta):
    with pytest.raises(ValueError, match="theta_hat"):
        predict(sim, theta[:-1], task.test_starts, task.test_goals)
    swapped = theta.clone()
    swapped[0], swapped[1] = theta[1], theta[0]
    with pytest.raises(ValueError, match="theta_hat"):
        predict(sim, swapped, task.test_starts, task.test_goals)


def test_predict_bad_starts_name_starts(task, sim, theta):
    with pytest.raises(ValueError, match="starts"):
        predict(sim, theta, torch.zeros(5, 8, dtype=torch.float64), task.test_goals)


def test_predict_one_shared_start_posture_broadcasts(task, sim, theta):
    one = predict(sim, theta, task.test_starts[0], task.test_goals)
    many = predict(sim, theta, task.test_starts, task.test_goals)
    torch.testing.assert_close(one.q, many.q, rtol=0, atol=0)


def test_subject_profiles_valid_for_every_panda_subject(sim):
    """Every named profile gives a task whose observations respect its limits (smoke over subjects)."""
    for name in subject_names("panda"):
        th = subject_theta(sim, "panda", name)
        t = make_reaching_task(sim, th, n_train=2, n_test=2, seed=1)
        lim = theta_to_limits(th)
        for o in t.observations:
            assert bool((o.q >= lim[:, 0] - 1e-9).all() and (o.q <= lim[:, 1] + 1e-9).all())
