"""A tiny simulator satisfying the Simulator protocol, for tests of the inference layer.

A point robot with n "joints" = Cartesian coordinates (FK(q) = q padded to 3-D) that moves
straight toward the goal at a fixed step, clamped to its limits every step.
"""

from __future__ import annotations

import torch

from camo_sbi._validation import check_theta
from camo_sbi.simulators.base import Trajectories


class ToySimulator:
    def __init__(self, n: int = 2, max_steps: int = 30, step: float = 0.1):
        self.n_joints = n
        self.joint_names = [f"x{i}" for i in range(n)]
        self.bounds = torch.tensor([[-1.0, 1.0]] * n, dtype=torch.float64)
        self.start = torch.zeros(n, dtype=torch.float64)
        self.urdf = ""
        self.max_steps, self.step = max_steps, step

    def forward_kinematics(self, q):
        pad = torch.zeros(*q.shape[:-1], 3 - self.n_joints, dtype=q.dtype)
        return torch.cat([q, pad], dim=-1)

    def simulate(self, theta, goal, start=None):
        theta = check_theta(theta, self.n_joints)
        B, dt = theta.shape[0], theta.dtype
        lo, hi = theta[:, 0::2], theta[:, 1::2]
        q = (self.start if start is None else start).to(dt).expand(B, -1).clone()
        g = goal.to(dt).expand(B, 3)[:, : self.n_joints]
        qs = torch.empty(B, self.max_steps, self.n_joints, dtype=dt)
        length = torch.full((B,), self.max_steps, dtype=torch.int64)
        done = torch.zeros(B, dtype=torch.bool)
        for t in range(self.max_steps):
            qs[:, t] = q
            e = g - q
            newly = (~done) & (e.norm(dim=1) < 1e-3)
            length[newly] = t + 1
            done |= newly
            step = e * torch.clamp(self.step / e.norm(dim=1, keepdim=True).clamp_min(1e-12), max=1.0)
            q = torch.where(done[:, None], q, torch.minimum(torch.maximum(q + step, lo), hi))
        reached = (qs[torch.arange(B), length - 1] - g).norm(dim=1) < 1e-3
        # padding repeats the final posture
        idx = torch.minimum(torch.arange(self.max_steps)[None, :], (length - 1)[:, None])
        qs = torch.gather(qs, 1, idx[..., None].expand(-1, -1, self.n_joints))
        return Trajectories(qs, self.forward_kinematics(qs), length, reached)
