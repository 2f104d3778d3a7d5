"""The method registry: every method's run, config class, capabilities and variants, in one place.

    run_method(name, task, observations=None, *, budget, seed, config=None) -> PosteriorResult

Each entry (`MethodSpec`) names its implementation through a loader function that imports
the method's module on first use (sbi, pyabc and numba modules take seconds to import),
its `Capabilities` (which observation spaces it can use, whether it is continual,
simulates, returns a posterior, needs a work directory or the true limits, is a baseline)
and, for a variant, the base method and the config values the variant stands for.

Experiments never hard-code method names: they read capabilities (`capabilities`,
`names`). Variants always apply their defaults: `make_config("camo-hull", CamoConfig())`
is a camo-hull config (contain_observed=True), and a dict that sets a variant's field to
another value is refused, so a result can never carry a label it was not computed under.
The simulation budget is counted by a `CountingSimulator` here, never self-reported.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, NamedTuple

# nothing heavy at import time: the CLI's --help lists the registered methods (numpy, torch and
# the task are imported by the functions that run a method)
if TYPE_CHECKING:
    from camo_sbi.inference.result import PosteriorResult
    from camo_sbi.task import Task

__all__ = [
    "Capabilities",
    "Implementation",
    "MethodSpec",
    "capabilities",
    "get_method",
    "make_config",
    "budget_defaults",
    "check_budget",
    "failed_result",
    "names",
    "register",
    "run_method",
    "run_method_sequence",
    "space_of",
]


class Implementation(NamedTuple):
    """What a method's module provides: the run contract, its config class, for a
    continual method ``run_sequence`` (a generator yielding the result after each task),
    ``min_budget(config) -> int`` when a config needs a least per-task budget (the rule
    the method's own ``run`` enforces; `check_budget` lets a grid refuse before it starts),
    and ``setup()``, the imports its run needs (timed apart, as ``import_time``)."""

    run: Callable[..., PosteriorResult]
    config: type
    run_sequence: Callable | None = None
    min_budget: Callable[[Any], int] | None = None
    setup: Callable[[], None] | None = None
    """Imports what the method would otherwise import lazily inside its run (NPE: sbi, and with it
    scikit-learn), called by the registry before the run's clock starts and timed as ``import_time``."""


@dataclass(frozen=True)
class Capabilities:
    """What a method can do, read by every experiment instead of its name.

    Attributes:
        spaces: observation spaces the method can use; () for methods that use none
            (nominal, oracle). A method whose config has a ``space`` field reads that one.
        continual: observes tasks once and yields a result after each (``run_sequence``).
        simulates: consumes the simulation budget.
        posterior: returns a distribution (weighted samples), not only a point.
        workdir: its config has a ``workdir`` for artefacts (pyabc databases, flows).
        needs_truth: needs the true limits (synthetic studies only: the oracle).
        amortized: trained once per body model, no simulation per person.
        baseline: a trivial answer every table shows next to the methods.
        also_reads: observation spaces read besides the scored one (camo-seq-cs: the joint
            postures for its proposals, as the authors' CS); data without them is refused,
            naming ``space``.
        exact: not simulation-based: evaluates the exact likelihood of the noise model
            (exact-likelihood, the Bayes limit with the data). Its simulations are counted
            (``n_simulations``) but not capped by the budget: it is exempt from the budget
            comparisons, and tables label it so.
    """

    spaces: tuple[str, ...] = ("joint", "cartesian")
    continual: bool = False
    simulates: bool = True
    posterior: bool = True
    workdir: bool = False
    needs_truth: bool = False
    amortized: bool = False
    baseline: bool = False
    also_reads: tuple[str, ...] = ()
    exact: bool = False


@dataclass(frozen=True)
class MethodSpec:
    """A registered method (or a variant of one).

    Attributes:
        name: registry name.  description: one line for tables and ``--help``.
        loader: zero-argument function importing the module, returning its `Implementation`.
        capabilities: `Capabilities`.
        base: for a variant, the name of the method it specialises (shares its loader).
        defaults: for a variant, the config values it stands for (always applied).
        paper: True for what the paper itself runs (its CAMO-JS / CAMO-CS and naive).
        budget_defaults: ``budget -> {field: value}``, config values a grid gives the method at
            that per-task budget under the user's ``--config`` (abc-smc: a first population
            that leaves room for about three); None: none. Read through `budget_defaults`.
    """

    name: str
    description: str
    loader: Callable[[], Implementation]
    capabilities: Capabilities
    base: str | None = None
    defaults: Mapping[str, Any] = field(default_factory=dict)
    paper: bool = False
    budget_defaults: Callable[[int], Mapping[str, Any]] | None = None

    def load(self) -> Implementation:
        impl = self.loader()
        if not isinstance(impl, Implementation):
            raise TypeError(f"method {self.name!r}: its loader returned {type(impl).__name__}, "
                            f"not an Implementation")
        return impl


_REGISTRY: dict[str, MethodSpec] = {}


def register(spec: MethodSpec) -> MethodSpec:
    """Add ``spec`` to the registry (ValueError if the name is taken or the variant's base unknown)."""
    if not isinstance(spec, MethodSpec):
        raise TypeError(f"spec: expected a MethodSpec, got {type(spec).__name__}")
    if spec.name in _REGISTRY:
        raise ValueError(f"spec: a method named {spec.name!r} is already registered")
    if spec.base is not None and spec.base not in _REGISTRY:
        raise ValueError(f"spec: variant {spec.name!r} of unknown method {spec.base!r}")
    _REGISTRY[spec.name] = spec
    return spec


def _load_plugins() -> None:
    """The methods other installed packages declare (entry points ``camo_sbi.methods``; once per
    process, `camo_sbi._plugins`)."""
    from camo_sbi import _plugins

    _plugins.load("camo_sbi.methods", register, MethodSpec)


def get_method(name: str) -> MethodSpec:
    """The registered method called ``name`` (ValueError listing the known names)."""
    if isinstance(name, str) and name not in _REGISTRY:
        _load_plugins()
    if not isinstance(name, str) or name not in _REGISTRY:
        raise ValueError(f"method: unknown method {name!r}; known: {', '.join(_REGISTRY)}")
    return _REGISTRY[name]


def names(*, baseline: bool | None = None, **required: Any) -> list[str]:
    """Registered names, in registration order, filtered by capabilities.

    ``baseline=True/False`` keeps only baselines / only methods; other keywords require a
    capability value (``names(simulates=True)``, ``names(space="cartesian")`` keeps methods
    that can use Cartesian observations or need none).
    """
    _load_plugins()
    space = required.pop("space", None)
    out = []
    for name, spec in _REGISTRY.items():
        cap = spec.capabilities
        if baseline is not None and cap.baseline != baseline:
            continue
        if space is not None and cap.spaces and space not in cap.spaces:
            continue
        if any(getattr(cap, k) != v for k, v in required.items()):
            continue
        out.append(name)
    return out


def capabilities(name: str) -> Capabilities:
    return get_method(name).capabilities


def grid_budgets(name: str, budgets: Sequence[int]) -> list[int]:
    """The budgets ``compare --reference`` runs method ``name`` at: every one of ``budgets``, or
    for a method exempt from the budget (`Capabilities.exact`: its run does not depend on the
    budget, so every budget would repeat the same run) only the smallest, where its rows are
    filed. The plain ``compare`` grid does not use it: its figures and summary are drawn at the
    largest budget, so it runs an exact method at every budget."""
    budgets = list(budgets)
    return [min(budgets)] if budgets and capabilities(name).exact else budgets


def make_config(name: str, config=None, **overrides):
    """The method's frozen config, from defaults, an existing config, or a dict, plus overrides.

    A variant's ``defaults`` are always applied: over a config object (whatever it holds
    in those fields) and under a dict, which may not set a variant field to another value
    (ValueError naming the field). Unknown fields raise ValueError naming them.
    """
    spec = get_method(name)
    config_cls = spec.load().config
    if isinstance(config, Mapping):
        overrides = {**config, **overrides}
        config = None
    if config is not None and not isinstance(config, config_cls):
        raise TypeError(f"config: expected {config_cls.__name__} for method {name!r}, got {type(config).__name__}")
    known = {f.name for f in dataclasses.fields(config_cls)}
    for old, new in getattr(config_cls, "RENAMED", {}).items():
        if old in overrides:
            raise ValueError(f"config: field {old!r} of method {name!r} is now called {new!r}")
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise ValueError(f"config: unknown field(s) {unknown} for method {name!r}; known: {sorted(known)}")
    conflict = {k: v for k, v in overrides.items() if k in spec.defaults and v != spec.defaults[k]}
    if conflict:
        k = next(iter(conflict))
        raise ValueError(f"config: method {name!r} is defined by {k}={spec.defaults[k]!r}; got {k}="
                         f"{conflict[k]!r} (use {spec.base or 'another method'!r} instead)")
    if config is None:
        return config_cls(**{**spec.defaults, **overrides})
    changes = {**spec.defaults, **overrides}
    return replace(config, **changes) if changes else config


def budget_defaults(name: str, budget: int) -> dict:
    """The config values method ``name`` declares for a per-task ``budget`` ({} if none)."""
    rule = get_method(name).budget_defaults
    return dict(rule(budget)) if rule is not None else {}


def check_budget(name: str, config, budget: int) -> None:
    """ValueError naming ``budget`` when ``config`` (dict, config object or None) needs more
    simulations per task than ``budget``, by the method's own rule (`Implementation.min_budget`)."""
    spec = get_method(name)
    rule = spec.load().min_budget
    if rule is None:
        return
    need = int(rule(make_config(name, config)))
    if budget < need:
        raise ValueError(f"budget: {name} needs at least {need} simulations per task with its config, got {budget}")


def space_of(name: str, config) -> str | None:
    """The observation space ``name`` reads under ``config`` (None for methods that read none)."""
    spaces = capabilities(name).spaces
    if not spaces:
        return None
    return getattr(config, "space", spaces[0])


def _prepare(name, task, observations, budget, seed, config):
    from camo_sbi._validation import check_positive_int
    from camo_sbi.task import Task, check_observations

    if not isinstance(task, Task):
        raise TypeError(f"task: expected a camo_sbi.task.Task, got {type(task).__name__}")
    spec = get_method(name)
    t0 = time.perf_counter()
    impl = spec.load()  # the first load imports the method's module (abc-smc: pyabc)
    if impl.setup is not None:
        impl.setup()  # what the run would import lazily (npe: sbi, scikit-learn)
    imported = time.perf_counter() - t0
    cfg = make_config(name, config)
    observations = check_observations(task, observations, space_of(name, cfg))
    for other in spec.capabilities.also_reads:
        check_observations(task, observations, other)
    budget = check_positive_int(budget, "budget")
    seed = check_positive_int(seed, "seed", minimum=0)
    if spec.capabilities.needs_truth:
        task.require_truth(f"method {name!r}")
    return spec, impl, cfg, observations, budget, seed, imported


_ERRORS = ("raise", "record")


def _check_errors(errors) -> str:
    if errors not in _ERRORS:
        raise ValueError(f"errors: expected one of {_ERRORS}, got {errors!r}")
    return errors


def _check_estimate(result) -> None:
    """ValueError unless ``result.estimate`` is a usable limit vector (finite, lo <= hi), the
    check every downstream metric applies: with ``errors="record"`` an unusable estimate is the
    method's failure, recorded, not a crash later in the grid's scoring."""
    import torch

    from camo_sbi._validation import check_theta

    est = torch.as_tensor(result.estimate)
    check_theta(est, est.shape[-1] // 2, "estimate")


def failed_result(name: str, task: Task, n_tasks: int, exc: BaseException) -> PosteriorResult:
    """The result of a method that raised ``exc``: `result.failed_at_prior_centre` with the reason
    ``"<type>: <message>"``, ``extras["error"]`` that text and ``extras["traceback"]`` its traceback."""
    import traceback

    from camo_sbi.inference.result import failed_at_prior_centre

    text = " ".join(f"{type(exc).__name__}: {exc}".split())
    return failed_at_prior_centre(name, task.prior, n_tasks, text,
                                  extras={"error": text, "traceback": "".join(traceback.format_exception(exc))})


def _attempt(step: Callable[[], Any], errors: str) -> tuple[Any, Exception | None]:
    """``(step(), None)``; with ``errors="record"`` a result's estimate is checked
    (`_check_estimate`) and an exception (or a failed check) comes back as ``(None, exc)``.
    ``errors="raise"`` and an `InputError` (bad input only the run can judge) raise."""
    from camo_sbi._validation import InputError

    try:
        result = step()
        if result is not None and errors == "record":
            _check_estimate(result)
        return result, None
    except Exception as exc:
        if errors == "raise" or isinstance(exc, InputError):
            raise
        return None, exc


def _cap(spec: MethodSpec, budget: int, n_tasks: int) -> int | None:
    """The run's simulation cap: ``budget`` per task, or None (counted, uncapped) for an exact method."""
    return None if spec.capabilities.exact else budget * n_tasks


def _warn_status(name: str, result: PosteriorResult) -> None:
    from camo_sbi.inference.result import STATUS_OK

    if result.status != STATUS_OK:
        warnings.warn(f"method {name!r} after {result.n_tasks} task(s): {result.status}", RuntimeWarning,
                      stacklevel=3)


class _CompileClock:
    """Seconds numba spends compiling while installed (a context manager).

    numba broadcasts a ``numba:compiler_lock`` event around each compilation, including loading
    a compiled kernel from its disk cache and waiting for another thread's compilation. The
    clock adds up the union of those intervals over all threads (nested or concurrent ones count
    once). A method's ``wall_time`` is its elapsed time minus this, so the first run in a
    process is not charged for compiling the kernels every later run reuses.
    """

    def __enter__(self):
        import threading

        from numba.core import event

        clock = self
        self._lock, self._depth, self._since, self._total = threading.Lock(), 0, 0.0, 0.0

        class _Listener(event.Listener):
            def on_start(self, ev):
                with clock._lock:
                    if clock._depth == 0:
                        clock._since = time.perf_counter()
                    clock._depth += 1

            def on_end(self, ev):
                with clock._lock:
                    if clock._depth == 0:  # began before the clock was installed
                        return
                    clock._depth -= 1
                    if clock._depth == 0:
                        clock._total += time.perf_counter() - clock._since

        self._event, self._listener = event, _Listener()
        event.register("numba:compiler_lock", self._listener)
        return self

    def __exit__(self, *exc):
        self._event.unregister("numba:compiler_lock", self._listener)

    @property
    def seconds(self) -> float:
        """Compilation so far (an interval still open counts up to now)."""
        with self._lock:
            return self._total + (time.perf_counter() - self._since if self._depth else 0.0)


def _resumed_seconds(result: PosteriorResult) -> float:
    """Seconds of work a result read back from an earlier process's checkpoints (its
    ``extras["resumed_seconds"]``, e.g. NPE's per-task flows): added to ``wall_time``."""
    v = result.extras.get("resumed_seconds", 0.0) if isinstance(result.extras, dict) else 0.0
    return float(v) if isinstance(v, (int, float)) and v > 0 else 0.0


def run_method(name: str, task: Task, observations: Sequence | None = None, *, budget: int, seed: int,
               config=None, errors: str = "raise") -> PosteriorResult:
    """Run method ``name`` on ``observations`` (default: all of the task's) under a counted budget.

    The simulator is wrapped in a `CountingSimulator` capped at ``budget * len(observations)``
    (uncapped, still counted, for a method with `Capabilities.exact`);
    the result's ``method``, ``n_simulations``, ``wall_time``, ``compile_time``, ``import_time``
    and ``n_tasks`` are set here (``wall_time`` excludes the numba compilation measured as
    ``compile_time`` and the imports measured as ``import_time``: loading the method's module
    and its ``setup``, done before the clock starts; it includes the recorded seconds of work
    the method read back from an earlier, killed run's checkpoints, ``extras["resumed_seconds"]``).
    A result whose status is not "ok" is warned about (RuntimeWarning).

    ``errors``: ``"raise"`` (default) lets an exception raised inside the method propagate;
    ``"record"`` (the experiment grids) turns it, or an estimate no metric can score (not finite,
    a lower limit above its upper one), into a ``"failed: <type>: <message>"`` result
    (`failed_result`), so one method that breaks is a marked row, not a stopped grid. Bad
    arguments (name, task, observations, budget, seed, config) raise either way, before the run,
    and so does an `InputError` raised inside it (bad input only the run can judge, such as an
    amortized estimator file that does not fit the task).
    """
    errors = _check_errors(errors)
    spec, impl, cfg, observations, budget, seed, imported = _prepare(name, task, observations, budget, seed,
                                                                     config)
    counted, counter = task.with_budget(_cap(spec, budget, len(observations)))
    with _CompileClock() as jit:
        t0 = time.perf_counter()
        result, exc = _attempt(lambda: impl.run(counted, observations, budget=budget, seed=seed, config=cfg), errors)
        if exc is not None:
            result = failed_result(name, task, len(observations), exc)
        elapsed = time.perf_counter() - t0
    result = replace(result, method=name, n_simulations=counter.n_simulations,
                     wall_time=max(0.0, elapsed - jit.seconds) + _resumed_seconds(result),
                     compile_time=jit.seconds, import_time=imported, n_tasks=len(observations))
    _warn_status(name, result)
    return result


def run_method_sequence(name: str, task: Task, observations: Sequence | None = None, *, budget: int,
                        seed: int, config=None, errors: str = "raise") -> list[PosteriorResult]:
    """Results conditioned on the first 1, 2, ..., K observations.

    Continual methods (`Capabilities.continual`) observe the tasks once; the others are
    rerun from scratch for each k with a fresh counter capped at ``budget * k``. For a
    continual method the k-th result's ``n_simulations``, ``wall_time`` and ``compile_time``
    are read from the counter (cap ``budget * K``) and the clocks here when it yields task k's
    result (both cumulative; ``wall_time`` without the compilation so far); ``import_time``, paid
    before the first task, is the same on every result (on the first only for the others).

    ``errors``: as in `run_method`; with ``"record"`` a continual method that raises at task k
    keeps its results for the tasks before k, and tasks k..K are failed results.
    """
    errors = _check_errors(errors)
    spec, impl, cfg, observations, budget, seed, imported = _prepare(name, task, observations, budget, seed,
                                                                     config)
    if not spec.capabilities.continual or impl.run_sequence is None:
        out = [run_method(name, task, observations[: k + 1], budget=budget, seed=seed, config=cfg, errors=errors)
               for k in range(len(observations))]
        # the imports happened in the _prepare above: the first result's
        return [replace(out[0], import_time=out[0].import_time + imported), *out[1:]]
    counted, counter = task.with_budget(_cap(spec, budget, len(observations)))
    out = []
    with _CompileClock() as jit:
        t0 = time.perf_counter()

        def produced():  # run_sequence is called at the first next(), so one returning a list raises there too
            yield from impl.run_sequence(counted, observations, budget=budget, seed=seed, config=cfg)

        results, failure = produced(), None
        while len(out) < len(observations):
            if failure is None:  # a generator that raised is finished: this task and the later ones fail
                r, failure = _attempt(lambda: next(results, None), errors)
            if failure is not None:
                r = failed_result(name, task, len(out) + 1, failure)
            if r is None:
                break
            compiling = jit.seconds
            r = replace(r, method=name, n_tasks=len(out) + 1, n_simulations=counter.n_simulations,
                        wall_time=max(0.0, time.perf_counter() - t0 - compiling) + _resumed_seconds(r),
                        compile_time=compiling,
                        import_time=imported)
            _warn_status(name, r)
            out.append(r)
        if failure is None and next(results, None) is not None:
            raise RuntimeError(f"method {name!r}: run_sequence yielded more results than the "
                               f"{len(observations)} observations")
    if len(out) != len(observations):
        raise RuntimeError(f"method {name!r}: run_sequence yielded {len(out)} results for "
                           f"{len(observations)} observations")
    return out


# ---------------------------------------------------------------------------------- built-ins
# Loaders import lazily: a real import statement per module (no module-path strings).


def _camo() -> Implementation:
    from camo_sbi.inference import camo

    return Implementation(camo.run, camo.CamoConfig, camo.run_sequence)


def _touched() -> Implementation:
    from camo_sbi.inference import camo, touched

    return Implementation(touched.run, camo.CamoConfig, touched.run_sequence)


def _naive() -> Implementation:
    from camo_sbi.inference import naive

    return Implementation(naive.run, naive.NaiveConfig, naive.run_sequence)


def _nominal() -> Implementation:
    from camo_sbi.inference import baselines

    return Implementation(baselines.run_nominal, baselines.NominalConfig, baselines.sequence_nominal)


def _oracle() -> Implementation:
    from camo_sbi.inference import baselines

    return Implementation(baselines.run_oracle, baselines.OracleConfig, baselines.sequence_oracle)


def _abc_smc() -> Implementation:
    from camo_sbi.inference import abc_smc

    # abc_smc.run warns on a non-ok status itself; run_method warns here instead (once)
    return Implementation(abc_smc.run_unwarned, abc_smc.AbcSmcConfig, min_budget=abc_smc.min_budget)


def _abc_budget_defaults(budget: int) -> dict:
    """A first population of min(100, budget // 3) particles (at least 2): about three fit."""
    return {"population_size": max(2, min(100, budget // 3))}


def _npe() -> Implementation:
    from camo_sbi.inference import npe, sbi_adapter

    return Implementation(npe.run, npe.NpeConfig, npe.run_sequence, setup=sbi_adapter.import_sbi)


def _npe_amortized() -> Implementation:
    from camo_sbi.inference import amortized

    return Implementation(amortized.run, amortized.AmortizedConfig)


def _exact() -> Implementation:
    from camo_sbi.inference import exact

    return Implementation(exact.run, exact.ExactConfig)


def _nle() -> Implementation:
    from camo_sbi.inference import nle

    return Implementation(nle.run, nle.NleConfig, nle.run_sequence)


def _nre() -> Implementation:
    from camo_sbi.inference import nre

    return Implementation(nre.run, nre.NreConfig, nre.run_sequence)


def _fmpe() -> Implementation:
    from camo_sbi.inference import fmpe

    return Implementation(fmpe.run, fmpe.FmpeConfig, fmpe.run_sequence)


def _npse() -> Implementation:
    from camo_sbi.inference import npse

    return Implementation(npse.run, npse.NpseConfig, npse.run_sequence)


def _tsnpe() -> Implementation:
    from camo_sbi.inference import tsnpe

    return Implementation(tsnpe.run, tsnpe.TsnpeConfig, tsnpe.run_sequence)


_CAMO = Capabilities(continual=True)
_BASELINE = Capabilities(spaces=(), continual=True, simulates=False, posterior=False, baseline=True)

register(MethodSpec("camo", "CAMO (Algorithm 1): rejection sampling, per-task KDEs, product, argmax",
                    _camo, _CAMO))
register(MethodSpec("camo-js", "CAMO on joint-space observations (the paper's CAMO-JS, Algorithm 1 as written: "
                    "prior draws every task)", _camo,
                    replace(_CAMO, spaces=("joint",)), base="camo", defaults={"space": "joint"}, paper=True))
register(MethodSpec("camo-cs", "CAMO on Cartesian observations (the paper's CAMO-CS, Algorithm 1 as written: "
                    "prior draws every task)", _camo,
                    replace(_CAMO, spaces=("cartesian",)), base="camo", defaults={"space": "cartesian"},
                    paper=True))
register(MethodSpec("camo-hull", "CAMO-JS with the prior conditioned on the observed postures (not in "
                    "the paper)", _camo, replace(_CAMO, spaces=("joint",)), base="camo",
                    defaults={"space": "joint", "contain_observed": True}))
register(MethodSpec("camo-seq", "CAMO-JS as the authors' code runs it (their JS): sequential proposals, each "
                    "task draws from the last task's KDE, clipped to the observed hull", _camo,
                    replace(_CAMO, spaces=("joint",)), base="camo",
                    defaults={"space": "joint", "proposal": "sequential"}, paper=True))
register(MethodSpec("camo-seq-cs", "CAMO-CS as the authors' code runs it (their CS): Cartesian scores of "
                    "candidates from the sequential JS bank (reads the joint observations for its proposals)",
                    _camo, replace(_CAMO, spaces=("cartesian",), also_reads=("joint",)), base="camo",
                    defaults={"space": "cartesian", "proposal": "sequential-js"}, paper=True))
register(MethodSpec("naive", "observed min/max per joint (the paper's baseline)", _naive,
                    replace(_BASELINE, spaces=("joint",)), paper=True))
register(MethodSpec("nominal", "the model's full range of motion (no inference)", _nominal, _BASELINE))
register(MethodSpec("oracle", "the true limits (synthetic studies; every prediction error is 0)", _oracle,
                    replace(_BASELINE, needs_truth=True)))
register(MethodSpec("abc-smc", "ABC-SMC (pyabc) on the joint posterior of all observed tasks", _abc_smc,
                    Capabilities(workdir=True), budget_defaults=_abc_budget_defaults))
register(MethodSpec("npe", "neural posterior estimation (sbi), one flow per task, combined", _npe,
                    Capabilities(continual=True, workdir=True)))
register(MethodSpec("npe-amortized", "amortized NPE (sbi): one flow per body model, trained once, conditioned on "
                    "the set of a person's reaches (or per reach, combined); no simulation per person", _npe_amortized,
                    Capabilities(amortized=True, simulates=False, posterior=True, spaces=("joint", "cartesian"))))
register(MethodSpec("camo-touched", "camo-seq with the touched bounds (a joint seen resting at its extreme while "
                    "the arm moves) set to their observed values (issue 23; not in the paper)", _touched,
                    replace(_CAMO, spaces=("joint",)), defaults={"space": "joint", "proposal": "sequential"}))
register(MethodSpec("exact-likelihood", "NOT simulation-based: tempered SMC on the exact likelihood of the noise "
                    "model, the Bayes limit with these data (simulations counted, exempt from the budget)", _exact,
                    Capabilities(exact=True)))
register(MethodSpec("nle", "neural likelihood estimation (sbi NLE_A), one likelihood per task, summed, sampled by "
                    "tempered SMC", _nle, Capabilities(continual=True, workdir=True)))
register(MethodSpec("nre", "neural ratio estimation (sbi NRE_C), one ratio per task, summed, sampled by tempered SMC",
                    _nre, Capabilities(continual=True)))
register(MethodSpec("fmpe", "flow-matching posterior estimation (sbi FMPE), one posterior per task, combined as "
                    "npe's flows", _fmpe, Capabilities(continual=True)))
register(MethodSpec("npse", "neural posterior score estimation (sbi NPSE, ODE density), one posterior per task, "
                    "combined as npe's flows", _npse, Capabilities(continual=True)))
register(MethodSpec("tsnpe", "truncated sequential NPE (sbi NPE_C + RestrictedPrior, 3 rounds per task), "
                    "combined as npe's flows", _tsnpe, Capabilities(continual=True, workdir=True)))
