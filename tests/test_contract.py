"""One contract test over every registered method, as sbibm's task-interface test does.

For each name in the registry: the budget cap, the same seed giving the same numbers, the
estimate inside the prior box, bad input rejected with an error naming the argument, and
the result's type and fields. A method registered later is covered without edits here
(its entry in FAST only keeps the run short).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from camo_sbi.inference import registry
from camo_sbi.inference.registry import capabilities, get_method, run_method, run_method_sequence
from camo_sbi.inference.result import PosteriorResult, check_status
from camo_sbi.scenarios.reaching import make_reaching_task
from camo_sbi.task import NoiseModel, Observation
from tests.toy_sim import ToySimulator

TRUE = torch.tensor([-0.3, 0.4, -0.5, 0.6], dtype=torch.float64)
BUDGET = 60
K = 2

# settings that only make the runs short (the contract does not depend on them)
FAST = {
    "abc-smc": {"population_size": 20, "max_populations": 3},
    "npe": {"max_epochs": 3, "num_transforms": 1, "hidden_features": 8, "training_batch_size": 20,
            "n_posterior_samples": 200, "is_rounds": 2},
}
_TINY_SBI = {"max_epochs": 3, "hidden_features": 8, "training_batch_size": 20, "n_posterior_samples": 200}
FAST.update({
    "nle": {**_TINY_SBI, "num_transforms": 1},
    "nre": _TINY_SBI,
    "fmpe": {**_TINY_SBI, "num_layers": 2, "is_rounds": 1},
    "npse": {**_TINY_SBI, "num_layers": 2, "is_rounds": 0, "n_posterior_samples": 32, "ode_atol": 1e-2,
             "ode_rtol": 1e-1},
    "tsnpe": {**_TINY_SBI, "num_transforms": 1, "is_rounds": 2, "rounds": 2, "support_samples": 500},
})
for _name in registry.names():
    if "camo" in (_name, get_method(_name).base):
        FAST[_name] = {"keep_best": 10}
# amortized methods: a tiny estimator trained once for the toy model (`trained_estimators` below)
TINY_AMORTIZED = {"simulations": 400, "spaces": ("joint", "cartesian"), "max_epochs": 2, "hidden_features": 8,
                  "num_transforms": 1, "training_batch_size": 50}
FAST["npe-amortized"] = {"n_posterior_samples": 200, "is_rounds": 1, "min_ess": 0.0}
FAST["exact-likelihood"] = {"particles": 64, "moves": 2, "mcmc_steps": 20, "min_ess": 0.0}
EXACT_NOISE = NoiseModel(joint_deg=1.0, ee_mm=5.0)  # the exact likelihood needs a noise model

METHODS = registry.names()


@pytest.fixture(scope="module", autouse=True)
def trained_estimators(tmp_path_factory):
    """Train each amortized method's estimator once for the toy model and point FAST at it."""
    from camo_sbi.inference import amortized

    path = tmp_path_factory.mktemp("amortized") / "toy.pt"
    amortized.train(ToySimulator(), model="toy", config=amortized.TrainConfig(**TINY_AMORTIZED), seed=0).save(path)
    for name in METHODS:
        if capabilities(name).amortized:
            FAST[name] = {**FAST.get(name, {}), "estimator_path": str(path)}
    return path


@pytest.fixture(scope="module")
def task():
    return make_reaching_task(ToySimulator(), TRUE, n_train=K, n_test=2, seed=0, name="toy", subject="toy")


def task_for(name, task):
    """The task a method runs on: with a noise model for an exact-likelihood method (its likelihood is
    degenerate without noise), as is for every other (their behaviour under noise is tested elsewhere)."""
    from dataclasses import replace

    return replace(task, noise=EXACT_NOISE) if capabilities(name).exact else task


@pytest.fixture(scope="module")
def runs(task):
    """Two runs per method with the same seed, and one with another seed."""
    out = {}
    for name in METHODS:
        cfg = FAST.get(name, {})
        out[name] = [run_method(name, task_for(name, task), budget=BUDGET, seed=s, config=cfg) for s in (3, 3, 4)]
    return out


