"""Synthetic reaching subjects: reachable goals, observed reaches and the `Task` that holds them.

The goal design, shared by every experiment: goals are joint configurations drawn
uniformly inside the subject's TRUE limits, mapped through FK, and kept only if the
subject's controller reaches them (the paper's "reachable random goals"). Goals therefore
depend on the true limits (a reach is only attempted where the person can go), which
the methods ignore: they treat goals as given.

The informative design (``workspace="nominal"``, `nominal_workspace_goals`) draws goals inside
the NOMINAL limits instead, so some lie beyond the subject's reach and the restriction shapes
many reaches. `binding_reaches` / `binding_fraction` measure how many reaches a restriction
actually touches: every experiment records it (``binding_test_fraction``).
"""

from __future__ import annotations

import torch

from camo_sbi._validation import as_tensor, check_positive_int, check_theta, torch_generator
from camo_sbi.priors import BoxPrior
from camo_sbi.simulators.base import Trajectories, theta_to_limits
from camo_sbi.task import NoiseModel, Observation, Task

__all__ = ["BINDING_TOL_M", "binding_fraction", "binding_reaches", "informative_test_goals", "make_reaching_task",
           "nominal_workspace_goals", "observe", "reachable_goals", "task_binding_metrics"]

BINDING_TOL_M = 1e-3
"""A reach binds if relaxing the restriction moves its end-effector path by more than this (metres)."""


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


def _max_path_move(a, b) -> torch.Tensor:
    """(M,) largest end-effector distance between reach i of ``a`` and of ``b`` (Trajectories) over
    the steps either uses, each reach holding its final valid point after it stops."""
    la, lb = a.length.long(), b.length.long()
    steps = int(torch.maximum(la, lb).max())
    t = torch.arange(steps).expand(la.shape[0], steps)

    def held(x, length):
        idx = torch.minimum(t, (length - 1).unsqueeze(-1))
        return x.to(torch.float64).gather(1, idx.unsqueeze(-1).expand(-1, -1, 3))

    return (held(a.ee, la) - held(b.ee, lb)).norm(dim=-1).amax(dim=1)


def binding_reaches(simulator, true_theta, nominal_theta, starts, goals, *, tol_m: float = BINDING_TOL_M,
                    per_bound: bool = False) -> torch.Tensor:
    """Which reaches the subject's restriction touches.

    Reach i (from ``starts`` (M, n) or (n,) to ``goals`` (M, 3)) binds if its TRUE end-effector
    path (limits ``true_theta`` (2n,)) moves by more than ``tol_m`` metres at some step when
    every restricted bound (those differing from ``nominal_theta`` (2n,)) is relaxed to its
    nominal value. Returns (M,) bool; with ``per_bound=True`` a (2n, M) bool instead, row c
    relaxing bound c alone (rows of unrestricted bounds are all False). One batched simulate.
    """
    truth = check_theta(as_tensor(true_theta, "true_theta", dtype=torch.float64), simulator.n_joints,
                        "true_theta")[0]
    nominal = check_theta(as_tensor(nominal_theta, "nominal_theta", dtype=torch.float64), simulator.n_joints,
                          "nominal_theta")[0]
    goals = as_tensor(goals, "goals", dtype=torch.float64)
    if goals.dim() != 2 or goals.shape[1] != 3:
        raise ValueError(f"goals: expected shape (M, 3), got {tuple(goals.shape)}")
    if not tol_m > 0:
        raise ValueError(f"tol_m: must be > 0, got {tol_m}")
    m = goals.shape[0]
    starts = as_tensor(starts, "starts", dtype=torch.float64)
    starts = starts.expand(m, -1) if starts.dim() == 1 else starts
    restricted = [c for c in range(truth.shape[0]) if abs(float(truth[c] - nominal[c])) > 1e-12]
    if per_bound:
        out = torch.zeros(truth.shape[0], m, dtype=torch.bool)
        rows = []
        for c in restricted:
            r = truth.clone()
            r[c] = nominal[c]
            rows.append(r)
    else:
        out = torch.zeros(m, dtype=torch.bool)
        relaxed = truth.clone()
        relaxed[restricted] = nominal[restricted]
        rows = [relaxed]
    if not restricted:
        return out
    k = len(rows)
    thetas = torch.cat([truth.expand(m, -1)] + [r.expand(m, -1) for r in rows])
    sims = simulator.simulate(thetas, goals.repeat(k + 1, 1), starts.repeat(k + 1, 1))
    moved = torch.stack([_max_path_move(_rows(sims, 0, m), _rows(sims, (j + 1) * m, m)) > tol_m
                         for j in range(k)])
    if not per_bound:
        return moved[0]
    out[restricted] = moved
    return out


def _rows(traj: Trajectories, first: int, m: int) -> Trajectories:
    sl = slice(first, first + m)
    return Trajectories(traj.q[sl], traj.ee[sl], traj.length[sl], traj.reached[sl])


def binding_fraction(simulator, true_theta, nominal_theta, starts, goals, *, tol_m: float = BINDING_TOL_M) -> float:
    """The share of reaches the restriction touches (`binding_reaches`), in [0, 1]."""
    return float(binding_reaches(simulator, true_theta, nominal_theta, starts, goals, tol_m=tol_m)
                 .to(torch.float64).mean())


