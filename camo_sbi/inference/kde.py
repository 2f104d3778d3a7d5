"""Gaussian kernel density estimation with a diagonal bandwidth (CAMO Eq. 3-4).

    P(theta) = 1/|Q| sum_{q in Q} N(theta; q, H),   H = diag(h)

Kernel sums run in one numba loop per query point (parallel over queries): squared
scaled differences accumulated directly in float64 (no precision lost to the
``|x|^2 + |y|^2 - 2 x.y`` expansion) into one (m,) row per query, then a max-shifted
logsumexp, so evaluating m kernels at N points makes no (N, m) temporaries. The centres
are stored transposed (d, m) so the inner loop vectorises without reordering any sum
(against the earlier one-pass online logsumexp: ``benchmarks/bench_kde.py``).

Note: the paper's Eq. 4 prints the constant as ``2 pi``; a normalised Gaussian kernel
has ``(2 pi)^(-d/2)``. With one bandwidth shared by all tasks the constant does not
change the argmax; with per-task bandwidths (``"scott"``) the normalised form matters,
so it is used throughout.
"""

from __future__ import annotations

import math
import sys

import numba
import numpy as np
import torch

from camo_sbi._validation import as_tensor, check_finite
from camo_sbi.inference.distances.numba_cache import use_private_cache

__all__ = ["GaussianKDE", "scott_bandwidth"]



@numba.njit(parallel=True, cache=True)
def _log_kernel_sums(xs, ps_t, out):  # pragma: no cover - compiled
    """out[i] = log sum_j exp(-0.5 |xs[i] - ps[j]|^2) (inputs already scaled by 1/sqrt(h)).

    xs: (n, d) queries; ps_t: (d, m) the kernel centres, transposed so the innermost loop
    runs over centres (independent lanes, so it vectorises without reassociating any sum:
    each squared distance is still accumulated over k = 0..d-1 in order). Two passes per
    query: the squared distances and their minimum, then the shifted exponential sum.
    """
    n, d = xs.shape
    m = ps_t.shape[1]
    for i in numba.prange(n):
        d2 = np.zeros(m)
        for k in range(d):
            xk = xs[i, k]
            for j in range(m):
                t = xk - ps_t[k, j]
                d2[j] += t * t
        best = np.inf
        for j in range(m):
            if d2[j] < best:
                best = d2[j]
        acc = 0.0
        for j in range(m):
            acc += math.exp(-0.5 * (d2[j] - best))
        out[i] = -0.5 * best + math.log(acc)


use_private_cache([sys.modules[__name__]])  # numba's cache in a private directory, never the package


def scott_bandwidth(points: torch.Tensor, *, floor: float = 1e-6) -> torch.Tensor:
    """(d,) per-dimension kernel variances by Scott's rule: (sigma_d * m^(-1/(d+4)))^2.

    points: (m, d). Dimensions with zero spread get ``floor``.
    """
    m, d = points.shape
    sd = points.std(dim=0, unbiased=True) if m > 1 else torch.zeros(d, dtype=points.dtype)
    h = (sd * m ** (-1.0 / (d + 4))) ** 2
    return torch.clamp(h, min=floor)


class GaussianKDE:
    """Gaussian KDE over ``points`` (m, d) with kernel variances ``bandwidth`` (d,) or scalar."""

    def __init__(self, points, bandwidth):
        pts = as_tensor(points, "points", dtype=torch.float64).cpu()
        if pts.dim() != 2 or pts.shape[0] < 1:
            raise ValueError(f"points: expected shape (m >= 1, d), got {tuple(pts.shape)}")
        check_finite(pts, "points")
        h = as_tensor(bandwidth, "bandwidth", dtype=torch.float64).cpu().reshape(-1)
        if h.numel() == 1:
            h = h.expand(pts.shape[1]).clone()
        if h.shape != (pts.shape[1],):
            raise ValueError(f"bandwidth: expected a scalar or shape ({pts.shape[1]},), got {tuple(h.shape)}")
        if not bool(torch.isfinite(h).all()) or bool((h <= 0).any()):
            raise ValueError("bandwidth: kernel variances must be finite and > 0")
        self.points, self.bandwidth = pts, h
        self._inv_sd = h.rsqrt()
        self._scaled_t = np.ascontiguousarray((pts * self._inv_sd).numpy().T)  # (d, m)
        d = pts.shape[1]
        self._log_norm = -math.log(pts.shape[0]) - 0.5 * (d * math.log(2 * math.pi) + float(torch.log(h).sum()))

    @property
    def dim(self) -> int:
        return self.points.shape[1]

    def log_density(self, x) -> torch.Tensor:
        """x: (N, d) -> (N,) float64 log P(x)."""
        x = as_tensor(x, "x", dtype=torch.float64).cpu()
        if x.dim() != 2 or x.shape[1] != self.dim:
            raise ValueError(f"x: expected shape (N, {self.dim}), got {tuple(x.shape)}")
        xs = np.ascontiguousarray((x * self._inv_sd).numpy())
        out = np.empty(x.shape[0], dtype=np.float64)
        _log_kernel_sums(xs, self._scaled_t, out)
        return torch.from_numpy(out) + self._log_norm
