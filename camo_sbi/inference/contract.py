"""The run contract every inference method follows, and its argument checks.

    run(task, observations, *, budget, seed, config) -> PosteriorResult

``budget`` is the number of simulated trajectories allowed *per observed task* (the
paper's b), so a run conditioned on k tasks may simulate at most ``budget * k``.
`camo_sbi.inference.registry.run_method` wraps the task's simulator in a
`CountingSimulator` that enforces that cap and supplies ``n_simulations``: methods never
self-report it. A method called directly (not through the registry) validates its
arguments with `check_run_args`, so both paths raise the same errors.
"""

from __future__ import annotations

from camo_sbi._validation import check_positive_int
from camo_sbi.priors import BoxPrior
from camo_sbi.task import Task, check_observations

__all__ = ["check_run_args"]


def check_run_args(task, observations, budget, seed, config, config_cls, *, space: str | None = None):
    """Validate a method's ``run`` arguments; returns (config, budget, seed, observations, prior).

    ``config`` None -> ``config_cls()``. ``space``: the observation space the method will
    read (every observation must have it; ValueError naming ``space`` otherwise). Errors
    name the argument (task, config, budget, seed, observations, task.prior, space).
    """
    if not isinstance(task, Task):
        raise TypeError(f"task: expected a camo_sbi.task.Task, got {type(task).__name__}")
    config = config_cls() if config is None else config
    if not isinstance(config, config_cls):
        raise TypeError(f"config: expected {config_cls.__name__}, got {type(config).__name__}")
    budget = check_positive_int(budget, "budget")
    seed = check_positive_int(seed, "seed", minimum=0)
    if space is None:
        space = getattr(config, "space", None)
    observations = check_observations(task, observations, space)
    prior = task.prior
    if not isinstance(prior, BoxPrior):
        raise TypeError(f"task.prior: expected a BoxPrior, got {type(prior).__name__}")
    return config, budget, seed, observations, prior
