"""The batched torch reference controller (pytorch_kinematics FK/Jacobian + batched solve).

This is the readable statement of the controller law, the correctness reference for the
generated numba kernel (`kernel.py`), the backend for non-CPU devices and the baseline
of ``benchmarks/bench_simulator.py``. At step t, for every sample still moving::

    x = fk(q_t);  e = goal - x;  ||e|| < tol  ->  done, length = t + 1   (early_stop only)
    v = gain * e - derivative_gain * (x_t - x_{t-1}), rescaled so that ||v|| <= max_cartesian_step
    J = position Jacobian (3, n);  A = J J^T + damping^2 I       (solved in float64, see below)
    dq0 = null_gain * (mid - q_t),  mid = (lo + hi) / 2          (pushes into the limits)
        + 2 limit_gain clip(lo + limit_buffer - q_t, 0, limit_cap)   (the authors' lower-buffer push)
        + 2 limit_gain clip(q_t - hi - limit_buffer, 0, limit_cap)   (their upper term, as written)
    h = limit_gain (max(lo - q_t, 0) + max(q_t - hi, 0))            (their hard-limit penalty, as written)
    dq = J^T A^-1 v + (I - J^T A^-1 J) dq0 + h  =  J^T A^-1 (v - J dq0) + dq0 + h
    dq rescaled so that max_i |dq_i| <= max_joint_step
    q_{t+1} = clamp(q_t + dq, lo, hi)

The limit terms are those of the authors' ``Simulator.controller`` (``3D_Manipulator/
Simulator_rtb.py``; ``limit_gain`` = their dt * KN = 0.02 * 10, buffer 0.01 rad, cap 0.2),
signs as their code writes them: the lower push acts inside the limits, within
``limit_buffer`` of a lower limit; the upper push and both hard penalties act only on a
posture outside the limits, which after the clamp is at most the start (their upper terms,
written with the lower terms' sign, would push further out). ``limit_gain=0`` (default): off.

The damped solve ``A^-1`` runs in float64 in float32 simulations whose lambda^2 is below
`SOLVE64_BELOW_LAMBDA2` (1e-6, damping 1e-3: below that, lambda^2 is within a few float32 ulps of
``J J^T`` for metre-scale arms); the Jacobian is computed in float32 and cast. The paper
setting's damping 1e-6 (lambda^2 = 1e-12) is far below float32 resolution, so a float32 solve at
a singular posture (their start has a straight elbow) divided by a zero determinant and
returned NaN. Larger dampings (the default 0.05) solve in the simulation dtype, as before.

At most ``max_steps`` points are produced (the start included); afterwards the final
posture and position are repeated. With ``early_stop=False`` every reach runs all
``max_steps`` points (a fixed horizon, as the authors' code) and ``reached`` is judged at
the last point. ``x_{-1} = x_0`` (no derivative term at the first step).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

from camo_sbi._validation import check_bool, check_positive_float, check_positive_int
from camo_sbi.simulators.base import Trajectories
from camo_sbi.simulators.chain import KinematicChain

__all__ = ["SOLVE64_BELOW_LAMBDA2", "ControllerConfig", "controller_step", "reference_simulate"]

SOLVE64_BELOW_LAMBDA2 = 1e-6
"""damping^2 below which float32 simulations do the damped 3x3 solve in float64."""


@dataclass(frozen=True)
class ControllerConfig:
    """Damped-least-squares reaching controller with null-space limit avoidance.

    Attributes:
        max_steps: trajectory points T, the start included.
        tol: goal tolerance (m): a reach ends once ||goal - ee|| < tol.
        gain: proportional gain on the Cartesian error (per step).
        damping: DLS damping lambda (m); A = J J^T + lambda^2 I.
        max_cartesian_step: cap on the commanded end-effector displacement per step (m).
        max_joint_step: cap on max_i |dq_i| per step (rad or m).
        null_gain: gain of the null-space motion towards the middle of the limits (0: off:
            inside the limits, the limits then do not change the path at all).
        derivative_gain: damping on the previous step's end-effector displacement,
            ``v = gain * e - derivative_gain * (x_t - x_{t-1})`` (0: off). The authors' PD step
            ``dq = dt J+ (P e + D de)`` with dt = 0.02, P = 5, D = 0.5 is gain = 0.1,
            derivative_gain = 0.5.
        early_stop: a reach ends once within ``tol`` of its goal (False: a fixed horizon of
            ``max_steps`` points, no early stop).
        limit_gain: the authors' joint-limit terms (see the module docstring): their dt * KN
            (0.02 * 10 = 0.2 in ``--setting paper``); 0: off.
        limit_buffer: distance to a limit within which their null-space push acts (rad or m;
            theirs: 0.01).
        limit_cap: the push's clip ``clip(., 0, limit_cap)`` (theirs: 0.2).

    The defaults were tuned on the share of goals sampled uniformly inside the limits
    that the arm reaches (docs/studies/design_measurements.md). A larger ``null_gain``
    lowers that share (the null-space term then dominates the joint-step cap); 0.01 keeps
    every trajectory a continuous function of all limits.
    """

    max_steps: int = 100
    tol: float = 0.01
    gain: float = 0.8
    damping: float = 0.05
    max_cartesian_step: float = 0.04
    max_joint_step: float = 0.1
    null_gain: float = 0.01
    derivative_gain: float = 0.0
    early_stop: bool = True
    limit_gain: float = 0.0
    limit_buffer: float = 0.01
    limit_cap: float = 0.2

    def __post_init__(self):
        check_positive_int(self.max_steps, "max_steps")
        for name in ("tol", "gain", "damping", "max_cartesian_step", "max_joint_step"):
            check_positive_float(getattr(self, name), name)
        check_positive_float(self.null_gain, "null_gain", allow_zero=True)
        check_positive_float(self.derivative_gain, "derivative_gain", allow_zero=True)
        check_bool(self.early_stop, "early_stop")
        check_positive_float(self.limit_gain, "limit_gain", allow_zero=True)
        check_positive_float(self.limit_buffer, "limit_buffer", allow_zero=True)
        check_positive_float(self.limit_cap, "limit_cap", allow_zero=True)

    def replace(self, **changes) -> ControllerConfig:
        """A copy with ``changes`` applied (unknown names raise TypeError)."""
        return dataclasses.replace(self, **changes)


def controller_step(J: torch.Tensor, e: torch.Tensor, q: torch.Tensor, lo: torch.Tensor,
                    hi: torch.Tensor, config: ControllerConfig, dx: torch.Tensor | None = None) -> torch.Tensor:
    """One step of the law. J (B, 3, n), e (B, 3), q/lo/hi (B, n), dx (B, 3) the previous
    end-effector displacement (None: 0) -> q_next (B, n)."""
    c = config
    v = c.gain * e
    if dx is not None:
        v = v - c.derivative_gain * dx
    vn = v.norm(dim=-1, keepdim=True)
    v = v * torch.where(vn > c.max_cartesian_step, c.max_cartesian_step / vn, torch.ones_like(vn))
    dq0 = c.null_gain * (0.5 * (lo + hi) - q)
    zero = torch.zeros((), dtype=q.dtype, device=q.device)
    cap = torch.tensor(c.limit_cap, dtype=q.dtype, device=q.device)
    if c.limit_gain > 0:
        lg = c.limit_gain
        dq0 = (dq0 + 2 * lg * torch.clamp(lo + c.limit_buffer - q, min=zero, max=cap)
               + 2 * lg * torch.clamp(q - hi - c.limit_buffer, min=zero, max=cap))
    # the damped solve, in float64 when lambda^2 lies below float32 resolution (module docstring)
    sdt = torch.float64 if J.dtype == torch.float32 and c.damping * c.damping < SOLVE64_BELOW_LAMBDA2 else J.dtype
    Js, vs, dq0s = J.to(sdt), v.to(sdt), dq0.to(sdt)
    eye = torch.eye(3, dtype=sdt, device=J.device)
    A = Js @ Js.transpose(1, 2) + (c.damping * c.damping) * eye
    r = vs - (Js @ dq0s.unsqueeze(-1)).squeeze(-1)
    w = torch.linalg.solve(A, r)
    dq = ((Js.transpose(1, 2) @ w.unsqueeze(-1)).squeeze(-1) + dq0s).to(q.dtype)
    if c.limit_gain > 0:
        dq = dq + c.limit_gain * (torch.clamp(lo - q, min=zero) + torch.clamp(q - hi, min=zero))
    m = dq.abs().amax(dim=-1, keepdim=True)
    dq = dq * torch.where(m > c.max_joint_step, c.max_joint_step / m, torch.ones_like(m))
    return torch.clamp(q + dq, min=lo, max=hi)


def reference_simulate(chain: KinematicChain, theta: torch.Tensor, goal: torch.Tensor,
                       start: torch.Tensor, config: ControllerConfig) -> Trajectories:
    """Simulate B reaches with pk: theta (B, 2n), goal (B, 3), start (B, n), validated, one dtype/device.

    Each step calls ``chain.jacobian(q, ret_eef_pose=True)`` on the whole batch and one
    batched 3x3 solve. Returns `Trajectories` with T = config.max_steps.
    """
    B, n = start.shape
    T = config.max_steps
    lo, hi = theta[:, 0::2], theta[:, 1::2]
    q_out = torch.empty(B, T, n, dtype=theta.dtype, device=theta.device)
    x_out = torch.empty(B, T, 3, dtype=theta.dtype, device=theta.device)
    length = torch.full((B,), T, dtype=torch.int64, device=theta.device)
    active = torch.ones(B, dtype=torch.bool, device=theta.device)
    q = start.clone()
    t_last = T - 1
    x_prev = None
    for t in range(T):
        J6, pose = chain.reference_jacobian(q)
        x = pose[:, :3, 3]
        q_out[:, t] = q
        x_out[:, t] = x
        e = goal - x
        if config.early_stop:
            done_now = active & (e.norm(dim=-1) < config.tol)
            length = torch.where(done_now, t + 1, length)
            active = active & ~done_now
        if t == T - 1 or not bool(active.any()):
            t_last = t
            break
        dx = torch.zeros_like(x) if x_prev is None else x - x_prev
        x_prev = x
        q = torch.where(active.unsqueeze(-1), controller_step(J6[:, :3], e, q, lo, hi, config, dx), q)
    # padding: every step after length - 1 repeats the final point
    idx = torch.minimum(torch.arange(T, device=theta.device).expand(B, T), (length - 1).unsqueeze(-1))
    idx = torch.minimum(idx, torch.tensor(t_last, device=theta.device))
    q_out = q_out.gather(1, idx.unsqueeze(-1).expand(B, T, n))
    x_out = x_out.gather(1, idx.unsqueeze(-1).expand(B, T, 3))
    reached = (goal - x_out[:, -1]).norm(dim=-1) < config.tol
    return Trajectories(q_out, x_out, length, reached)
