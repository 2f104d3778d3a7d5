"""A simulator wrapper that counts and caps simulations: budgets are enforced, never self-reported."""

from __future__ import annotations

import numpy as np

from camo_sbi._validation import check_positive_int
from camo_sbi.simulators.base import Trajectories

__all__ = ["BudgetExceededError", "CountingSimulator", "charge", "unwrap_simulator"]


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


def _rows(x) -> int:
    """Batch rows of one `simulate` argument: 1 for a single vector, else the leading size.

    Works for every array type `simulate` accepts (torch tensors, numpy arrays, nested
    lists/tuples): a 2-D argument is a batch of ``shape[0]`` rows.
    """
    shape = getattr(x, "shape", None)
    if shape is None:
        shape = np.shape(x)
    return int(shape[0]) if len(shape) == 2 else 1


def _batch_size(theta, goal, start) -> int:
    """Number of trajectories a call produces: the broadcast batch of theta, goal and start."""
    return max(_rows(x) for x in (theta, goal, start) if x is not None)


def unwrap_simulator(simulator):
    """The simulator under any budget-counting wrappers (what is shipped to workers)."""
    while hasattr(simulator, "wrapped") and hasattr(simulator, "n_simulations"):
        simulator = simulator.wrapped
    return simulator


def charge(simulator, n: int) -> None:
    """Count ``n`` simulations run elsewhere against a counting wrapper's budget, beforehand.

    Mirrors `CountingSimulator.simulate`: raises `BudgetExceededError` if the budget would
    be exceeded, before anything is simulated. A plain simulator is not counted.
    """
    n = int(n)
    wrappers = []
    while hasattr(simulator, "wrapped") and hasattr(simulator, "n_simulations"):
        wrappers.append(simulator)
        simulator = simulator.wrapped
    for w in wrappers:
        budget = getattr(w, "budget", None)
        if budget is not None and w.n_simulations + n > budget:
            raise BudgetExceededError(
                f"budget: {w.n_simulations} simulations used, {n} more requested, budget is {budget}"
            )
    for w in wrappers:  # only after every wrapper accepted the request
        w.n_simulations += n
