"""A method that raises is a marked "failed" row in a grid, never a stopped grid (``errors="record"``)."""

import warnings
from dataclasses import dataclass

import numpy as np
import pandas as pd
import pytest
import torch

from camo_sbi.experiments.cli import main as cli_main
from camo_sbi.inference import registry
from camo_sbi.inference.registry import (
    Capabilities,
    Implementation,
    MethodSpec,
    run_method,
    run_method_sequence,
)
from camo_sbi.inference.result import PosteriorResult
from camo_sbi.scenarios.reaching import make_reaching_task
from tests.toy_sim import ToySimulator

TRUE = torch.tensor([-0.3, 0.4, -0.5, 0.6], dtype=torch.float64)


@dataclass(frozen=True)
class BoomConfig:
    fail_at: int = 1  # the task (1-based) at which the method raises
    space: str = "joint"


def _point(task, k):
    n = task.prior.dim
    return PosteriorResult(method="boom", samples=np.zeros((2, n)), weights=None, estimate=np.zeros(n),
                           n_simulations=0, wall_time=0.0, n_tasks=k)


def _run(task, observations, *, budget, seed, config):
    task.simulator.simulate(task.prior.sample(3, np.random.default_rng(seed)), observations[0].goal,
                            observations[0].start)
    if len(observations) >= config.fail_at:
        raise RuntimeError(f"boom at task {len(observations)}\n(second line)")
    return _point(task, len(observations))


def _run_sequence(task, observations, *, budget, seed, config):
    for k in range(1, len(observations) + 1):
        if k >= config.fail_at:
            raise RuntimeError(f"boom at task {k}")
        yield _point(task, k)


@pytest.fixture
def boom(monkeypatch):
    plain = Implementation(_run, BoomConfig)
    continual = Implementation(_run, BoomConfig, _run_sequence)
    monkeypatch.setitem(registry._REGISTRY, "boom", MethodSpec("boom", "raises (test)", lambda: plain, Capabilities()))
    monkeypatch.setitem(registry._REGISTRY, "boom-seq", MethodSpec("boom-seq", "raises (test)", lambda: continual,
                                                                   Capabilities(continual=True)))
    return "boom"


@pytest.fixture(scope="module")
def toy_task():
    return make_reaching_task(ToySimulator(), TRUE, n_train=3, n_test=2, seed=0)


def test_by_default_the_exception_propagates(boom, toy_task):
    with pytest.raises(RuntimeError, match="boom at task 3"):
        run_method("boom", toy_task, budget=10, seed=0)
    with pytest.raises(RuntimeError, match="boom at task 2"):
        run_method_sequence("boom-seq", toy_task, budget=10, seed=0, config={"fail_at": 2})


def test_recorded_failure_is_a_marked_result_at_the_priors_centre(boom, toy_task):
    with pytest.warns(RuntimeWarning, match=r"method 'boom' after 3 task\(s\): failed: RuntimeError: boom at task 3"):
        res = run_method("boom", toy_task, budget=10, seed=0, errors="record")
    assert res.status == "failed: RuntimeError: boom at task 3 (second line); the result is the prior's centre"
    centre = ((toy_task.prior.low + toy_task.prior.high) / 2).numpy()
    np.testing.assert_array_equal(res.estimate, centre)
    assert res.samples.shape == (1, 4) and res.method == "boom" and res.n_tasks == 3
    assert res.n_simulations == 3  # what it consumed before raising, counted by the wrapper
    assert "RuntimeError: boom at task 3" in res.extras["traceback"] and "_run" in res.extras["traceback"]


def test_recorded_failure_in_a_continual_method_keeps_the_earlier_tasks(boom, toy_task):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        out = run_method_sequence("boom-seq", toy_task, budget=10, seed=0, config={"fail_at": 2}, errors="record")
    assert [r.n_tasks for r in out] == [1, 2, 3]
    assert out[0].status == "ok"
    assert [r.status.split(";")[0] for r in out[1:]] == ["failed: RuntimeError: boom at task 2"] * 2
    # a non-continual method is rerun per prefix: only the prefixes that raise fail
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        out = run_method_sequence("boom", toy_task, budget=10, seed=0, config={"fail_at": 3}, errors="record")
    assert [r.status == "ok" for r in out] == [True, True, False]


