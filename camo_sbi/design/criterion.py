"""The design criterion: how much a reach to each candidate goal would tell about the limits.

Given K equally weighted posterior draws theta_k (resampled from a `PosteriorResult` with
``seed``) and a candidate goal g, every draw is simulated reaching g from the next reach's
start. Its outcome y_k is the predicted end point, with a draw that reaches the goal put at
the goal (a reached goal says "reached"; where inside the controller's tolerance it stopped
is not used), so y separates draws by whether and where a limit stops the reach. The end
point is observed with resolution ``sigma`` (``resolution_mm``: the observation noise, or at
least `MIN_RESOLUTION_MM`). Two criteria:

* ``"variance"`` (the default): the expected reduction of the posterior variance of the
  limits, ``sum_d Var(theta_d) - E_y[sum_d Var(theta_d | y)]`` (rad^2), in its linear-Gaussian
  (ensemble Kalman) form ``tr(C_ty (C_yy + sigma^2 I)^-1 C_yt)`` with the draws' covariances.
  Chosen because it is what the toolkit is judged on, the error of the limits in their own
  unit, and because a 3-number outcome can only explain the part of the limits' spread that
  it co-varies with: with K discrete draws, the exact plug-in update would "identify" a whole
  draw (all 2n limits) from any outcome that differs between draws, and every goal a
  restriction touches would tie at the whole variance.
* ``"eig"``: the expected information gain on the outcome in the BALD / disagreement form,
  ``-E_k log E_j L_kj`` with ``L_kj = exp(-|y_k - y_j|^2 / (2 sigma^2))`` (nats; the pairwise
  estimate of the mutual information between outcome and theta for a deterministic
  simulator). It is at most log K and saturates there on every goal that tells all K draws
  apart.

A goal that every draw reaches (well inside every draw's limits) scores ~0 under both. The
cost is K simulations per candidate, counted by a `CountingSimulator` capped at ``budget``
(reported as ``n_simulations``: design simulations, apart from the method's). Only posterior
draws and the simulator are used, so any registered method that returns draws can drive it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from camo_sbi._validation import (
    as_tensor,
    check_choice,
    check_finite,
    check_positive_float,
    check_positive_int,
    numpy_generator,
)
from camo_sbi.budget import CountingSimulator
from camo_sbi.inference.result import PosteriorResult
from camo_sbi.task import Task, contain

__all__ = ["CRITERIA", "DesignInfo", "next_goal", "rank_goals"]

CRITERIA = ("variance", "eig")
MIN_RESOLUTION_MM = 1.0
"""The default resolution's floor: an end point is not resolved finer than this (mm)."""
NEGLIGIBLE = 1e-3
"""A best score below this share of the criterion's ceiling (the draws' whole variance; log K
nats) separates nothing: the ranking is then a fallback."""


@dataclass(frozen=True)
class DesignInfo:
    """Every candidate ranked by the criterion, best first.

    Attributes:
        goals: (C, 3) float64 candidate goals, best first (model's base frame, metres).
        scores: (C,) the criterion per goal, best first (rad^2 for "variance", nats for "eig").
        index: (C,) each ranked goal's row in the ``candidates`` given.
        criterion: "variance" or "eig".  method: the method whose draws were used.
        n_draws: posterior draws simulated per candidate.
        n_simulations: design simulations, counted (C x n_draws).
        resolution_mm: the end-point resolution sigma of the likelihood.
        wall_time: seconds spent ranking.
        status: "ok", or "fallback: <reason>" when no candidate separates the draws (every
            score below `NEGLIGIBLE` of the criterion's ceiling).
    """

    goals: np.ndarray
    scores: np.ndarray
    index: np.ndarray
    criterion: str
    method: str
    n_draws: int
    n_simulations: int
    resolution_mm: float
    wall_time: float
    status: str = "ok"

    @property
    def best(self) -> np.ndarray:
        return self.goals[0]


def _draws(result: PosteriorResult, k: int, seed) -> np.ndarray:
    if not isinstance(result, PosteriorResult):
        raise TypeError(f"result: expected a PosteriorResult, got {type(result).__name__}")
    if np.unique(result.samples, axis=0).shape[0] < 2:
        raise ValueError(f"result: method {result.method!r} returned a single limit vector; active design needs "
                         "posterior draws (a method whose capabilities say posterior=True)")
    return result.resample(k, numpy_generator(seed))


def _scores(theta: np.ndarray, y: np.ndarray, sigma: float, criterion: str) -> np.ndarray:
    """(m,) scores of m candidates from K draws theta (K, D) and their outcomes y (m, K, 3)."""
    k = theta.shape[0]
    if criterion == "eig":
        sq = (y * y).sum(-1)
        d2 = np.maximum(sq[:, :, None] + sq[:, None, :] - 2.0 * y @ y.transpose(0, 2, 1), 0.0)  # (m, K, K)
        return np.maximum(-np.log(np.exp(-d2 / (2.0 * sigma * sigma)).mean(axis=2)).mean(axis=1), 0.0)
    tc = theta - theta.mean(axis=0)
    yc = y - y.mean(axis=1, keepdims=True)
    c_ty = np.einsum("kd,mke->mde", tc, yc) / (k - 1)  # (m, D, 3)
    c_yy = np.einsum("mke,mkf->mef", yc, yc) / (k - 1) + sigma * sigma * np.eye(3)
    gain = np.linalg.solve(c_yy, c_ty.transpose(0, 2, 1))  # (m, 3, D)
    return np.maximum(np.einsum("mde,med->m", c_ty, gain), 0.0)