@pytest.mark.parametrize("name", METHODS)
def test_result_type_and_fields(name, task, runs):
    res = runs[name][0]
    assert isinstance(res, PosteriorResult)
    assert res.method == name and res.n_tasks == K
    check_status(res.status)
    assert res.status == "ok", res.status
    n = task.prior.dim
    assert res.samples.ndim == 2 and res.samples.shape[1] == n and res.samples.dtype == np.float64
    assert res.estimate.shape == (n,) and np.isfinite(res.estimate).all()
    if res.weights is not None:
        assert res.weights.shape == (res.samples.shape[0],) and np.isclose(res.weights.sum(), 1.0)
    assert res.wall_time >= 0 and isinstance(res.extras, dict)
    if not capabilities(name).posterior:
        assert res.samples.shape[0] == 1


@pytest.mark.parametrize("name", METHODS)
def test_budget_cap_is_counted_and_respected(name, runs):
    res = runs[name][0]
    if capabilities(name).exact:  # counted, but not capped: exempt from the budget (registry docstring)
        assert res.n_simulations > BUDGET * K
        return
    assert 0 <= res.n_simulations <= BUDGET * K
    if capabilities(name).simulates:
        assert res.n_simulations > 0
    else:
        assert res.n_simulations == 0


@pytest.mark.parametrize("name", METHODS)
def test_same_seed_same_numbers(name, runs):
    a, b, _ = runs[name]
    np.testing.assert_array_equal(a.samples, b.samples)
    np.testing.assert_array_equal(a.estimate, b.estimate)
    if a.weights is None:
        assert b.weights is None
    else:
        np.testing.assert_array_equal(a.weights, b.weights)
    assert a.n_simulations == b.n_simulations


@pytest.mark.parametrize("name", [m for m in METHODS if capabilities(m).simulates])
def test_another_seed_other_draws(name, runs):
    a, _, c = runs[name]
    assert not np.array_equal(a.samples, c.samples)


@pytest.mark.parametrize("name", METHODS)
def test_estimate_and_samples_inside_the_prior_box(name, task, runs):
    res = runs[name][0]
    assert bool(task.prior.contains(torch.from_numpy(res.estimate)).all())
    assert bool(task.prior.contains(torch.from_numpy(res.samples)).all())