def test_bad_arguments_raise_even_when_recording(boom, toy_task):
    with pytest.raises(ValueError, match="^errors: expected one of"):
        run_method("boom", toy_task, budget=10, seed=0, errors="ignore")
    with pytest.raises(ValueError, match="budget"):
        run_method("boom", toy_task, budget=0, seed=0, errors="record")
    with pytest.raises(ValueError, match="fail_a"):
        run_method("boom", toy_task, budget=10, seed=0, config={"fail_a": 1}, errors="record")


def test_compare_writes_failed_rows_and_finishes_the_grid(boom, tmp_path):
    out = tmp_path / "run"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        code = cli_main(["compare", "--methods", "boom,naive", "--seeds", "1", "--tasks", "2", "--test-goals", "2",
                         "--budgets", "10", "--config", 'boom={"fail_at": 2}', "--no-report", "--out", str(out)])
    assert code == 0
    df = pd.read_csv(out / "results.csv")
    boom_rows = df[df.method == "boom"]
    status = boom_rows.groupby("n_tasks").status.first()
    assert status[1] == "ok" and status[2].startswith("failed: RuntimeError: boom at task 2")
    # the other methods and the baselines ran to the end
    assert {"naive", "nominal", "oracle"} <= set(df.method) and (df[df.method == "naive"].status == "ok").all()


def _bad_input(task, observations, *, budget, seed, config):
    from camo_sbi._validation import InputError

    raise InputError("estimator: trained for another model (test)")


def test_bad_input_found_inside_the_run_is_never_recorded(monkeypatch, toy_task):
    """An `InputError` (bad input only the run can judge, e.g. an amortized estimator that does not
    fit the task) propagates even when recording, so the CLI exits 2 naming the argument."""
    monkeypatch.setitem(registry._REGISTRY, "picky", MethodSpec(
        "picky", "refuses its input (test)", lambda: Implementation(_bad_input, BoomConfig), Capabilities()))
    with pytest.raises(ValueError, match="^estimator: trained for another model"):
        run_method("picky", toy_task, budget=10, seed=0, errors="record")
    with pytest.raises(ValueError, match="^estimator: trained for another model"):
        run_method_sequence("picky", toy_task, budget=10, seed=0, errors="record")


def _bad_estimate(task, observations, *, budget, seed, config):
    n = task.prior.dim
    est = np.zeros(n)
    est[0], est[1] = 0.3, -0.3  # lo > hi on joint 0, far beyond rounding
    return PosteriorResult(method="x", samples=est[None], weights=None, estimate=est, n_simulations=0,
                           wall_time=0.0, n_tasks=len(observations))


def test_an_estimate_no_metric_can_score_is_a_recorded_failure(monkeypatch, toy_task):
    """nre once returned lo > hi (by rounding) and the grid stopped later, in the scoring; an
    unusable estimate is now the method's recorded failure, caught where the method returns."""
    monkeypatch.setitem(registry._REGISTRY, "inverted", MethodSpec(
        "inverted", "returns lo > hi (test)", lambda: Implementation(_bad_estimate, BoomConfig), Capabilities()))
    with pytest.warns(RuntimeWarning, match="failed: ValueError: estimate: lower limit exceeds upper limit"):
        res = run_method("inverted", toy_task, budget=10, seed=0, errors="record")
    assert res.status.startswith("failed: ValueError: estimate: lower limit exceeds upper limit (sample 0, joint 0")
    res = run_method("inverted", toy_task, budget=10, seed=0)  # raise mode: returned as the method made it
    assert res.status == "ok" and res.estimate[0] > res.estimate[1]
