"""The method registry and the one `run` contract every inference method follows.

    run(task, observations, *, budget, seed, config) -> PosteriorResult

``budget`` is the number of simulated trajectories allowed *per observed task* (the
paper's b), so a run conditioned on k tasks may simulate at most ``budget * k``
trajectories. `run_method` wraps the task's simulator in a `CountingSimulator` that
enforces that cap and supplies ``n_simulations``: methods never self-report it.
"""

from __future__ import annotations

import dataclasses
import importlib
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from camo_sbi._validation import check_positive_int
from camo_sbi.inference.budget import CountingSimulator
from camo_sbi.inference.result import PosteriorResult

__all__ = ["METHODS", "MethodSpec", "check_run_args", "get_method", "make_config", "run_method",
           "run_method_sequence"]


@dataclass(frozen=True)
class MethodSpec:
    """A registered method: its module (imported lazily), the names of its run/config, and
    config defaults that differ from the config class's own (a variant of another method)."""

    name: str
    module: str
    run_name: str = "run"
    config_name: str = "Config"
    defaults: Mapping[str, Any] = field(default_factory=dict)

    def load(self) -> tuple[Callable, type]:
        mod = importlib.import_module(self.module)
        return getattr(mod, self.run_name), getattr(mod, self.config_name)

    def load_sequence(self) -> Callable | None:
        """The module's continual ``run_sequence`` (results after each task), if it has one."""
        return getattr(importlib.import_module(self.module), "run_sequence", None)


METHODS: dict[str, MethodSpec] = {
    "camo": MethodSpec("camo", "camo_sbi.inference.camo", config_name="CamoConfig"),
    # not in the paper: CAMO with the prior conditioned on the observed joint postures
    "camo-hull": MethodSpec("camo-hull", "camo_sbi.inference.camo", config_name="CamoConfig",
                            defaults={"contain_observed": True}),
    "naive": MethodSpec("naive", "camo_sbi.inference.naive", config_name="NaiveConfig"),
    "abc-smc": MethodSpec("abc-smc", "camo_sbi.inference.abc_smc", config_name="AbcSmcConfig"),
    "npe": MethodSpec("npe", "camo_sbi.inference.npe", config_name="NpeConfig"),
}


def check_run_args(task, observations, budget, seed, config, config_cls):
    """Validate a method's ``run`` arguments; returns (config, budget, seed, observations, prior).

    ``config`` None -> ``config_cls()``. Errors name the argument (config, budget, seed,
    observations, task.prior).
    """
    from camo_sbi.inference.priors import BoxPrior

    config = config_cls() if config is None else config
    if not isinstance(config, config_cls):
        raise TypeError(f"config: expected {config_cls.__name__}, got {type(config).__name__}")
    budget = check_positive_int(budget, "budget")
    seed = check_positive_int(seed, "seed", minimum=0)
    observations = tuple(observations)
    if not observations:
        raise ValueError("observations: at least one observed task is required")
    prior = task.prior
    if not isinstance(prior, BoxPrior):
        raise TypeError(f"task.prior: expected a BoxPrior, got {type(prior).__name__}")
    return config, budget, seed, observations, prior


def get_method(name: str) -> MethodSpec:
    """The registered method called ``name`` (ValueError listing the known names)."""
    if not isinstance(name, str) or name not in METHODS:
        raise ValueError(f"method: unknown method {name!r}; known: {', '.join(METHODS)}")
    return METHODS[name]


def make_config(name: str, config=None, **overrides):
    """The method's frozen config, from defaults, an existing config, or a dict, plus overrides.

    Defaults are the config class's, then the registry entry's ``defaults`` (camo-hull:
    ``contain_observed=True``); a config object passed in is used as given (plus
    ``overrides``). Unknown fields raise ValueError naming them (never silently ignored).
    """
    spec = get_method(name)
    _, config_cls = spec.load()
    if isinstance(config, dict):
        overrides = {**config, **overrides}
        config = None
    if config is not None and not isinstance(config, config_cls):
        raise TypeError(f"config: expected {config_cls.__name__} for method {name!r}, got {type(config).__name__}")
    known = {f.name for f in dataclasses.fields(config_cls)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise ValueError(f"config: unknown field(s) {unknown} for method {name!r}; known: {sorted(known)}")
    if config is not None:
        return replace(config, **overrides) if overrides else config
    return config_cls(**{**spec.defaults, **overrides})


def run_method(name: str, task, observations: Sequence | None = None, *, budget: int, seed: int,
               config=None) -> PosteriorResult:
    """Run method ``name`` on ``observations`` (default: all of the task's) under a counted budget.

    The simulator is wrapped in a `CountingSimulator` capped at ``budget * len(observations)``;
    the returned result's ``n_simulations`` and ``wall_time`` come from this wrapper.
    """
    spec = get_method(name)
    run, _ = spec.load()
    cfg = make_config(name, config)
    observations = tuple(task.observations if observations is None else observations)
    if not observations:
        raise ValueError("observations: at least one observed task is required")
    budget = check_positive_int(budget, "budget")
    counter = CountingSimulator(task.simulator, budget * len(observations))
    t0 = time.perf_counter()
    result = run(task.with_simulator(counter), observations, budget=budget, seed=seed, config=cfg)
    wall = time.perf_counter() - t0
    return replace(result, method=name, n_simulations=counter.n_simulations, wall_time=wall,
                   n_tasks=len(observations))


def run_method_sequence(name: str, task, observations: Sequence | None = None, *, budget: int,
                        seed: int, config=None) -> list[PosteriorResult]:
    """Results conditioned on the first 1, 2, ..., K observations.

    Continual methods (a module-level generator ``run_sequence`` yielding one result per
    task) observe the tasks once; the others are rerun from scratch for each k with a fresh
    counter capped at ``budget * k``. For a continual method the k-th result's
    ``n_simulations`` and ``wall_time`` are read from the counter and the clock here when
    it yields task k's result (cap ``budget * K``), never taken from the method.
    """
    spec = get_method(name)
    seq = spec.load_sequence()
    cfg = make_config(name, config)
    observations = tuple(task.observations if observations is None else observations)
    if not observations:
        raise ValueError("observations: at least one observed task is required")
    budget = check_positive_int(budget, "budget")
    if seq is None:
        return [run_method(name, task, observations[: k + 1], budget=budget, seed=seed, config=cfg)
                for k in range(len(observations))]
    counter = CountingSimulator(task.simulator, budget * len(observations))
    out, t0 = [], time.perf_counter()
    # a continual method yields after each task; the count and the clock are read here
    for k, r in enumerate(seq(task.with_simulator(counter), observations, budget=budget, seed=seed,
                              config=cfg)):
        out.append(replace(r, method=name, n_tasks=k + 1, n_simulations=counter.n_simulations,
                           wall_time=time.perf_counter() - t0))
    if len(out) != len(observations):
        raise RuntimeError(f"method {name!r}: run_sequence yielded {len(out)} results for "
                           f"{len(observations)} observations")
    return out
