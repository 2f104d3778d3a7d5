"""NPE (sbi adapter): summaries, product combination, seeding, save/load, budget, configs."""

import math

import numpy as np
import pytest
import torch
from torch import nn

from camo_sbi.inference import npe, samplers
from camo_sbi.inference.flow_space import trajectory_summary
from camo_sbi.inference.npe import NpeConfig
from camo_sbi.inference.npe_posterior import NpePosterior, load_posterior
from camo_sbi.inference.registry import make_config, run_method, run_method_sequence
from camo_sbi.priors import BoxPrior
from tests.test_abc_smc import TRUE, toy_task
from tests.toy_sim import ToySimulator

# a deliberately tiny flow: these tests check plumbing, not accuracy
TINY = {"hidden_features": 16, "num_transforms": 2, "max_epochs": 8, "stop_after_epochs": 3,
        "n_posterior_samples": 500, "is_rounds": 1, "n_points": 8}


# ---------------------------------------------------------------------------------------------
# summaries
# ---------------------------------------------------------------------------------------------


def test_summarize_resamples_valid_part_and_ignores_padding():
    T = 11
    line = torch.linspace(0, 1, T)[:, None].repeat(1, 2) * torch.tensor([1.0, -2.0])
    short = line.clone()
    short[6:] = 99.0  # padding beyond length 6 must never be read
    traj = torch.stack([line, short])
    x = trajectory_summary(traj, torch.tensor([T, 6]), n_points=5)
    assert x.shape == (2, 5 * 2 + 1)
    t = torch.arange(1, 6, dtype=torch.float64) / 5
    np.testing.assert_allclose(x[0, :-1].reshape(5, 2).numpy(), (t[:, None] * torch.tensor([1.0, -2.0])).numpy(),
                               atol=1e-12)
    # length 6: the valid part spans 0 .. 0.5 of the line
    np.testing.assert_allclose(x[1, :-1].reshape(5, 2).numpy(),
                               (0.5 * t[:, None] * torch.tensor([1.0, -2.0])).numpy(), atol=1e-6)
    assert x[:, -1].tolist() == [T, 6]
    assert trajectory_summary(traj, torch.tensor([T, 6]), n_points=5, include_length=False).shape == (2, 10)
    one = trajectory_summary(torch.zeros(1, 3), torch.tensor([1]), n_points=4)
    assert torch.all(one[0, :-1] == 0) and one[0, -1] == 1


def test_summarize_rejects_bad_lengths():
    with pytest.raises(ValueError, match="^lengths"):
        trajectory_summary(torch.zeros(2, 5, 3), torch.tensor([0, 5]))
    with pytest.raises(ValueError, match="^lengths"):
        trajectory_summary(torch.zeros(2, 5, 3), torch.tensor([2.0, 5.0]))
    with pytest.raises(ValueError, match="^traj"):
        trajectory_summary(torch.zeros(5), torch.tensor([5]))


# ---------------------------------------------------------------------------------------------
# the product combination, with analytic "flows"
# ---------------------------------------------------------------------------------------------


class _Gauss(nn.Module):
    """A stand-in density estimator: N(mu, diag(sd^2)) whatever the condition."""

    def __init__(self, mu, sd):
        super().__init__()
        self.register_buffer("mu", torch.as_tensor(mu, dtype=torch.float32))
        self.register_buffer("sd", torch.as_tensor(sd, dtype=torch.float32))

    def log_prob(self, input, condition):  # noqa: A002
        d = torch.distributions.Normal(self.mu, self.sd)
        return d.log_prob(input).sum(-1)

    def sample(self, sample_shape, condition):
        n = int(torch.Size(sample_shape).numel())
        return (self.mu + self.sd * torch.randn(n, condition.shape[0], self.mu.shape[0])).reshape(
            *sample_shape, condition.shape[0], -1)


