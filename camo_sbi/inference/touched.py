"""Touched bounds: the limits a reach is seen resting against, read exactly from the data.

A joint held at its limit while the controller still drives the arm stays at exactly the same
value for consecutive samples while other joints move (the limit clamps it). Such a bound is
observed: the observed extreme IS the limit. The observed min/max (`naive`) uses that
directly; a posterior point estimate (the argmax of a KDE product, a posterior mean) blurs it.
`touched_bounds` finds these bounds in joint observations; `with_touched` replaces them in a
method's result by the observed value (in the estimate and in every posterior sample) and keeps
the posterior for every other bound: the issue-23 fix "touched bounds from the data combined
with the posterior for the rest" (registered as ``camo-touched``: camo-seq combined so).

Detection rule (noise-free joint data): bound ``hi_j`` is touched if some reach that starts
away from the largest observed value of joint j has two consecutive samples within ``tol`` of
it while another joint moves by more than ``move_tol`` between them; ``lo_j`` likewise. (A
joint that never leaves its start, e.g. a roll that does not move the end effector, sits at
both its extremes while the others move: without the first condition it would count.) With joint noise of
standard deviation s, ``tol`` widens to 3 sigma (an honest approximation: at a clamp the noise-free
value is constant, the noisy one scatters around it).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

__all__ = ["noise_tol", "run", "run_sequence", "touched_bounds", "with_touched"]

TOL = 1e-9
MOVE_TOL = 1e-6


def touched_bounds(joint_trajectories, *, tol: float = TOL, move_tol: float = MOVE_TOL) -> tuple[np.ndarray, np.ndarray]:
    """((2n,) bool touched, (2n,) observed extremes [min_1, max_1, ...]) over (L_i, n) joint trajectories."""
    qs = [torch.as_tensor(q, dtype=torch.float64) for q in joint_trajectories]
    if not qs:
        raise ValueError("joint_trajectories: at least one trajectory is required")
    n = qs[0].shape[-1]
    allq = torch.cat(qs)
    ext = torch.stack([allq.min(dim=0).values, allq.max(dim=0).values], dim=1)  # (n, 2)
    touched = np.zeros((n, 2), dtype=bool)
    for q in qs:
        if q.shape[0] < 2:
            continue
        step = (q[1:] - q[:-1]).abs()  # (L-1, n)
        for side in (0, 1):
            at = (q - ext[:, side]).abs() <= tol  # (L, n)
            held = at[1:] & at[:-1]  # (L-1, n) two consecutive samples at the extreme
            moved_there = (q[0] - ext[:, side]).abs() > tol  # a joint that never left its start proves nothing
            for j in range(n):
                if not bool(moved_there[j]):
                    continue
                others = torch.cat([step[:, :j], step[:, j + 1:]], dim=1).amax(dim=1) > move_tol
                if bool((held[:, j] & others).any()):
                    touched[j, side] = True
    return touched.reshape(-1), ext.reshape(-1).numpy()


def noise_tol(task) -> float:
    """The detection tolerance for ``task``'s joint noise: 3 standard deviations (rad), or `TOL`."""
    return max(TOL, 3.0 * float(np.radians(task.noise.joint_deg)))


def with_touched(result, observations, prior, *, tol: float = TOL):
    """``result`` with every touched bound (`touched_bounds` of the joint observations) set to
    its observed value, in the estimate and in every sample; the other bounds, the weights and
    the status as the method left them. Known (fixed) coordinates keep their known values.
    ``extras["touched"]``: the (2n,) mask used."""
    touched, ext = touched_bounds([o.q for o in observations], tol=tol)
    touched &= prior.free_mask.numpy()
    est = np.array(result.estimate, dtype=np.float64, copy=True)
    samples = np.array(result.samples, dtype=np.float64, copy=True)
    est[touched] = ext[touched]
    samples[:, touched] = ext[touched]
    return replace(result, estimate=est, samples=samples,
                   extras={**result.extras, "touched": touched.tolist()})


def run_sequence(task, observations, *, budget: int, seed: int, config=None):
    """camo-touched: the configured CAMO (the registry applies camo-seq's defaults) after each
    task, its touched bounds replaced by their observed values (`with_touched`)."""
    from camo_sbi.inference import camo

    tol = noise_tol(task)
    for k, res in enumerate(camo.run_sequence(task, observations, budget=budget, seed=seed, config=config)):
        yield with_touched(res, observations[: k + 1], task.prior, tol=tol)


def run(task, observations, *, budget: int, seed: int, config=None):
    """The run contract for camo-touched (`run_sequence`'s last result)."""
    from camo_sbi.inference import camo

    res = camo.run(task, observations, budget=budget, seed=seed, config=config)
    return with_touched(res, observations, task.prior, tol=noise_tol(task))
