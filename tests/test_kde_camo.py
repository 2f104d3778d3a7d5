"""CAMO's KDE, joint density, argmax, fallback and recovery; the naive baseline."""

import math
import warnings

import numpy as np
import pytest
import torch
from scipy.stats import gaussian_kde

from camo_sbi.inference.camo import Camo, CamoConfig
from camo_sbi.inference.kde import GaussianKDE, scott_bandwidth
from camo_sbi.inference.naive import naive_limits
from camo_sbi.inference.registry import make_config, run_method, run_method_sequence
from camo_sbi.priors import BoxPrior
from camo_sbi.scenarios.reaching import observe
from tests.toy_sim import ToySimulator


def test_kde_matches_scipy_gaussian_kde_1d():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=300)
    x = np.linspace(-4, 4, 41)
    ref = gaussian_kde(pts)
    ours = GaussianKDE(pts[:, None], float(ref.covariance[0, 0]))
    np.testing.assert_allclose(ours.log_density(x[:, None]).numpy(), ref.logpdf(x), rtol=1e-9)


def test_kde_matches_explicit_formula_diagonal_h():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(200, 3)) * np.array([1.0, 2.0, 0.5])
    x = rng.normal(size=(50, 3))
    H = np.array([0.3, 0.7, 0.05])
    diff = x[:, None, :] - pts[None, :, :]
    k = np.exp(-0.5 * (diff**2 / H).sum(-1)) / np.sqrt((2 * np.pi) ** 3 * np.prod(H))
    np.testing.assert_allclose(GaussianKDE(pts, H).log_density(x).numpy(), np.log(k.mean(1)), rtol=1e-10)


def test_kde_far_points_finite_and_chunked():
    pts = torch.zeros(3, 2, dtype=torch.float64)
    kde = GaussianKDE(pts, 0.01)
    far = torch.full((5000, 2), 10.0, dtype=torch.float64)  # > one chunk
    lp = kde.log_density(far)
    expected = -0.5 * 200 / 0.01 - math.log(2 * math.pi * 0.01)
    assert torch.isfinite(lp).all()
    np.testing.assert_allclose(lp.numpy(), expected, rtol=1e-12)


def test_kde_bad_input():
    with pytest.raises(ValueError, match="bandwidth"):
        GaussianKDE(torch.zeros(3, 2), -1.0)
    with pytest.raises(ValueError, match="points"):
        GaussianKDE(torch.zeros(0, 2), 1.0)
    with pytest.raises(ValueError, match="x"):
        GaussianKDE(torch.zeros(3, 2), 1.0).log_density(torch.zeros(4, 3))


