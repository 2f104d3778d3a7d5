"""Reaches from generators the methods do not assume (issue 33): a subject that does not move
like the controller.

Every method conditions on the differential-kinematics controller (`camo_sbi.simulators.controller`):
a Cartesian error shrunk by a gain every step, i.e. an exponentially converging straight line. A
person moves otherwise. `HumanLikeReaches` wraps a `KinematicSimulator` (same chain, start,
bounds) and implements the same ``simulate(theta, goal, start)`` contract with another law:

* ``"minimum-jerk"``: the hand follows the task-space minimum-jerk path from the start's end
  effector position ``x0`` to the goal (Flash & Hogan, 1985)::

      x_d(t) = x0 + (goal - x0) s(t / D),   s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5

  whose speed ``|goal - x0| s'(tau) / D``, ``s'(tau) = 30 tau^2 - 60 tau^3 + 30 tau^4``, is
  bell-shaped and peaks at mid-time (1.875 times the mean speed).
* ``"via-point"``: the same through an intermediate point, lift then place: two minimum-jerk
  segments ``x0 -> via -> goal`` (the hand stops at the via point), ``via`` the midpoint of
  ``x0`` and the goal raised by ``h`` metres along the base z axis (up on both built-in models).
* ``"controller"``: no wrapper: the simulator itself (the exact model).

**Tracking.** The path is tracked by damped-least-squares IK that respects the subject's true
limits ``theta``: at step t, ``dq = J^T (J J^T + lambda^2 I)^-1 (x_d(t+1) - x(t))`` with the
joint step capped at ``max_joint_step`` and ``q`` clamped into ``[lo, hi]`` (no null-space pull:
a different law from the controller's). A goal beyond the limits ends where the limits stop the
hand. After the path's last point the hand keeps being pulled to the goal until it is within
the controller's ``tol`` or moves less than ``STOP_M`` in a step (stopped by its limits).

**Sampling convention.** One sample per controller step, so a reach's length is comparable with
the controller's: the duration in steps is ``D = ceil(k L / max_cartesian_step)``, ``L`` the
straight-line path length, ``k`` the subject's slowness drawn per reach from ``slowness``
(default U(2, 4): peak speed ``1.875 L / D`` between 0.47 and 0.94 of the controller's step
cap, the controller itself moving at its cap for most of a long reach). A person's reach
therefore takes about twice the controller's steps, as the issue measured on a real recording
(50 against 25). ``D`` is capped so that the path ends by the last of the ``max_steps`` points.

**Physiological tremor** (``tremor_mm``, default 0): a smooth random displacement (AR(1) with
coefficient 0.7 per step, marginal sd ``tremor_mm`` per coordinate) added to the desired path
while the hand moves (zero at its two ends), tracked by the same IK, so joint angles and end
effector stay consistent and inside the limits. The recorder's noise (`camo_sbi.task.NoiseModel`)
goes on top, as for controller data.

**Determinism.** The per-reach nuisances (slowness, lift height, tremor) are drawn from a
numpy Generator keyed on ``(seed, goal, start)`` (rounded to 1e-9), so ``simulate`` is a pure
function: the same reach under other limits (the binding checks relax one bound at a time) has
the same timing, and any batch order or number of workers gives the same numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from camo_sbi._validation import check_positive_float
from camo_sbi.simulators.base import Trajectories

__all__ = ["GENERATORS", "REACH_MODEL_SEED", "STOP_M", "reach_model", "GeneratorConfig", "HumanLikeReaches", "make_generator", "minimum_jerk",
           "minimum_jerk_speed"]

GENERATORS = ("controller", "minimum-jerk", "via-point")
"""Names accepted by ``--generator``: the exact model and the two human-like generators."""

STOP_M = 5e-4
"""A reach past its path's end stops once its hand moves less than this per step (metres)."""

_AR = 0.7  # tremor AR(1) coefficient per step


def minimum_jerk(tau):
    """The minimum-jerk position profile s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 on [0, 1]."""
    return 10 * tau**3 - 15 * tau**4 + 6 * tau**5


def minimum_jerk_speed(tau):
    """ds/dtau = 30 tau^2 - 60 tau^3 + 30 tau^4 (peak 1.875 at tau = 0.5)."""
    return 30 * tau**2 - 60 * tau**3 + 30 * tau**4


