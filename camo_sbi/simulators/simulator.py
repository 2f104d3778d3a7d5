"""`KinematicSimulator`: any serial URDF chain + the differential-kinematics reaching controller.

Build one with `from_urdf` (or `panda()`, `human()`). ``simulate`` validates and
broadcasts its inputs, then runs either the generated numba kernel (CPU tensors,
``backend="auto"`` or ``"numba"``) or the torch/pytorch_kinematics reference
(``"torch"``, and any non-CPU device under ``"auto"``). Both implement the same law
(see `controller.py`) and agree to ~1e-9 in float64.
"""

from __future__ import annotations

import numpy as np
import torch

from camo_sbi._validation import (
    as_tensor,
    check_finite,
    check_positive_int,
    check_theta,
    cpu_array,
    torch_generator,
)
from camo_sbi.simulators.base import Trajectories
from camo_sbi.simulators.chain import KinematicChain, load_chain
from camo_sbi.simulators.controller import ControllerConfig, reference_simulate

__all__ = ["KinematicSimulator", "from_urdf", "sample_goals", "BACKENDS"]

BACKENDS = ("auto", "torch", "numba")
START_SLACK = 1e-6  # radians / metres a start posture may lie outside its limits


class KinematicSimulator:
    """Batched reaching simulator for one serial chain (implements `base.Simulator`).

    Attributes:
        joint_names: list of n actuated joints, base to tip.
        n_joints: n.
        bounds: (n, 2) float64 URDF limits.
        start: (n,) float64 default start posture.
        urdf: URDF text.
        end_effector: link name.
        config: `ControllerConfig`.
        backend: "auto", "torch" or "numba".
        chain: the parsed `KinematicChain` (``chain.spec`` is the plain `ChainSpec`).
    """

    def __init__(self, chain: KinematicChain, start=None, *, config: ControllerConfig | None = None,
                 backend: str = "auto"):
        if not isinstance(chain, KinematicChain):
            raise TypeError(f"chain: expected a KinematicChain, got {type(chain).__name__}")
        config = ControllerConfig() if config is None else config
        if not isinstance(config, ControllerConfig):
            raise TypeError(f"controller: expected a ControllerConfig, got {type(config).__name__}")
        if backend not in BACKENDS:
            raise ValueError(f"backend: expected one of {BACKENDS}, got {backend!r}")
        self.chain = chain
        self.config = config
        self.backend = backend
        self.bounds = torch.tensor(np.array(chain.spec.limits), dtype=torch.float64)
        n = chain.n_joints
        if start is None:
            start = torch.zeros(n, dtype=torch.float64).clamp(self.bounds[:, 0], self.bounds[:, 1])
        start = check_finite(as_tensor(start, "start", dtype=torch.float64, device="cpu"), "start")
        if start.shape != (n,):
            raise ValueError(f"start: expected shape ({n},) for joints {chain.joint_names}, got {tuple(start.shape)}")
        if bool(((start < self.bounds[:, 0] - START_SLACK) | (start > self.bounds[:, 1] + START_SLACK)).any()):
            raise ValueError(f"start: {start.tolist()} lies outside the URDF limits {self.bounds.tolist()}")
        self.start = start.clone()

    # -- contract attributes
    @property
    def joint_names(self) -> list[str]:
        return self.chain.joint_names

    @property
    def n_joints(self) -> int:
        return self.chain.n_joints

    @property
    def urdf(self) -> str:
        return self.chain.urdf

    @property
    def spec(self):
        return self.chain.spec

    @property
    def end_effector(self) -> str:
        return self.chain.spec.end_effector

    def __repr__(self) -> str:
        return (f"KinematicSimulator({self.spec.base_link!r} -> {self.end_effector!r}, n_joints={self.n_joints}, "
                f"backend={self.backend!r}, config={self.config})")

    def scaled(self, factor: float) -> KinematicSimulator:
        """The same chain with every segment ``factor`` times as long (`chain.scale_urdf`), same
        joints, start, controller and backend: a person taller or shorter than the model."""
        from camo_sbi.simulators.chain import scale_urdf

        chain = load_chain(scale_urdf(self.urdf, factor), self.end_effector, self.joint_names,
                           base_link=self.spec.base_link)
        return KinematicSimulator(chain, self.start, config=self.config, backend=self.backend)

    def with_config(self, config: ControllerConfig | None = None, *, backend: str | None = None,
                    **changes) -> KinematicSimulator:
        """Same chain and start with another config (or ``changes`` to this one) / backend."""
        cfg = self.config if config is None else config
        if changes:
            cfg = cfg.replace(**changes)
        return KinematicSimulator(self.chain, self.start, config=cfg, backend=backend or self.backend)

    # -- kinematics
    def forward_kinematics(self, q) -> torch.Tensor:
        """q (..., n) -> end-effector position (..., 3) via pytorch_kinematics (the reference FK)."""
        q = check_finite(as_tensor(q, "q"), "q")
        if q.dim() == 0 or q.shape[-1] != self.n_joints:
            raise ValueError(f"q: expected shape (..., {self.n_joints}), got {tuple(q.shape)}")
        return self.chain.reference_fk(q)

    # -- simulation
    def _inputs(self, theta, goal, start):
        theta = as_tensor(theta, "theta")
        if theta.dtype not in (torch.float32, torch.float64):
            raise TypeError(f"theta: dtype must be float32 or float64, got {theta.dtype}")
        theta = check_theta(theta.detach(), self.n_joints, "theta")
        dt, dev = theta.dtype, theta.device
        n = self.n_joints
        goal = check_finite(as_tensor(goal, "goal", dtype=dt, device=dev).detach(), "goal")
        if goal.dim() == 1:
            goal = goal.unsqueeze(0)
        if goal.dim() != 2 or goal.shape[1] != 3:
            raise ValueError(f"goal: expected shape (3,) or (B, 3), got {tuple(goal.shape)}")
        start = self.start if start is None else start
        start = check_finite(as_tensor(start, "start", dtype=dt, device=dev).detach(), "start")
        if start.dim() == 1:
            start = start.unsqueeze(0)
        if start.dim() != 2 or start.shape[1] != n:
            raise ValueError(f"start: expected shape ({n},) or (B, {n}), got {tuple(start.shape)}")
        sizes = {"theta": theta.shape[0], "goal": goal.shape[0], "start": start.shape[0]}
        B = theta.shape[0] if theta.shape[0] != 1 else max(sizes.values())
        for name, b in sizes.items():
            if b not in (1, B):
                raise ValueError(f"{name}: batch size {b} does not match the batch size {B} "
                                 f"(sizes: {sizes}; each must be 1 or B)")
        # on the CPU in numpy, single-threaded (`camo_sbi._validation.cpu_array` says why)
        arrays = [cpu_array(t) for t in (theta, goal, start)]
        if all(a is not None for a in arrays):
            a_th, a_go, a_st = (np.require(a if a.shape[0] == B else np.broadcast_to(a, (B, a.shape[1])),
                                           requirements=("C", "W")) for a in arrays)
            theta, goal, start = torch.from_numpy(a_th), torch.from_numpy(a_go), torch.from_numpy(a_st)
            bad = (a_st < a_th[:, 0::2] - START_SLACK) | (a_st > a_th[:, 1::2] + START_SLACK)
        else:
            theta, goal, start = (t.expand(B, -1).contiguous() for t in (theta, goal, start))
            bad = ((start < theta[:, 0::2] - START_SLACK) | (start > theta[:, 1::2] + START_SLACK)).cpu().numpy()
        lo, hi = theta[:, 0::2], theta[:, 1::2]
        if bad.any():
            b, j = (int(v) for v in np.argwhere(bad)[0])
            raise ValueError(f"start: joint {self.joint_names[j]} = {float(start[b, j]):.6g} lies outside "
                             f"theta's limits [{float(lo[b, j]):.6g}, {float(hi[b, j]):.6g}] (sample {b})")
        return theta, goal, start

    def simulate(self, theta, goal, start=None) -> Trajectories:
        """Reach ``goal`` from ``start`` with joint limits ``theta``.

        Args:
            theta: (B, 2n) or (2n,) limits [lo_1, hi_1, ..., lo_n, hi_n], float32/float64.
            goal: (3,) or (B, 3) Cartesian goal in the base frame (m).
            start: None (``self.start``), (n,) or (B, n); must lie inside theta's limits.
                A batch dimension of 1 broadcasts against the others.

        Returns:
            `Trajectories` q (B, T, n), ee (B, T, 3), length (B,) int64, reached (B,) bool,
            T = config.max_steps, dtype/device of ``theta``.
        """
        theta, goal, start = self._inputs(theta, goal, start)
        use_numba = self.backend == "numba" or (self.backend == "auto" and theta.device.type == "cpu")
        if self.backend == "numba" and theta.device.type != "cpu":
            raise ValueError(f"theta: the numba backend needs CPU tensors, got device {theta.device}")
        if not use_numba:
            return reference_simulate(self.chain, theta, goal, start, self.config)
        from camo_sbi.simulators.kernel import kernel_simulate

        B, T, n = theta.shape[0], self.config.max_steps, self.n_joints
        q = torch.empty(B, T, n, dtype=theta.dtype)
        ee = torch.empty(B, T, 3, dtype=theta.dtype)
        length = torch.empty(B, dtype=torch.int64)
        reached = torch.empty(B, dtype=torch.bool)
        c = self.config
        kernel_simulate(self.spec, theta.numpy(), goal.numpy(), start.numpy(),
                        max_steps=T, tol=c.tol, gain=c.gain, damping=c.damping,
                        max_cartesian_step=c.max_cartesian_step, max_joint_step=c.max_joint_step,
                        null_gain=c.null_gain, derivative_gain=c.derivative_gain, early_stop=c.early_stop,
                        limit_gain=c.limit_gain, limit_buffer=c.limit_buffer, limit_cap=c.limit_cap,
                        out=(q.numpy(), ee.numpy(), length.numpy(), reached.numpy()))
        return Trajectories(q, ee, length, reached)