def test_scott_bandwidth_formula():
    pts = torch.randn(100, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    h = scott_bandwidth(pts)
    expected = (pts.std(0) * 100 ** (-1 / 8)) ** 2
    torch.testing.assert_close(h, expected)


def _camo(n=2, n_samples=2000, **cfg):
    sim = ToySimulator(n=n)
    prior = BoxPrior(sim.bounds, sim.start)
    return sim, prior, Camo(sim, prior, CamoConfig(**cfg), n_samples=n_samples, seed=3)


def test_joint_density_is_sum_of_per_task_log_densities_and_argmax():
    sim, prior, camo = _camo(n_samples=300, keep_best=30, bandwidth=0.01)
    true = torch.tensor([-0.3, 0.4, -0.5, 0.6], dtype=torch.float64)
    goals = torch.tensor([[0.9, 0.9, 0], [-0.9, -0.9, 0], [0.9, -0.9, 0]], dtype=torch.float64)
    for o in observe(sim, true, goals):
        camo.observe(o.start, o.goal, o.q)
    kept = camo.kept
    total = sum(k.log_density(kept) for k in camo._kdes)
    torch.testing.assert_close(camo.joint_log_density, total)
    i = int(torch.argmax(total))
    np.testing.assert_array_equal(camo.estimate(), kept[i].numpy())
    assert kept.shape[0] == 90


def test_argmax_on_hand_made_case():
    """Three tasks whose kept sets overlap only near one vector: that vector is the argmax."""
    sim, prior, camo = _camo(n_samples=10, keep_best=3, bandwidth=0.001)
    target = torch.tensor([-0.5, 0.5, -0.5, 0.5], dtype=torch.float64)
    from camo_sbi.inference.kde import GaussianKDE as K

    sets = [
        torch.stack([target, target + 0.5, target - 0.4]),
        torch.stack([target + 0.01, target + 0.3, target - 0.2]),
        torch.stack([target - 0.01, target - 0.3, target + 0.2]),
    ]
    logp = torch.zeros(0, dtype=torch.float64)
    kdes = [K(s, 0.001) for s in sets]
    allv = torch.cat(sets)
    logp = sum(k.log_density(allv) for k in kdes)
    assert int(torch.argmax(logp)) == 0
    camo._kdes, camo._kept, camo._logp = kdes, allv, logp
    camo.records = [None, None, None]
    np.testing.assert_array_equal(camo.estimate(), target.numpy())


def test_zero_acceptance_falls_back_to_best_k_and_records_it():
    sim, prior, camo = _camo(n_samples=50, epsilon=1e-9, keep_best=None, fallback_keep=7)
    o = observe(sim, torch.tensor([-0.3, 0.4, -0.5, 0.6]), torch.tensor([[0.9, 0.9, 0.0]]))[0]
    with pytest.warns(RuntimeWarning, match="no sample within epsilon"):
        rec = camo.observe(o.start, o.goal, o.q)
    assert rec.fallback and rec.kept.shape[0] == 7 and rec.n_accepted_epsilon == 0
    res = camo.result()
    assert res.extras["fallback_tasks"] == [0]


def test_recovery_on_synthetic_case():
    """Goals outside the true box make the toy hit its limits; CAMO recovers them to 0.1."""
    sim, prior, camo = _camo(n_samples=4000, keep_best=40, bandwidth=0.002)
    true = torch.tensor([-0.3, 0.4, -0.5, 0.6], dtype=torch.float64)
    goals = torch.tensor([[0.9, 0.9, 0], [-0.9, -0.9, 0], [0.9, -0.9, 0], [-0.9, 0.9, 0]], dtype=torch.float64)
    for o in observe(sim, true, goals):
        camo.observe(o.start, o.goal, o.q)
    est = camo.estimate()
    np.testing.assert_allclose(est, true.numpy(), atol=0.1)


def test_same_seed_same_estimate_and_continual_equals_batch():
    sim = ToySimulator()
    from camo_sbi.scenarios.reaching import make_reaching_task

    true = torch.tensor([-0.3, 0.4, -0.5, 0.6], dtype=torch.float64)
    task = make_reaching_task(sim, true, n_train=3, n_test=2, seed=0)
    a = run_method("camo", task, budget=200, seed=5, config={"keep_best": 20})
    b = run_method("camo", task, budget=200, seed=5, config={"keep_best": 20})
    np.testing.assert_array_equal(a.samples, b.samples)
    seq = run_method_sequence("camo", task, budget=200, seed=5, config={"keep_best": 20})
    np.testing.assert_array_equal(seq[-1].estimate, a.estimate)
    assert [r.n_simulations for r in seq] == [200, 400, 600]
    assert a.n_simulations == 600 and a.n_tasks == 3


def test_bad_configs_rejected():
    with pytest.raises(ValueError, match="epsilon"):
        CamoConfig(epsilon=None, keep_best=None)
    with pytest.raises(ValueError, match="space"):
        CamoConfig(space="polar")
    with pytest.raises(ValueError, match="bandwidth"):
        CamoConfig(bandwidth=0.0)
    with pytest.raises(ValueError, match="unknown field"):
        make_config("camo", {"kep_best": 3})
    with pytest.raises(ValueError, match="method"):
        make_config("camo2")
    sim, prior, camo = _camo()
    with pytest.raises(ValueError, match="trajectory"):
        camo.observe(sim.start, torch.zeros(3), torch.zeros(5, 3))
    with pytest.raises(ValueError, match="goal"):
        camo.observe(sim.start, torch.zeros(2), torch.zeros(5, 2))
    with pytest.raises(RuntimeError, match="estimate"):
        _camo()[2].estimate()


def test_naive_min_max():
    q1 = torch.tensor([[0.0, 1.0], [0.5, -1.0]])
    q2 = torch.tensor([[-0.2, 0.3]])
    np.testing.assert_allclose(naive_limits([q1, q2]), [-0.2, 0.5, -1.0, 1.0])
    with pytest.raises(ValueError, match="joint_trajectories"):
        naive_limits([])


def test_no_warning_when_accepting():
    sim, prior, camo = _camo(n_samples=100, keep_best=10)
    o = observe(sim, torch.tensor([-0.3, 0.4, -0.5, 0.6]), torch.tensor([[0.5, 0.5, 0.0]]))[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        camo.observe(o.start, o.goal, o.q)


# --- contain_observed: the prior conditioned on the observed postures ---------------------


def test_contain_observed_keeps_only_vectors_that_contain_every_observed_posture():
    sim, prior, camo = _camo(n_samples=400, keep_best=40, bandwidth=0.01, contain_observed=True)
    true = torch.tensor([-0.3, 0.4, -0.5, 0.6], dtype=torch.float64)
    goals = torch.tensor([[0.9, 0.9, 0], [-0.9, -0.9, 0], [0.2, -0.9, 0]], dtype=torch.float64)
    seen = [sim.start.unsqueeze(0)]
    for i, o in enumerate(observe(sim, true, goals)):
        rec = camo.observe(o.start, o.goal, o.q)
        seen.append(o.q)
        q = torch.cat(seen)
        lo_ok = (rec.kept[:, 0::2] <= q.min(0).values).all()
        hi_ok = (rec.kept[:, 1::2] >= q.max(0).values).all()
        assert bool(lo_ok and hi_ok), f"task {i}: a new candidate excludes an observed posture"
        kept, logp = camo.kept, camo.joint_log_density
        contains = (kept[:, 0::2] <= q.min(0).values).all(1) & (kept[:, 1::2] >= q.max(0).values).all(1)
        assert bool(torch.isfinite(logp[contains]).all()) and bool(torch.isinf(logp[~contains]).all())
        est = camo.estimate()
        assert (est[0::2] <= q.min(0).values.numpy()).all() and (est[1::2] >= q.max(0).values.numpy()).all()
    assert int((~contains).sum()) > 0  # earlier tasks' vectors were ruled out by later postures
    res = camo.result()
    assert np.isclose(res.weights.sum(), 1.0) and res.weights[~contains.numpy()].max() == 0.0


def test_contain_observed_changes_draws_only_when_on_and_is_seeded():
    sim = ToySimulator()
    from camo_sbi.scenarios.reaching import make_reaching_task

    true = torch.tensor([-0.3, 0.4, -0.5, 0.6], dtype=torch.float64)
    task = make_reaching_task(sim, true, n_train=3, n_test=2, seed=0)
    cfg = {"keep_best": 20, "contain_observed": True}
    a = run_method("camo", task, budget=200, seed=5, config=cfg)
    b = run_method("camo", task, budget=200, seed=5, config=cfg)
    off = run_method("camo", task, budget=200, seed=5, config={"keep_best": 20})
    np.testing.assert_array_equal(a.samples, b.samples)
    np.testing.assert_array_equal(a.weights, b.weights)
    assert not np.array_equal(a.samples, off.samples)
    # the registry's camo-hull is exactly CAMO with contain_observed=True
    assert make_config("camo-hull").contain_observed and not make_config("camo").contain_observed
    hull = run_method("camo-hull", task, budget=200, seed=5, config={"keep_best": 20})
    np.testing.assert_array_equal(hull.samples, a.samples)
    assert hull.method == "camo-hull" and a.method == "camo"
    with pytest.raises(ValueError, match="^config: method 'camo-hull' is defined by space='joint'"):
        make_config("camo-hull", {"space": "cartesian"})


def test_contain_observed_config_errors():
    with pytest.raises(ValueError, match="contain_observed"):
        CamoConfig(contain_observed=True, space="cartesian")
    with pytest.raises(TypeError, match="contain_observed"):
        CamoConfig(contain_observed=1)


def test_kde_proposal_draws_around_kept_vectors_inside_the_box():
    from camo_sbi.inference.camo import KdeProposal

    points = torch.tensor([[-0.5, 0.5], [-0.2, 0.8]], dtype=torch.float64)
    sd = torch.tensor([0.05, 0.0], dtype=torch.float64)  # second coordinate fixed
    low = torch.tensor([-1.0, 0.0], dtype=torch.float64)
    high = torch.tensor([-0.3, 1.0], dtype=torch.float64)
    prop = KdeProposal(points, sd, low, high)
    x = prop.sample(20000, np.random.default_rng(0))
    assert bool((x >= low).all()) and bool((x <= high).all())
    assert set(x[:, 1].tolist()) == {0.5, 0.8}  # zero-width kernel: the kept value itself
    near_first = x[x[:, 1] == 0.5, 0]
    assert abs(float(near_first.mean()) + 0.5) < 0.005 and abs(float(near_first.std()) - 0.05) < 0.005
    second = x[x[:, 1] == 0.8, 0]  # around -0.2, outside the box: clipped onto its edge (97.7 % of draws)
    assert bool((second <= -0.3).all()) and float((second == -0.3).double().mean()) > 0.95
    torch.testing.assert_close(x, prop.sample(20000, np.random.default_rng(0)))


def test_sequential_proposals_contain_every_observed_posture():
    """camo-seq: from the second task on, candidates come from the last KDE clipped to the
    observed hull, so every kept vector of tasks >= 2 contains every posture seen so far."""
    sim, prior, camo = _camo(n_samples=300, keep_best=20, bandwidth=0.01, proposal="sequential")
    true = torch.tensor([-0.6, 0.5, -0.4, 0.7], dtype=torch.float64)
    goals = torch.tensor([[0.9, -0.9, 0.0], [-0.9, 0.9, 0.0], [0.3, 0.2, 0.0]], dtype=torch.float64)
    obs = observe(sim, true, goals)
    seen = []
    for i, o in enumerate(obs):
        camo.observe(o.start, o.goal, o.q)
        seen.append(o.q)
        if i >= 1:
            q = torch.cat(seen)
            kept = camo.records[-1].kept
            assert bool((kept[:, 0::2] <= q.min(0).values + 1e-12).all())
            assert bool((kept[:, 1::2] >= q.max(0).values - 1e-12).all())
    # the first task still draws from the prior: its kept vectors need not contain later postures
    plain = _camo(n_samples=300, keep_best=20, bandwidth=0.01)[2]
    plain.observe(obs[0].start, obs[0].goal, obs[0].q)
    torch.testing.assert_close(plain.records[0].kept, camo.records[0].kept)


def test_euclidean_distance_with_epsilon_acceptance():
    """distance='euclidean' is Eq. 2 on the held observation; epsilon alone decides acceptance."""
    from camo_sbi.inference.camo import CamoConfig, _distances

    traj = torch.tensor([[0.0, 0.0], [1.0, 1.0]], dtype=torch.float64)
    sims = torch.tensor([[[0.0, 0.0], [1.0, 1.0], [1.0, 1.0]], [[0.0, 0.0], [1.0, 2.0], [1.0, 3.0]]],
                        dtype=torch.float64)
    d = _distances(traj, sims, torch.tensor([2, 3]), CamoConfig(distance="euclidean"), keep_best=None)
    torch.testing.assert_close(d, torch.tensor([0.0, math.sqrt(1 + 4)], dtype=torch.float64))
    with pytest.raises(ValueError, match="^trajectory:"):
        _distances(torch.zeros(5, 2), sims, torch.tensor([3, 3]), CamoConfig(distance="euclidean"), keep_best=None)
    sim, prior, camo = _camo(n_samples=400, epsilon=0.3, keep_best=None, distance="euclidean",
                             sim_dtype="float64")
    o = observe(sim, torch.tensor([-0.6, 0.5, -0.4, 0.7], dtype=torch.float64),
                torch.tensor([[0.9, -0.9, 0.0]], dtype=torch.float64))[0]
    rec = camo.observe(o.start, o.goal, o.q)
    assert not rec.fallback and rec.n_accepted_epsilon == rec.kept.shape[0] > 0
    assert bool((rec.distances < 0.3).all())


def test_point_estimators_from_the_weighted_posterior():
    """point_estimate='mean' / 'median' / 'outer' are functions of the same kept vectors and weights."""
    from camo_sbi.inference.result import weighted_quantile

    true = torch.tensor([-0.6, 0.5, -0.4, 0.7], dtype=torch.float64)
    goals = torch.tensor([[0.9, -0.9, 0.0], [-0.9, 0.9, 0.0]], dtype=torch.float64)
    obs = observe(ToySimulator(), true, goals)
    est = {}
    for name in ("mode", "mean", "median", "outer"):
        _, _, camo = _camo(n_samples=300, keep_best=30, bandwidth=0.01, point_estimate=name, outer_quantile=0.1)
        for o in obs:
            camo.observe(o.start, o.goal, o.q)
        est[name] = camo.estimate()
        kept, w = camo.kept.numpy(), camo.posterior_weights()
    assert np.array_equal(est["mode"], kept[np.argmax(w)])
    np.testing.assert_allclose(est["mean"], w @ kept, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(est["median"], weighted_quantile(kept, w, 0.5))
    outer = weighted_quantile(kept, w, [0.1, 0.9])  # (2, 4): 0.1 for the lower bounds, 0.9 for the upper
    np.testing.assert_array_equal(est["outer"], [outer[0, 0], outer[1, 1], outer[0, 2], outer[1, 3]])
    assert (est["outer"][0::2] <= est["median"][0::2]).all() and (est["outer"][1::2] >= est["median"][1::2]).all()
    with pytest.raises(ValueError, match="^outer_quantile:"):
        CamoConfig(outer_quantile=0.7)
    with pytest.raises(ValueError, match="^point_estimate:"):
        CamoConfig(point_estimate="argmin")
    # the old names are refused, naming the new ones
    with pytest.raises(ValueError, match="^point_estimate: 'argmax' is now called 'mode'"):
        CamoConfig(point_estimate="argmax")
    with pytest.raises(TypeError, match="^estimator: renamed 'point_estimate'"):
        CamoConfig(estimator="mode")
