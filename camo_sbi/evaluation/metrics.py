"""Prediction and limit metrics: the one module every experiment, table and figure uses.

Prediction metrics compare a true and a predicted batch of reaches (`Trajectories` with the
same goals and starts, reach b of one against reach b of the other):

``cartesian_error_mm`` (per reach)
    Mean Euclidean distance per point between the two end-effector paths, in millimetres,
    over the steps ``t < max(L_true, L_pred)``: the valid steps of the longer reach, the
    one that stopped earlier holding its final point until the other stops. Steps beyond
    both valid lengths (padding) are never counted, so the value does not depend on the
    simulator's ``max_steps`` once both reaches have stopped.
``joint_error_deg`` (per reach)
    The same in joint space: mean absolute error per joint per point, in degrees.
``eq2_cartesian`` / ``eq2_joint`` (per reach; tables sum them over the test goals, as Fig. 2)
    The paper's Eq. 2, the L2 norm of the stacked difference ``sqrt(sum_t |x_t - y_t|^2)``
    over ALL ``T`` points of the fixed-horizon arrays (metres / radians). It grows with the
    horizon by construction: with an early-stopping controller and ``T = 100`` the repeated
    final point is counted ~80 times; compare it only between runs of the same horizon.
``reference_cartesian`` / ``reference_joint`` (per reach; tables sum them over the test goals)
    The authors' code's metric (``REFERENCE_SETTING.md``, ``test_estimated_parameters*``):
    ``np.sum(np.linalg.norm(true - pred, axis=0))`` on a (T, D) trajectory, i.e. the L2
    norm over time of each axis, summed over the axes; over all ``T`` points like Eq. 2.

Reachability (informative setting: goals from the nominal workspace, some beyond the subject):
``reachability_precision`` / ``reachability_recall`` / ``reachability_f1`` / ``reachability_accuracy``
    Predicted reached / not reached (the controller stops within its tolerance) against the
    true labels, "reached" being the positive class as "person" is in the block-stacking
    scene, with its zero-denominator rule: precision with no predicted reach is 1 if no goal
    is truly reached and 0 otherwise; recall likewise.

Limit metrics (degrees; prismatic joints: their value in metres times 180/pi) cover the
prior's free coordinates only (known limits are never estimated):

``limit_error_deg``
    Mean absolute error over all free bounds.
``limit_error_binding_deg``
    Over the bounds that the true limits *bind* on the test reaches (`binding_bounds`):
    relaxing that single bound to the full range of motion changes a true test
    trajectory. These are the bounds the test reaches can identify.
``limit_error_free_deg``
    Over the other free bounds, which the test reaches cannot identify.
"""

from __future__ import annotations

import numpy as np
import torch

from camo_sbi.evaluation import catalog
from camo_sbi.simulators.base import Trajectories
from camo_sbi.task import contain

__all__ = [
    "BINDING_TOL_RAD",
    "binding_bounds",
    "cartesian_error_mm",
    "eq2_cartesian",
    "eq2_joint",
    "joint_error_deg",
    "limit_error_groups",
    "limit_errors",
    "prediction_metrics",
    "reachability_metrics",
    "reference_cartesian",
    "reference_joint",
]

BINDING_TOL_RAD = 1e-3
"""A bound binds if relaxing it moves some joint of some true test reach by more than this (rad)."""

def _pair(true: Trajectories, pred: Trajectories) -> None:
    if not isinstance(true, Trajectories) or not isinstance(pred, Trajectories):
        raise TypeError(f"pred: expected Trajectories for true and pred, got {type(true).__name__} "
                        f"and {type(pred).__name__}")
    if true.q.shape != pred.q.shape:
        raise ValueError(f"pred: shape {tuple(pred.q.shape)} does not match true {tuple(true.q.shape)}")


def _held(x: torch.Tensor, length: torch.Tensor, steps: int) -> torch.Tensor:
    """x (B, T, D) -> (B, steps, D): step t is x[min(t, length - 1)] (the final valid point held)."""
    B, _, D = x.shape
    t = torch.arange(steps, device=x.device).expand(B, steps)
    idx = torch.minimum(t, (length.to(x.device).long() - 1).unsqueeze(-1))
    return x.gather(1, idx.unsqueeze(-1).expand(B, steps, D))