@dataclass(frozen=True)
class GeneratorConfig:
    """A human-like reach generator (see the module docstring).

    Attributes:
        kind: "minimum-jerk" or "via-point".
        seed: keys every reach's nuisances with its goal and start.
        slowness: (min, max) of the per-reach slowness k, duration D = ceil(k L / max_cartesian_step).
        via_height: (min, max) metres the via point is raised above the start-goal midpoint.
        tremor_mm: sd of the tremor per coordinate (mm; 0: none).
        damping: the IK's damping lambda (m).
        max_joint_step: the IK's cap on max_i |dq_i| per step (rad or m).
    """

    kind: str = "minimum-jerk"
    seed: int = 0
    slowness: tuple[float, float] = (2.0, 4.0)
    via_height: tuple[float, float] = (0.10, 0.20)
    tremor_mm: float = 0.0
    damping: float = 0.02
    max_joint_step: float = 0.2

    def __post_init__(self):
        if self.kind not in GENERATORS[1:]:
            raise ValueError(f"kind: expected one of {GENERATORS[1:]}, got {self.kind!r}")
        if not isinstance(self.seed, (int, np.integer)) or isinstance(self.seed, bool) or self.seed < 0:
            raise ValueError(f"seed: expected an integer >= 0, got {self.seed!r}")
        for name in ("slowness", "via_height"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi):
                raise ValueError(f"{name}: expected (min, max) with 0 <= min <= max, got {(lo, hi)}")
        if self.slowness[0] <= 0:
            raise ValueError(f"slowness: the minimum must be > 0, got {self.slowness}")
        check_positive_float(self.tremor_mm, "tremor_mm", allow_zero=True)
        check_positive_float(self.damping, "damping")
        check_positive_float(self.max_joint_step, "max_joint_step")


def _reach_rng(seed: int, goal: np.ndarray, start: np.ndarray) -> np.random.Generator:
    key = [int(seed)] + [int(round(float(v) * 1e9)) % (1 << 63) for v in np.concatenate([goal, start])]
    return np.random.default_rng(np.random.SeedSequence(key))