@pytest.mark.parametrize("reuse", [False, True])
def test_product_of_gaussians_recovered_by_importance_sampling(reuse):
    # raw coordinates, a box so wide the uniform prior is flat: target = product of Gaussians
    low = torch.tensor([-50.0, 0.0, -50.0, 0.0])
    high = torch.tensor([0.0, 50.0, 0.0, 50.0])
    mus = [[-3.0, 4.0, -2.0, 1.0], [-2.0, 5.0, -1.5, 2.0], [-2.5, 4.5, -3.0, 1.5]]
    sds = [[1.0, 0.5, 1.0, 1.0], [0.5, 1.0, 1.0, 0.7], [1.0, 1.0, 0.5, 1.0]]
    ests = [_Gauss(m, s) for m, s in zip(mus, sds, strict=True)]
    post = NpePosterior(ests, [torch.zeros(1)] * 3, low, high, theta_transform="none")
    prec = sum(1 / torch.tensor(s, dtype=torch.float64) ** 2 for s in sds)
    mean = sum(torch.tensor(m, dtype=torch.float64) / torch.tensor(s, dtype=torch.float64) ** 2
               for m, s in zip(mus, sds, strict=True)) / prec
    draws = post.sample_is(20000, seed=0, is_rounds=2, reuse_mixture_draws=reuse)
    assert draws.ess > 2000 and draws.samples.shape == (20000, 4)
    w, th = draws.weights.numpy(), draws.samples.numpy()
    m = w @ th
    v = w @ (th - m) ** 2
    np.testing.assert_allclose(m, mean.numpy(), atol=0.03)
    np.testing.assert_allclose(v, (1 / prec).numpy(), rtol=0.1)
    # log_prob: sum of the Gaussians' log densities minus (k - 1) log(uniform density)
    th = torch.tensor([[-2.0, 4.0, -2.0, 1.0]], dtype=torch.float64)
    expect = sum(e.log_prob(th.float(), None).double() for e in ests) + 2 * math.log(50.0**4)
    np.testing.assert_allclose(post.log_prob(th).numpy(), expect.numpy(), rtol=1e-5)
    assert post.log_prob(torch.tensor([1.0, 4.0, -2.0, 1.0])).item() == -math.inf


def test_single_task_logit_weights_are_uniform():
    low, high = torch.tensor([-1.0, 0.0]), torch.tensor([0.0, 1.0])
    post = NpePosterior([_Gauss([0.3, -0.2], [1.0, 0.8])], [torch.zeros(1)], low, high)
    draws = post.sample_is(1000, seed=1, is_rounds=0)
    assert draws.ess == pytest.approx(1000)
    th = draws.samples.numpy()
    assert np.all((th >= low.numpy()) & (th <= high.numpy()))


def test_sbi_style_sample_resamples_the_importance_draws():
    """``NpePosterior.sample(sample_shape, seed=None)`` returns (*sample_shape, 2n) equally weighted
    draws (importance draws resampled by weight), like sbi; seeded, and without a seed never
    touching the global random state."""
    low = torch.tensor([-50.0, 0.0])
    high = torch.tensor([0.0, 50.0])
    ests = [_Gauss([-3.0, 4.0], [1.0, 0.5]), _Gauss([-2.0, 5.0], [0.5, 1.0])]
    post = NpePosterior(ests, [torch.zeros(1)] * 2, low, high, theta_transform="none")
    x = post.sample((4000,), seed=1)
    assert x.shape == (4000, 2) and x.dtype == torch.float64
    assert post.sample((3, 5), seed=1).shape == (3, 5, 2)
    with pytest.raises(ValueError, match="^sample_shape:"):
        post.sample((-2,), seed=1)
    torch.testing.assert_close(post.sample((50,), seed=2), post.sample((50,), seed=2))
    # product of N(-3, 1) and N(-2, 0.5^2): mean -2.2, sd sqrt(0.2); of N(4, .25), N(5, 1): 4.2, sqrt(0.2)
    np.testing.assert_allclose(x.mean(0).numpy(), [-2.2, 4.2], atol=0.05)
    np.testing.assert_allclose(x.std(0).numpy(), [0.2**0.5] * 2, rtol=0.1)
    torch.manual_seed(5)
    state = torch.get_rng_state()
    np.random.seed(5)
    np_state = np.random.get_state()
    assert post.sample((10,)).shape == (10, 2)
    assert torch.equal(torch.get_rng_state(), state)
    assert np.array_equal(np.random.get_state()[1], np_state[1])