def from_urdf(urdf, end_effector: str, start=None, joints=None, *,
              controller: ControllerConfig | None = None, backend: str = "auto",
              base_link: str | None = None) -> KinematicSimulator:
    """A `KinematicSimulator` for the serial chain ``base_link`` -> ``end_effector`` of ``urdf``.

    Args:
        urdf: URDF text or a path. Revolute, continuous (limits [-pi, pi]) and prismatic
            joints are supported; fixed joints are folded into the constants.
        end_effector: end-effector link name.
        start: (n,) default start posture (default: 0 clipped into the URDF limits).
        joints: actuated joint names (base to tip); other movable joints on the path are
            locked at 0. None: all movable joints on the path.
        controller: `ControllerConfig`.  backend: "auto", "torch" or "numba".
        base_link: chain root (default: the URDF root link).
    """
    return KinematicSimulator(load_chain(urdf, end_effector, joints, base_link=base_link), start,
                              config=controller, backend=backend)


def sample_goals(sim, limits, n: int, generator) -> torch.Tensor:
    """(n, 3) float64 goals: configurations uniform inside ``limits`` (n_joints, 2), through FK.

    ``generator`` is a torch.Generator (or an int seed); goals are reachable by construction.
    """
    n = check_positive_int(n, "n")
    gen = torch_generator(generator, "generator")
    limits = check_finite(as_tensor(limits, "limits", dtype=torch.float64, device="cpu"), "limits")
    if limits.shape != (sim.n_joints, 2):
        raise ValueError(f"limits: expected shape ({sim.n_joints}, 2), got {tuple(limits.shape)}")
    if bool((limits[:, 0] > limits[:, 1]).any()):
        raise ValueError("limits: lower limit exceeds upper limit")
    u = torch.rand(n, sim.n_joints, generator=gen, dtype=torch.float64)
    q = limits[:, 0] + (limits[:, 1] - limits[:, 0]) * u
    return sim.forward_kinematics(q).to(torch.float64)