def rank_goals(task: Task, result: PosteriorResult, candidates, *, seed, budget: int, start=None,
               criterion: str = "variance", resolution_mm: float | None = None, max_draws: int = 200) -> DesignInfo:
    """Rank ``candidates`` (C, 3) goals by what a reach to each would tell about the limits.

    Args:
        task: the task so far (its simulator, prior, noise and observations).
        result: a method's current `PosteriorResult` on ``task`` (posterior draws needed).
        candidates: (C, 3) goals in the model's base frame (e.g. `nominal_workspace_goals`).
        seed: int or numpy Generator for resampling the draws (same seed, same ranking).
        budget: design simulations allowed; ``min(max_draws, budget // C)`` draws are
            simulated per candidate (at least 2).
        start: (n,) the next reach's start (default: the last observed reach's start, or the
            simulator's start posture).
        criterion: "variance" (default) or "eig" (see the module docstring).
        resolution_mm: sigma of the end-point likelihood (default: the task's end-effector
            noise, at least `MIN_RESOLUTION_MM`).
        max_draws: most draws per candidate.
    """
    t0 = time.perf_counter()
    if not isinstance(task, Task):
        raise TypeError(f"task: expected a Task, got {type(task).__name__}")
    criterion = check_choice(criterion, CRITERIA, "criterion")
    budget = check_positive_int(budget, "budget")
    max_draws = check_positive_int(max_draws, "max_draws", minimum=2)
    cand = check_finite(as_tensor(candidates, "candidates", dtype=torch.float64), "candidates")
    if cand.dim() != 2 or cand.shape[1] != 3 or cand.shape[0] < 1:
        raise ValueError(f"candidates: expected shape (C >= 1, 3), got {tuple(cand.shape)}")
    c = cand.shape[0]
    k = min(max_draws, budget // c)
    if k < 2:
        raise ValueError(f"budget: {budget} simulations allow fewer than 2 posterior draws for each of {c} "
                         f"candidates; give at least {2 * c}")
    if resolution_mm is None:
        resolution_mm = max(task.noise.ee_mm, MIN_RESOLUTION_MM)
    resolution_mm = check_positive_float(resolution_mm, "resolution_mm")
    n = task.n_joints
    if result.n_joints != n:
        raise ValueError(f"result: has {result.n_joints} joints, the task has {n}")
    if start is None:
        start = task.observations[-1].start if task.observations else task.simulator.start
    start = as_tensor(start, "start", dtype=torch.float64)
    if start.shape != (n,):
        raise ValueError(f"start: expected shape ({n},), got {tuple(start.shape)}")
    theta = contain(task.prior.with_known(torch.from_numpy(_draws(result, k, seed))), start)  # (K, 2n)
    counter = CountingSimulator(task.simulator, budget)
    scores = np.empty(c)
    th = theta.numpy()
    # one simulate call per candidate: batching several candidates per call was measured well
    # below the 2x over this loop that would pay for it (benchmarks/bench_design.py, issue 38),
    # so the plain loop is kept
    for i in range(c):
        goals = cand[i].expand(k, 3)
        traj = counter.simulate(theta, goals, start)
        end = torch.where(traj.reached.unsqueeze(-1), goals, traj.ee[:, -1].to(torch.float64))
        scores[i] = _scores(th, end.numpy()[None], resolution_mm / 1000.0, criterion)[0]
    cn = cand.numpy()
    order = np.lexsort((cn[:, 2], cn[:, 1], cn[:, 0], -scores))  # ties by the goal's coordinates: order-free
    status = "ok"
    ceiling = th.var(axis=0, ddof=1).sum() if criterion == "variance" else np.log(k)
    if not scores.max() > NEGLIGIBLE * ceiling:
        status = ("fallback: no candidate separates the posterior draws (every score is ~0); "
                  "the best-scored candidate is kept, chosen by next to nothing")
    return DesignInfo(goals=cn[order].copy(), scores=scores[order], index=order, criterion=criterion,
                      method=result.method, n_draws=k, n_simulations=counter.n_simulations,
                      resolution_mm=float(resolution_mm), wall_time=time.perf_counter() - t0, status=status)


def next_goal(task: Task, result: PosteriorResult, candidates, *, seed, budget: int,
              **kwargs) -> tuple[torch.Tensor, DesignInfo]:
    """The best of ``candidates`` (a (3,) float64 tensor) and the full ranking (`rank_goals`)."""
    info = rank_goals(task, result, candidates, seed=seed, budget=budget, **kwargs)
    return torch.from_numpy(info.goals[0].copy()), info
