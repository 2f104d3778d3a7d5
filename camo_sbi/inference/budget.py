"""A simulator wrapper that counts and caps simulations: budgets are enforced, never self-reported."""

from __future__ import annotations

from camo_sbi._validation import check_positive_int
from camo_sbi.simulators.base import Trajectories

__all__ = ["BudgetExceededError", "CountingSimulator"]


class BudgetExceededError(RuntimeError):
    """Raised when a method asks for more simulated trajectories than its budget allows."""


class CountingSimulator:
    """Wraps a simulator; one simulated trajectory (one theta for one goal) costs one unit.

    Every attribute other than ``simulate`` is delegated to the wrapped simulator, so the
    wrapper satisfies the `Simulator` protocol. A call that would exceed ``budget``
    raises `BudgetExceededError` before simulating anything.
    """

    def __init__(self, simulator, budget: int | None):
        self._sim = simulator
        self.budget = None if budget is None else check_positive_int(budget, "budget")
        self.n_simulations = 0

    @property
    def wrapped(self):
        return self._sim

    @property
    def remaining(self) -> int | None:
        return None if self.budget is None else self.budget - self.n_simulations

    def simulate(self, theta, goal, start=None) -> Trajectories:
        b = _batch_size(theta, goal, start)
        if self.budget is not None and self.n_simulations + b > self.budget:
            raise BudgetExceededError(
                f"budget: {self.n_simulations} simulations used, {b} more requested, "
                f"budget is {self.budget}"
            )
        out = self._sim.simulate(theta, goal, start)
        self.n_simulations += b
        return out

    def __getattr__(self, name):
        return getattr(self._sim, name)




def _batch_size(theta, goal, start) -> int:
    """Number of trajectories a call produces: the broadcast batch of theta, goal and start."""
    sizes = [int(x.shape[0]) for x in (theta, goal, start)
             if x is not None and hasattr(x, "dim") and x.dim() == 2]
    if not sizes:
        return 1
    return max(sizes)
