"""The task contract: everything an inference method or a scenario is given, and the model rules.

    Task(name, subject, simulator, prior, observations, test_starts, test_goals, true_theta, noise)

A `Task` bundles (as sbibm's task does) the simulator, the prior over
``theta = [lo_1, hi_1, ..., lo_n, hi_n]``, the observed reaches in the order they arrive,
optional held-out goals, the true limits of a synthetic subject (None for recorded data)
and the observation-noise model. Every method's ``run(task, observations, *, budget, seed,
config)`` receives one.

The model rules live here, written once:

* **Observed postures bound the limits** (`contain`): the controller clamps to the
  limits, so every posture it is seen in, the start first of all, lies inside them.
  Candidate limit vectors are widened to contain the start of the reach they are
  simulated for, and a prediction widens the estimate to contain its start.
* **Fixed joints** are the prior's zero-width coordinates (`BoxPrior.expand`,
  `BoxPrior.with_known`): never inferred, always their known value.
* **The budgeted simulator** (`Task.with_budget`): methods only ever see a
  `CountingSimulator`, so a method's simulation count is measured, never reported.
* **Observation noise** (`NoiseModel`): i.i.d. Gaussian noise on each recorded joint angle
  (``joint_deg``) and each end-effector coordinate (``ee_mm``). Methods read it from the
  task; a task without noise has ``NoiseModel()`` (both 0).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from camo_sbi._validation import as_tensor, check_finite, check_theta
from camo_sbi.budget import CountingSimulator
from camo_sbi.priors import BoxPrior
from camo_sbi.simulators.base import Trajectories

__all__ = ["NOISE_K", "SPACES", "NoiseModel", "Observation", "Task", "check_observations", "contain", "predict"]

SPACES = ("joint", "cartesian")
"""Observation spaces: joint angles (q) or end-effector positions (ee)."""

NOISE_K = 3.0
"""Noise standard deviations treated as the plausible reach of observation noise (3 sigma: a
value beyond it has probability < 0.3 % per coordinate)."""


def contain(theta, postures) -> torch.Tensor:
    """Limit vectors widened to contain ``postures``: the rule "observed postures bound the limits".

    theta: (B, 2n) or (2n,) [lo_1, hi_1, ...]; postures: (n,) one posture for every row, or
    (B, n) one per row. Returns a new (B, 2n) tensor (dtype of ``theta``) with
    ``lo_i <= posture_i <= hi_i``; rows that already contain their posture are unchanged.
    """
    t = as_tensor(theta, "theta")
    t = t.unsqueeze(0) if t.dim() == 1 else t
    p = as_tensor(postures, "postures", dtype=t.dtype, device=t.device)
    if t.dim() != 2 or t.shape[1] % 2:
        raise ValueError(f"theta: expected shape (B, 2n), got {tuple(t.shape)}")
    n = t.shape[1] // 2
    if p.shape not in ((n,), (t.shape[0], n)) and not (p.dim() == 2 and p.shape == (1, n)):
        raise ValueError(f"postures: expected shape ({n},) or ({t.shape[0]}, {n}), got {tuple(p.shape)}")
    out = t.clone()
    out[:, 0::2] = torch.minimum(t[:, 0::2], p)
    out[:, 1::2] = torch.maximum(t[:, 1::2], p)
    return out


def predict(simulator, theta_hat, starts, goals) -> Trajectories:
    """Trajectories predicted with limits ``theta_hat`` (2n,) for ``goals`` (M, 3) from ``starts``.

    starts: (M, n) one per goal, or (n,) shared. The estimate is widened to contain each
    start (`contain`: the start is observed). Simulated in float64.
    """
    n = simulator.n_joints
    theta_hat = check_theta(as_tensor(theta_hat, "theta_hat", dtype=torch.float64), n, "theta_hat")
    if theta_hat.shape[0] != 1:
        raise ValueError(f"theta_hat: expected one limit vector (2n,), got {tuple(theta_hat.shape)}")
    goals = as_tensor(goals, "goals", dtype=torch.float64)
    if goals.dim() != 2 or goals.shape[1] != 3:
        raise ValueError(f"goals: expected shape (M, 3), got {tuple(goals.shape)}")
    starts = as_tensor(starts, "starts", dtype=torch.float64)
    if starts.dim() == 1 and starts.shape == (n,):
        starts = starts.expand(goals.shape[0], -1)
    if starts.shape != (goals.shape[0], n):
        raise ValueError(f"starts: expected shape ({goals.shape[0]}, {n}) (one per row of goals) or ({n},), "
                         f"got {tuple(starts.shape)}")
    theta_b = contain(theta_hat.expand(starts.shape[0], -1), starts)
    return simulator.simulate(theta_b, goals, starts)


@dataclass(frozen=True)
class NoiseModel:
    """I.i.d. Gaussian observation noise, per recorded value.

    Attributes:
        joint_deg: standard deviation of the noise on each joint angle, degrees.
        ee_mm: standard deviation of the noise on each end-effector coordinate, millimetres.
    """

    joint_deg: float = 0.0
    ee_mm: float = 0.0

    def __post_init__(self):
        for name in ("joint_deg", "ee_mm"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or v < 0:
                raise ValueError(f"{name}: expected a finite number >= 0, got {v!r}")
            object.__setattr__(self, name, float(v))

    @property
    def is_zero(self) -> bool:
        return self.joint_deg == 0.0 and self.ee_mm == 0.0

    def sigma(self, space: str) -> float:
        """Noise standard deviation in the space's own unit: radians (joint) or metres (cartesian)."""
        if space == "joint":
            return math.radians(self.joint_deg)
        if space == "cartesian":
            return self.ee_mm / 1000.0
        raise ValueError(f"space: expected one of {SPACES}, got {space!r}")

    def perturb(self, x: torch.Tensor, space: str, generator) -> torch.Tensor:
        """``x`` plus noise of this model in ``space`` (a new tensor; unchanged if sigma is 0).

        generator: a ``torch.Generator`` or a ``numpy.random.Generator`` (no draw is made when
        sigma is 0, so a noise-free model leaves the generator's stream untouched).
        """
        s = self.sigma(space)
        if s == 0.0:
            return x.clone()
        if isinstance(generator, np.random.Generator):
            noise = torch.from_numpy(generator.standard_normal(tuple(x.shape)))
        elif isinstance(generator, torch.Generator):
            noise = torch.randn(x.shape, generator=generator, dtype=torch.float64)
        else:
            raise TypeError(f"generator: expected a torch or numpy Generator, got {type(generator).__name__}")
        return x + (s * noise).to(device=x.device, dtype=x.dtype)

    def tolerance(self, space: str) -> float:
        """``NOISE_K`` standard deviations in the space's unit: how far noise may plausibly move a
        value (camo-hull's containment margin; the recording loader's bound check)."""
        return NOISE_K * self.sigma(space)


