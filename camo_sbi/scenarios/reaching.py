"""Synthetic reaching subjects: reachable goals, observed reaches and the `Task` that holds them.

The goal design, shared by every experiment: goals are joint configurations drawn
uniformly inside the subject's TRUE limits, mapped through FK, and kept only if the
subject's controller reaches them (the paper's "reachable random goals"). Goals therefore
depend on the true limits (a reach is only attempted where the person can go), which
the methods ignore: they treat goals as given.
"""

from __future__ import annotations

import torch

from camo_sbi._validation import as_tensor, check_positive_int, check_theta, torch_generator
from camo_sbi.priors import BoxPrior
from camo_sbi.simulators.base import theta_to_limits
from camo_sbi.task import NoiseModel, Observation, Task

__all__ = ["make_reaching_task", "nominal_workspace_goals", "observe", "reachable_goals"]


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


def nominal_workspace_goals(simulator, n: int, generator) -> torch.Tensor:
    """(n, 3) float64 goals: FK of configurations drawn uniformly inside the NOMINAL limits
    (``simulator.bounds``), with ``generator`` (a torch.Generator or an int seed). A subject with
    restricted limits may not reach some of them: that is the point of the informative design."""
    from camo_sbi.simulators import sample_goals

    return sample_goals(simulator, simulator.bounds.to(torch.float64), n, generator).to(torch.float64)


def make_reaching_task(simulator, true_theta, *, n_train: int = 10, n_test: int = 20, seed,
                       prior: BoxPrior | None = None, name: str = "reaching",
                       subject: str = "custom", start=None, noise: NoiseModel | None = None,
                       require_reached: bool = True) -> Task:
    """A synthetic subject with limits ``true_theta`` (2n,) observed on ``n_train`` goals.

    Goals (train and test) are joint configurations drawn uniformly inside the true
    limits mapped through FK, kept only if the subject's controller actually reaches
    them (`reachable_goals`; the paper's "reachable random goals"). All
    reaches start from ``start`` (default: the simulator's start posture). The default
    prior is the simulator's full range split at the start posture. ``noise``: the
    observation-noise model recorded in the task (the observations themselves are exact;
    add noise with `NoiseModel.perturb`). ``require_reached=False`` keeps every sampled
    goal (the authors' design: their fixed-horizon controller does not converge, so no goal
    is "reached"; goals are FK images of configurations inside the true limits all the same).
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
    if require_reached:
        goals = reachable_goals(simulator, true_theta, n_train + n_test, gen, start)
    else:
        from camo_sbi.simulators import sample_goals

        goals = sample_goals(simulator, theta_to_limits(true_theta), n_train + n_test, gen).to(torch.float64)
    obs = observe(simulator, true_theta, goals[:n_train], start)
    if prior is None:
        prior = BoxPrior(simulator.bounds, start)
    return Task(
        name=name, subject=subject, simulator=simulator, prior=prior, observations=obs,
        test_starts=start.expand(n_test, -1).clone(), test_goals=goals[n_train:].clone(),
        true_theta=true_theta.clone(), noise=NoiseModel() if noise is None else noise,
    )