# ---------------------------------------------------------------------------------------------
# training on the toy simulator
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def toy():
    return toy_task()


def test_run_budget_seeding_and_rng_isolation(toy):
    torch.manual_seed(99)
    state = torch.get_rng_state()
    np.random.seed(3)
    np_state = np.random.get_state()
    r1 = run_method("npe", toy, toy.observations[:2], budget=300, seed=4, config=TINY)
    assert torch.equal(torch.get_rng_state(), state)
    assert np.array_equal(np.random.get_state()[1], np_state[1])
    assert r1.method == "npe" and r1.n_tasks == 2
    assert r1.n_simulations == 600  # exactly budget x tasks, counted by the wrapper
    assert r1.samples.shape == (500, 4) and r1.weights.shape == (500,)
    assert bool(toy.prior.contains(torch.from_numpy(r1.samples)).all())
    ex = r1.extras
    assert len(ex["tasks"]) == 2 and all(t["epochs"] >= 1 for t in ex["tasks"])
    assert 1 <= ex["ess"] <= 500 and len(ex["ess_rounds"]) == 2
    r2 = run_method("npe", toy, toy.observations[:2], budget=300, seed=4, config=TINY)
    np.testing.assert_array_equal(r1.samples, r2.samples)
    np.testing.assert_array_equal(r1.weights, r2.weights)
    r3 = run_method("npe", toy, toy.observations[:2], budget=300, seed=5, config=TINY)
    assert not np.array_equal(r1.samples, r3.samples)


@pytest.mark.parametrize("warm_start", [False, True])
def test_run_sequence_equals_reruns(toy, warm_start):
    config = {**TINY, "warm_start": warm_start}
    seq = run_method_sequence("npe", toy, budget=300, seed=2, config=config)
    assert [r.n_tasks for r in seq] == [1, 2, 3]
    assert [r.n_simulations for r in seq] == [300, 600, 900]
    again = run_method("npe", toy, toy.observations[:2], budget=300, seed=2, config=config)
    np.testing.assert_array_equal(seq[1].samples, again.samples)
    np.testing.assert_array_equal(seq[1].weights, again.weights)


def test_warm_start_keeps_every_feature_and_continues_from_the_previous_flow(toy):
    """``warm_start``: every task's flow sees the whole summary (a feature constant over the
    task's simulations is 0 in the training data and the observation, not dropped), task 1's
    training starts from task 0's weights; without it (the default) the constant features are
    dropped."""
    warm, info = npe.fit(toy, toy.observations[:2], budget=300, seed=0, config=NpeConfig(**TINY, warm_start=True))
    cold, cold_info = npe.fit(toy, toy.observations[:2], budget=300, seed=0, config=NpeConfig(**TINY))
    full = {x.numel() for x in warm.x_obs}
    assert len(full) == 1 and [t["warm_start"] for t in info["tasks"]] == [False, True]
    for x_w, x_c, t in zip(warm.x_obs, cold.x_obs, info["tasks"], strict=True):
        x_w, x_c = x_w.reshape(-1), x_c.reshape(-1)
        assert x_c.numel() == t["n_features"] <= x_w.numel()
        kept = x_w != 0  # the toy's observed features are never exactly 0
        assert int(kept.sum()) == t["n_features"]
        torch.testing.assert_close(x_w[kept], x_c)
    assert not any(t["warm_start"] for t in cold_info["tasks"])
    # task 0 is trained alike in both arms (nothing to start from)
    z = torch.zeros(1, 1, 4)
    with torch.no_grad():
        torch.testing.assert_close(warm.estimators[0].log_prob(z, condition=warm.x_obs[0].reshape(1, -1)),
                                   cold.estimators[0].log_prob(z, condition=cold.x_obs[0].reshape(1, -1)))


