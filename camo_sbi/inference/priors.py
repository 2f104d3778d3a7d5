"""Priors over joint limits: a box split at the observed start posture.

The start posture ``s`` is observed, so every plausible limit vector satisfies
``lo_i <= s_i <= hi_i``. With full range of motion ``[L_i, U_i]`` the prior is the
product of independent uniforms::

    lo_i ~ U[L_i, s_i],   hi_i ~ U[s_i, U_i]

which is a box in theta space: ``lo < hi`` holds by construction, and the box
converts exactly to pyabc's / sbi's independent uniforms. A "strong prior" fixes
some joints' limits to known values (those coordinates have zero width and are
excluded from the free parameters that ABC-SMC and NPE see).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch
from scipy.stats import qmc

from camo_sbi._validation import as_tensor, check_finite, check_positive_int, numpy_generator

__all__ = ["BoxPrior"]

_SAMPLING = ("uniform", "lhs")


class BoxPrior:
    """Independent uniform prior over theta = [lo_1, hi_1, ..., lo_n, hi_n].

    Args:
        bounds: (n, 2) full range of motion [L_i, U_i] in radians.
        start: (n,) observed start posture, L_i <= s_i <= U_i; None -> midpoint of bounds.
        fixed: optional {joint index: (lo, hi)} of known limits (strong prior).
        sampling: "uniform" (i.i.d.) or "lhs" (scipy Latin hypercube).
    """

    def __init__(self, bounds, start=None, *, fixed: Mapping[int, tuple[float, float]] | None = None,
                 sampling: str = "uniform"):
        b = as_tensor(bounds, "bounds", dtype=torch.float64).cpu()
        if b.dim() != 2 or b.shape[1] != 2:
            raise ValueError(f"bounds: expected shape (n, 2), got {tuple(b.shape)}")
        check_finite(b, "bounds")
        if bool((b[:, 0] >= b[:, 1]).any()):
            raise ValueError("bounds: every joint needs lower < upper")
        n = b.shape[0]
        s = b.mean(dim=1) if start is None else as_tensor(start, "start", dtype=torch.float64).cpu()
        if s.shape != (n,):
            raise ValueError(f"start: expected shape ({n},), got {tuple(s.shape)}")
        check_finite(s, "start")
        if bool(((s < b[:, 0]) | (s > b[:, 1])).any()):
            raise ValueError("start: posture lies outside bounds")
        if sampling not in _SAMPLING:
            raise ValueError(f"sampling: expected one of {_SAMPLING}, got {sampling!r}")
        low = torch.empty(2 * n, dtype=torch.float64)
        high = torch.empty(2 * n, dtype=torch.float64)
        low[0::2], high[0::2] = b[:, 0], s
        low[1::2], high[1::2] = s, b[:, 1]
        if fixed is not None and not isinstance(fixed, Mapping):
            raise TypeError(f"fixed: expected a mapping {{joint index: (lo, hi)}}, got {type(fixed).__name__}")
        fixed = dict(fixed or {})
        for j, pair in fixed.items():
            if isinstance(j, bool) or not isinstance(j, (int, np.integer)) or not 0 <= j < n:
                raise ValueError(f"fixed: joint index {j!r} out of range 0..{n - 1}")
            try:
                lo, hi = (float(v) for v in pair)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"fixed: joint {j} needs a pair of numbers (lo, hi), got {pair!r}") from exc
            if not (np.isfinite(lo) and np.isfinite(hi)):
                raise ValueError(f"fixed: joint {j} limits must be finite")
            if not (b[j, 0] <= lo <= s[j] <= hi <= b[j, 1]):
                raise ValueError(
                    f"fixed: joint {j} limits ({lo:.4g}, {hi:.4g}) must satisfy "
                    f"bound_lo <= lo <= start <= hi <= bound_hi"
                )
            low[2 * j] = high[2 * j] = lo
            low[2 * j + 1] = high[2 * j + 1] = hi
        self.bounds, self.start, self.fixed, self.sampling = b, s, fixed, sampling
        self.low, self.high = low, high
        self.free_mask = high > low

    @property
    def n_joints(self) -> int:
        return self.bounds.shape[0]

    @property
    def dim(self) -> int:
        """Number of theta coordinates (2n)."""
        return self.low.shape[0]

    @property
    def n_free(self) -> int:
        return int(self.free_mask.sum())

    def with_sampling(self, sampling: str) -> BoxPrior:
        """The same box with another sampling scheme."""
        return BoxPrior(self.bounds, self.start, fixed=self.fixed, sampling=sampling)

    def sample(self, n: int, seed) -> torch.Tensor:
        """(n, 2n) float64 draws; ``seed``: int or numpy Generator. Fixed coordinates are constant."""
        n = check_positive_int(n, "n")
        rng = numpy_generator(seed)
        k = self.n_free
        if self.sampling == "lhs" and k > 0:
            u = qmc.LatinHypercube(d=k, seed=rng).random(n)
        else:
            u = rng.random((n, k))
        theta = self.low.repeat(n, 1)
        lo, hi = self.low[self.free_mask], self.high[self.free_mask]
        theta[:, self.free_mask] = lo + torch.from_numpy(u) * (hi - lo)
        return theta

    def contains(self, theta) -> torch.Tensor:
        """(B,) bool: inside the box (fixed coordinates equal to their value within 1e-9)."""
        t = as_tensor(theta, "theta", dtype=torch.float64).cpu()
        t = t.unsqueeze(0) if t.dim() == 1 else t
        if t.shape[-1] != self.dim:
            raise ValueError(f"theta: expected last dimension {self.dim}, got {t.shape[-1]}")
        return ((t >= self.low - 1e-9) & (t <= self.high + 1e-9)).all(dim=-1)

    def log_prob(self, theta) -> torch.Tensor:
        """(B,) log density over the free coordinates (-inf outside the box)."""
        inside = self.contains(theta)
        width = (self.high - self.low)[self.free_mask]
        lp = torch.full(inside.shape, float(-torch.log(width).sum()), dtype=torch.float64)
        lp[~inside] = -float("inf")
        return lp

    def free(self, theta) -> torch.Tensor:
        """(B, 2n) -> (B, n_free): the coordinates that are not fixed."""
        t = as_tensor(theta, "theta", dtype=torch.float64)
        if t.shape[-1] != self.dim:
            raise ValueError(f"theta: expected last dimension {self.dim}, got {t.shape[-1]}")
        return t[..., self.free_mask.to(t.device)]

    def expand(self, free_theta) -> torch.Tensor:
        """(B, n_free) -> (B, 2n), filling fixed coordinates with their known values."""
        f = as_tensor(free_theta, "free_theta", dtype=torch.float64).cpu()
        f = f.unsqueeze(0) if f.dim() == 1 else f
        if f.shape[-1] != self.n_free:
            raise ValueError(f"free_theta: expected last dimension {self.n_free}, got {f.shape[-1]}")
        theta = self.low.repeat(f.shape[0], 1)
        theta[:, self.free_mask] = f
        return theta

    def __repr__(self) -> str:
        return f"BoxPrior(n_joints={self.n_joints}, free={self.n_free}/{self.dim}, sampling={self.sampling!r})"
