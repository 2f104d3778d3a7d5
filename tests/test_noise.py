"""The observation-noise model and how every method honours it (plumbing; statistics in the
robustness study)."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from camo_sbi.inference.naive import median3
from camo_sbi.inference.registry import run_method
from camo_sbi.scenarios.reaching import make_reaching_task
from camo_sbi.task import NOISE_K, NoiseModel, Observation
from tests.toy_sim import ToySimulator

TRUE = torch.tensor([-0.3, 0.4, -0.5, 0.6], dtype=torch.float64)
NOISY = NoiseModel(joint_deg=1.0, ee_mm=5.0)
FAST = {"camo-js": {"keep_best": 10}, "camo-cs": {"keep_best": 10}, "camo-hull": {"keep_best": 10},
        "abc-smc": {"population_size": 20, "max_populations": 3},
        "npe": {"max_epochs": 3, "num_transforms": 1, "hidden_features": 8, "training_batch_size": 20,
                "n_posterior_samples": 200, "is_rounds": 1}}


@pytest.fixture(scope="module")
def task():
    return make_reaching_task(ToySimulator(), TRUE, n_train=2, n_test=2, seed=0)


def test_noise_model_units_validation_and_streams():
    m = NoiseModel(joint_deg=2.0, ee_mm=4.0)
    assert m.sigma("joint") == pytest.approx(math.radians(2.0)) and m.sigma("cartesian") == pytest.approx(0.004)
    assert m.tolerance("joint") == pytest.approx(NOISE_K * math.radians(2.0))
    for bad in (-1.0, float("nan"), float("inf"), "1"):
        with pytest.raises(ValueError, match="^joint_deg:"):
            NoiseModel(joint_deg=bad)
    x = torch.zeros(20000, 3, dtype=torch.float64)
    a = m.perturb(x, "cartesian", np.random.default_rng(1))
    assert abs(float(a.std()) - 0.004) < 1e-4 and abs(float(a.mean())) < 1e-4
    torch.testing.assert_close(a, m.perturb(x, "cartesian", np.random.default_rng(1)))
    torch.testing.assert_close(m.perturb(x, "joint", torch.Generator().manual_seed(0)),
                               m.perturb(x, "joint", torch.Generator().manual_seed(0)))
    rng = np.random.default_rng(3)
    assert torch.equal(NoiseModel().perturb(x, "joint", rng), x)
    assert rng.random() == np.random.default_rng(3).random()  # sigma 0 draws nothing
    with pytest.raises(TypeError, match="^generator:"):
        m.perturb(x, "joint", 7)


@pytest.mark.parametrize("name", ["camo-js", "camo-cs", "abc-smc", "npe"])
def test_simulating_methods_see_candidates_through_the_noise(name, task):
    """With a noise model the candidates' trajectories are perturbed (noisy ABC / noise-augmented
    NPE training): the result changes, and the same seed still gives the same numbers."""
    cfg = FAST[name]
    budget = 200 if name == "abc-smc" else 60  # past ABC-SMC's prior population (eps = inf)
    clean = run_method(name, task, budget=budget, seed=2, config=cfg)
    noisy_task = replace(task, noise=NOISY)
    a = run_method(name, noisy_task, budget=budget, seed=2, config=cfg)
    b = run_method(name, noisy_task, budget=budget, seed=2, config=cfg)
    np.testing.assert_array_equal(a.samples, b.samples)
    assert not np.array_equal(a.samples, clean.samples) or not np.array_equal(a.weights, clean.weights)


def test_camo_hull_tolerates_a_noisy_posture_beyond_a_bound(task):
    """A noisy posture 0.033 rad beyond the model's bound: a ValueError without a noise model
    (it cannot be a clamped posture), accepted within 3 sigma of a 1 degree noise model."""
    o = task.observations[0]
    q = o.q.clone()
    q[len(q) // 2, 0] = task.simulator.bounds[0, 1] + 0.033
    bad = task.with_observations([Observation(o.start, o.goal, q, o.ee)])
    with pytest.raises(ValueError, match="^postures:"):
        run_method("camo-hull", bad, budget=60, seed=0, config=FAST["camo-hull"])
    res = run_method("camo-hull", replace(bad, noise=NOISY), budget=60, seed=0, config=FAST["camo-hull"])
    assert res.status == "ok" and bool(task.prior.contains(torch.from_numpy(res.estimate)).all())


def test_naive_is_not_fooled_by_a_single_outlier(task):
    o = task.observations[0]
    q = o.q.clone()
    spike = len(q) // 2
    q[spike, 1] = float(q[:, 1].max()) + 0.3  # one outlying sample on joint 1
    spiked = task.with_observations([Observation(o.start, o.goal, q, o.ee)])
    plain = run_method("naive", spiked, budget=1, seed=0).estimate
    robust = run_method("naive", replace(spiked, noise=NOISY), budget=1, seed=0).estimate
    assert plain[3] == pytest.approx(float(q[:, 1].max()))  # without noise the spike is a posture
    assert robust[3] < plain[3] - 0.2  # with noise one sample cannot set a limit
    clean = run_method("naive", task.with_observations([o]), budget=1, seed=0).estimate
    assert abs(robust[3] - clean[3]) < 0.05


def test_median3_hand_computed():
    q = torch.tensor([[0.0], [1.0], [5.0], [2.0], [3.0]])
    torch.testing.assert_close(median3(q).flatten(), torch.tensor([0.5, 1.0, 2.0, 3.0, 2.5]))
    short = torch.tensor([[1.0], [9.0]])
    assert torch.equal(median3(short), short)
