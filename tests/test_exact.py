"""The exact likelihood (inference/exact.py) against hand computations, and its posterior sampler
against a posterior computed on a grid."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import norm

from camo_sbi.inference import exact
from camo_sbi.priors import BoxPrior
from camo_sbi.simulators import from_urdf
from camo_sbi.task import NoiseModel, Observation, Task
from tests.test_design import (  # a planar 1-joint arm of radius R: q puts the tool at (R cos q, R sin q, 0)
    ARM1,
    R,
)

A1, A2 = 0.4, 0.3
ARM2 = f"""<robot name="arm2">
  <link name="base"/><link name="l1"/><link name="l2"/><link name="tool"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><origin xyz="0 0 0"/>
    <axis xyz="0 0 1"/><limit lower="-2.5" upper="2.5" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="{A1} 0 0"/>
    <axis xyz="0 0 1"/><limit lower="-2.5" upper="2.5" effort="1" velocity="1"/></joint>
  <joint name="tip" type="fixed"><parent link="l2"/><child link="tool"/><origin xyz="{A2} 0 0"/></joint>
</robot>"""  # a planar 2-joint arm


@pytest.fixture(scope="module")
def arm1():
    return from_urdf(ARM1, "tool", start=[0.0])


def _hand_reach(sim_x, sim_len, obs_x, sigma):
    """The module docstring's formula, written out with scipy: the recorded samples' Gaussian log
    density against the simulation held at rest after its length, plus the imputed steps."""
    out = []
    L = obs_x.shape[0]
    for x, s in zip(sim_x, sim_len, strict=True):
        held = [x[min(t, s - 1, x.shape[0] - 1)] for t in range(max(L, s))]  # at rest after its length s
        total = sum(norm.logpdf(obs_x[t], held[t], sigma).sum() for t in range(L))
        for t in range(L, s):  # the simulation still moves after the recording ended: imputed at rest
            total += -0.5 * np.sum((obs_x[-1] - held[t]) ** 2) / sigma**2
        out.append(total)
    return np.array(out)


def test_reach_log_likelihood_matches_the_formula_for_every_length_case():
    rng = np.random.default_rng(0)
    sim = rng.normal(size=(3, 6, 2))
    for b, s in enumerate((2, 4, 6)):  # rows hold their final posture after their length
        sim[b, s:] = sim[b, s - 1]
    lengths = np.array([2, 4, 6])
    for L in (1, 4, 8):  # shorter than, equal to, and longer than the horizon T = 6
        obs = rng.normal(size=(L, 2))
        got = exact.reach_log_likelihood(torch.from_numpy(sim), torch.from_numpy(lengths), torch.from_numpy(obs), 0.3)
        np.testing.assert_allclose(got.numpy(), _hand_reach(sim, lengths, obs, 0.3), rtol=1e-12, atol=1e-9)


def test_one_joint_arm_likelihood_by_hand_in_both_spaces(arm1):
    """The log-likelihood of a noisy reach of the 1-joint arm, by hand: the joint space against the
    simulated angles, the Cartesian space against the hand forward kinematics (R cos q, R sin q, 0)."""
    true = torch.tensor([-1.0, 0.8], dtype=torch.float64)
    goal = torch.tensor([R * math.cos(1.3), R * math.sin(1.3), 0.0], dtype=torch.float64)  # beyond hi: binds
    start = torch.tensor([0.0], dtype=torch.float64)
    clean = arm1.simulate(true[None], goal, start)
    L = int(clean.length[0])
    rng = np.random.default_rng(1)
    noise = NoiseModel(joint_deg=2.0, ee_mm=4.0)
    q_obs = clean.q[0, :L].numpy() + math.radians(2.0) * rng.normal(size=(L, 1))
    ee_obs = clean.ee[0, :L].numpy() + 0.004 * rng.normal(size=(L, 3))
    obs = Observation(start, goal, torch.from_numpy(q_obs), torch.from_numpy(ee_obs))
    theta = torch.tensor([[-1.0, 0.8], [-1.0, 0.6], [-2.0, 1.2], [-0.1, 2.4]], dtype=torch.float64)
    sims = arm1.simulate(theta, goal, start)
    q = sims.q[:, :, 0].numpy()
    lengths = sims.length.numpy()
    got_q = exact.log_likelihood(arm1, theta, [obs], noise, space="joint").numpy()
    np.testing.assert_allclose(got_q, _hand_reach(q[..., None], lengths, q_obs, math.radians(2.0)), rtol=1e-10)
    ee_hand = np.stack([R * np.cos(q), R * np.sin(q), np.zeros_like(q)], axis=-1)  # FK by hand
    got_ee = exact.log_likelihood(arm1, theta, [obs], noise, space="cartesian").numpy()
    np.testing.assert_allclose(got_ee, _hand_reach(ee_hand, lengths, ee_obs, 0.004), rtol=1e-6)
    # two reaches are independent given theta: their log-likelihoods add
    both = exact.log_likelihood(arm1, theta, [obs, obs], noise, space="joint").numpy()
    np.testing.assert_allclose(both, 2 * got_q, rtol=1e-12)
    # the likelihood of the binding upper bound peaks at the truth (within 2 degrees), over a fine grid
    his = np.linspace(0.3, 1.6, 261)
    grid = torch.tensor([[-1.0, h] for h in his], dtype=torch.float64)
    ll = exact.log_likelihood(arm1, grid, [obs], noise, space="joint").numpy()
    assert abs(his[np.argmax(ll)] - 0.8) < math.radians(2.0)


def test_log_posterior_is_prior_plus_likelihood_and_minus_inf_outside(arm1):
    prior = BoxPrior(arm1.bounds, torch.tensor([0.0]))
    goal = torch.tensor([0.0, R, 0.0], dtype=torch.float64)
    o = Observation(torch.zeros(1, dtype=torch.float64), goal, torch.zeros(3, 1, dtype=torch.float64), None)
    task = Task("arm1", "toy", arm1, prior, (o,), noise=NoiseModel(joint_deg=1.0))
    theta = torch.tensor([[-1.0, 0.8], [-1.0, 2.6], [0.2, 1.0]], dtype=torch.float64)  # 2nd: beyond the bound
    lp = exact.log_posterior(task, theta).numpy()
    ll = exact.log_likelihood(arm1, theta[[0]], [o], task.noise).numpy()
    np.testing.assert_allclose(lp[0], ll[0] + float(prior.log_prob(theta[[0]])[0]), rtol=1e-12)
    assert lp[1] == -np.inf and lp[2] == -np.inf  # outside the box: the start is not inside [0.2, 1.0]


def test_noise_free_task_is_a_failed_run_not_a_posterior(arm1):
    from camo_sbi.inference.registry import run_method

    goal = torch.tensor([0.0, R, 0.0], dtype=torch.float64)
    o = Observation(torch.zeros(1, dtype=torch.float64), goal, torch.zeros(3, 1, dtype=torch.float64), None)
    task = Task("arm1", "toy", arm1, BoxPrior(arm1.bounds, torch.tensor([0.0])), (o,))
    with pytest.warns(RuntimeWarning, match="failed: no observation noise in the joint space"):
        res = run_method("exact-likelihood", task, budget=1, seed=0, config={"particles": 50})
    assert res.status.startswith("failed: ") and res.n_simulations == 0


def test_the_run_does_not_depend_on_the_budget_so_a_grid_runs_it_once(arm1):
    """Why `compare --reference` may run exact-likelihood at one budget only (`registry.grid_budgets`;
    its cells: tests/test_reference.py): the same seed gives the same draws at any budget."""
    from camo_sbi.inference.registry import grid_budgets, run_method

    goal = torch.tensor([0.0, R, 0.0], dtype=torch.float64)
    o = Observation(torch.zeros(1, dtype=torch.float64), goal, torch.zeros(3, 1, dtype=torch.float64), None)
    task = Task("arm1", "toy", arm1, BoxPrior(arm1.bounds, torch.tensor([0.0])), (o,),
                noise=NoiseModel(joint_deg=1.0))
    cfg = {"particles": 64, "moves": 2, "mcmc_steps": 0, "min_ess": 0.0}
    small, large = (run_method("exact-likelihood", task, budget=b, seed=3, config=cfg) for b in (10, 100_000))
    np.testing.assert_array_equal(small.samples, large.samples)
    np.testing.assert_array_equal(small.weights, large.weights)
    assert small.n_simulations == large.n_simulations > 10  # counted, never capped by the budget
    assert grid_budgets("exact-likelihood", [1000, 100, 10_000]) == [100]
    assert grid_budgets("camo-seq", [1000, 100]) == [1000, 100] and grid_budgets("exact-likelihood", []) == []


def test_bad_input_names_the_argument(arm1):
    goal = torch.tensor([0.0, R, 0.0], dtype=torch.float64)
    o = Observation(torch.zeros(1, dtype=torch.float64), goal, torch.zeros(3, 1, dtype=torch.float64), None)
    theta = torch.tensor([[-1.0, 0.8]], dtype=torch.float64)
    with pytest.raises(ValueError, match="^noise: the exact likelihood needs observation noise"):
        exact.log_likelihood(arm1, theta, [o], NoiseModel())
    with pytest.raises(ValueError, match="^space:"):
        exact.log_likelihood(arm1, theta, [o], NoiseModel(1.0, 1.0), space="cartesian")  # no ee recorded
    with pytest.raises(ValueError, match="^space:"):
        exact.log_likelihood(arm1, theta, [o], NoiseModel(1.0, 1.0), space="polar")
    with pytest.raises(ValueError, match="^theta:"):
        exact.log_likelihood(arm1, theta[0], [o], NoiseModel(1.0))
    with pytest.raises(ValueError, match="^observations:"):
        exact.log_likelihood(arm1, theta, [], NoiseModel(1.0))
    with pytest.raises(ValueError, match="^particles:"):
        exact.ExactConfig(particles=3)


# ------------------------------------------------------------------ the sampler against a grid posterior


def _grid_posterior_draws(task, n, rng, *, coarse=60, fine=160, drop=30.0):
    """Draws of the posterior over the 2 free coordinates, computed on a grid: a coarse grid over
    the prior box finds where the log posterior is within ``drop`` of its maximum, a fine grid
    over that region (one coarse cell wider) is normalised, and draws are cells picked by their
    mass, uniformly jittered inside the cell."""
    lo, hi = task.prior.low[task.prior.free_mask].numpy(), task.prior.high[task.prior.free_mask].numpy()

    def logpost(a, b):
        aa, bb = np.meshgrid(a, b, indexing="ij")
        free = torch.from_numpy(np.stack([aa.ravel(), bb.ravel()], 1))
        return exact.log_posterior(task, task.prior.expand(free)).numpy().reshape(aa.shape)

    centres = [lo[i] + (np.arange(coarse) + 0.5) * (hi[i] - lo[i]) / coarse for i in range(2)]
    lp = logpost(*centres)
    keep = np.argwhere(lp > lp.max() - drop)
    step = (hi - lo) / coarse
    box_lo = np.maximum(lo, np.array([centres[i][keep[:, i].min()] for i in range(2)]) - 1.5 * step)
    box_hi = np.minimum(hi, np.array([centres[i][keep[:, i].max()] for i in range(2)]) + 1.5 * step)
    width = (box_hi - box_lo) / fine
    fc = [box_lo[i] + (np.arange(fine) + 0.5) * width[i] for i in range(2)]
    lp = logpost(*fc)
    p = np.exp(lp - lp.max()).ravel()
    idx = rng.choice(p.size, size=n, p=p / p.sum())
    i, j = np.unravel_index(idx, lp.shape)
    return np.stack([fc[0][i], fc[1][j]], 1) + (rng.random((n, 2)) - 0.5) * width


@pytest.mark.slow
def test_smc_recovers_a_two_joint_grid_posterior():
    """A 2-joint arm with its first joint's limits known (a strong prior): the exact posterior over
    the second joint's (lo, hi), from two noisy reaches that bind at both bounds, is computed on a
    grid; the SMC draws of ``exact-likelihood`` must be within C2ST 0.55 of the grid's draws."""
    from camo_sbi.diagnostics.calibration import c2st, distinct_draws
    from camo_sbi.inference.registry import run_method

    sim = from_urdf(ARM2, "tool", start=[0.3, 0.2])
    start = torch.tensor([0.3, 0.2], dtype=torch.float64)
    true = torch.tensor([-2.0, 2.0, -0.5, 0.6], dtype=torch.float64)
    prior = BoxPrior(sim.bounds, start, fixed={0: (-2.0, 2.0)})
    noise = NoiseModel(joint_deg=3.0, ee_mm=5.0)
    rng = np.random.default_rng(3)
    obs = []
    for q in ((0.6, 1.4), (-0.2, -1.3)):  # goals whose joint-2 angle lies beyond hi, then beyond lo
        goal = sim.forward_kinematics(torch.tensor(q, dtype=torch.float64))
        clean = sim.simulate(true[None], goal, start)
        L = int(clean.length[0])
        qn = clean.q[0, :L].numpy() + math.radians(3.0) * rng.normal(size=(L, 2))
        obs.append(Observation(start, goal, torch.from_numpy(qn), None))
    task = Task("arm2", "toy", sim, prior, tuple(obs), noise=noise)
    res = run_method("exact-likelihood", task, budget=1, seed=0, config={"particles": 1000, "moves": 10, "mcmc_steps": 100})
    assert res.status == "ok", res.status
    draws = distinct_draws(res.samples, res.weights, 1500, 0)[:, 2:]  # no sample twice (see distinct_draws)
    grid = _grid_posterior_draws(task, 1500, np.random.default_rng(1))
    acc = c2st(draws, grid, 0)
    assert acc <= 0.55, f"C2ST {acc:.3f} between the SMC draws and the grid posterior"