def _per_point(true: Trajectories, pred: Trajectories, space: str) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, S, D) true and predicted points over S = max valid length, each reach holding its end;
    plus the (B, S) mask of the steps t < max(L_true[b], L_pred[b]) that count."""
    _pair(true, pred)
    lt, lp = true.length.long(), pred.length.long()
    span = torch.maximum(lt, lp)
    steps = int(span.max())
    a = true.q if space == "joint" else true.ee
    b = pred.q if space == "joint" else pred.ee
    a, b = _held(a.to(torch.float64), lt, steps), _held(b.to(torch.float64), lp, steps)
    mask = torch.arange(steps, device=a.device).expand(a.shape[0], steps) < span.to(a.device).unsqueeze(-1)
    return a - b, mask


def cartesian_error_mm(true: Trajectories, pred: Trajectories) -> torch.Tensor:
    """(M,) mean Euclidean end-effector distance per point (mm), padding-free (module docstring)."""
    diff, mask = _per_point(true, pred, "cartesian")
    d = diff.norm(dim=-1) * mask
    return 1000.0 * d.sum(dim=1) / mask.sum(dim=1)


def joint_error_deg(true: Trajectories, pred: Trajectories) -> torch.Tensor:
    """(M,) mean absolute joint error per joint per point (degrees), padding-free."""
    diff, mask = _per_point(true, pred, "joint")
    d = diff.abs().mean(dim=-1) * mask
    return torch.rad2deg(d.sum(dim=1) / mask.sum(dim=1))


def _fixed_horizon(true: Trajectories, pred: Trajectories, space: str) -> torch.Tensor:
    _pair(true, pred)
    x = (true.q, pred.q) if space == "joint" else (true.ee, pred.ee)
    return x[0].to(torch.float64) - x[1].to(torch.float64)  # (M, T, D)


def eq2_cartesian(true: Trajectories, pred: Trajectories) -> torch.Tensor:
    """(M,) the paper's Eq. 2 on end-effector paths: sqrt(sum over all T points and axes of diff^2) [m]."""
    return _fixed_horizon(true, pred, "cartesian").pow(2).sum(dim=(1, 2)).sqrt()


def eq2_joint(true: Trajectories, pred: Trajectories) -> torch.Tensor:
    """(M,) the paper's Eq. 2 on joint paths [rad]."""
    return _fixed_horizon(true, pred, "joint").pow(2).sum(dim=(1, 2)).sqrt()


def reference_cartesian(true: Trajectories, pred: Trajectories) -> torch.Tensor:
    """(M,) the authors' metric on end-effector paths: sum over axes of the L2 norm over time [m]."""
    return _fixed_horizon(true, pred, "cartesian").pow(2).sum(dim=1).sqrt().sum(dim=-1)


def reference_joint(true: Trajectories, pred: Trajectories) -> torch.Tensor:
    """(M,) the authors' metric on joint paths [rad]."""
    return _fixed_horizon(true, pred, "joint").pow(2).sum(dim=1).sqrt().sum(dim=-1)


def prediction_metrics(true: Trajectories, pred: Trajectories) -> dict[str, float]:
    """Every prediction metric of the catalog (``group="prediction"``, in its order) aggregated
    over the test reaches as the tables report them: ``cartesian_error_mm`` and
    ``joint_error_deg`` the mean over reaches; ``eq2_*`` and ``reference_*`` the sum over
    reaches (the paper's Fig. 2 sums over its 20 test goals)."""
    _pair(true, pred)
    s = _PairScoring(true, pred)
    return {m.name: m.reduce(m.score(s)) for m in catalog.METRICS if m.group == "prediction" and m.score}


class _PairScoring:
    """What a prediction metric's score reads of `camo_sbi.evaluation.evaluate.Scoring`: one pair."""

    def __init__(self, true: Trajectories, pred: Trajectories):
        self.true_test, self.pred = true, pred

    def trajectory_error(self, name: str) -> torch.Tensor:
        return _PER_REACH[name](self.true_test, self.pred)


_PER_REACH = {f.__name__: f for f in (cartesian_error_mm, joint_error_deg, eq2_cartesian, eq2_joint,
                                       reference_cartesian, reference_joint)}