def test_train_npe_warm_start_starts_from_the_given_weights():
    """With a learning rate too small to move them, a warm-started estimator is the one it
    started from (same data and seed, so the same training split and z-scoring), a fresh one
    is not; other sizes are refused."""
    from camo_sbi.inference import sbi_adapter

    gen = torch.Generator().manual_seed(0)
    theta = torch.randn(200, 2, generator=gen)
    x = theta + 0.1 * torch.randn(200, 2, generator=gen)
    kw = {"hidden_features": 8, "num_transforms": 2, "max_epochs": 3, "stop_after_epochs": 2}
    first, _ = sbi_adapter.train_npe(theta, x, seed=1, **kw)
    again, info = sbi_adapter.train_npe(theta, x, seed=1, learning_rate=1e-12, init_from=first, **kw)
    fresh, _ = sbi_adapter.train_npe(theta, x, seed=1, learning_rate=1e-12, **kw)
    probe, cond = torch.randn(5, 1, 2, generator=gen), x[:1]
    with torch.no_grad():
        torch.testing.assert_close(again.log_prob(probe, condition=cond), first.log_prob(probe, condition=cond))
        assert not torch.allclose(fresh.log_prob(probe, condition=cond), first.log_prob(probe, condition=cond))
    assert info["epochs"] >= 1
    with pytest.raises(ValueError, match="^init_from"):
        sbi_adapter.train_npe(theta, torch.cat([x, x], dim=1), seed=2, init_from=first, **kw)


def test_save_load_round_trip(toy, tmp_path):
    res = run_method("npe", toy, toy.observations[:2], budget=300, seed=0,
                     config={**TINY, "workdir": str(tmp_path), "embedding": "mlp", "embedding_dim": 8})
    path = res.extras["posterior_path"]
    assert path == str(tmp_path / "npe_posterior_k2_seed0.pt")
    post = load_posterior(path)
    again = load_posterior(path)
    assert post.n_tasks == 2 and post.n_free == 4
    theta = torch.from_numpy(res.samples[:50])
    lp = post.log_prob(theta)
    assert torch.isfinite(lp).all()
    torch.testing.assert_close(again.log_prob(theta), lp, rtol=0, atol=0)
    a = post.sample_is(200, seed=3)
    b = again.sample_is(200, seed=3)
    np.testing.assert_array_equal(a.samples.numpy(), b.samples.numpy())
    np.testing.assert_array_equal(a.weights, b.weights)
    # the reloaded posterior reproduces the run's own samples (same sampling seed)
    fresh = load_posterior(path).sample_is(TINY["n_posterior_samples"], npe._seed_int(0, 2) % 2**32,
                                        is_rounds=TINY["is_rounds"], reuse_mixture_draws=True)
    np.testing.assert_array_equal(fresh.samples.numpy(), res.samples)
    with pytest.raises(ValueError, match="^path"):
        load_posterior(tmp_path / "missing.pt")
    torch.save({"format": "other"}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="^path"):
        load_posterior(tmp_path / "other.pt")


@pytest.mark.parametrize("warm_start", [False, True])
def test_killed_run_resumes_from_task_checkpoints_with_the_same_numbers(toy, tmp_path, monkeypatch, warm_start):
    config = {**TINY, "warm_start": warm_start}
    fresh = run_method("npe", toy, toy.observations[:3], budget=300, seed=6, config=config)
    real_train = npe.sbi_adapter.train_npe
    calls = []

    def dies_at_the_third_task(*args, **kwargs):  # a kill while task 2 trains
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real_train(*args, **kwargs)

    work = {**config, "workdir": str(tmp_path)}
    monkeypatch.setattr(npe.sbi_adapter, "train_npe", dies_at_the_third_task)
    with pytest.raises(KeyboardInterrupt):
        run_method("npe", toy, toy.observations[:3], budget=300, seed=6, config=work)
    assert len(list((tmp_path / "npe_tasks").glob("task*.pt"))) == 2
    calls.clear()
    monkeypatch.setattr(npe.sbi_adapter, "train_npe", lambda *a, **k: (calls.append(1), real_train(*a, **k))[1])
    resumed = run_method("npe", toy, toy.observations[:3], budget=300, seed=6, config=work)
    assert len(calls) == 1  # only task 2 is trained again
    assert resumed.extras["resumed_tasks"] == [0, 1]
    assert resumed.n_simulations == 900  # the resumed tasks' simulations are still counted
    np.testing.assert_array_equal(resumed.samples, fresh.samples)
    np.testing.assert_array_equal(resumed.weights, fresh.weights)
    # their recorded cost is in the wall time: resuming never makes the method look faster
    recorded = sum(t["time_simulate"] + t["time_train"] for t in resumed.extras["tasks"][:2])
    assert resumed.wall_time >= recorded > 0
    # other settings never read these checkpoints: another seed trains every task
    calls.clear()
    run_method("npe", toy, toy.observations[:3], budget=300, seed=7, config=work)
    assert len(calls) == 3