# ------------------------------------------------------------------ distances to a reference posterior


def test_distinct_draws_never_repeat_a_sample_and_skip_zero_weights():
    from camo_sbi.diagnostics.calibration import distinct_draws

    x = np.arange(20.0).reshape(10, 2)
    w = np.r_[np.zeros(4), np.full(6, 1 / 6)]
    d = distinct_draws(x, w, 50, 0)
    assert d.shape == (6, 2) and np.unique(d, axis=0).shape[0] == 6 and set(d[:, 0]) == set(x[4:, 0])
    with pytest.raises(ValueError, match="^weights:"):
        distinct_draws(x, -w, 5, 0)


def test_reference_distances_on_known_distributions():
    """Draws of the reference's own distribution: C2ST near 0.5 and MMD near 0; a shifted one: both
    large; a point estimate: NaN and not a posterior (never a number made up for it)."""
    from camo_sbi.diagnostics.calibration import reference_distances
    from camo_sbi.inference.result import PosteriorResult

    rng = np.random.default_rng(0)
    ref = rng.normal(size=(500, 4))
    same = PosteriorResult("m", rng.normal(size=(500, 4)), None, np.zeros(4), 0, 0.0, 1)
    moved = PosteriorResult("m", rng.normal(size=(500, 4)) + [2.0, 0, 0, 0], None, np.zeros(4), 0, 0.0, 1)
    point = PosteriorResult("naive", np.zeros((1, 4)), None, np.zeros(4), 0, 0.0, 1)
    a = reference_distances(same, ref, 0, n=500)
    b = reference_distances(moved, ref, 0, n=500)
    assert a["posterior"] and 0.4 < a["c2st"] < 0.58 and abs(a["mmd"]) < 0.02
    assert b["c2st"] > 0.75 and b["mmd"] > 0.1  # optimal accuracy for a 2-sd shift: 0.84
    c = reference_distances(point, ref, 0)
    assert not c["posterior"] and np.isnan(c["c2st"]) and np.isnan(c["mmd"])
