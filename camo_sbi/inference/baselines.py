"""The trivial answers every comparison shows next to the methods: nominal and oracle.

* ``nominal``: the model's full range of motion, what a robot assumes without observing
  anyone (the prior's outer box; a strong prior's known joints at their known limits).
  The authors' code computes it as ``fixed`` (``sim_fixed``); the paper does not plot it.
* ``oracle``: the true limits of a synthetic subject. Its prediction errors are exactly 0,
  which makes it a built-in check of the evaluation pipeline; it needs ``task.true_theta``.

Neither simulates nor reads the observations (beyond the run contract's checks), so each
result is a point estimate with ``n_simulations = 0``. The observed-min/max baseline
(``naive``) is in `camo_sbi.inference.naive`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from camo_sbi.inference.contract import check_run_args
from camo_sbi.inference.result import PosteriorResult

__all__ = ["NominalConfig", "OracleConfig", "point_result", "run_nominal", "run_oracle",
           "sequence_nominal", "sequence_oracle"]


@dataclass(frozen=True)
class NominalConfig:
    """The nominal baseline has no hyperparameters."""


@dataclass(frozen=True)
class OracleConfig:
    """The oracle has no hyperparameters."""


def point_result(method: str, estimate, n_tasks: int, t0: float, extras: dict | None = None) -> PosteriorResult:
    """A point estimate as a `PosteriorResult`: one sample, no weights, no simulations."""
    est = estimate.numpy() if hasattr(estimate, "numpy") else estimate
    return PosteriorResult(method, est[None, :], None, est, 0, time.perf_counter() - t0, n_tasks,
                           extras=dict(extras or {}))


def run_nominal(task, observations, *, budget: int, seed: int, config: NominalConfig | None = None):
    """The run contract: the full range of motion (``budget`` and ``seed`` unused)."""
    t0 = time.perf_counter()
    _, _, _, observations, prior = check_run_args(task, observations, budget, seed, config, NominalConfig)
    return point_result("nominal", prior.outer_theta(), len(observations), t0)


def run_oracle(task, observations, *, budget: int, seed: int, config: OracleConfig | None = None):
    """The run contract: the true limits (ValueError naming the method on recorded data)."""
    t0 = time.perf_counter()
    _, _, _, observations, _ = check_run_args(task, observations, budget, seed, config, OracleConfig)
    return point_result("oracle", task.require_truth("method 'oracle'").clone(), len(observations), t0)


def _sequence(run):
    def run_sequence(task, observations, *, budget: int, seed: int, config=None):
        """Yield the (constant) result after each observed task."""
        for k in range(len(observations)):
            yield run(task, observations[: k + 1], budget=budget, seed=seed, config=config)
    return run_sequence


sequence_nominal = _sequence(run_nominal)
sequence_oracle = _sequence(run_oracle)
