"""Gaussian kernel density estimation with a diagonal bandwidth (CAMO Eq. 3-4).

    P(theta) = 1/|Q| sum_{q in Q} N(theta; q, H),   H = diag(h)

Kernel sums are computed as matrix products (``|x|^2 + |y|^2 - 2 x.y``) in float64,
chunked over queries, and reduced with logsumexp, so evaluating m kernels at N points
costs one (N, d) @ (d, m) product.

Note: the paper's Eq. 4 prints the constant as ``2 pi``; a normalised Gaussian kernel
has ``(2 pi)^(-d/2)``. With one bandwidth shared by all tasks the constant does not
change the argmax; with per-task bandwidths (``"scott"``) the normalised form matters,
so it is used throughout.
"""

from __future__ import annotations

import math

import torch

from camo_sbi._validation import as_tensor, check_finite

__all__ = ["GaussianKDE", "scott_bandwidth"]

_CHUNK = 4096


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
        self._scaled = pts * self._inv_sd  # (m, d)
        self._sq = (self._scaled**2).sum(dim=1)  # (m,)
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
        out = torch.empty(x.shape[0], dtype=torch.float64)
        for i in range(0, x.shape[0], _CHUNK):
            xs = x[i : i + _CHUNK] * self._inv_sd
            d2 = (xs**2).sum(dim=1, keepdim=True) + self._sq - 2.0 * (xs @ self._scaled.T)
            out[i : i + _CHUNK] = torch.logsumexp(-0.5 * d2.clamp_min(0.0), dim=1)
        return out + self._log_norm