@dataclass(frozen=True)
class Observation:
    """One observed reach: its start, its goal and the trajectory seen, in one or both spaces.

    Attributes:
        start: (n,) start posture (observed; the first row of ``q`` when ``q`` is given).
        goal: (3,) Cartesian goal, known to the observer.
        q: (L, n) joint trajectory including the start, or None (end-effector-only recording).
        ee: (L, 3) end-effector trajectory, or None (joint-only recording).
    """

    start: torch.Tensor
    goal: torch.Tensor
    q: torch.Tensor | None = None
    ee: torch.Tensor | None = None

    def __post_init__(self):
        start = as_tensor(self.start, "start", dtype=torch.float64)
        goal = as_tensor(self.goal, "goal", dtype=torch.float64)
        if start.dim() != 1:
            raise ValueError(f"start: expected shape (n,), got {tuple(start.shape)}")
        if goal.shape != (3,):
            raise ValueError(f"goal: expected shape (3,), got {tuple(goal.shape)}")
        check_finite(start, "start")
        check_finite(goal, "goal")
        if self.q is None and self.ee is None:
            raise ValueError("q: an observation needs a joint trajectory (q), an end-effector one (ee), or both")
        lengths = []
        for name, width in (("q", start.shape[0]), ("ee", 3)):
            x = getattr(self, name)
            if x is None:
                continue
            x = as_tensor(x, name, dtype=torch.float64)
            if x.dim() != 2 or x.shape[1] != width or x.shape[0] < 1:
                raise ValueError(f"{name}: expected shape (L >= 1, {width}), got {tuple(x.shape)}")
            check_finite(x, name)
            object.__setattr__(self, name, x)
            lengths.append(x.shape[0])
        if len(lengths) == 2 and lengths[0] != lengths[1]:
            raise ValueError(f"ee: has {lengths[1]} samples but q has {lengths[0]}")
        object.__setattr__(self, "start", start)
        object.__setattr__(self, "goal", goal)

    @property
    def spaces(self) -> tuple[str, ...]:
        """The observation spaces this reach was recorded in."""
        return tuple(s for s, x in (("joint", self.q), ("cartesian", self.ee)) if x is not None)

    @property
    def length(self) -> int:
        return int((self.q if self.q is not None else self.ee).shape[0])

    def trajectory(self, space: str) -> torch.Tensor:
        """(L, n) for space='joint', (L, 3) for space='cartesian'."""
        if space not in SPACES:
            raise ValueError(f"space: expected one of {SPACES}, got {space!r}")
        x = self.q if space == "joint" else self.ee
        if x is None:
            other = "end-effector" if space == "joint" else "joint"
            raise ValueError(f"space: this observation has no {space} trajectory ({other} only); "
                             f"use space={self.spaces[0]!r} or a method that can")
        return x


