"""`PosteriorResult`: the one type every inference method returns."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["PosteriorResult", "weighted_median"]


@dataclass(frozen=True)
class PosteriorResult:
    """Outcome of ``run(task, observations, budget=..., seed=..., config=...)``.

    Attributes:
        method: registry name of the method ("camo", "naive", "abc-smc", "npe", ...).
        samples: (N, 2n) float64 posterior samples laid out [lo_1, hi_1, ..., lo_n, hi_n].
        weights: (N,) non-negative weights summing to 1, or None for equally weighted draws.
        estimate: (2n,) float64 point estimate (CAMO: the argmax of the joint density).
        n_simulations: simulations actually consumed, as counted by the budget wrapper.
        wall_time: seconds spent in ``run``.
        n_tasks: number of observed tasks the posterior conditions on.
        extras: method-specific data (e.g. per-task acceptance counts, epsilons).
    """

    method: str
    samples: np.ndarray
    weights: np.ndarray | None
    estimate: np.ndarray
    n_simulations: int
    wall_time: float
    n_tasks: int
    extras: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        s = np.asarray(self.samples, dtype=np.float64)
        if s.ndim != 2 or s.shape[1] % 2:
            raise ValueError(f"samples: expected shape (N, 2n), got {s.shape}")
        object.__setattr__(self, "samples", s)
        e = np.asarray(self.estimate, dtype=np.float64)
        if e.shape != (s.shape[1],):
            raise ValueError(f"estimate: expected shape ({s.shape[1]},), got {e.shape}")
        object.__setattr__(self, "estimate", e)
        if self.weights is not None:
            w = np.asarray(self.weights, dtype=np.float64)
            if w.shape != (s.shape[0],):
                raise ValueError(f"weights: expected shape ({s.shape[0]},), got {w.shape}")
            if not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
                raise ValueError("weights: must be finite, non-negative and not all zero")
            object.__setattr__(self, "weights", w / w.sum())

    @property
    def n_joints(self) -> int:
        return self.samples.shape[1] // 2

    def normalized_weights(self) -> np.ndarray:
        """(N,) weights summing to one (uniform when ``weights`` is None)."""
        if self.weights is None:
            return np.full(self.samples.shape[0], 1.0 / self.samples.shape[0])
        return self.weights

    def mean(self) -> np.ndarray:
        """(2n,) weighted posterior mean."""
        return self.normalized_weights() @ self.samples

    def resample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, 2n) equally weighted draws (multinomial resampling by ``weights``)."""
        idx = rng.choice(self.samples.shape[0], size=n, replace=True, p=self.normalized_weights())
        return self.samples[idx]


def weighted_median(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Coordinate-wise weighted median of ``x`` (N, D) with weights ``w`` (N,) -> (D,)."""
    out = np.empty(x.shape[1])
    for j in range(x.shape[1]):
        order = np.argsort(x[:, j], kind="stable")
        cw = np.cumsum(w[order])
        out[j] = x[order[np.searchsorted(cw, 0.5 * cw[-1])], j]
    return out