def task_binding_metrics(task: Task, simulator=None, *, nominal_theta=None) -> dict[str, float]:
    """``binding_test_fraction``, ``binding_test_reaches`` (count) and ``binding_train_fraction``,
    ``binding_train_reaches`` of a synthetic task: its held-out goals and its observed reaches'
    goals (`binding_reaches`); ``binding_test_bound_min_fraction``: the least, over the
    restricted bounds, share of held-out reaches that relaxing that bound alone moves. ``nominal_theta``: the nominal limits (default: the prior's outer
    bounds, the full range of motion). ``simulator``: the subject's body when it differs from
    ``task.simulator`` (robustness)."""
    sim = task.simulator if simulator is None else simulator
    truth = task.require_truth("task_binding_metrics")
    nominal = task.prior.outer_theta() if nominal_theta is None else nominal_theta
    out = {}
    sets = [("test", task.test_starts, task.test_goals)]
    if task.observations and all(o.goal is not None for o in task.observations):
        sets.append(("train", torch.stack([o.start for o in task.observations]),
                     torch.stack([o.goal for o in task.observations])))
    for which, s, g in sets:
        if g is None:
            continue
        hit = binding_reaches(sim, truth, nominal, s, torch.as_tensor(g, dtype=torch.float64))
        out[f"binding_{which}_fraction"] = float(hit.to(torch.float64).mean())
        out[f"binding_{which}_reaches"] = float(hit.sum())
    restricted = (truth - torch.as_tensor(nominal, dtype=torch.float64)).abs() > 1e-12
    if bool(restricted.any()):
        per = binding_reaches(sim, truth, nominal, task.test_starts, task.test_goals, per_bound=True)
        out["binding_test_bound_min_fraction"] = float(per[restricted].to(torch.float64).mean(dim=1).min())
    return out


def informative_test_goals(simulator, true_theta, n: int, generator, start, *, min_binding: float = 0.5,
                           max_rounds: int = 50) -> torch.Tensor:
    """(n, 3) goals from the nominal workspace of which at least ``min_binding`` bind (`binding_reaches`).

    Candidates are drawn in rounds of 2n (`nominal_workspace_goals`) and kept in draw order
    until n are kept, a non-binding one only while fewer than ``n - ceil(min_binding * n)`` are
    kept: the plain draw whenever its first n bind often enough, else later binding goals
    replace the surplus non-binding ones (a quota; every table states ``binding_test_fraction``).
    """
    import math

    n = check_positive_int(n, "n")
    if not 0.0 <= min_binding <= 1.0:
        raise ValueError(f"min_binding: expected a value in [0, 1], got {min_binding}")
    need = math.ceil(min_binding * n)
    nominal = simulator.bounds.to(torch.float64).reshape(-1)
    kept, n_free = [], 0
    for _ in range(max_rounds):
        cand = nominal_workspace_goals(simulator, 2 * n, generator)
        hit = binding_reaches(simulator, true_theta, nominal, start, cand)
        for g, h in zip(cand, hit.tolist(), strict=True):
            if not h and n_free >= n - need:
                continue
            kept.append(g)
            n_free += not h
            if len(kept) == n:
                return torch.stack(kept)
    raise ValueError(f"true_theta: fewer than {need} of {2 * n * max_rounds} nominal-workspace goals bind")


def make_reaching_task(simulator, true_theta, *, n_train: int = 10, n_test: int = 20, seed,
                       prior: BoxPrior | None = None, name: str = "reaching",
                       subject: str = "custom", start=None, noise: NoiseModel | None = None,
                       require_reached: bool = True, workspace: str = "true",
                       min_binding_test: float | None = None) -> Task:
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
    ``workspace="nominal"``: goals are drawn inside the NOMINAL limits (`nominal_workspace_goals`)
    and all kept, reached or not (the informative design); ``require_reached`` is then ignored.
    ``min_binding_test``: with ``workspace="nominal"``, at least this share of the test goals
    bind (`informative_test_goals`; None: the plain draw).
    """
    if workspace not in ("true", "nominal"):
        raise ValueError(f"workspace: expected 'true' or 'nominal', got {workspace!r}")
    n_train = check_positive_int(n_train, "n_train")
    n_test = check_positive_int(n_test, "n_test")
    true_theta = check_theta(as_tensor(true_theta, "true_theta", dtype=torch.float64),
                             simulator.n_joints, "true_theta")[0]
    start = simulator.start.to(torch.float64) if start is None else as_tensor(start, "start", dtype=torch.float64)
    lim = theta_to_limits(true_theta)
    if bool(((start < lim[:, 0] - 1e-9) | (start > lim[:, 1] + 1e-9)).any()):
        raise ValueError("start: posture lies outside true_theta's limits")
    gen = torch_generator(seed)
    if workspace == "nominal" and min_binding_test is not None:
        goals = torch.cat([nominal_workspace_goals(simulator, n_train, gen),
                           informative_test_goals(simulator, true_theta, n_test, gen, start,
                                                  min_binding=min_binding_test)])
    elif workspace == "nominal":
        goals = nominal_workspace_goals(simulator, n_train + n_test, gen)
    elif require_reached:
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
