"""sbi's other families (nle, nre, fmpe, npse, tsnpe) beyond the contract test: how the tasks
combine (checked against a grid computation), what a sampler with no usable draw gives, how
TSNPE spends its budget, and the configs' refusals. The registry, budgets, seeds and continual
use of all five are in tests/test_contract.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from camo_sbi.inference import sbi_adapter, sbi_family
from camo_sbi.inference.flow_space import logistic_log_prob
from camo_sbi.inference.registry import make_config, run_method
from camo_sbi.priors import BoxPrior
from camo_sbi.scenarios.reaching import make_reaching_task
from tests.toy_sim import ToySimulator

TRUE = torch.tensor([-0.3, 0.4, -0.5, 0.6], dtype=torch.float64)


@pytest.fixture(scope="module")
def task():
    return make_reaching_task(ToySimulator(), TRUE, n_train=2, n_test=2, seed=0, name="toy", subject="toy")


def test_likelihood_terms_are_summed_with_the_prior_as_a_grid_says():
    """The likelihood families' posterior is log p(z) + sum_i term_i(z), sampled by SMC. With two
    Gaussian terms per coordinate (an exact, independent posterior), the weighted mean and sd of
    each z coordinate match a 1-D grid integration of logistic x N x N within 0.05 (posterior sd
    about 0.35; 1000 particles)."""
    prior = BoxPrior(torch.tensor([[-1.0, 1.0], [-1.0, 1.0]]))
    mu = torch.tensor([[0.8, -0.5, 1.5, 0.2], [0.4, -0.9, 1.1, -0.2]], dtype=torch.float64)  # task x coordinate
    sd = 0.5
    terms = [lambda z, m=m: (-0.5 * ((z - m) / sd) ** 2).sum(-1) for m in mu]
    draws, density = sbi_family._likelihood_draws(prior, terms, sbi_family.FamilyConfig(n_posterior_samples=1000),
                                                  seed=0)
    assert draws.failure is None and draws.ess > 250
    lo, width = prior.low[prior.free_mask], (prior.high - prior.low)[prior.free_mask]
    u = ((draws.samples[:, prior.free_mask] - lo) / width).clamp(1e-12, 1 - 1e-12)
    z = torch.logit(u)
    w = draws.weights
    grid = torch.linspace(-8, 8, 20001, dtype=torch.float64)
    for j in range(4):
        logp = logistic_log_prob(grid[:, None]) + sum(-0.5 * ((grid - m[j]) / sd) ** 2 for m in mu)
        p = torch.softmax(logp, 0)
        mean, var = float(p @ grid), float(p @ grid**2) - float(p @ grid) ** 2
        m_hat = float(w @ z[:, j])
        s_hat = math.sqrt(float(w @ (z[:, j] - m_hat) ** 2))
        assert abs(m_hat - mean) < 0.05, (j, m_hat, mean)
        assert abs(s_hat - math.sqrt(var)) < 0.05, (j, s_hat, math.sqrt(var))
    # the result's density is the same target in theta coordinates: differences between draws agree
    lp = density(draws.samples[:50])
    lt = draws.log_density[:50]
    np.testing.assert_allclose((lp - lp[0]).numpy(), (lt - lt[0]).numpy(), atol=1e-8)


class _NaNPosterior:
    """A posterior estimator whose density is NaN everywhere (as a diverged score model's)."""

    def eval(self):
        return self

    def log_prob(self, input, condition):  # noqa: A002
        return torch.full((input.reshape(-1, input.shape[-1]).shape[0],), float("nan"))

    def sample(self, sample_shape, condition):
        return torch.zeros(*sample_shape, 4)


def test_a_posterior_with_no_usable_draw_is_a_failed_result_not_an_exception(task):
    def train(z, x, x_obs, simulate, seed, config, budget):
        return _NaNPosterior(), {"time_train": 0.0}

    counted, counter = task.with_budget(60 * 2)
    res = sbi_family.run(counted, None, budget=60, seed=0, config=None, config_cls=sbi_family.FamilyConfig,
                         train=train, kind="posterior", method="npse")
    assert res.status.startswith("failed: ") and "importance weight" in res.status
    assert "prior's centre" in res.status
    np.testing.assert_allclose(res.estimate, ((task.prior.low + task.prior.high) / 2).numpy())
    assert counter.n_simulations == 120 and res.n_simulations == 120 and res.n_tasks == 2


def test_tsnpe_spends_each_task_budget_in_rounds_and_never_hangs(task):
    """61 simulations per task in 2 rounds: 31 prior draws, then 30 from the truncated prior; when
    the truncated region's prior acceptance is below ``min_acceptance`` (here: half the posterior
    mass cut away, 0.999 asked for) it is drawn by SIR from the posterior (bounded time)."""
    cfg = {"max_epochs": 3, "hidden_features": 8, "num_transforms": 1, "training_batch_size": 20,
           "n_posterior_samples": 200, "rounds": 2, "support_samples": 500}
    for extra, how in (({"min_acceptance": 1e-9}, "rejection"), ({"min_acceptance": 0.999, "quantile": 0.5}, "sir")):
        res = run_method("tsnpe", task, budget=61, seed=1, config={**cfg, **extra})
        assert res.n_simulations == 122
        for t in res.extras["tasks"]:
            assert [r["n"] for r in t["rounds"]] == [31, 30]
            assert t["rounds"][1]["truncation"] == how
    with pytest.raises(ValueError, match="^budget: 40 simulations per task leave too few"):
        run_method("tsnpe", task, budget=40, seed=1, config={**cfg, "rounds": 4})


_TINY = {"nle": {"max_epochs": 3, "hidden_features": 8, "num_transforms": 1, "training_batch_size": 20,
                 "n_posterior_samples": 200, "smc_max_stages": 20},
         "tsnpe": {"max_epochs": 3, "hidden_features": 8, "num_transforms": 1, "training_batch_size": 20,
                   "n_posterior_samples": 200, "rounds": 2, "support_samples": 500}}


@pytest.mark.parametrize(("name", "trainer"), [("nle", "train_nle"), ("tsnpe", "train_tsnpe")])
def test_killed_run_resumes_from_task_checkpoints_with_the_same_numbers(task, tmp_path, monkeypatch, name, trainer):
    """A kill while task 1 trains; the re-run reads task 0 back (trains task 1 only) and gives
    exactly the uninterrupted run's draws, its counted simulations and task 0's recorded seconds."""
    cfg = _TINY[name]
    fresh = run_method(name, task, budget=61, seed=3, config=cfg)
    real, calls = getattr(sbi_adapter, trainer), []

    def counted(*args, **kwargs):
        calls.append(1)
        if kill and len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(sbi_adapter, trainer, counted)
    work = {**cfg, "workdir": str(tmp_path)}
    kill = True
    with pytest.raises(KeyboardInterrupt):
        run_method(name, task, budget=61, seed=3, config=work)
    assert len(list((tmp_path / f"{name}_tasks").glob("task000-*.pt"))) == 1
    kill, calls[:] = False, []
    resumed = run_method(name, task, budget=61, seed=3, config=work)
    assert len(calls) == 1 and resumed.extras["resumed_tasks"] == [0]
    assert resumed.n_simulations == fresh.n_simulations == 122
    np.testing.assert_array_equal(resumed.samples, fresh.samples)
    np.testing.assert_array_equal(resumed.weights, fresh.weights)
    first = resumed.extras["tasks"][0]
    assert resumed.wall_time >= first["time_simulate"] + first["time_train"] > 0
    calls[:] = []  # another seed is another key: nothing is read back
    run_method(name, task, budget=61, seed=4, config=work)
    assert len(calls) == 2


@pytest.mark.parametrize(("name", "field", "value", "error"), [
    ("nle", "density_estimator", "mdn", ValueError),
    ("nle", "num_transforms", 0, ValueError),
    ("nre", "num_classes", 0, ValueError),
    ("nre", "gamma", -1.0, ValueError),
    ("nre", "classifier", "cnn", ValueError),
    ("fmpe", "ode_exact", 1, TypeError),
    ("fmpe", "num_layers", 0, ValueError),
    ("npse", "sde_type", "ou", ValueError),
    ("npse", "ode_rtol", 0.0, ValueError),
    ("tsnpe", "quantile", 1.5, ValueError),
    ("tsnpe", "rounds", 0, ValueError),
    ("tsnpe", "device", "no-such-device", ValueError),
    ("nle", "smc_max_stages", 0, ValueError),
    ("fmpe", "validation_fraction", 0.6, ValueError),
    ("nle", "workdir", 3, TypeError),
    ("tsnpe", "workdir", 3.0, TypeError),
])
def test_configs_refuse_bad_values_naming_the_field(name, field, value, error):
    with pytest.raises(error, match=f"^{field}:"):
        make_config(name, {field: value})


def test_the_logistic_prior_is_the_box_prior_in_logit_coordinates():
    """sbi's view of the prior (`sbi_adapter.logistic_prior`) has the density `flow_space` uses."""
    prior = sbi_adapter.logistic_prior(3)
    z = torch.linspace(-6, 6, 30).reshape(10, 3)
    torch.testing.assert_close(prior.log_prob(z).double(), logistic_log_prob(z.double()), atol=1e-4, rtol=0)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        u = torch.sigmoid(prior.sample((20000,)))
    assert abs(float(u.mean()) - 0.5) < 0.01 and abs(float(u.var()) - 1 / 12) < 0.003