def reachability_metrics(true: Trajectories, pred: Trajectories) -> dict[str, float]:
    """Precision, recall, F1 and accuracy of the predicted reached labels against the true ones
    (module docstring; "reached" is the positive class)."""
    _pair(true, pred)
    t, p = true.reached.bool(), pred.reached.bool()
    tp, fp = int((t & p).sum()), int((~t & p).sum())
    fn, tn = int((t & ~p).sum()), int((~t & ~p).sum())
    precision = tp / (tp + fp) if tp + fp else float(fn == 0)
    recall = tp / (tp + fn) if tp + fn else float(fp == 0)
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {"reachability_precision": precision, "reachability_recall": recall, "reachability_f1": f1,
            "reachability_accuracy": (tp + tn) / max(1, tp + fp + fn + tn)}


def binding_bounds(simulator, true_theta, starts, goals, prior, *, tol: float = BINDING_TOL_RAD) -> np.ndarray:
    """(2n,) bool: the free bounds that the true limits bind on the reaches ``goals`` from ``starts``.

    Bound c binds if replacing it alone by the prior's outer bound (the full range of motion)
    changes some true trajectory: some joint of some reach, over the steps either version
    uses, moves by more than ``tol`` radians. A bound already at its outer value, and every
    fixed (known) coordinate, does not bind. One batched ``simulate`` call of 2n x M reaches.
    """
    truth = torch.as_tensor(true_theta, dtype=torch.float64).reshape(-1)
    goals = torch.as_tensor(goals, dtype=torch.float64)
    starts = torch.as_tensor(starts, dtype=torch.float64)
    m, dim = goals.shape[0], truth.shape[0]
    outer = prior.outer_theta()
    cand = [c for c in range(dim) if bool(prior.free_mask[c]) and abs(float(outer[c] - truth[c])) > 1e-12]
    out = np.zeros(dim, dtype=bool)
    if not cand:
        return out
    relaxed = truth.repeat(len(cand), 1)
    for row, c in enumerate(cand):
        relaxed[row, c] = outer[c]
    base = simulator.simulate(contain(truth.expand(m, -1), starts), goals, starts)
    theta_r = contain(relaxed.repeat_interleave(m, 0), starts.repeat(len(cand), 1))
    sims = simulator.simulate(theta_r, goals.repeat(len(cand), 1), starts.repeat(len(cand), 1))
    ref = Trajectories(base.q.repeat(len(cand), 1, 1), base.ee.repeat(len(cand), 1, 1),
                       base.length.repeat(len(cand)), base.reached.repeat(len(cand)))
    diff, mask = _per_point(ref, sims, "joint")
    moved = (diff.abs().amax(dim=-1) * mask).amax(dim=1).reshape(len(cand), m).amax(dim=1)
    for row, c in enumerate(cand):
        out[c] = bool(moved[row] > tol)
    return out


def limit_error_groups(estimate, true_theta, prior, binding: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The absolute errors in degrees of the prior's free bounds, per group: ``limit_error_deg``
    (every free bound) and, with ``binding`` ((2n,) bool from `binding_bounds`),
    ``limit_error_binding_deg`` and ``limit_error_free_deg``. A group with no bound in it
    (e.g. no bound binds) is left out."""
    est = torch.as_tensor(estimate, dtype=torch.float64).reshape(-1)
    truth = torch.as_tensor(true_theta, dtype=torch.float64).reshape(-1)
    err = np.degrees((est - truth).abs().numpy())
    free = prior.free_mask.numpy()
    groups = {"limit_error_deg": free}
    if binding is not None:
        groups["limit_error_binding_deg"] = free & binding
        groups["limit_error_free_deg"] = free & ~binding
    return {name: err[mask] for name, mask in groups.items() if mask.any()}


def limit_errors(estimate, true_theta, prior, binding: np.ndarray | None = None) -> dict[str, float]:
    """Limit errors in degrees over the prior's free coordinates (module docstring): the mean
    of each group of `limit_error_groups` (None ``binding``: only ``limit_error_deg``; a group
    with no bound in it is left out of the result, not NaN)."""
    return {name: float(err.mean()) for name, err in limit_error_groups(estimate, true_theta, prior, binding).items()}