@pytest.mark.parametrize("name", METHODS)
def test_sbi_style_sample_and_log_prob(name, task, runs):
    """``result.sample((100,))`` is a (100, 2n) tensor of draws inside the prior box, the same
    for the same seed; ``log_prob`` evaluates a density where the method has one and otherwise
    raises NotImplementedError naming the method."""
    res = runs[name][0]
    n = task.prior.dim
    draws = res.sample((100,), seed=0)
    assert isinstance(draws, torch.Tensor) and draws.shape == (100, n) and draws.dtype == torch.float64
    assert res.sample((5, 4)).shape == (5, 4, n) and res.sample().shape == (n,)
    torch.testing.assert_close(res.sample((100,), seed=0), draws)
    assert bool(task.prior.contains(draws).all())
    if res.samples.shape[0] == 1:  # a point estimate: every draw is that point
        assert bool((draws == torch.from_numpy(res.estimate)).all())
    else:  # draws are samples of the result (resampled by weight), not something else
        assert {tuple(r) for r in draws.numpy()} <= {tuple(r) for r in res.samples}
    with pytest.raises(ValueError, match="^sample_shape:"):
        res.sample((-1,))
    with pytest.raises(ValueError, match="^seed:"):
        res.sample((2,), seed=-1)
    if res.density is None:
        with pytest.raises(NotImplementedError, match=f"^log_prob: method {name!r}"):
            res.log_prob(draws)
    else:
        lp = res.log_prob(draws[:10])
        assert lp.shape == (10,) and bool(torch.isfinite(lp).all())
        if "camo" in (name, get_method(name).base):  # CAMO weights its kept vectors by that density (Eq. 6)
            w = torch.softmax(res.log_prob(torch.from_numpy(res.samples)), dim=0).numpy()
            np.testing.assert_allclose(w, res.weights, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("name", [m for m in METHODS if capabilities(m).continual])
def test_continual_sequence_equals_reruns(name, task):
    """The k-th result of one continual pass equals a fresh run on the first k tasks."""
    cfg = FAST.get(name, {})
    seq = run_method_sequence(name, task, budget=BUDGET, seed=3, config=cfg)
    assert [r.n_tasks for r in seq] == list(range(1, K + 1))
    for k, r in enumerate(seq, start=1):
        ref = run_method(name, task, task.observations[:k], budget=BUDGET, seed=3, config=cfg)
        np.testing.assert_array_equal(r.estimate, ref.estimate)
        assert r.n_simulations <= BUDGET * k


@pytest.mark.parametrize("name", METHODS)
def test_bad_input_names_the_argument(name, task):
    cfg = FAST.get(name, {})
    task = task_for(name, task)
    with pytest.raises(ValueError, match="^budget:"):
        run_method(name, task, budget=0, seed=0, config=cfg)
    with pytest.raises(TypeError, match="^budget:"):
        run_method(name, task, budget=2.5, seed=0, config=cfg)
    with pytest.raises(ValueError, match="^seed:"):
        run_method(name, task, budget=BUDGET, seed=-1, config=cfg)
    with pytest.raises(ValueError, match="^observations:"):
        run_method(name, task, [], budget=BUDGET, seed=0, config=cfg)
    with pytest.raises(TypeError, match="^observations:"):
        run_method(name, task, ["not an observation"], budget=BUDGET, seed=0, config=cfg)
    with pytest.raises(ValueError, match="^config:"):
        run_method(name, task, budget=BUDGET, seed=0, config={**cfg, "no_such_field": 1})
    with pytest.raises(TypeError, match="^task:"):
        run_method(name, object(), budget=BUDGET, seed=0, config=cfg)
    # a reach of the wrong model (3 joints on a 2-joint task)
    o = task.observations[0]
    wrong = Observation(torch.zeros(3), o.goal, torch.zeros(4, 3))
    with pytest.raises(ValueError, match="^observations:"):
        run_method(name, task, [wrong], budget=BUDGET, seed=0, config=cfg)


@pytest.mark.parametrize("name", METHODS)
def test_a_space_the_method_cannot_use_names_space(name, task):
    """End-effector-only reaches: methods that need joints say so, naming ``space``."""
    cfg = FAST.get(name, {})
    task = task_for(name, task)
    ee_only = task.with_observations(Observation(o.start, o.goal, None, o.ee) for o in task.observations)
    spaces = capabilities(name).spaces
    if spaces and ("cartesian" not in spaces or "joint" in capabilities(name).also_reads):
        with pytest.raises(ValueError, match="^space:"):
            run_method(name, ee_only, budget=BUDGET, seed=0, config=cfg)
    elif len(spaces) > 1:  # a method that chooses its space: joint on EE-only data is refused, cartesian runs
        with pytest.raises(ValueError, match="^space:"):
            run_method(name, ee_only, budget=BUDGET, seed=0, config={**cfg, "space": "joint"})
        res = run_method(name, ee_only, budget=BUDGET, seed=0, config={**cfg, "space": "cartesian"})
        assert res.status == "ok"
    else:  # needs no trajectory, or only Cartesian ones
        assert run_method(name, ee_only, budget=BUDGET, seed=0, config=cfg).status == "ok"


def test_oracle_needs_the_truth(task):
    from dataclasses import replace

    recorded = replace(task, true_theta=None, test_goals=None, test_starts=None)
    with pytest.raises(ValueError, match="^method 'oracle':"):
        run_method("oracle", recorded, budget=BUDGET, seed=0)


def test_budget_rules_are_declared_on_the_method_not_written_as_name_checks():
    """issue 26: a per-method budget rule lives on the method (registry), never as ``m == "abc-smc"``
    in a command; a grid refuses a config its budget cannot pay for, by the method's own rule."""
    import pathlib
    import re

    from camo_sbi.inference.registry import budget_defaults, check_budget

    assert budget_defaults("abc-smc", 150) == {"population_size": 50}
    assert budget_defaults("abc-smc", 3000) == {"population_size": 100}
    assert budget_defaults("camo", 150) == {}
    with pytest.raises(ValueError, match=r"^budget: abc-smc needs at least 160 simulations per task"):
        check_budget("abc-smc", {"population_size": 80, "initial_epsilon": "from_sample"}, 100)
    check_budget("abc-smc", {"population_size": 80}, 80)  # exactly enough
    check_budget("camo", None, 1)
    experiments = pathlib.Path(__file__).parents[1] / "camo_sbi" / "experiments"
    for f in experiments.glob("*.py"):
        assert not re.search(r"""[=!]= ?["']abc-smc["']""", f.read_text()), f.name