def test_damaged_task_checkpoint_is_trained_again_with_a_warning(toy, tmp_path):
    work = {**TINY, "workdir": str(tmp_path)}
    first = run_method("npe", toy, toy.observations[:2], budget=300, seed=6, config=work)
    assert first.extras["resumed_tasks"] == []
    weights = sorted((tmp_path / "npe_tasks").glob("task000-*.pt"))[0]
    data = bytearray(weights.read_bytes())
    data[-10] ^= 0xFF
    weights.write_bytes(bytes(data))
    with pytest.warns(RuntimeWarning, match="task000-.*sha256.*task 0 is trained again"):
        again = run_method("npe", toy, toy.observations[:2], budget=300, seed=6, config=work)
    assert again.extras["resumed_tasks"] == [1]
    np.testing.assert_array_equal(again.samples, first.samples)


def test_fixed_coordinates_not_trained(toy):
    sim = ToySimulator(n=2)
    prior = BoxPrior(sim.bounds, sim.start, fixed={1: (-0.4, 0.7)})
    task = toy_task(prior)
    post, info = npe.fit(task, task.observations[:1], budget=300, seed=0, config=NpeConfig(**TINY))
    assert post.n_free == 2
    assert post.sample_is(100, seed=0).samples.shape == (100, 4)
    res = run_method("npe", task, task.observations[:1], budget=300, seed=0, config=TINY)
    assert np.all(res.samples[:, 2] == -0.4) and np.all(res.samples[:, 3] == 0.7)
    assert res.estimate[2] == -0.4 and res.estimate[3] == 0.7


@pytest.mark.parametrize(
    ("overrides", "exc", "field"),
    [
        ({"density_estimator": "mdn"}, ValueError, "density_estimator"),
        ({"space": "polar"}, ValueError, "space"),
        ({"embedding": "cnn"}, ValueError, "embedding"),
        ({"theta_transform": "probit"}, ValueError, "theta_transform"),
        ({"n_points": 0}, ValueError, "n_points"),
        ({"max_epochs": 1.5}, TypeError, "max_epochs"),
        ({"learning_rate": -1e-3}, ValueError, "learning_rate"),
        ({"validation_fraction": 0.7}, ValueError, "validation_fraction"),
        ({"defensive_fraction": 1.0}, ValueError, "defensive_fraction"),
        ({"is_rounds": -1}, ValueError, "is_rounds"),
        ({"point_estimate": "argmin"}, ValueError, "point_estimate"),
        ({"point_estimate": "map"}, ValueError, "point_estimate"),  # the mode's old name
        ({"estimator": "mean"}, ValueError, "config"),  # point_estimate's old name
        ({"simulation_batch_size": 64}, ValueError, "config"),  # chunk_size's old name
        ({"device": "gpu0"}, ValueError, "device"),
        ({"n_threads": 0}, ValueError, "n_threads"),
        ({"epochs": 3}, ValueError, "config"),
    ],
)
def test_bad_configs_rejected(overrides, exc, field):
    with pytest.raises(exc, match=f"^{field}"):
        make_config("npe", **overrides)


def test_bad_run_arguments_rejected(toy):
    with pytest.raises(ValueError, match="^budget"):
        run_method("npe", toy, budget=10, seed=0, config=TINY)
    with pytest.raises(TypeError, match="^config"):
        npe.run(toy, toy.observations, budget=300, seed=0, config={"n_points": 3})
    with pytest.raises(ValueError, match="^seed"):
        npe.run(toy, toy.observations, budget=300, seed=-2, config=NpeConfig(**TINY))


