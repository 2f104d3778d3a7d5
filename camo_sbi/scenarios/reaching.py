"""Reaching tasks: observed trajectories, held-out test goals, prediction and its errors.

A `ReachingTask` bundles everything a method needs (as sbibm's task): the simulator,
the prior, the observations (start, goal, trajectory), held-out test goals and, for
synthetic subjects, the true limits.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from camo_sbi._validation import as_tensor, check_positive_int, check_theta, torch_generator
from camo_sbi.inference.priors import BoxPrior
from camo_sbi.simulators.base import Trajectories, theta_to_limits

__all__ = [
    "Observation",
    "ReachingTask",
    "cumulative_cartesian_error",
    "cumulative_joint_error",
    "make_reaching_task",
    "observe",
    "predict",
    "reachable_goals",
]

SPACES = ("joint", "cartesian")


@dataclass(frozen=True)
class Observation:
    """One observed reach.

    Attributes:
        start: (n,) start posture.  goal: (3,) Cartesian goal.
        q: (L, n) observed joint trajectory (valid steps only).
        ee: (L, 3) observed end-effector trajectory.
    """

    start: torch.Tensor
    goal: torch.Tensor
    q: torch.Tensor
    ee: torch.Tensor

    def trajectory(self, space: str) -> torch.Tensor:
        """(L, n) for space='joint', (L, 3) for space='cartesian'."""
        if space == "joint":
            return self.q
        if space == "cartesian":
            return self.ee
        raise ValueError(f"space: expected one of {SPACES}, got {space!r}")


@dataclass(frozen=True)
class ReachingTask:
    """A subject to infer: simulator, prior, observations and held-out test goals.

    Attributes:
        name: task name (e.g. "panda").  subject: ground-truth profile name.
        simulator: a `Simulator`.  prior: `BoxPrior` over theta (2n,).
        observations: training observations in the order they arrive.
        test_starts: (M, n) and test_goals: (M, 3) held-out reaches.
        true_theta: (2n,) float64 true limits, or None for real data.
    """

    name: str
    subject: str
    simulator: object
    prior: BoxPrior
    observations: tuple[Observation, ...]
    test_starts: torch.Tensor
    test_goals: torch.Tensor
    true_theta: torch.Tensor | None = None

    @property
    def n_joints(self) -> int:
        return self.simulator.n_joints

    def with_simulator(self, simulator) -> ReachingTask:
        return replace(self, simulator=simulator)


def observe(simulator, theta, goals, start=None) -> tuple[Observation, ...]:
    """Simulate the subject with limits ``theta`` (2n,) reaching ``goals`` (M, 3) from ``start``.

    start: (n,) shared, (M, n) per goal, or None (the simulator's start posture).
    Returns one `Observation` per goal, trimmed to its valid length, float64.
    """
    theta = check_theta(as_tensor(theta, "theta", dtype=torch.float64), simulator.n_joints)
    goals = as_tensor(goals, "goals", dtype=torch.float64)
    if goals.dim() != 2 or goals.shape[1] != 3:
        raise ValueError(f"goals: expected shape (M, 3), got {tuple(goals.shape)}")
    m = goals.shape[0]
    start = simulator.start if start is None else start
    start = as_tensor(start, "start", dtype=torch.float64)
    starts = start.expand(m, -1) if start.dim() == 1 else start
    traj = simulator.simulate(theta.expand(m, -1), goals, starts)
    return tuple(
        Observation(starts[i].clone(), goals[i].clone(), traj.trimmed(i, "joint").clone(),
                    traj.trimmed(i, "cartesian").clone())
        for i in range(m)
    )


def predict(simulator, theta_hat, starts, goals) -> Trajectories:
    """Trajectories predicted with limits ``theta_hat`` (2n,) for ``goals`` (M, 3) from ``starts`` (M, n) or (n,).

    An estimate that excludes a start posture is widened to contain it (the start is observed).
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
    lim = theta_to_limits(theta_hat[0])
    # the observed start bounds the limits: widen an estimate that excludes it
    lo = torch.minimum(lim[:, 0].expand_as(starts), starts)
    hi = torch.maximum(lim[:, 1].expand_as(starts), starts)
    theta_b = torch.stack([lo, hi], dim=-1).reshape(starts.shape[0], -1)
    return simulator.simulate(theta_b, goals, starts)


def cumulative_cartesian_error(true: Trajectories, pred: Trajectories) -> torch.Tensor:
    """(M,) per goal: sum over time steps of ||ee_true(t) - ee_pred(t)||, padded trajectories
    compared step by step (a trajectory that stopped early holds its final point)."""
    _check_pair(true, pred)
    return (true.ee - pred.ee).norm(dim=-1).sum(dim=-1)


def cumulative_joint_error(true: Trajectories, pred: Trajectories) -> torch.Tensor:
    """(M,) per goal: sum over time steps of ||q_true(t) - q_pred(t)|| (joint space, radians)."""
    _check_pair(true, pred)
    return (true.q - pred.q).norm(dim=-1).sum(dim=-1)


def _check_pair(true: Trajectories, pred: Trajectories) -> None:
    if not isinstance(true, Trajectories) or not isinstance(pred, Trajectories):
        raise TypeError("true/pred: expected Trajectories")
    if true.q.shape != pred.q.shape:
        raise ValueError(f"pred: shape {tuple(pred.q.shape)} does not match true {tuple(true.q.shape)}")


def reachable_goals(simulator, true_theta, n: int, generator, start=None, *, max_rounds: int = 20) -> torch.Tensor:
    """(n, 3) float64 goals that the subject with limits ``true_theta`` reaches from ``start``.

    Candidates are FK images of configurations drawn uniformly inside the limits
    (`sample_goals`), drawn in rounds of 2n with ``generator``; candidates the controller
    does not reach within tolerance are dropped, in draw order.
    """
    from camo_sbi.simulators import sample_goals

    n = check_positive_int(n, "n")
    lim = theta_to_limits(true_theta.reshape(-1))
    start = simulator.start if start is None else start
    found = []
    total = 0
    for _ in range(max_rounds):
        cand = sample_goals(simulator, lim, 2 * n, generator).to(torch.float64)
        traj = simulator.simulate(true_theta.reshape(1, -1).expand(2 * n, -1), cand,
                                  torch.as_tensor(start, dtype=torch.float64))
        found.append(cand[traj.reached])
        total += int(traj.reached.sum())
        if total >= n:
            return torch.cat(found)[:n]
    raise ValueError(f"true_theta: only {total} of {2 * n * max_rounds} sampled goals were reachable")


def make_reaching_task(simulator, true_theta, *, n_train: int = 10, n_test: int = 20, seed,
                       prior: BoxPrior | None = None, name: str = "reaching",
                       subject: str = "custom", start=None) -> ReachingTask:
    """A synthetic subject with limits ``true_theta`` (2n,) observed on ``n_train`` goals.

    Goals (train and test) are joint configurations drawn uniformly inside the true
    limits mapped through FK, kept only if the subject's controller actually reaches
    them (`reachable_goals`; the paper's "reachable random goals"). All
    reaches start from ``start`` (default: the simulator's start posture). The default
    prior is the simulator's full range split at the start posture.
    """
    n_train = check_positive_int(n_train, "n_train")
    n_test = check_positive_int(n_test, "n_test")
    true_theta = check_theta(as_tensor(true_theta, "true_theta", dtype=torch.float64),
                             simulator.n_joints, "true_theta")[0]
    start = simulator.start.to(torch.float64) if start is None else as_tensor(start, "start", dtype=torch.float64)
    lim = theta_to_limits(true_theta)
    if bool(((start < lim[:, 0] - 1e-9) | (start > lim[:, 1] + 1e-9)).any()):
        raise ValueError("start: posture lies outside true_theta's limits")
    gen = torch_generator(seed)
    goals = reachable_goals(simulator, true_theta, n_train + n_test, gen, start)
    obs = observe(simulator, true_theta, goals[:n_train], start)
    if prior is None:
        prior = BoxPrior(simulator.bounds, start)
    return ReachingTask(
        name=name, subject=subject, simulator=simulator, prior=prior, observations=obs,
        test_starts=start.expand(n_test, -1).clone(), test_goals=goals[n_train:].clone(),
        true_theta=true_theta.clone(),
    )
