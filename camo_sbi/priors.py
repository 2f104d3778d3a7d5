"""Priors over joint limits: a box split at the observed start posture.

The start posture ``s`` is observed, so every plausible limit vector satisfies
``lo_i <= s_i <= hi_i``. With full range of motion ``[L_i, U_i]`` the prior is the
product of independent uniforms::

    lo_i ~ U[L_i, s_i],   hi_i ~ U[s_i, U_i]

which is a box in theta space: ``lo < hi`` holds by construction, and the box
converts exactly to pyabc's / sbi's independent uniforms. A "strong prior" fixes
some joints' limits to known values (those coordinates have zero width and are
excluded from the free parameters that ABC-SMC and NPE see).

The same argument holds for every observed posture, not only the start: the
controller clamps to the limits, so a joint-space observation ``q_t`` proves
``lo_i <= q_t,i <= hi_i``. `BoxPrior.containing` returns the box split at the
hull of the start and such postures ``[a_i, b_i]``: ``lo_i ~ U[L_i, a_i]``,
``hi_i ~ U[b_i, U_i]`` (the prior conditioned on that hard evidence).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from camo_sbi._validation import as_tensor, check_finite, check_positive_int, numpy_generator

__all__ = ["BoxPrior"]

_SAMPLING = ("uniform", "lhs", "grid")
GRID_LEVELS = 5
"""Levels per joint of the ``"grid"`` sampling (the authors' code: a 5-level grid per bound)."""


class BoxPrior:
    """Independent uniform prior over theta = [lo_1, hi_1, ..., lo_n, hi_n].

    Args:
        bounds: (n, 2) full range of motion [L_i, U_i] in radians.
        start: (n,) observed start posture, L_i <= s_i <= U_i; None -> midpoint of bounds.
        fixed: optional {joint index: (lo, hi)} of known limits (strong prior).
        sampling: "uniform" (i.i.d.), "lhs" (scipy Latin hypercube) or "grid": each free
            bound drawn uniformly from the ``GRID_LEVELS`` equally spaced values of its joint's
            full range that lie on its side of the split (lower bounds <= the split, upper
            bounds > it; the range's end itself when none does), as the authors' code does;
            the full range's ends are grid values, so a bound at its nominal value can be drawn
            exactly.
        inner: optional (n, 2) [a_i, b_i] with a_i <= s_i <= b_i, postures known to lie
            inside the limits (see `containing`); the split is at it instead of at the start.
    """

    def __init__(self, bounds, start=None, *, fixed: Mapping[int, tuple[float, float]] | None = None,
                 sampling: str = "uniform", inner=None):
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
        if inner is None:
            box = torch.stack([s, s], dim=1)
        else:
            box = as_tensor(inner, "inner", dtype=torch.float64).cpu()
            if box.shape != (n, 2):
                raise ValueError(f"inner: expected shape ({n}, 2), got {tuple(box.shape)}")
            check_finite(box, "inner")
            if bool(((box[:, 0] > s) | (box[:, 1] < s)).any()):
                raise ValueError("inner: every [a_i, b_i] must contain the start posture")
            if bool(((box[:, 0] < b[:, 0]) | (box[:, 1] > b[:, 1])).any()):
                raise ValueError("inner: lies outside bounds")
        low = torch.empty(2 * n, dtype=torch.float64)
        high = torch.empty(2 * n, dtype=torch.float64)
        low[0::2], high[0::2] = b[:, 0], box[:, 0]
        low[1::2], high[1::2] = box[:, 1], b[:, 1]
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
            if not (b[j, 0] <= lo <= box[j, 0] <= box[j, 1] <= hi <= b[j, 1]):
                raise ValueError(
                    f"fixed: joint {j} limits ({lo:.4g}, {hi:.4g}) must satisfy "
                    f"bound_lo <= lo <= start <= hi <= bound_hi"
                    + ("" if inner is None else " and contain the inner box")
                )
            low[2 * j] = high[2 * j] = lo
            low[2 * j + 1] = high[2 * j + 1] = hi
        self.bounds, self.start, self.fixed, self.sampling = b, s, fixed, sampling
        self.inner = box  # (n, 2) postures known to lie inside the limits
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
        return BoxPrior(self.bounds, self.start, fixed=self.fixed, sampling=sampling, inner=self.inner)

    def containing(self, postures, *, tol: float = 1e-5, margin: float = 0.0) -> BoxPrior:
        """The prior conditioned on observed joint-space postures lying inside the limits.

        postures: (L, n) observed joint positions (any number of rows). Returns a new
        `BoxPrior` whose inner box is the hull of the current one and ``postures``, so
        ``lo_i <= min_t q_t,i`` and ``hi_i >= max_t q_t,i`` for every draw. Postures
        beyond a bound or a fixed (known) limit by at most ``tol`` (float32 rounding of a
        clamped simulation, or observation noise) are clipped onto it; farther ones raise
        ValueError. ``margin`` >= 0 (noisy postures: k sigma) shrinks the postures' hull on
        each side first, ``[min q + margin, max q - margin]`` (a joint whose shrunk hull is
        empty adds nothing), so a noisy posture constrains the limits only as far as noise
        cannot explain it.
        """
        q = as_tensor(postures, "postures", dtype=torch.float64).cpu()
        if q.dim() != 2 or q.shape[1] != self.n_joints:
            raise ValueError(f"postures: expected shape (L, {self.n_joints}), got {tuple(q.shape)}")
        check_finite(q, "postures")
        if q.shape[0] == 0:
            return self
        margin = float(margin)
        if not margin >= 0.0:
            raise ValueError(f"margin: must be a finite number >= 0, got {margin}")
        qa, qb = q.min(dim=0).values + margin, q.max(dim=0).values - margin
        empty = qa > qb
        qa, qb = torch.where(empty, self.inner[:, 0], qa), torch.where(empty, self.inner[:, 1], qb)
        a = torch.minimum(self.inner[:, 0], qa)
        b = torch.maximum(self.inner[:, 1], qb)
        outer_lo, outer_hi = self.low[0::2], self.high[1::2]  # bounds or fixed limits
        outside = (a < outer_lo - tol) | (b > outer_hi + tol)
        if bool(outside.any()):
            j = int(torch.nonzero(outside)[0])
            raise ValueError(
                f"postures: joint {j} moves to [{float(a[j]):.6g}, {float(b[j]):.6g}], outside its "
                f"possible limits [{float(outer_lo[j]):.6g}, {float(outer_hi[j]):.6g}]")
        a = torch.maximum(a, outer_lo)
        b = torch.minimum(b, outer_hi)
        return BoxPrior(self.bounds, self.start, fixed=self.fixed, sampling=self.sampling,
                        inner=torch.stack([a, b], dim=1))

    def outer_theta(self) -> torch.Tensor:
        """(2n,) the widest limits the prior allows: the full range of motion, known joints fixed."""
        theta = torch.empty(self.dim, dtype=torch.float64)
        theta[0::2], theta[1::2] = self.low[0::2], self.high[1::2]
        return theta

    def with_known(self, theta) -> torch.Tensor:
        """``theta`` (2n,) or (B, 2n) with the fixed (known) coordinates set to their known values."""
        t = as_tensor(theta, "theta", dtype=torch.float64).clone()
        if t.shape[-1] != self.dim:
            raise ValueError(f"theta: expected last dimension {self.dim}, got {t.shape[-1]}")
        fixed = ~self.free_mask
        t[..., fixed] = self.low[fixed]
        return t

    def sample(self, n: int, seed) -> torch.Tensor:
        """(n, 2n) float64 draws; ``seed``: int or numpy Generator. Fixed coordinates are constant."""
        n = check_positive_int(n, "n")
        rng = numpy_generator(seed)
        k = self.n_free
        if self.sampling == "grid" and k > 0:
            theta = self.low.repeat(n, 1)
            for c in torch.nonzero(self.free_mask).flatten().tolist():
                values = self._grid_values(c)
                theta[:, c] = values[torch.from_numpy(rng.integers(0, values.shape[0], size=n))]
            return theta
        if self.sampling == "lhs" and k > 0:
            from scipy.stats import qmc  # imports all of scipy.stats (~1 s): only for LHS draws

            u = qmc.LatinHypercube(d=k, seed=rng).random(n)
        else:
            u = rng.random((n, k))
        theta = self.low.repeat(n, 1)
        lo, hi = self.low[self.free_mask], self.high[self.free_mask]
        theta[:, self.free_mask] = lo + torch.from_numpy(u) * (hi - lo)
        return theta

    def _grid_values(self, c: int) -> torch.Tensor:
        """The grid values free coordinate ``c`` may take (see ``sampling="grid"``)."""
        j = c // 2
        grid = torch.linspace(float(self.bounds[j, 0]), float(self.bounds[j, 1]), GRID_LEVELS, dtype=torch.float64)
        lo, hi = float(self.low[c]), float(self.high[c])
        if c % 2 == 0:  # a lower bound: grid values in [L, split]
            values = grid[(grid >= lo) & (grid <= hi)]
            return values if values.numel() else torch.tensor([lo], dtype=torch.float64)
        values = grid[(grid > lo) & (grid <= hi)]  # an upper bound: strictly above the split
        return values if values.numel() else torch.tensor([hi], dtype=torch.float64)

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