@dataclass(frozen=True)
class Task:
    """A subject to infer (see the module docstring).

    Attributes:
        name: task name (e.g. "panda").  subject: ground-truth profile name or "recorded".
        simulator: a `Simulator` (or a `CountingSimulator` around one).
        prior: `BoxPrior` over theta (2n,).
        observations: observed reaches in the order they arrive.
        test_starts: (M, n) and test_goals: (M, 3) held-out reaches, or None (real data).
        true_theta: (2n,) float64 true limits, or None (real data).
        noise: `NoiseModel` of the observations.
    """

    name: str
    subject: str
    simulator: object
    prior: BoxPrior
    observations: tuple[Observation, ...]
    test_starts: torch.Tensor | None = None
    test_goals: torch.Tensor | None = None
    true_theta: torch.Tensor | None = None
    noise: NoiseModel = field(default_factory=NoiseModel)

    def __post_init__(self):
        if not isinstance(self.prior, BoxPrior):
            raise TypeError(f"prior: expected a BoxPrior, got {type(self.prior).__name__}")
        n = self.simulator.n_joints
        if self.prior.n_joints != n:
            raise ValueError(f"prior: has {self.prior.n_joints} joints, the simulator has {n}")
        obs = tuple(self.observations)
        for i, o in enumerate(obs):
            if not isinstance(o, Observation):
                raise TypeError(f"observations: item {i} is a {type(o).__name__}, not an Observation")
            if o.start.shape != (n,):
                raise ValueError(f"observations: reach {i} has a start of shape {tuple(o.start.shape)}, "
                                 f"the simulator has {n} joints")
        object.__setattr__(self, "observations", obs)
        if (self.test_goals is None) != (self.test_starts is None):
            raise ValueError("test_goals: give test_goals and test_starts together, or neither")
        if self.test_goals is not None:
            g = as_tensor(self.test_goals, "test_goals", dtype=torch.float64)
            s = as_tensor(self.test_starts, "test_starts", dtype=torch.float64)
            if g.dim() != 2 or g.shape[1] != 3 or s.shape != (g.shape[0], n):
                raise ValueError(f"test_goals: expected (M, 3) goals and (M, {n}) starts, got "
                                 f"{tuple(g.shape)} and {tuple(s.shape)}")
            object.__setattr__(self, "test_goals", g)
            object.__setattr__(self, "test_starts", s)
        if self.true_theta is not None:
            t = check_theta(as_tensor(self.true_theta, "true_theta", dtype=torch.float64), n, "true_theta")[0]
            object.__setattr__(self, "true_theta", t)
        if not isinstance(self.noise, NoiseModel):
            raise TypeError(f"noise: expected a NoiseModel, got {type(self.noise).__name__}")

    @property
    def n_joints(self) -> int:
        return self.simulator.n_joints

    @property
    def spaces(self) -> tuple[str, ...]:
        """Observation spaces in which every observed reach was recorded."""
        if not self.observations:
            return SPACES
        return tuple(s for s in SPACES if all(s in o.spaces for o in self.observations))

    @property
    def nominal_theta(self) -> torch.Tensor:
        """(2n,) the prior's full range of motion, known joints at their known limits."""
        return self.prior.outer_theta()

    def with_simulator(self, simulator) -> Task:
        return replace(self, simulator=simulator)

    def with_observations(self, observations) -> Task:
        return replace(self, observations=tuple(observations))

    def with_budget(self, budget: int | None) -> tuple[Task, CountingSimulator]:
        """This task with its simulator wrapped in a `CountingSimulator` capped at ``budget``."""
        counter = CountingSimulator(self.simulator, budget)
        return self.with_simulator(counter), counter

    def require_truth(self, what: str) -> torch.Tensor:
        """The true limits, or ValueError naming ``what`` (real data has none)."""
        if self.true_theta is None:
            raise ValueError(f"{what}: needs the true limits (task.true_theta), which recorded data does not have")
        return self.true_theta

    def observed_postures(self, observations=None) -> torch.Tensor | None:
        """(sum L, n) every observed joint posture (starts included), or None without joint data."""
        obs = self.observations if observations is None else tuple(observations)
        if not obs or any(o.q is None for o in obs):
            return None
        return torch.cat([torch.cat([o.start.unsqueeze(0), o.q]) for o in obs])


def check_observations(task: Task, observations, space: str | None = None) -> tuple[Observation, ...]:
    """Validated observations for a run: at least one, each an `Observation` with ``space``."""
    obs = tuple(task.observations if observations is None else observations)
    if not obs:
        raise ValueError("observations: at least one observed task is required")
    for i, o in enumerate(obs):
        if not isinstance(o, Observation):
            raise TypeError(f"observations: item {i} is a {type(o).__name__}, not an Observation")
        if o.start.shape != (task.n_joints,):
            raise ValueError(f"observations: reach {i} has a start of shape {tuple(o.start.shape)}, "
                             f"the task has {task.n_joints} joints")
        if space is not None:
            o.trajectory(space)  # ValueError naming `space` if this reach lacks it
    return obs