@pytest.mark.slow  # statistical recovery, trains flows (~14 s)
def test_smoke_recovery_toy(toy):
    """A short training (budget 800 per task, 3 tasks) lands within 0.25 rad of the truth."""
    cfg = {**TINY, "max_epochs": 60, "stop_after_epochs": 10, "hidden_features": 32,
           "n_posterior_samples": 2000}
    res = run_method("npe", toy, budget=800, seed=0, config=cfg)
    np.testing.assert_allclose(res.estimate, TRUE.numpy(), atol=0.25)


@pytest.mark.slow
@pytest.mark.parametrize("space", ["joint", "cartesian"])
def test_recovery_toy_slow(toy, space):
    """Default settings, budget 2000 per task, 3 tasks: within 0.08 rad of the truth
    (measured 0.005), ESS > 100 (measured ~2500 of 10000)."""
    res = run_method("npe", toy, budget=2000, seed=1, config={"space": space})
    np.testing.assert_allclose(res.estimate, TRUE.numpy(), atol=0.08)
    assert res.extras["ess"] > 100


@pytest.mark.slow
def test_panda_slow():
    """Panda, 5 reaches, budget 2000 per task, default settings: the estimate predicts
    held-out reaches better than the prior mean (joint_error_deg); ESS of the combined
    posterior > 20 (measured 50-230 of 10000)."""
    from camo_sbi.evaluation.metrics import joint_error_deg
    from camo_sbi.task import predict
    from tests.test_abc_smc import impaired_panda_task

    task = impaired_panda_task()
    sim = task.simulator
    res = run_method("npe", task, budget=2000, seed=0)
    truth = predict(sim, task.true_theta, task.test_starts, task.test_goals)

    def err(theta):
        pred = predict(sim, torch.as_tensor(theta), task.test_starts, task.test_goals)
        return float(joint_error_deg(truth, pred).mean())

    prior_mean = (task.prior.low + task.prior.high) / 2
    assert err(res.estimate) < 0.8 * err(prior_mean)
    assert res.extras["ess"] > 20


class _StubPosterior:
    """What `npe._result` reads from an `NpePosterior`: ``sample_is``, ``log_prob``, ``info``, ``n_tasks``."""

    def __init__(self, weights):
        self.weights = np.asarray(weights, dtype=np.float64)
        self.n_tasks = 2
        self.info = {"tasks": [{"time_simulate": 0.0, "time_train": 0.0}] * 2}

    def log_prob(self, theta):  # pragma: no cover - carried by the result, not called here
        raise NotImplementedError

    def sample_is(self, n, seed, *, is_rounds, defensive_fraction, reuse_mixture_draws):  # noqa: ARG002
        w = self.weights / self.weights.sum()
        # distinct draws near the truth (identical ones would be a collapse, a fallback of its own)
        theta = TRUE.numpy()[None, :] + 1e-6 * np.arange(len(w))[:, None]
        ess = float(1 / np.sum(w**2))
        return samplers.WeightedDraws(torch.from_numpy(theta), torch.from_numpy(w), torch.zeros(len(w)), ess, "is",
                                      diagnostics={"ess_rounds": [ess]})


@pytest.mark.parametrize(
    ("weights", "status"),
    [
        (np.ones(1000), "ok"),
        (np.r_[np.ones(25), np.full(975, 1e-12)], "ok"),  # ESS 25 >= 20
        (np.r_[np.ones(5), np.full(995, 1e-12)],
         "fallback: low effective sample size (ESS 5.0 of 1000 importance draws, below 20)"),
        (np.ones(30), "ok"),  # few draws, all equal: ESS 30 of 30
        (np.r_[np.ones(4), np.full(26, 1e-12)],
         "fallback: low effective sample size (ESS 4.0 of 30 importance draws, below 15)"),
    ],
)
def test_result_status_from_the_effective_sample_size(weights, status):
    """A combined importance sample below min(min_ess = 20, N / 2) effective draws is a
    recorded fallback (measured: degenerate human runs ESS 4.5-9.2 of 10000, usable ones >= 50)."""
    task = toy_task()
    cfg = NpeConfig(n_posterior_samples=len(weights))
    res = npe._result(task, _StubPosterior(weights), cfg, budget=100, seed=0, t_start=0.0)
    assert res.status == status
    assert res.extras["ess"] == pytest.approx(1 / np.sum((weights / weights.sum()) ** 2))
