"""Coordinates, summaries and thread settings shared by the flow-based methods (npe, npe-amortized).

- `trajectory_summary`: the fixed-size summary of a padded trajectory both NPE forms condition on.
- `to_unconstrained` / `from_unconstrained`: the flow coordinates z = logit of the position
  inside the prior box (so a flow has no mass outside it), with the log-Jacobian, and
  `logistic_log_prob`, the uniform box prior pushed to z (a standard logistic per coordinate).
- `torch_threads`: torch's intra-op thread count for a block (small flows train and sample
  fastest on one thread), restored afterwards.
"""

from __future__ import annotations

import contextlib

import torch
from torch import nn

from camo_sbi._validation import as_tensor, check_positive_int

__all__ = ["from_unconstrained", "logistic_log_prob", "trajectory_summary", "to_unconstrained", "torch_threads"]

# positions inside the box are clamped to [_U_EPS, 1 - _U_EPS] before the logit
_U_EPS = 1e-6


def trajectory_summary(traj, lengths, *, n_points: int = 20, include_length: bool = True) -> torch.Tensor:
    """Fixed-size summaries of padded trajectories.

    traj: (B, T, D) (steps >= length are padding) or (T, D); lengths: (B,) ints in [1, T]
    (or an int for a single trajectory). Returns (B, n_points * D [+ 1]) float64: the valid
    part linearly resampled at times (L - 1) * j / n_points, j = 1..n_points (the start,
    j = 0, is left out), flattened time-major, then the length L if ``include_length``.
    """
    x = as_tensor(traj, "traj", dtype=torch.float64)
    if x.dim() == 2:
        x = x.unsqueeze(0)
    if x.dim() != 3 or x.shape[1] < 1:
        raise ValueError(f"traj: expected shape (B, T, D), got {tuple(x.shape)}")
    B, T, D = x.shape
    L = torch.as_tensor(lengths).reshape(-1).to(device=x.device)
    if L.is_floating_point() or L.shape[0] != B:
        raise ValueError(f"lengths: expected {B} integer lengths, got {tuple(L.shape)} {L.dtype}")
    if bool(((L < 1) | (L > T)).any()):
        raise ValueError(f"lengths: must lie in [1, {T}]")
    n_points = check_positive_int(n_points, "n_points")
    last = (L - 1).to(torch.float64)
    pos = last[:, None] * (torch.arange(1, n_points + 1, dtype=torch.float64, device=x.device) / n_points)
    i0 = pos.floor().long().clamp(max=T - 1)
    i1 = torch.minimum(i0 + 1, (L - 1)[:, None].long())
    frac = (pos - i0.to(torch.float64)).unsqueeze(-1)
    x0 = torch.gather(x, 1, i0.unsqueeze(-1).expand(-1, -1, D))
    x1 = torch.gather(x, 1, i1.unsqueeze(-1).expand(-1, -1, D))
    feats = (x0 + frac * (x1 - x0)).reshape(B, n_points * D)
    if include_length:
        feats = torch.cat([feats, L.to(torch.float64)[:, None]], dim=1)
    return feats


def to_unconstrained(theta_free: torch.Tensor, lo: torch.Tensor, width: torch.Tensor,
                      transform: str) -> torch.Tensor:
    """Free coordinates (N, d) -> flow coordinates: logit of the position in the box, or as is."""
    theta_free = theta_free.to(torch.float64)
    if transform == "none":
        return theta_free
    return torch.logit(((theta_free - lo) / width).clamp(_U_EPS, 1 - _U_EPS))


def from_unconstrained(z: torch.Tensor, lo: torch.Tensor, width: torch.Tensor,
                       transform: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse of `to_unconstrained`: z (N, d) -> (free coordinates (N, d), log |d theta / d z| (N,))."""
    z = z.to(torch.float64)
    if transform == "none":
        return z, torch.zeros(z.shape[0], dtype=torch.float64)
    theta = lo + width * torch.sigmoid(z)
    logdet = (torch.log(width) + nn.functional.logsigmoid(z) + nn.functional.logsigmoid(-z)).sum(-1)
    return theta, logdet


def logistic_log_prob(z: torch.Tensor) -> torch.Tensor:
    """(N,) log density in logit coordinates z of the uniform box prior: z = logit(u), u ~ U(0, 1),
    a standard logistic per coordinate."""
    return (nn.functional.logsigmoid(z) + nn.functional.logsigmoid(-z)).sum(-1)


@contextlib.contextmanager
def torch_threads(n: int | None):
    """torch's intra-op thread count set to ``n`` for the block (None: unchanged)."""
    old = torch.get_num_threads()
    if n is not None and n != old:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if torch.get_num_threads() != old:
            torch.set_num_threads(old)

