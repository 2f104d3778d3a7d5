"""Scoring one method's result on a task's held-out reaches: the rows every experiment writes.

The true held-out trajectories and every prediction go through the same function
(`camo_sbi.task.predict`), so the oracle (the true limits) scores exactly 0 on every
prediction metric: a check of the pipeline that runs in every synthetic experiment.
"""

from __future__ import annotations

import numpy as np
import torch

from camo_sbi.evaluation.metrics import (
    cartesian_error_mm,
    limit_errors,
    prediction_metrics,
    reachability_metrics,
)
from camo_sbi.inference.result import PosteriorResult
from camo_sbi.simulators.base import Trajectories
from camo_sbi.task import Task, contain, predict

__all__ = ["PPC_DRAWS", "evaluate_result", "posterior_predictive", "predictive_trajectories",
           "true_test_trajectories"]

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


def posterior_predictive(task: Task, result: PosteriorResult, true_test: Trajectories,
                         n_draws: int = PPC_DRAWS) -> dict[str, float]:
    """Posterior-predictive scores from ``n_draws`` systematic-resampled posterior draws.

    ``ppc_cartesian_error_mm``: the expected `cartesian_error_mm` of a prediction drawn from
    the posterior (mean over draws and reaches). ``pp_mean_cartesian_error_mm``: the error of
    the posterior-predictive mean path (at each step the mean over draws of the predicted
    end-effector position, each draw holding its final point). Draws are deterministic
    (`PosteriorResult.systematic`), so these numbers never change between evaluations.
    """
    draws = result.systematic(n_draws)
    m = task.test_goals.shape[0]
    pred = predictive_trajectories(task.simulator, draws, task.test_starts, task.test_goals)
    ref = Trajectories(true_test.q.repeat(n_draws, 1, 1), true_test.ee.repeat(n_draws, 1, 1),
                       true_test.length.repeat(n_draws), true_test.reached.repeat(n_draws))
    ppc = float(cartesian_error_mm(ref, pred).mean())
    T = pred.ee.shape[1]
    mean_ee = pred.ee.to(torch.float64).reshape(n_draws, m, T, 3).mean(dim=0)
    mean_len = pred.length.reshape(n_draws, m).amax(dim=0)
    mean_path = Trajectories(true_test.q, mean_ee, mean_len, true_test.reached)
    return {"ppc_cartesian_error_mm": ppc,
            "pp_mean_cartesian_error_mm": float(cartesian_error_mm(true_test, mean_path).mean())}


def evaluate_result(task: Task, result: PosteriorResult, true_test: Trajectories | None,
                    binding: np.ndarray | None = None, *, posterior_predictive_draws: int | None = None,
                    reachability: bool = False) -> dict[str, float]:
    """Every metric of one result: prediction metrics on the held-out reaches (when the
    task has them), limit errors (when it has the truth) and, for a posterior with
    ``posterior_predictive_draws``, the posterior-predictive scores; with ``reachability``
    the predicted reached/not-reached labels scored against the true ones."""
    out: dict[str, float] = {}
    if true_test is not None:
        pred = predict(task.simulator, result.estimate, task.test_starts, task.test_goals)
        out.update(prediction_metrics(true_test, pred))
        if reachability:
            out.update(reachability_metrics(true_test, pred))
        if posterior_predictive_draws and result.samples.shape[0] > 1:
            out.update(posterior_predictive(task, result, true_test, posterior_predictive_draws))
    if task.true_theta is not None:
        out.update(limit_errors(result.estimate, task.true_theta, task.prior, binding))
    return out
