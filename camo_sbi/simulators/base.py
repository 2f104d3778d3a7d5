"""The simulator contract: `Trajectories`, the `Simulator` protocol and theta layout helpers.

Layout convention used everywhere in camo_sbi::

    theta: (B, 2n) = [lo_1, hi_1, lo_2, hi_2, ..., lo_n, hi_n]   (radians)
    limits: (n, 2)  = [[lo_1, hi_1], ..., [lo_n, hi_n]]
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import torch

__all__ = ["Trajectories", "Simulator", "theta_to_limits", "limits_to_theta"]


@dataclass(frozen=True)
class Trajectories:
    """A batch of simulated reaches.

    Attributes:
        q: (B, T, n) joint angles; steps at index >= length[b] repeat the final posture.
        ee: (B, T, 3) end-effector positions (metres, base frame).
        length: (B,) int64 number of valid steps (1 <= length <= T), start included.
        reached: (B,) bool, final end-effector within the controller tolerance of the goal.
    """

    q: torch.Tensor
    ee: torch.Tensor
    length: torch.Tensor
    reached: torch.Tensor

    @property
    def batch_size(self) -> int:
        return int(self.q.shape[0])

    def __len__(self) -> int:
        return self.batch_size

    def __getitem__(self, idx) -> Trajectories:
        """Select samples along the batch axis (int, slice, index tensor or bool mask)."""
        if isinstance(idx, int):
            idx = slice(idx, idx + 1) if idx != -1 else slice(-1, None)
        return Trajectories(self.q[idx], self.ee[idx], self.length[idx], self.reached[idx])

    def trimmed(self, b: int, space: str = "joint") -> torch.Tensor:
        """Valid part of sample ``b`` in ``space`` ('joint' -> (L, n), 'cartesian' -> (L, 3))."""
        L = int(self.length[b])
        if space == "joint":
            return self.q[b, :L]
        if space == "cartesian":
            return self.ee[b, :L]
        raise ValueError(f"space: expected 'joint' or 'cartesian', got {space!r}")

    def to(self, device=None, dtype=None) -> Trajectories:
        """Move to ``device`` and/or cast the float fields to ``dtype``."""
        return Trajectories(
            self.q.to(device=device, dtype=dtype),
            self.ee.to(device=device, dtype=dtype),
            self.length.to(device=device),
            self.reached.to(device=device),
        )

    @staticmethod
    def concatenate(parts: list[Trajectories]) -> Trajectories:
        """Concatenate along the batch axis (all parts must share T)."""
        return Trajectories(
            torch.cat([p.q for p in parts]),
            torch.cat([p.ee for p in parts]),
            torch.cat([p.length for p in parts]),
            torch.cat([p.reached for p in parts]),
        )


def theta_to_limits(theta: torch.Tensor) -> torch.Tensor:
    """(..., 2n) -> (..., n, 2)."""
    return theta.reshape(*theta.shape[:-1], theta.shape[-1] // 2, 2)


def limits_to_theta(limits: torch.Tensor) -> torch.Tensor:
    """(..., n, 2) -> (..., 2n)."""
    return limits.reshape(*limits.shape[:-2], limits.shape[-2] * 2)


@runtime_checkable
class Simulator(Protocol):
    """What every simulator offers (built by `camo_sbi.simulators.from_urdf`).

    Attributes:
        joint_names: list of n movable joint names, base to tip.
        n_joints: n.
        bounds: (n, 2) float64 full range of motion [lo, hi] in radians.
        start: (n,) default start posture, inside ``bounds``.
        urdf: the URDF text the chain was built from.
    """

    joint_names: list[str]
    n_joints: int
    bounds: torch.Tensor
    start: torch.Tensor
    urdf: str

    def forward_kinematics(self, q: torch.Tensor) -> torch.Tensor:
        """q: (..., n) -> end-effector position (..., 3)."""
        ...

    def simulate(self, theta: torch.Tensor, goal: torch.Tensor, start: torch.Tensor | None = None) -> Trajectories:
        """theta: (B, 2n) [lo_1, hi_1, ...]; goal: (3,) or (B, 3); start: (n,) or (B, n) or None.

        Returns Trajectories with q (B, T, n), ee (B, T, 3), length (B,), reached (B,),
        T = max_steps. Deterministic; same dtype/device as ``theta``.
        """
        ...
