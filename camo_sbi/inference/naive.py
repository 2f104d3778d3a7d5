"""The paper's naive baseline: per joint, the minimum and maximum observed joint value."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from camo_sbi.inference.result import PosteriorResult

__all__ = ["NaiveConfig", "naive_limits", "run", "run_sequence"]


@dataclass(frozen=True)
class NaiveConfig:
    """The naive baseline has no hyperparameters; it needs joint-space observations."""


def naive_limits(joint_trajectories) -> np.ndarray:
    """(2n,) [min_1, max_1, ...] over every observed joint trajectory ((L_i, n) each)."""
    qs = [torch.as_tensor(q, dtype=torch.float64) for q in joint_trajectories]
    if not qs:
        raise ValueError("joint_trajectories: at least one trajectory is required")
    n = qs[0].shape[-1]
    if any(q.dim() != 2 or q.shape[1] != n for q in qs):
        raise ValueError(f"joint_trajectories: every trajectory must have shape (L, {n})")
    allq = torch.cat(qs)
    return torch.stack([allq.min(dim=0).values, allq.max(dim=0).values], dim=1).reshape(-1).numpy()


def _result(observations, t0: float) -> PosteriorResult:
    est = naive_limits([o.q for o in observations])
    return PosteriorResult("naive", est[None, :], None, est, 0, time.perf_counter() - t0, len(observations))


def run_sequence(task, observations, *, budget: int, seed: int, config: NaiveConfig):
    """Yield the result after each observed task (no simulation)."""
    t0 = time.perf_counter()
    for k in range(len(observations)):
        yield _result(observations[: k + 1], t0)


def run(task, observations, *, budget: int, seed: int, config: NaiveConfig) -> PosteriorResult:
    """The run contract: min/max of the observed joint values (``budget`` and ``seed`` unused)."""
    return _result(observations, time.perf_counter())