class HumanLikeReaches:
    """A subject that reaches along a minimum-jerk (or via-point) path: the `Simulator` contract
    (``simulate(theta, goal, start) -> Trajectories``, ``forward_kinematics``, ``joint_names``,
    ``n_joints``, ``bounds``, ``start``, ``urdf``) on the chain of ``sim``.

    Attributes:
        base: the wrapped `KinematicSimulator` (its controller config gives ``max_steps``,
            ``tol`` and ``max_cartesian_step``).  generator: the `GeneratorConfig`.
    """

    def __init__(self, sim, generator: GeneratorConfig):
        if not isinstance(generator, GeneratorConfig):
            raise TypeError(f"generator: expected a GeneratorConfig, got {type(generator).__name__}")
        if not hasattr(sim, "chain") or not hasattr(sim, "_inputs"):
            raise TypeError(f"sim: expected a KinematicSimulator, got {type(sim).__name__}")
        self.base = sim
        self.generator = generator

    # -- the contract attributes, the wrapped body's
    joint_names = property(lambda self: self.base.joint_names)
    n_joints = property(lambda self: self.base.n_joints)
    bounds = property(lambda self: self.base.bounds)
    start = property(lambda self: self.base.start)
    urdf = property(lambda self: self.base.urdf)
    chain = property(lambda self: self.base.chain)
    spec = property(lambda self: self.base.spec)
    config = property(lambda self: self.base.config)
    end_effector = property(lambda self: self.base.end_effector)

    def __repr__(self) -> str:
        return f"HumanLikeReaches({self.generator}, body={self.base!r})"

    def forward_kinematics(self, q) -> torch.Tensor:
        return self.base.forward_kinematics(q)

    def _stepper(self):
        """The body with a one-step controller: ``simulate(theta, x_target, q)`` returns q_{t+1}
        = clamp(q + capped DLS step towards x_target) (the numba kernel on CPU tensors)."""
        from camo_sbi.simulators.controller import ControllerConfig

        g = self.generator
        return self.base.with_config(ControllerConfig(
            max_steps=2, tol=1e-9, gain=1.0, damping=g.damping, max_cartesian_step=1e3,
            max_joint_step=g.max_joint_step, null_gain=0.0, early_stop=False))

    def desired_paths(self, x0: np.ndarray, goal: np.ndarray, T: int, rngs) -> tuple[np.ndarray, np.ndarray]:
        """Per reach the desired hand path (B, T, 3) (holding the goal after its end) and its
        duration D (B,) in steps: x0 (B, 3) the start's end-effector positions, goal (B, 3),
        ``rngs`` one numpy Generator per reach (keyed on (seed, goal, start)). No tremor."""
        g = self.generator
        cap = self.config.max_cartesian_step
        B = x0.shape[0]
        out = np.empty((B, T, 3))
        dur = np.empty(B, dtype=np.int64)
        for b in range(B):
            rng = rngs[b]
            k = rng.uniform(*g.slowness)
            if g.kind == "via-point":
                h = rng.uniform(*g.via_height)
                via = 0.5 * (x0[b] + goal[b]) + np.array([0.0, 0.0, h])
                points = [x0[b], via, goal[b]]
            else:
                points = [x0[b], goal[b]]
            seg_len = [float(np.linalg.norm(points[i + 1] - points[i])) for i in range(len(points) - 1)]
            steps = [max(2, math.ceil(k * s / cap)) for s in seg_len]
            total = sum(steps)
            if total > T - 1:  # the path ends by the last point: shrink every segment alike
                steps = [max(1, int(s * (T - 1) // total)) for s in steps]
                total = sum(steps)
            t0 = 0
            out[b, 0] = points[0]
            for i, d in enumerate(steps):
                tau = np.arange(1, d + 1) / d
                out[b, t0 + 1:t0 + d + 1] = points[i] + np.outer(minimum_jerk(tau), points[i + 1] - points[i])
                t0 += d
            out[b, total + 1:] = goal[b]
            dur[b] = total
        return out, dur

    def _tremor(self, dur: np.ndarray, T: int, rngs) -> np.ndarray:
        B = dur.shape[0]
        out = np.zeros((B, T, 3))
        sd = self.generator.tremor_mm * 1e-3
        if sd == 0:
            return out
        for b in range(B):
            e = rngs[b].standard_normal((T, 3)) * sd * math.sqrt(1 - _AR**2)
            x = np.zeros((T, 3))
            x[0] = rngs[b].standard_normal(3) * sd
            for t in range(1, T):
                x[t] = _AR * x[t - 1] + e[t]
            d = int(dur[b])
            out[b, 1:d] = x[1:d]  # while the hand moves; zero at its two ends
        return out

    def simulate(self, theta, goal, start=None) -> Trajectories:
        """Reach ``goal`` from ``start`` along the generator's path, IK inside ``theta``'s limits.

        Args and returns as `KinematicSimulator.simulate`: theta (B, 2n) or (2n,), goal (3,) or
        (B, 3), start None, (n,) or (B, n); `Trajectories` with T = ``config.max_steps``,
        dtype of ``theta``; ``reached``: the final hand within the controller's ``tol``.
        """
        theta, goal, start = self.base._inputs(theta, goal, start)
        dtype = theta.dtype
        th, gl, st = theta.to(torch.float64).cpu(), goal.to(torch.float64).cpu(), start.to(torch.float64).cpu()
        B, n, T = th.shape[0], self.n_joints, self.config.max_steps
        lo, hi = th[:, 0::2], th[:, 1::2]
        gn, sn = gl.numpy(), st.numpy()
        rngs = [_reach_rng(self.generator.seed, gn[b], sn[b]) for b in range(B)]
        q = torch.minimum(torch.maximum(st, lo), hi)
        x0 = self.chain.reference_fk(q).numpy()
        path, dur = self.desired_paths(x0, gn, T, rngs)
        path = torch.from_numpy(path + self._tremor(dur, T, rngs))
        dur_t = torch.from_numpy(dur)
        q_out = torch.empty(B, T, n, dtype=torch.float64)
        x_out = torch.empty(B, T, 3, dtype=torch.float64)
        length = torch.full((B,), T, dtype=torch.int64)
        active = torch.ones(B, dtype=torch.bool)
        x_prev = None
        last = T - 1
        stepper = self._stepper()
        x = self.chain.reference_fk(q)
        for t in range(T):
            q_out[:, t], x_out[:, t] = q, x
            if t > 0:
                ended = t >= dur_t
                done = active & ended & (((gl - x).norm(dim=-1) < self.config.tol)
                                         | ((x - x_prev).norm(dim=-1) < STOP_M))
                length = torch.where(done, t + 1, length)
                active = active & ~done
            if t == T - 1 or not bool(active.any()):
                last = t
                break
            x_prev = x
            # one DLS step towards x_d(t+1), clamped into the limits: the kernel's controller step
            # with gain 1, no step cap in Cartesian space, no null-space term (module docstring)
            step = stepper.simulate(th, path[:, min(t + 1, T - 1)].contiguous(), q)
            keep = active.unsqueeze(-1)
            q = torch.where(keep, step.q[:, 1].to(torch.float64), q)
            x = torch.where(keep, step.ee[:, 1].to(torch.float64), x)
        idx = torch.minimum(torch.arange(T).expand(B, T), (length - 1).unsqueeze(-1)).clamp(max=last)
        q_out = q_out.gather(1, idx.unsqueeze(-1).expand(B, T, n))
        x_out = x_out.gather(1, idx.unsqueeze(-1).expand(B, T, 3))
        reached = (gl - x_out[:, -1]).norm(dim=-1) < self.config.tol
        dev = theta.device
        return Trajectories(q_out.to(dtype=dtype, device=dev), x_out.to(dtype=dtype, device=dev),
                            length.to(dev), reached.to(dev))


def make_generator(sim, name: str, *, seed: int = 0, tremor_mm: float = 0.0):
    """The subject's reach generator ``name`` (one of `GENERATORS`) on the body ``sim``:
    ``sim`` itself for "controller" (then ``tremor_mm`` must be 0), else `HumanLikeReaches`."""
    if name not in GENERATORS:
        raise ValueError(f"generator: expected one of {GENERATORS}, got {name!r}")
    if name == "controller":
        if tremor_mm:
            raise ValueError("tremor_mm: tremor needs a human-like generator (minimum-jerk or via-point)")
        return sim
    return HumanLikeReaches(sim, GeneratorConfig(kind=name, seed=int(seed), tremor_mm=float(tremor_mm)))


def misspecified_observations(task, generator, *, noise=None, seed: int = 0):
    """``task`` (synthetic: with ``true_theta``) with its observed reaches re-recorded from
    ``generator`` (the subject's true body and way of moving; e.g. `HumanLikeReaches`), same
    goals and starts, and the trajectories the subject would really follow on the held-out
    goals. ``task.simulator`` (what the methods condition on) is unchanged. ``noise``: a
    `NoiseModel` whose perturbation is added to the recorded values (seeded by ``seed``;
    None: the task's own model, exact when it is zero). Returns (task, true_test Trajectories)."""
    from camo_sbi._validation import torch_generator
    from camo_sbi.scenarios.reaching import observe
    from camo_sbi.task import Observation, predict

    truth = task.require_truth("misspecified_observations")
    starts = torch.stack([o.start for o in task.observations])
    goals = torch.stack([o.goal for o in task.observations])
    obs = observe(generator, truth, goals, starts)
    noise = task.noise if noise is None else noise
    if noise.joint_deg or noise.ee_mm:
        gen = torch_generator(seed)
        obs = tuple(Observation(o.start, o.goal, noise.perturb(o.q, "joint", gen), noise.perturb(o.ee, "cartesian",
                                                                                              gen)) for o in obs)
    true_test = predict(generator, truth, task.test_starts, task.test_goals)
    return task.with_observations(obs), true_test


REACH_MODEL_SEED = 0
"""The inference model's own nuisance seed (unused with a fixed slowness: kept for the key)."""


def reach_model(sim, name: str = "minimum-jerk") -> HumanLikeReaches:
    """A human-like model to INFER with (issue 33): `HumanLikeReaches` of kind ``name`` whose
    duration is normalised, not sampled: the slowness is fixed at the middle of the generator's
    range (k = 3, D = ceil(3 L / max_cartesian_step)), no tremor. Same simulator contract, so
    every method takes it as ``task.with_simulator(reach_model(sim))``."""
    mid = 0.5 * sum(GeneratorConfig().slowness)
    return HumanLikeReaches(sim, GeneratorConfig(kind=name, seed=REACH_MODEL_SEED, slowness=(mid, mid)))
