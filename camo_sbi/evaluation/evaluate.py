"""Scoring one method's result on a task's held-out reaches: the rows every experiment writes.

`evaluate_result` is the one scorer: every command's rows of a result come from it, one per
metric of `camo_sbi.evaluation.catalog.METRICS` that has a score function and applies (a
`Scoring` holds what the score functions share, computed once).

The true held-out trajectories and every prediction go through the same function
(`camo_sbi.task.predict`), so the oracle (the true limits) scores exactly 0 on every
prediction metric: a check of the pipeline that runs in every synthetic experiment.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
import torch

from camo_sbi.evaluation import catalog, metrics
from camo_sbi.evaluation.metrics import (
    cartesian_error_mm,
    limit_error_groups,
    reachability_metrics,
)
from camo_sbi.inference.result import PosteriorResult, weighted_quantile
from camo_sbi.simulators.base import Trajectories
from camo_sbi.task import Task, contain, predict

__all__ = ["PPC_DRAWS", "PredictivePaths", "Scoring", "coverage90", "evaluate_result", "posterior_predictive",
           "posterior_predictive_paths", "predictive_trajectories", "true_test_trajectories"]

PPC_DRAWS = 64
"""Posterior draws for the posterior-predictive metrics (systematic resampling: deterministic)."""


def true_test_trajectories(task: Task) -> Trajectories:
    """The subject's held-out reaches under its true limits (synthetic tasks only)."""
    truth = task.require_truth("true_test_trajectories")
    if task.test_goals is None:
        raise ValueError("task.test_goals: the task has no held-out goals to evaluate on")
    return predict(task.simulator, truth, task.test_starts, task.test_goals)


def predictive_trajectories(simulator, draws, starts, goals) -> Trajectories:
    """Every draw (S, 2n) on every reach (M goals (M, 3) from starts (M, n)): S * M trajectories,
    draw-major (row ``s * M + i`` is draw s on reach i), each draw widened to contain its start."""
    theta = torch.as_tensor(draws, dtype=torch.float64)
    goals = torch.as_tensor(goals, dtype=torch.float64)
    starts = torch.as_tensor(starts, dtype=torch.float64)
    if theta.dim() != 2 or goals.dim() != 2 or starts.shape[0] != goals.shape[0]:
        raise ValueError(f"draws: expected (S, 2n) draws, (M, 3) goals and (M, n) starts, got "
                         f"{tuple(theta.shape)}, {tuple(goals.shape)}, {tuple(starts.shape)}")
    s, m = theta.shape[0], goals.shape[0]
    reps = starts.repeat(s, 1)
    return simulator.simulate(contain(theta.repeat_interleave(m, 0), reps), goals.repeat(s, 1), reps)


class PredictivePaths(NamedTuple):
    """The posterior-predictive reaches of one result (`posterior_predictive_paths`)."""

    reference: Trajectories
    """the true held-out reaches, repeated once per draw (draw-major)"""
    predicted: Trajectories
    """every draw on every held-out reach (draw-major)"""
    mean_path: Trajectories
    """per held-out reach the mean over draws of the predicted end-effector path"""


def posterior_predictive_paths(task: Task, result: PosteriorResult, true_test: Trajectories,
                               n_draws: int = PPC_DRAWS) -> PredictivePaths:
    """The reaches `posterior_predictive` scores: ``n_draws`` systematic-resampled draws on
    every held-out reach, and the posterior-predictive mean path (at each step the mean over
    draws of the predicted end-effector position, each draw holding its final point)."""
    draws = result.systematic(n_draws)
    m = task.test_goals.shape[0]
    pred = predictive_trajectories(task.simulator, draws, task.test_starts, task.test_goals)
    ref = Trajectories(true_test.q.repeat(n_draws, 1, 1), true_test.ee.repeat(n_draws, 1, 1),
                       true_test.length.repeat(n_draws), true_test.reached.repeat(n_draws))
    T = pred.ee.shape[1]
    mean_ee = pred.ee.to(torch.float64).reshape(n_draws, m, T, 3).mean(dim=0)
    mean_len = pred.length.reshape(n_draws, m).amax(dim=0)
    return PredictivePaths(ref, pred, Trajectories(true_test.q, mean_ee, mean_len, true_test.reached))


def posterior_predictive(task: Task, result: PosteriorResult, true_test: Trajectories,
                         n_draws: int = PPC_DRAWS) -> dict[str, float]:
    """Posterior-predictive scores from ``n_draws`` systematic-resampled posterior draws.

    ``ppc_cartesian_error_mm``: the expected `cartesian_error_mm` of a prediction drawn from
    the posterior (mean over draws and reaches). ``pp_mean_cartesian_error_mm``: the error of
    the posterior-predictive mean path (`posterior_predictive_paths`). Draws are deterministic
    (`PosteriorResult.systematic`), so these numbers never change between evaluations.
    """
    paths = posterior_predictive_paths(task, result, true_test, n_draws)
    return {"ppc_cartesian_error_mm": float(cartesian_error_mm(paths.reference, paths.predicted).mean()),
            "pp_mean_cartesian_error_mm": float(cartesian_error_mm(true_test, paths.mean_path).mean())}


