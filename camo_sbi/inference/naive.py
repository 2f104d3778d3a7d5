"""The paper's naive baseline: per joint, the minimum and maximum observed joint value.

Known (fixed) joints of a strong prior take their known limits, as every method does.
The start posture is part of each reach (its first row), so the estimate contains it.

Noise rule: with joint-space observation noise (``task.noise.joint_deg > 0``), each
reach's joint trajectory is median-filtered over 3 consecutive samples (the end points over
the 2 they have) before the min/max, so no single outlying sample can set a limit; a real
excursion lasts at least 2 samples and survives the filter. Without noise nothing is filtered.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from camo_sbi.inference.baselines import point_result
from camo_sbi.inference.contract import check_run_args

__all__ = ["NaiveConfig", "median3", "naive_limits", "run", "run_sequence"]


@dataclass(frozen=True)
class NaiveConfig:
    """The naive baseline has no hyperparameters; it needs joint-space observations."""


def naive_limits(joint_trajectories) -> np.ndarray:
    """(2n,) [min_1, max_1, ...] over every observed joint trajectory ((L_i, n) each)."""
    qs = [torch.as_tensor(q, dtype=torch.float64) for q in joint_trajectories]
    if not qs:
        raise ValueError("joint_trajectories: at least one trajectory is required")
    n = qs[0].shape[-1]
    if any(q.dim() != 2 or q.shape[1] != n or q.shape[0] < 1 for q in qs):
        raise ValueError(f"joint_trajectories: every trajectory must have shape (L >= 1, {n})")
    allq = torch.cat(qs)
    if not bool(torch.isfinite(allq).all()):
        raise ValueError("joint_trajectories: contains NaN or inf values")
    return torch.stack([allq.min(dim=0).values, allq.max(dim=0).values], dim=1).reshape(-1).numpy()


def median3(q: torch.Tensor) -> torch.Tensor:
    """(L, n) -> (L, n): the median of each sample and its neighbours (2 at the ends; L < 3 as is)."""
    if q.shape[0] < 3:
        return q
    mid = torch.stack([q[:-2], q[1:-1], q[2:]]).median(dim=0).values
    ends = [torch.stack([q[:2]]).mean(dim=1), torch.stack([q[-2:]]).mean(dim=1)]  # median of 2 = their mean
    return torch.cat([ends[0], mid, ends[1]])


def _estimate(task, prior, observations) -> np.ndarray:
    qs = [o.q for o in observations]
    if task.noise.joint_deg > 0:
        qs = [median3(q) for q in qs]
    return prior.with_known(torch.from_numpy(naive_limits(qs))).numpy()


def run_sequence(task, observations, *, budget: int, seed: int, config: NaiveConfig | None = None):
    """Yield the result after each observed task (no simulation)."""
    t0 = time.perf_counter()
    _, _, _, observations, prior = check_run_args(task, observations, budget, seed, config, NaiveConfig,
                                                  space="joint")
    for k in range(len(observations)):
        yield point_result("naive", _estimate(task, prior, observations[: k + 1]), k + 1, t0)


def run(task, observations, *, budget: int, seed: int, config: NaiveConfig | None = None):
    """The run contract: min/max of the observed joint values (``budget`` and ``seed`` unused)."""
    t0 = time.perf_counter()
    _, _, _, observations, prior = check_run_args(task, observations, budget, seed, config, NaiveConfig,
                                                  space="joint")
    return point_result("naive", _estimate(task, prior, observations), len(observations), t0)
