"""ABC-SMC (pyabc) on the joint posterior of every observed task; the only module importing pyabc.

Why one module of ~950 lines: it is the pyabc adapter, and the project keeps each third-party
library behind ONE module, so an API change in pyabc touches this file only. The batched
sampler, the stable transition, the prior conversion and the seeding all subclass or call
pyabc types; splitting them would spread pyabc over several modules.

Target: the ABC posterior of theta given ALL observed tasks at once. One particle theta is
simulated to every observed task's goal from that task's start, and its distance is the sum
of the per-task exact DTW distances (observed vs simulated trajectory, in ``config.space``)::

    d(theta) = sum_i DTW(tau_i^obs, tau_i(theta))

pyabc supplies everything that makes the method ABC-SMC: the adaptive epsilon schedule
(`pyabc.MedianEpsilon`, eps_t = weighted median of the previous population's distances),
the perturbation kernel (pyabc's default Gaussian KDE with Silverman's bandwidth, here as
`StableMultivariateNormalTransition`, whose covariance cannot lose rank: see there),
importance weights prior / proposal, the population bookkeeping and its SQL history.

Only pyabc's public interfaces are used: `pyabc.ABCSMC` (``transitions=``, ``eps=``,
``sampler=``), the `pyabc.sampler.Sampler` base (``sample_until_n_accepted`` with
``all_accepted``, ``sample_factory``, ``nr_evaluations_``), `pyabc.transition.Transition`,
`pyabc.population.Particle`, `pyabc.MedianEpsilon` and the history. The sampler reads a
generation's epsilon and kernel from the objects this module created and passed to
ABCSMC, never from pyabc's internal simulate function (tested with pyabc 0.12.18 and
0.13.0: ``tests/test_abc_smc.py::test_pyabc_version_is_a_tested_one``).

Batched sampling. pyabc evaluates one particle per model call; the Python overhead of one
simulate/DTW call per particle would dominate (docs/studies/design_measurements.md).
`BatchedSampler` (a `pyabc.sampler.Sampler`) instead
draws a batch of proposals from pyabc's own transition (rejecting, without simulating,
proposals outside the prior box as pyabc does), simulates the batch with one ``simulate``
call per task, computes its distances with one ``dtw_distances`` call per task, and accepts
``d <= eps_t`` (pyabc's `UniformAcceptor`). Accepted particles are taken in proposal order
up to the n-th acceptance, exactly as pyabc's `SingleCoreSampler` would, and weighted
``prior(theta) / transition(theta)`` (the model-perturbation factor of a single model is a
constant and cancels on normalisation), in log space where that ratio is not finite.
``config.sampler = "single"`` runs pyabc's stock per-particle pipeline instead (one
simulate call per particle and task), as a reference.

Degenerate populations. In 14-18 free coordinates with 100 particles the importance
weights degenerate, and with pyabc's own kernel the weighted covariance then loses rank
until every proposal has density 0 and pyabc stops with "population total weight nan"
(how often, and how fast: docs/studies/design_measurements.md). The kernel's eigenvalue
floor removes the crash; the status reports what is left: see `run_unwarned` for the status rules (prior-only, low ESS, pyabc error,
failed).

Early rejection (``config.early_rejection``, default on): distances are non-negative, so a
particle whose partial sum over the first tasks already exceeds eps_t is rejected without
simulating the remaining tasks; each task's DTW is also pruned at the remaining allowance
(`dtw_distances(epsilon=...)`). Accept/reject decisions are identical to the full
computation; only rejected particles' recorded distances become lower bounds (pyabc's
median epsilon only reads accepted ones). It lets ABC-SMC evaluate more particles with the
same simulation budget.

Budget. One particle costs one simulated trajectory per task evaluated, so a run on k
tasks with ``budget`` per task may evaluate at most ``budget`` particles without early
rejection. The sampler never starts a batch it could not pay for: when the remaining
budget cannot finish the current population, the population is abandoned (pyabc stops
with the last complete population; the partial one is reported in ``extras``). The first
population samples the prior with eps_0 = inf (``initial_epsilon="inf"``), so it costs
exactly ``population_size`` particles and eps_1 is the median of prior distances, which is
pyabc's ``"from_sample"`` calibration without paying for a separate calibration sample.

Seeding. pyabc draws from numpy's GLOBAL RNG. `run` seeds it inside `numpy_global_seed`,
which restores the caller's state afterwards (pyabc leaks no global state), and uses a
single-process sampler, so one seed gives identical populations.

Parameters: only the prior's free coordinates are pyabc parameters, named by joint and
bound (``shoulder_pitch_lo``, ``shoulder_pitch_hi``: what pyabc's History and its plots
show); fixed coordinates are re-inserted with `BoxPrior.expand`. Every conversion between
pyabc's parameters and theta goes through that list of names, never pyabc's column order.
See `parameter_names`, `to_pyabc_prior`.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import scipy.special
import scipy.stats as st
import torch

from camo_sbi._validation import (
    check_bool,
    check_choice,
    check_point_estimate,
    check_positive_float,
    check_positive_int,
    check_workdir,
    renamed_fields,
)
from camo_sbi.distributed import parse_scheduler, run_chunks
from camo_sbi.inference.contract import check_run_args
from camo_sbi.inference.distances import dtw_distances
from camo_sbi.inference.result import STATUS_OK, PosteriorResult, weighted_median
from camo_sbi.priors import BoxPrior
from camo_sbi.task import SPACES, NoiseModel, contain


def _import_pyabc():
    """Import pyabc without its process-wide side effect: on import it sets
    OMP_NUM_THREADS=1 when unset (affecting thread pools started later); restore that."""
    omp = os.environ.get("OMP_NUM_THREADS")
    try:
        import pyabc
        import pyabc.population
        import pyabc.sampler
        import pyabc.transition
    finally:
        if omp is None:
            os.environ.pop("OMP_NUM_THREADS", None)
        else:
            os.environ["OMP_NUM_THREADS"] = omp
    return pyabc


pyabc = _import_pyabc()
Sampler = pyabc.sampler.Sampler
Particle = pyabc.population.Particle
Transition = pyabc.transition.Transition

__all__ = [
    "AbcSmcConfig",
    "BatchedSampler",
    "JointDistance",
    "StableMultivariateNormalTransition",
    "numpy_global_seed",
    "parameter_names",
    "run",
    "run_unwarned",
    "to_pyabc_prior",
]

_SAMPLERS = ("batched", "single")
_POINT_ESTIMATES = ("mean", "median", "mode")
_DTYPES = {"float32": torch.float32, "float64": torch.float64}
_DISTANCE_KEY = "d"
# a batch proposes this fraction of the proposals expected to complete the population
_BATCH_FILL = 0.75


@renamed_fields(estimator="point_estimate")
@dataclass(frozen=True)
class AbcSmcConfig:
    """ABC-SMC settings.

    Attributes:
        space: "joint" (q) or "cartesian" (end-effector) trajectories for the DTW distance.
        population_size: particles per population (pyabc's ``population_size``); must not
            exceed the run's per-task budget (the first population costs exactly this).
        max_populations: pyabc's ``max_nr_populations``.
        min_epsilon: stop once eps_t <= min_epsilon (pyabc's ``minimum_epsilon``).
        min_acceptance_rate: stop when a population's acceptance rate drops below this.
        initial_epsilon: "inf" (first population = prior sample, see module docstring) or
            "from_sample" (pyabc's calibration sample, which costs one extra population).
        median_multiplier: eps_t = multiplier * weighted median (pyabc's MedianEpsilon).
        early_rejection: stop simulating a particle's remaining tasks once its partial
            distance exceeds eps_t (exact; see module docstring).
        sampler: "batched" (`BatchedSampler`) or "single" (pyabc's per-particle pipeline).
        min_batch_size, max_batch_size: proposals simulated per batch; the batch is sized
            to the expected number of proposals still needed (running acceptance rate).
        point_estimate: from the last population: "mean" (weighted mean), "median"
            (coordinate-wise weighted median) or "mode" (the particle of smallest distance,
            where the ABC kernel is highest). Old names ``estimator`` and "best" are refused
            naming these.
        sim_dtype: "float32" or "float64" for the simulations (CAMO's default: float32).
        log_level: level of pyabc's "ABC" logger during the run ("INFO" shows generations;
            "WARNING" also shows pyabc's near-zero population weight warnings, whose cause,
            weight degeneracy, is reported as ``extras["ess"]`` instead).
        workdir: None -> the pyabc history lives in a temporary directory removed after
            the run; else the directory (created) receiving ``abc_smc_k{k}_seed{seed}.db``.
        chunk_size: a batch is simulated and scored in chunks of this many particles (our
            batched sampler's simulate + distance calls, in-process or on Dask workers).
            Proposals are drawn on the driver (seeded) and a particle's acceptance, distance
            and simulation count do not depend on the chunks, so neither do the results.
        scheduler: None (in-process), "local:N" or a Dask scheduler address: where the
            chunks run (see `camo_sbi.distributed`). pyabc's own ``DaskDistributedSampler``
            is not used: it reseeds from the OS, so its results would not be reproducible.
        min_ess_fraction: the result's status is ``"fallback: low effective sample size
            ..."`` when the final population's ESS is below this fraction of
            ``population_size`` (0 disables the check). The final ESS seen on the toy, Panda
            and human models: docs/studies/design_measurements.md.
    """

    space: str = "joint"
    population_size: int = 100
    max_populations: int = 20
    min_epsilon: float = 0.0
    min_acceptance_rate: float = 0.0
    initial_epsilon: str = "inf"
    median_multiplier: float = 1.0
    early_rejection: bool = True
    sampler: str = "batched"
    min_batch_size: int = 8
    max_batch_size: int = 4096
    point_estimate: str = "mean"
    sim_dtype: str = "float32"
    log_level: str = "ERROR"
    workdir: str | os.PathLike | None = None
    chunk_size: int = 1024
    scheduler: str | None = None
    min_ess_fraction: float = 0.1

    def __post_init__(self):
        check_choice(self.space, SPACES, "space")
        check_positive_int(self.population_size, "population_size", minimum=2)
        check_positive_int(self.max_populations, "max_populations")
        check_positive_float(self.min_epsilon, "min_epsilon", allow_zero=True)
        check_positive_float(self.min_acceptance_rate, "min_acceptance_rate", allow_zero=True)
        if self.min_acceptance_rate >= 1:
            raise ValueError(f"min_acceptance_rate: must be < 1, got {self.min_acceptance_rate}")
        if self.initial_epsilon not in ("inf", "from_sample"):
            raise ValueError(
                f"initial_epsilon: expected 'inf' or 'from_sample', got {self.initial_epsilon!r}"
            )
        check_positive_float(self.median_multiplier, "median_multiplier")
        check_bool(self.early_rejection, "early_rejection")
        check_choice(self.sampler, _SAMPLERS, "sampler")
        check_positive_int(self.min_batch_size, "min_batch_size")
        check_positive_int(self.max_batch_size, "max_batch_size")
        if self.max_batch_size < self.min_batch_size:
            raise ValueError(
                f"max_batch_size: must be >= min_batch_size ({self.min_batch_size}), got {self.max_batch_size}"
            )
        check_point_estimate(self.point_estimate, _POINT_ESTIMATES)
        check_choice(self.sim_dtype, _DTYPES, "sim_dtype")
        if self.log_level not in ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"):
            raise ValueError(f"log_level: expected a logging level name, got {self.log_level!r}")
        check_workdir(self.workdir)
        check_positive_int(self.chunk_size, "chunk_size")
        parse_scheduler(self.scheduler)
        check_positive_float(self.min_ess_fraction, "min_ess_fraction", allow_zero=True)
        if self.min_ess_fraction >= 1:
            raise ValueError(f"min_ess_fraction: must be < 1, got {self.min_ess_fraction}")


# ----------------------------------------------------------------------------------------------
# prior conversion and seeding
# ----------------------------------------------------------------------------------------------


def parameter_names(prior: BoxPrior, joint_names=None) -> list[str]:
    """pyabc parameter names of the prior's free coordinates, in theta order.

    ``{joint}_lo`` / ``{joint}_hi`` from ``joint_names`` (n unique names, base to tip);
    without them ``theta_{i:02d}`` with i the index into the full (2n,) vector.
    """
    free = torch.nonzero(prior.free_mask).flatten().tolist()
    if joint_names is None:
        return [f"theta_{i:02d}" for i in free]
    names = [str(j) for j in joint_names]
    if len(names) != prior.n_joints or len(set(names)) != len(names) or not all(names):
        raise ValueError(f"joint_names: expected {prior.n_joints} unique non-empty names, got {names}")
    return [f"{names[i // 2]}_{('lo', 'hi')[i % 2]}" for i in free]


def to_pyabc_prior(prior: BoxPrior, joint_names=None) -> pyabc.Distribution:
    """The box prior's free coordinates as a `pyabc.Distribution` of independent uniforms.

    scipy's (hence pyabc's) ``RV("uniform", loc, scale)`` is uniform on [loc, loc + scale]:
    ``scale`` is the WIDTH ``high - low``, not the upper bound. Fixed (zero-width)
    coordinates are not pyabc parameters; `BoxPrior.expand` re-inserts them.
    """
    if not isinstance(prior, BoxPrior):
        raise TypeError(f"prior: expected a BoxPrior, got {type(prior).__name__}")
    if prior.n_free == 0:
        raise ValueError("prior: every coordinate is fixed; there is nothing to infer")
    low = prior.low[prior.free_mask].tolist()
    high = prior.high[prior.free_mask].tolist()
    return pyabc.Distribution(
        **{name: pyabc.RV("uniform", lo, hi - lo)
           for name, lo, hi in zip(parameter_names(prior, joint_names), low, high, strict=True)}
    )


@contextlib.contextmanager
def _quiet_pyabc(level: str):
    """pyabc's "ABC" logger at ``level`` for the block (pyabc sets it to INFO on import)."""
    logger = logging.getLogger("ABC")
    old = logger.level
    logger.setLevel(level)
    try:
        with warnings.catch_warnings():
            # pyabc compares eps_1 with eps_0 = inf (inf - inf) when checking min_eps_diff
            warnings.filterwarnings("ignore", message="invalid value encountered in scalar subtract",
                                    category=RuntimeWarning)
            yield
    finally:
        logger.setLevel(old)


@contextlib.contextmanager
def numpy_global_seed(seed: int):
    """Seed numpy's global RNG for the block and restore the caller's state afterwards.

    The state is derived with ``SeedSequence(seed)`` (any non-negative int works).
    """
    seed = check_positive_int(seed, "seed", minimum=0)
    saved = np.random.get_state()
    np.random.set_state(np.random.RandomState(np.random.MT19937(np.random.SeedSequence(seed))).get_state())
    try:
        yield
    finally:
        np.random.set_state(saved)


# ----------------------------------------------------------------------------------------------
# the batched joint distance (the "model")
# ----------------------------------------------------------------------------------------------


class JointDistance:
    """Sum over observed tasks of the DTW distance, for a batch of free-coordinate vectors.

    Args:
        simulator: the (budget-counting) simulator.
        prior: `BoxPrior` (for `expand`).
        observations: the observed tasks.
        space: "joint" or "cartesian".
        dtype: simulation dtype.
        budget: simulated trajectories this object may request in total; it never requests
            more (``remaining``).
        chunk_size: particles per chunk (see `AbcSmcConfig.chunk_size`).
        scheduler: None (in-process) or a Dask scheduler spec for the chunks.
    """

    def __init__(self, simulator, prior: BoxPrior, observations, *, space: str, dtype, budget: int,
                 chunk_size: int = 1024, scheduler: str | None = None, noise: NoiseModel | None = None,
                 seed: int = 0):
        self.simulator, self.prior, self.space, self.dtype = simulator, prior, space, dtype
        self.names = parameter_names(prior, getattr(simulator, "joint_names", None))  # theta order
        self.chunk_size = check_positive_int(chunk_size, "chunk_size")
        self.noise = NoiseModel() if noise is None else noise
        self.seed = check_positive_int(seed, "seed", minimum=0)
        self._calls = 0  # noise streams: default_rng([seed, call, task, chunk])
        parse_scheduler(scheduler)
        self.scheduler = scheduler
        self.budget = int(budget)
        self.n_simulations = 0
        self.time_simulate = 0.0
        self.time_distance = 0.0
        self.n_particles = 0
        n = prior.n_joints
        self._tasks = []
        for i, obs in enumerate(observations):
            start = torch.as_tensor(obs.start, dtype=torch.float64).cpu()
            goal = torch.as_tensor(obs.goal, dtype=torch.float64).cpu()
            traj = torch.as_tensor(obs.trajectory(space), dtype=torch.float64).cpu()
            if start.shape != (n,) or goal.shape != (3,) or traj.dim() != 2 or traj.shape[0] < 1:
                raise ValueError(
                    f"observations: task {i} has start {tuple(start.shape)}, goal {tuple(goal.shape)}, "
                    f"trajectory {tuple(traj.shape)}; expected ({n},), (3,), (L, D)"
                )
            self._tasks.append((start, goal, traj))

    @property
    def n_tasks(self) -> int:
        return len(self._tasks)

    @property
    def remaining(self) -> int:
        """Simulations still allowed (also bounded by a counting wrapper's own ``remaining``)."""
        left = self.budget - self.n_simulations
        other = getattr(self.simulator, "remaining", None)
        if isinstance(other, int):
            left = min(left, other)
        return max(left, 0)

    def __call__(self, free_theta: np.ndarray, eps: float = math.inf) -> tuple[np.ndarray, np.ndarray]:
        """Distances of ``free_theta`` (B, n_free).

        Returns (distance (B,), complete (B,) bool). With a finite ``eps`` the evaluation of a
        particle stops once its partial sum exceeds eps (complete False; its distance is then a
        lower bound > eps, possibly inf). The caller must ensure ``B * n_tasks <= remaining``.
        """
        theta = self.prior.expand(torch.as_tensor(free_theta, dtype=torch.float64))
        B = theta.shape[0]
        total = np.zeros(B)
        alive = np.ones(B, dtype=bool)
        call = self._calls
        self._calls += 1
        for i, (start, goal, traj) in enumerate(self._tasks):
            idx = np.flatnonzero(alive)
            if idx.size == 0:
                break
            # every alive particle is simulated to this task: charged before anything runs
            jobs = [(theta[torch.from_numpy(c)], float(total[c].min()), (self.seed, call, i, j))
                    for j, c in enumerate(np.array_split(idx, max(1, math.ceil(idx.size / self.chunk_size))))]
            parts = run_chunks(_task_chunk, jobs, simulator=self.simulator, n_simulations=int(idx.size),
                               scheduler=self.scheduler, start=start, goal=goal, trajectory=traj,
                               space=self.space, dtype=self.dtype, eps=eps, noise=self.noise)
            total[idx] += np.concatenate([p[0] for p in parts])
            self.n_simulations += int(idx.size)
            self.time_simulate += sum(p[1] for p in parts)
            self.time_distance += sum(p[2] for p in parts)
            if math.isfinite(eps):
                alive &= total <= eps
        self.n_particles += B
        complete = alive | ~math.isfinite(eps)
        return total, complete

    def single(self, parameter) -> dict:
        """pyabc model for ``sampler="single"``: one particle, all tasks, sum stat {"d": distance}."""
        if self.n_tasks > self.remaining:
            raise _OutOfBudget
        d, _ = self(np.array([[parameter[k] for k in self.names]]))
        return {_DISTANCE_KEY: float(d[0])}


def _task_chunk(job, *, simulator, start, goal, trajectory, space: str, dtype, eps: float, noise: NoiseModel):
    """DTW of one chunk of particles to one task (in-process or on a Dask worker).

    ``job`` = (theta (b, 2n) full vectors, the smallest partial distance among them, the key of
    its noise stream). With observation noise the simulated trajectories are perturbed by the
    same noise model before the DTW (noisy ABC), from ``default_rng(key)``. With a
    finite ``eps`` the DTW is pruned at the chunk's remaining allowance ``eps - that
    minimum``: a distance beyond it comes back as inf (> eps, rejected). An accepted
    particle's every term is below its allowance, so its distance is exact whatever the
    chunking; only rejected particles' lower bounds depend on it.
    Returns (distances (b,), simulate time, distance time).
    """
    theta, partial_min, key = job
    t0 = time.perf_counter()
    sims = simulator.simulate(contain(theta, start).to(dtype), goal=goal.to(dtype), start=start.to(dtype))
    t1 = time.perf_counter()
    x = sims.q if space == "joint" else sims.ee
    if noise.sigma(space) > 0:
        x = noise.perturb(x, space, np.random.default_rng(key))
    allowance = None
    if math.isfinite(eps):
        # DTW >= epsilon comes back as inf: nextafter makes that "> allowance"
        allowance = float(np.nextafter(max(eps - partial_min, 0.0), np.inf))
    d = dtw_distances(trajectory, x, sims.length, epsilon=allowance).numpy()
    return d, t1 - t0, time.perf_counter() - t1


class _OutOfBudget(Exception):
    """Raised by `JointDistance.single` when a particle would exceed the budget."""


def _distance_from_sumstat(x: dict, x_0: dict) -> float:  # noqa: ARG001
    """pyabc distance: the model output already is the distance to the observations."""
    return float(x[_DISTANCE_KEY])


# ----------------------------------------------------------------------------------------------
# the perturbation kernel
# ----------------------------------------------------------------------------------------------

#: smallest eigenvalue of the perturbation covariance, relative to its largest (see
#: `StableMultivariateNormalTransition`); scipy treats eigenvalues below ~2.2e-10 of the
#: largest as zero, this keeps a 100x margin above that cut
KERNEL_MIN_EIGENVALUE_RATIO = 1e-8


def _weighted_cov(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """pyabc's sample covariance of a population (its ``transition.util.smart_cov``)."""
    if x.shape[0] == 1:
        return np.diag(np.absolute(x[0]))
    return np.atleast_2d(np.cov(x, aweights=w, rowvar=False))


class StableMultivariateNormalTransition(Transition):
    """pyabc's default kernel (`pyabc.MultivariateNormalTransition`) with a full-rank covariance.

    The same Gaussian KDE: the population's weighted covariance times the squared
    Silverman factor of its effective sample size (times ``scaling``); a proposal picks a
    particle by weight and adds N(0, cov); the density is the weighted sum of the kernels.
    On a population whose covariance is well conditioned it draws the same random numbers
    and returns the same values as pyabc's kernel, bit for bit.

    It differs on a degenerate population. When a few particles carry nearly all the
    weight (common here in 14-18 free coordinates), the weighted covariance loses rank
    generation after generation (docs/studies/design_measurements.md). Once
    the smallest eigenvalue falls below ~2.2e-10 of the largest, scipy's
    ``multivariate_normal(allow_singular=True)`` (pyabc's density) is zero off the
    covariance's support, while numpy's sampler does not stay exactly on it: every
    proposal gets density 0, weight prior / 0 = inf, and pyabc stops with "population
    total weight nan" (pyabc issues #614 and #623 report the same). Here the eigenvalues
    below ``min_eigenvalue_ratio`` times the largest are raised to it, so the kernel
    stays a proper density on R^d; a covariance that is not finite or zero (all weight on
    one particle) is replaced by the unweighted covariance of the particles (same
    bandwidth). ``n_regularized`` counts the fits that needed either; ``last_fit``
    describes the latest fit (ESS, eigenvalue ratio before the floor, what was done).

    `logpdf` evaluates the log density without underflow (log-sum-exp over the kernels).
    A subclass of pyabc's public `pyabc.transition.Transition` base (the extension point
    for custom kernels): ``fit``, ``rvs_single``, ``rvs``, ``pdf``.
    """

    def __init__(self, scaling: float = 1, min_eigenvalue_ratio: float = KERNEL_MIN_EIGENVALUE_RATIO):
        self.scaling = scaling
        self.min_eigenvalue_ratio = min_eigenvalue_ratio
        self.n_regularized = 0
        self.last_fit: dict | None = None
        self.cov: np.ndarray | None = None
        self._columns: list[str] = []
        self._x = np.empty((0, 0))
        self._w = np.empty(0)
        self._normal = None

    def fit(self, X: pd.DataFrame, w: np.ndarray) -> None:
        # pyabc's Transition wrapper has already stored X and the normalised w (self.X, self.w)
        if len(X) == 0:
            raise pyabc.transition.NotEnoughParticles("Fitting not possible.")
        self._columns = list(X.columns)
        self._x = X.values
        self._w = w
        dim = self._x.shape[1]
        ess = 1 / (w**2).sum()
        bw = pyabc.transition.silverman_rule_of_thumb(ess, dim)
        with warnings.catch_warnings(), np.errstate(divide="ignore", invalid="ignore"):
            # all weight on one particle: np.cov's weighted normalisation divides by zero (handled below)
            warnings.simplefilter("ignore", RuntimeWarning)
            cov = _weighted_cov(self._x, w) * bw**2 * self.scaling
        action = None
        eig = np.linalg.eigvalsh(cov) if np.all(np.isfinite(cov)) else np.array([np.nan])
        if not (np.all(np.isfinite(eig)) and eig[-1] > 0):
            cov = np.atleast_2d(np.cov(self._x, rowvar=False)) * bw**2 * self.scaling
            eig = np.linalg.eigvalsh(cov)
            action = "unweighted covariance"
            if not (np.all(np.isfinite(eig)) and eig[-1] > 0):
                raise pyabc.transition.NotEnoughParticles("every particle is identical: no covariance")
        ratio = float(eig[0] / eig[-1])
        if ratio < self.min_eigenvalue_ratio:
            lam, vec = np.linalg.eigh(cov)
            cov = (vec * np.maximum(lam, self.min_eigenvalue_ratio * lam[-1])) @ vec.T
            cov = 0.5 * (cov + cov.T)
            action = "eigenvalue floor" if action is None else action + " + eigenvalue floor"
        if action is not None:
            self.n_regularized += 1
        self.last_fit = {"ess": float(ess), "eigenvalue_ratio": ratio, "regularized": action}
        self.cov = cov
        self._normal = st.multivariate_normal(cov=cov, allow_singular=True)

    def rvs_single(self) -> pyabc.Parameter:
        i = np.random.choice(np.arange(len(self._w)), p=self._w, replace=True)
        perturbed = self._x[i] + np.random.multivariate_normal(np.zeros(self.cov.shape[0]), self.cov)
        return pyabc.Parameter(dict(zip(self._columns, perturbed, strict=True)))

    def rvs(self, size: int | None = None) -> pyabc.Parameter | pd.DataFrame:
        if size is None:
            return self.rvs_single()
        idx = np.random.choice(np.arange(len(self._w)), size=size, p=self._w, replace=True)
        perturbed = self._x[idx] + np.random.multivariate_normal(np.zeros(self.cov.shape[0]), self.cov, size=size)
        return pd.DataFrame(perturbed, columns=self._columns)

    def _rows(self, x) -> np.ndarray:
        if isinstance(x, pd.DataFrame):
            return x[self._columns].to_numpy()
        if isinstance(x, dict | pd.Series):
            return np.array([x[key] for key in self._columns])
        return np.asarray(x, dtype=np.float64)

    def pdf(self, x) -> float | np.ndarray:
        x = self._rows(x)
        if x.ndim == 1:
            return float((self._normal.pdf(x - self._x) * self._w).sum())
        return np.array([float((self._normal.pdf(xi - self._x) * self._w).sum()) for xi in x])

    def logpdf(self, x) -> np.ndarray:
        """(b,) log density at the rows of ``x`` (a DataFrame, or (b, d) in fit column order)."""
        x = np.atleast_2d(self._rows(x))
        terms = self._normal.logpdf(x[:, None, :] - self._x[None, :, :]).reshape(x.shape[0], -1)
        with np.errstate(divide="ignore"):
            return scipy.special.logsumexp(terms + np.log(self._w)[None, :], axis=1)


# ----------------------------------------------------------------------------------------------
# samplers
# ----------------------------------------------------------------------------------------------


class BatchedSampler(Sampler):
    """A single-process pyabc sampler that simulates and scores proposals in batches.

    pyabc calls ``sample_until_n_accepted(n, simulate_one, t, max_eval=, all_accepted=)``
    once per generation; the sampler does not use ``simulate_one`` (pyabc's per-particle
    pipeline) but reads what a generation needs from pyabc's public interfaces:
    ``all_accepted=True`` marks pyabc's calibration sample (prior draws, everything
    accepted); generation ``t = 0`` samples the prior; later generations perturb the
    previous population with ``transition``, the kernel object this run passed to
    `pyabc.ABCSMC` (which fits it after every generation); the threshold is
    ``epsilon(t)``, the `pyabc.Epsilon` object passed to ABCSMC.

    Importance weights are ``prior / transition.pdf`` as in pyabc; where that is not a
    finite positive number (the density underflowed or overflowed) the whole population's
    weights are recomputed in log space, ``log prior - transition.logpdf``, shifted by the
    population's maximum (the log density floored at the smallest finite one), and the
    particles that needed it are counted (``log[i]["weights_guarded"]``).

    Args:
        distance: `JointDistance` (holds the budget).
        names: pyabc parameter names (free coordinates, theta order).
        low, high: (n_free,) box of the prior.
        epsilon: the run's `pyabc.Epsilon` (eps_t = ``epsilon(t)``).
        transition: the run's `StableMultivariateNormalTransition`.
        early_rejection, min_batch_size, max_batch_size: see `AbcSmcConfig`.
    """

    def __init__(self, distance: JointDistance, names: list[str], low: np.ndarray, high: np.ndarray, *,
                 epsilon, transition: StableMultivariateNormalTransition, early_rejection: bool = True,
                 min_batch_size: int = 8, max_batch_size: int = 4096):
        super().__init__()
        self.distance, self.names = distance, list(names)
        self.epsilon, self.transition = epsilon, transition
        self.low, self.high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
        self._log_prior = -float(np.log(self.high - self.low).sum())
        self.early_rejection = early_rejection
        self.min_batch_size, self.max_batch_size = min_batch_size, max_batch_size
        self._rate = 1.0
        self.log: list[dict] = []  # one entry per sample_until_n_accepted call
        self.time_proposal = 0.0
        self.time_weights = 0.0

    def _propose(self, b: int, transition) -> np.ndarray:
        """(b, d) proposals inside the box: the prior, or pyabc's transition with rejection."""
        d = len(self.names)
        if transition is None:
            return self.low + np.random.uniform(size=(b, d)) * (self.high - self.low)
        out, have, rounds = [], 0, 0
        while have < b:
            draw = transition.rvs(size=max(b - have, 8))[self.names].to_numpy()
            ok = np.all((draw >= self.low) & (draw <= self.high), axis=1)
            out.append(draw[ok][: b - have])
            have += int(ok.sum())
            rounds += 1
            if rounds == 1000:
                warnings.warn("abc-smc: the transition proposes mostly outside the prior box",
                              RuntimeWarning, stacklevel=2)
        return np.concatenate(out)[:b]

    def _weights(self, transition, theta: np.ndarray, dens: np.ndarray) -> tuple[np.ndarray, int]:
        """Unnormalised importance weights of the accepted ``theta`` and how many were guarded."""
        if transition is None:
            return np.ones(theta.shape[0]), 0
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
            w = math.exp(self._log_prior) / dens
        bad = ~(np.isfinite(w) & (w > 0))
        if not bad.any():
            return w, 0
        log_q = transition.logpdf(pd.DataFrame(theta, columns=self.names))
        finite = np.isfinite(log_q)
        if not finite.any():  # no usable density at all: equal weights (every one counted)
            return np.ones(theta.shape[0]), int(theta.shape[0])
        log_w = self._log_prior - np.where(finite, log_q, log_q[finite].min())
        return np.exp(log_w - log_w.max()), int(bad.sum())

    def sample_until_n_accepted(self, n, simulate_one, t, *, max_eval=np.inf, all_accepted=False,
                                ana_vars=None):  # noqa: ARG002
        calibration = bool(all_accepted)
        eps = math.inf if calibration else float(self.epsilon(t))
        transition = None if calibration or t <= 0 else self.transition
        kernel = None if transition is None else dict(transition.last_fit or {})
        sample = self.sample_factory()
        n_eval = 0  # pyabc's count: evaluations up to the n-th acceptance
        n_prop = 0  # everything simulated (includes the surplus after the n-th acceptance)
        n_acc = 0  # every acceptance, surplus included (acceptance-rate estimate)
        sims_before = self.distance.n_simulations
        k = self.distance.n_tasks
        # expected acceptance rate: 1 when everything is accepted, else the previous
        # population's; batches aim at a fraction of the expected need, since proposals
        # simulated after the n-th acceptance are wasted budget
        rate = 1.0 if calibration or not math.isfinite(eps) else self._rate
        ok = True
        rows = []  # (theta, distance, accepted) in proposal order, up to the n-th acceptance
        acc_theta, acc_dens = [], []
        n_taken = 0  # acceptances kept for the population (at most n)
        while n_taken < n:
            need = n - n_taken
            b = math.ceil(need / rate * (1.0 if rate >= 1.0 else _BATCH_FILL))
            b = min(max(b, self.min_batch_size), self.max_batch_size)
            b = min(b, self.distance.remaining // k)
            if math.isfinite(max_eval):
                b = min(b, int(max_eval) - n_eval)
            if b <= 0:
                ok = False
                break
            t0 = time.perf_counter()
            theta = self._propose(b, transition)
            self.time_proposal += time.perf_counter() - t0
            d, _ = self.distance(theta, eps if self.early_rejection else math.inf)
            acc_idx = np.flatnonzero(d <= eps)
            take = acc_idx[:need]
            last = int(take[-1]) + 1 if take.size == need else b
            n_eval += last
            n_prop += b
            n_acc += int(acc_idx.size)
            rate = n_acc / n_prop if n_acc else rate / 4
            rate = min(max(rate, 1e-4), 1.0)
            t0 = time.perf_counter()
            acc_theta.append(theta[take])
            n_taken += int(take.size)
            if transition is not None:
                acc_dens.append(np.asarray(transition.pdf(pd.DataFrame(theta[take], columns=self.names)),
                                           dtype=np.float64).reshape(-1))
            self.time_weights += time.perf_counter() - t0
            taken = set(take.tolist())
            for i in range(last):
                if i in taken:
                    rows.append((theta[i], d[i], True))
                elif sample.record_rejected:
                    rows.append((theta[i], d[i], False))
        t0 = time.perf_counter()
        theta_acc = np.concatenate(acc_theta) if acc_theta else np.empty((0, len(self.names)))
        dens = np.concatenate(acc_dens) if acc_dens else np.empty(0)
        w, n_guarded = self._weights(transition, theta_acc, dens)
        self.time_weights += time.perf_counter() - t0
        weights = iter(w.tolist())
        for theta_row, dist, accepted in rows:
            sample.append(self._particle(theta_row, dist, next(weights) if accepted else 0.0, accepted))
        # after an eps = inf population the median epsilon accepts about half
        self._rate = rate if math.isfinite(eps) else 0.5
        self.nr_evaluations_ = n_eval
        self.log.append({
            "t": int(t), "calibration": calibration, "eps": eps, "ok": ok, "accepted": sample.n_accepted,
            "evaluations": n_eval, "proposals": n_prop,
            "simulations": self.distance.n_simulations - sims_before,
            "weights_guarded": n_guarded, "kernel": kernel,
        })
        if not ok:
            sample.ok = False
        return sample

    def _particle(self, theta_row, dist, weight, accepted) -> Particle:
        return Particle(
            m=0,
            parameter=pyabc.Parameter(dict(zip(self.names, (float(v) for v in theta_row), strict=True))),
            weight=float(weight),
            sum_stat={_DISTANCE_KEY: float(dist)},
            distance=float(dist),
            accepted=bool(accepted),
            proposal_id=0,
            preliminary=False,
        )


class BudgetedSingleCoreSampler(Sampler):
    """pyabc's SingleCoreSampler (one model call per particle) that stops at the budget."""

    def __init__(self, distance: JointDistance):
        super().__init__()
        self.distance = distance
        self.log: list[dict] = []

    def sample_until_n_accepted(self, n, simulate_one, t, *, max_eval=np.inf, all_accepted=False,
                                ana_vars=None):  # noqa: ARG002
        sample = self._create_empty_sample()
        n_eval, ok = 0, True
        sims_before = self.distance.n_simulations
        while sample.n_accepted < n:
            if n_eval >= max_eval:
                ok = False
                break
            try:
                particle = simulate_one()
            except _OutOfBudget:
                ok = False
                break
            sample.append(particle)
            n_eval += 1
        self.nr_evaluations_ = n_eval
        self.log.append({
            "t": int(t), "ok": ok, "accepted": sample.n_accepted, "evaluations": n_eval,
            "proposals": n_eval, "simulations": self.distance.n_simulations - sims_before,
        })
        if not ok:
            sample.ok = False
        return sample


# ----------------------------------------------------------------------------------------------
# run
# ----------------------------------------------------------------------------------------------


#: what pyabc raises on a population it cannot use (e.g. "population total weight nan",
#: a transition that cannot be fitted); caught in `run`, which then returns the last
#: complete population (status "fallback") or a failed result. BudgetExceededError (a
#: RuntimeError) is not among them: a method exceeding its budget is a bug, not a result.
_PYABC_FAILURES = (AssertionError, ValueError, ArithmeticError, np.linalg.LinAlgError,
                   pyabc.transition.NotEnoughParticles)

PRIOR_ONLY = "only the prior population completed (epsilon inf) within the budget: the samples are prior draws"


def run(task, observations, *, budget: int, seed: int, config: AbcSmcConfig | None = None) -> PosteriorResult:
    """ABC-SMC on the joint posterior given ``observations``, within ``budget`` per task.

    `run_unwarned`, plus one RuntimeWarning when the result's status is not "ok" (the
    registry, which calls `run_unwarned`, warns instead).
    """
    result = run_unwarned(task, observations, budget=budget, seed=seed, config=config)
    if result.status != STATUS_OK:
        warnings.warn(f"abc-smc after {result.n_tasks} task(s): {result.status}", RuntimeWarning, stacklevel=2)
    return result


def min_budget(config: AbcSmcConfig) -> int:
    """The fewest simulations per task that pay for ``config``'s first population (with
    ``initial_epsilon="from_sample"``, its calibration sample as well)."""
    n_pop = config.population_size
    if config.initial_epsilon == "from_sample":
        n_pop = 2 * n_pop  # calibration sample + a first population at ~50% acceptance
    return n_pop


def run_unwarned(task, observations, *, budget: int, seed: int,
                 config: AbcSmcConfig | None = None) -> PosteriorResult:
    """ABC-SMC on the joint posterior given ``observations``, within ``budget`` per task.

    Returns the last complete population (free coordinates expanded to (N, 2n)) with its
    importance weights; ``estimate`` per ``config.point_estimate``. ``extras``: ``epsilons``,
    ``acceptance_rates``, ``n_evaluations``, ``n_populations``, per-generation sampler log
    (``generations``), ``aborted_population`` (True if the budget ran out mid-population;
    its simulations are ``n_simulations_discarded``), ``ess``, ``n_weights_guarded`` and
    ``n_kernels_regularized`` (over the completed populations, see `BatchedSampler` and
    `StableMultivariateNormalTransition`), ``error`` (what pyabc raised, or None), timings
    (``time_simulate``, ``time_distance``, ``time_total``, ``overhead_per_particle``),
    ``db`` (history path when ``config.workdir`` is set).

    ``status``:

    - ``"fallback: only the prior population completed (epsilon inf) ..."`` when no
      population below epsilon = inf completed within the budget (the samples are prior
      draws; typical at budget <= 2 * population_size);
    - ``"fallback: low effective sample size (ESS x of N ...)"`` when the final ESS is below
      ``config.min_ess_fraction * N``;
    - ``"fallback: pyabc stopped at generation t (<error>) ..."`` when pyabc raised on a
      population after at least one completed (the last complete one is returned);
    - ``"failed: <reason>"`` when no population completed at all (pyabc raised on the first
      one, or the simulator's own counter could not pay for it): the result is then the
      prior mean as its single sample and estimate, never a crash;
    - ``"ok"`` otherwise. A budget that ends a run mid-population is the normal end of a
      budgeted run (the last complete population is a valid ABC posterior at its epsilon)
      and is not a fallback by itself; it is recorded in ``extras``.
    """
    config, budget, seed, observations, prior = check_run_args(task, observations, budget, seed, config,
                                                               AbcSmcConfig)
    n_pop = min_budget(config)
    if n_pop > budget:
        raise ValueError(
            f"budget: {budget} simulations per task cannot pay for a first population of "
            f"{config.population_size} particles (initial_epsilon={config.initial_epsilon!r}); "
            f"lower population_size or raise the budget"
        )
    k = len(observations)
    t_start = time.perf_counter()
    distance = JointDistance(task.simulator, prior, observations, space=config.space,
                             dtype=_DTYPES[config.sim_dtype], budget=budget * k,
                             chunk_size=config.chunk_size, scheduler=config.scheduler, noise=task.noise, seed=seed)
    names = distance.names  # by joint and bound: what pyabc's History shows
    pyabc_prior = to_pyabc_prior(prior, getattr(task.simulator, "joint_names", None))
    low = prior.low[prior.free_mask].numpy()
    high = prior.high[prior.free_mask].numpy()
    eps = pyabc.MedianEpsilon(
        initial_epsilon=math.inf if config.initial_epsilon == "inf" else "from_sample",
        median_multiplier=config.median_multiplier,
    )
    transition = StableMultivariateNormalTransition()
    if config.sampler == "batched":
        sampler = BatchedSampler(distance, names, low, high, epsilon=eps, transition=transition,
                                 early_rejection=config.early_rejection,
                                 min_batch_size=config.min_batch_size, max_batch_size=config.max_batch_size)
    else:
        sampler = BudgetedSingleCoreSampler(distance)

    error = None
    with contextlib.ExitStack() as stack:
        if config.workdir is None:
            rundir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="camo_abc_smc_")))
        else:
            rundir = Path(config.workdir)
            rundir.mkdir(parents=True, exist_ok=True)
        db_path = rundir / f"abc_smc_k{k}_seed{seed}.db"
        if db_path.exists():
            db_path.unlink()
        stack.enter_context(numpy_global_seed(seed))
        stack.enter_context(_quiet_pyabc(config.log_level))
        abc = pyabc.ABCSMC(
            models=distance.single,
            parameter_priors=pyabc_prior,
            distance_function=_distance_from_sumstat,
            population_size=config.population_size,
            transitions=transition,
            eps=eps,
            sampler=sampler,
        )
        history = abc.new("sqlite:///" + str(db_path), {_DISTANCE_KEY: 0.0})
        # the only summary statistic is the distance itself, already stored per particle:
        # not writing it again cuts pyabc's per-particle database cost
        history.stores_sum_stats = False
        try:
            abc.run(
                minimum_epsilon=config.min_epsilon,
                max_nr_populations=config.max_populations,
                min_acceptance_rate=config.min_acceptance_rate,
            )
        except _PYABC_FAILURES as exc:
            error = f"{type(exc).__name__}: {exc}"
        n_complete = history.n_populations
        if n_complete:
            population = history.get_population(t=history.max_t)
            pops = history.get_all_populations()
        del history, abc
    t_total = time.perf_counter() - t_start

    log = sampler.log
    gens = [g for g in log if not g.get("calibration", False)]
    aborted = bool(gens) and not gens[-1]["ok"]
    completed = [g for g in gens if g["ok"]]
    t_model = distance.time_simulate + distance.time_distance
    extras = {
        "generations": log,
        "aborted_population": aborted,
        "n_simulations_discarded": int(gens[-1]["simulations"]) if aborted else 0,
        "n_particles_simulated": distance.n_particles,
        "n_weights_guarded": int(sum(g.get("weights_guarded", 0) for g in completed)),
        "n_kernels_regularized": int(sum(1 for g in completed if (g.get("kernel") or {}).get("regularized"))),
        "error": error,
        "time_simulate": distance.time_simulate,
        "time_distance": distance.time_distance,
        "time_total": t_total,
        "overhead_per_particle": (t_total - t_model) / max(distance.n_particles, 1),
        "sampler": config.sampler,
        "db": None if config.workdir is None else str(db_path),
    }
    n_simulations = int(getattr(task.simulator, "n_simulations", distance.n_simulations))
    if not n_complete:
        why = (f"pyabc raised {error} before any population completed" if error is not None
               else "no population completed within the budget")
        estimate = prior.with_known((prior.low + prior.high) / 2).numpy()
        extras.update({"epsilons": [], "acceptance_rates": [], "n_evaluations": [], "n_populations": 0,
                       "ess": 0.0, "distances": np.empty(0)})
        return PosteriorResult(
            method="abc-smc", samples=estimate[None, :], weights=None, estimate=estimate,
            n_simulations=n_simulations, wall_time=t_total, n_tasks=k, extras=extras,
            status=f"failed: {why}; the result is the prior mean",
        )

    particles = population.particles
    free = np.array([[p.parameter[name] for name in names] for p in particles], dtype=np.float64)
    w = np.array([p.weight for p in particles], dtype=np.float64)
    dist = np.array([p.distance for p in particles], dtype=np.float64)
    samples = prior.expand(torch.from_numpy(free)).numpy()
    w = w / w.sum()
    if config.point_estimate == "mean":
        estimate = w @ samples
    elif config.point_estimate == "median":
        estimate = weighted_median(samples, w)
    else:
        estimate = samples[int(np.argmin(dist))]
    estimate = prior.with_known(torch.from_numpy(estimate)).numpy()  # exact, not a mean of constants
    pops = pops[pops.t >= 0].sort_values("t")
    ess = float(1.0 / np.sum(w**2))
    epsilons = [float(e) for e in pops.epsilon]
    extras.update({
        "epsilons": epsilons,
        "acceptance_rates": [float(p) / float(s) for p, s in zip(pops.particles, pops.samples, strict=True)],
        "n_evaluations": [int(s) for s in pops.samples],
        "n_populations": int(len(pops)),
        "ess": ess,
        "distances": dist,
    })
    reasons = []
    if error is not None:
        reasons.append(f"pyabc stopped at generation {len(epsilons)} ({error}); the result is generation "
                       f"{len(epsilons) - 1}")
    if all(math.isinf(e) for e in epsilons):
        reasons.append(PRIOR_ONLY)
    elif ess < config.min_ess_fraction * len(w):
        reasons.append(f"low effective sample size (ESS {ess:.1f} of {len(w)} particles, below "
                       f"{config.min_ess_fraction:g} N)")
    return PosteriorResult(
        method="abc-smc", samples=samples, weights=w, estimate=estimate,
        n_simulations=n_simulations, wall_time=t_total, n_tasks=k, extras=extras,
        status="fallback: " + "; ".join(reasons) if reasons else STATUS_OK,
    )