def coverage90(result: PosteriorResult, truth, prior) -> float:
    """Share of the prior's free true limits inside the posterior's 90% central weighted interval
    (a point estimate covers only an exact value)."""
    w = result.normalized_weights()
    lo, hi = weighted_quantile(result.samples, w, [0.05, 0.95])
    t = torch.as_tensor(truth, dtype=torch.float64).numpy()
    free = prior.free_mask.numpy()
    inside = (lo - 1e-12 <= t) & (t <= hi + 1e-12)
    return float(inside[free].mean())


class Scoring:
    """What a metric's score function reads (`camo_sbi.evaluation.catalog`): one result on one
    task, each shared piece (the predicted reaches, the posterior-predictive paths, the limit
    errors) computed once, on first use, whichever metric asks first."""

    def __init__(self, task: Task, result: PosteriorResult, true_test: Trajectories | None,
                 binding: np.ndarray | None = None, *, posterior_predictive_draws: int | None = None,
                 reachability: bool = False, interval_coverage: bool = False):
        self.task, self.result, self.true_test, self.binding = task, result, true_test, binding
        self.posterior_predictive_draws = posterior_predictive_draws
        self.reachability_scored = bool(reachability)
        self.interval_coverage = bool(interval_coverage)

    @functools.cached_property
    def pred(self) -> Trajectories:
        """The estimate's predictions of the held-out reaches."""
        return predict(self.task.simulator, self.result.estimate, self.task.test_starts, self.task.test_goals)

    def trajectory_error(self, name: str):
        """The per-reach values of the metrics module's function ``name`` (e.g.
        ``"cartesian_error_mm"``) on the held-out reaches, or None without them."""
        if self.true_test is None:
            return None
        return getattr(metrics, name)(self.true_test, self.pred)

    @functools.cached_property
    def reachability(self) -> dict[str, float] | None:
        if self.true_test is None or not self.reachability_scored:
            return None
        return reachability_metrics(self.true_test, self.pred)

    @functools.cached_property
    def ppc_paths(self) -> PredictivePaths | None:
        draws = self.posterior_predictive_draws
        if self.true_test is None or not draws or self.result.samples.shape[0] <= 1:
            return None
        return posterior_predictive_paths(self.task, self.result, self.true_test, draws)

    @property
    def ppc_expected_error(self):
        """`cartesian_error_mm` of every posterior draw on every held-out reach, or None."""
        p = self.ppc_paths
        return None if p is None else cartesian_error_mm(p.reference, p.predicted)

    @property
    def ppc_mean_path_error(self):
        """`cartesian_error_mm` of the posterior-predictive mean path per held-out reach, or None."""
        p = self.ppc_paths
        return None if p is None else cartesian_error_mm(self.true_test, p.mean_path)

    @functools.cached_property
    def limit_groups(self) -> dict[str, np.ndarray] | None:
        """The free bounds' absolute errors (degrees) per group of `limit_error_groups`."""
        if self.task.true_theta is None:
            return None
        return limit_error_groups(self.result.estimate, self.task.true_theta, self.task.prior, self.binding)

    @functools.cached_property
    def joint_limit_errors(self) -> dict[str, np.ndarray] | None:
        """Per joint the absolute errors (degrees) of its two bounds (free or not)."""
        if self.task.true_theta is None:
            return None
        err = np.degrees(np.abs(self.result.estimate - self.task.true_theta.numpy()))
        return {name: err[2 * j : 2 * j + 2] for j, name in enumerate(self.task.simulator.joint_names)}

    @functools.cached_property
    def coverage90(self) -> float | None:
        if not self.interval_coverage or self.task.true_theta is None:
            return None
        return coverage90(self.result, self.task.true_theta, self.task.prior)


def evaluate_result(task: Task, result: PosteriorResult, true_test: Trajectories | None,
                    binding: np.ndarray | None = None, *, posterior_predictive_draws: int | None = None,
                    reachability: bool = False, interval_coverage: bool = False) -> dict[str, float]:
    """Every metric of `camo_sbi.evaluation.catalog.METRICS` that has a score and applies, in
    its order: prediction metrics on the held-out reaches (when the task has them), limit
    errors and per-joint limit errors (when it has the truth), for a posterior with
    ``posterior_predictive_draws`` the posterior-predictive scores, with ``reachability``
    the predicted reached/not-reached labels scored against the true ones, with
    ``interval_coverage`` the true limits' coverage by the 90% interval, and the result's
    cost (simulations, times)."""
    if not isinstance(task, Task):
        raise TypeError(f"task: expected a Task, got {type(task).__name__}")
    if not isinstance(result, PosteriorResult):
        raise TypeError(f"result: expected a PosteriorResult, got {type(result).__name__}")
    s = Scoring(task, result, true_test, binding, posterior_predictive_draws=posterior_predictive_draws,
                reachability=reachability, interval_coverage=interval_coverage)
    out: dict[str, float] = {}
    for metric in catalog.METRICS:
        if metric.score is None:
            continue
        value = metric.score(s)
        if value is None:
            continue
        if metric.per_joint:
            out.update({metric.row(joint): metric.reduce(v) for joint, v in value.items()})
        else:
            out[metric.name] = metric.reduce(value)
    return out
