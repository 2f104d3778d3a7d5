"""A simulator wrapper that counts and caps simulations: budgets are enforced, never self-reported."""

from __future__ import annotations

import numpy as np

from camo_sbi import _memory
from camo_sbi._memory import size_text as _size
from camo_sbi._validation import check_positive_int, renamed_fields
from camo_sbi.simulators.base import Trajectories

__all__ = ["BudgetExceededError", "CountingSimulator", "announce_simulation_time", "charge", "check_budget_fits",
           "estimate_simulation_time", "unwrap_simulator"]


class BudgetExceededError(RuntimeError):
    """Raised when a method asks for more simulated trajectories than its budget allows."""


@renamed_fields(budget="max_simulations")  # a total cap; budget is per task
class CountingSimulator:
    """Wraps a simulator; one simulated trajectory (one theta for one goal) costs one unit.

    Every attribute other than ``simulate`` is delegated to the wrapped simulator, so the
    wrapper satisfies the `Simulator` protocol. A call that would exceed ``max_simulations``
    (a total cap: a run's per-task ``budget`` times its tasks; None: no cap) raises
    `BudgetExceededError` before simulating anything. Its message names ``budget``, the
    argument a user sets. (The cap's old name, ``budget``, is refused naming the new one.)
    """

    def __init__(self, simulator, max_simulations: int | None = None):
        self._sim = simulator
        self.max_simulations = (None if max_simulations is None
                                else check_positive_int(max_simulations, "max_simulations"))
        self.n_simulations = 0

    @property
    def wrapped(self):
        return self._sim

    @property
    def remaining(self) -> int | None:
        return None if self.max_simulations is None else self.max_simulations - self.n_simulations

    def simulate(self, theta, goal, start=None) -> Trajectories:
        b = _batch_size(theta, goal, start)
        if self.max_simulations is not None and self.n_simulations + b > self.max_simulations:
            raise BudgetExceededError(
                f"budget: {self.n_simulations} simulations used, {b} more requested, "
                f"budget is {self.max_simulations}"
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
        budget = getattr(w, "max_simulations", None)
        if budget is not None and w.n_simulations + n > budget:
            raise BudgetExceededError(
                f"budget: {w.n_simulations} simulations used, {n} more requested, budget is {budget}"
            )
    for w in wrappers:  # only after every wrapper accepted the request
        w.n_simulations += n


# --------------------------------------------------------------------------- what a budget costs

def _duration(s: float) -> str:
    if s < 120:
        return f"{s:.3g} s"
    if s < 7200:
        return f"{s / 60:.3g} min"
    if s < 2 * 86400:
        return f"{s / 3600:.3g} h"
    return f"{s / 86400:.3g} days"


def check_budget_fits(budget: int, *, n_joints: int, flag: str, memory_bytes: int | None = None) -> int:
    """Refuse a per-task budget this machine cannot hold; returns the least memory it needs (bytes).

    The estimate is a lower bound: every method keeps at least each simulation's parameters
    (2n float64) and one number for it (a distance, a weight), 8 (2n + 1) bytes per simulation.
    ValueError naming ``flag`` when that alone exceeds the physical memory (``memory_bytes``).
    """
    budget = check_positive_int(budget, flag.lstrip("-"))
    need = budget * (2 * int(n_joints) + 1) * 8
    avail = _memory.physical_memory() if memory_bytes is None else int(memory_bytes)
    if avail and need > avail:
        raise ValueError(f"{flag}: {budget} simulations per task need at least {_size(need)} of memory (their "
                         f"parameters and one number each), this machine has {_size(avail)}; use a smaller {flag}")
    return need


def estimate_simulation_time(simulator, n_simulations: int, *, sample: int = 256) -> tuple[float, float]:
    """(estimated seconds for ``n_simulations`` reaches, measured seconds per reach) from a short
    calibration: ``sample`` reaches to an unreachable goal (so every step of the controller runs:
    an upper bound per reach) at the simulator's nominal limits, timed once after a warm-up."""
    import time

    import torch

    theta = simulator.bounds.reshape(1, -1).expand(sample, -1).contiguous()
    goal = torch.full((sample, 3), 1e3, dtype=theta.dtype)
    simulator.simulate(theta[:2], goal[:2])  # compiles, if it has to
    t0 = time.perf_counter()
    simulator.simulate(theta, goal)
    per = (time.perf_counter() - t0) / sample
    return per * int(n_simulations), per


def announce_simulation_time(simulator, n_simulations: int, *, what: str) -> float:
    """Log (a warning above 10 minutes) the calibrated time of ``n_simulations`` reaches; returns it."""
    import logging

    total, per = estimate_simulation_time(simulator, n_simulations)
    log = logging.getLogger(__name__)
    level = logging.WARNING if total > 600 else logging.INFO
    log.log(level, "%s: %d simulations, about %s of simulation at most (measured %.3g ms per reach, one thread)",
            what, int(n_simulations), _duration(total), per * 1e3)
    return total
