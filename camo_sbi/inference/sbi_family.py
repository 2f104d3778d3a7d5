"""What sbi's other method families share: NLE, NRE-C, FMPE, NPSE and truncated sequential NPE.

Each family is one small module (`nle`, `nre`, `fmpe`, `npse`, `tsnpe`): a frozen config
(`FamilyConfig` plus its own fields) and a trainer ``train(z, x, x_obs, simulate, seed, config)``
that fits one sbi estimator per observed task through `sbi_adapter` (the only sbi import). This
module does the rest, the same way for all five and the same way per-task NPE (`npe`) does it:

1. Per observed task i, ``budget`` limit vectors drawn from the prior with NPE's own seed
   stream (so NLE, NRE, FMPE, NPSE and NPE see the very same training draws for a seed),
   widened to contain the task's start, simulated to its goal in large batched chunks
   (``scheduler``: the one Dask path), summarised as NPE summarises (``trajectory_summary``,
   constant features dropped; observation noise added as NPE adds it). Parameters live in the
   logit coordinates z of the prior box (uniform prior = independent standard logistics).
2. How the tasks combine (a method's ``KIND``):

   - ``"likelihood"`` (NLE, NRE): the task terms are log-likelihoods (NLE: log q_i(x_i | z)) or
     log-ratios (NRE: log r_i(x_i, z) = log p(x_i | z) / p(x_i) + const); the posterior is
     log p(z) + sum_i term_i(z), exact for independent tasks. Sampled by tempered SMC from the
     prior (`samplers.smc`), the status by the samplers' one rule (`WeightedDraws.status`:
     SMC that does not reach the target, or too small an ESS of the weights or of the distinct
     draws, is a fallback).
   - ``"posterior"`` (FMPE, NPSE, TSNPE): each task gives a posterior q_i(z | x_i); combined as
     NPE combines its flows, p(z)^(1-k) prod_i q_i(z | x_i) (`npe_posterior.NpePosterior`),
     sampled by adaptive importance sampling from the mixture of the q_i.

3. Continual use: task i's draws, noise and training are seeded by (seed, i) only and the
   sampler by ``seed``, so `run_sequence` simulates and trains each task once and its k-th
   result equals `run` on the first k tasks. For the same reason a family that says how to
   save and rebuild its estimator (`Checkpoint`: NLE, TSNPE) and is given a ``workdir`` saves
   each trained task there, and a killed run resumes at its next task (`task_checkpoint`).

A sampler that cannot produce draws at all (every importance weight zero, e.g. an FMPE or NPSE
density that is NaN everywhere; sbi's ODE solver raising on a diverged vector field) is not an
exception that stops a grid: the result is ``failed: ...`` with the prior's centre as its
estimate, as CAMO and ABC-SMC do. Too few effective draws is a ``fallback`` (the samplers' rule).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from camo_sbi._validation import check_bool, check_choice, check_positive_float, check_positive_int
from camo_sbi.budget import charge
from camo_sbi.distributed import run_chunks
from camo_sbi.inference import samplers, sbi_adapter, task_checkpoint
from camo_sbi.inference.contract import check_run_args
from camo_sbi.inference.flow_space import (
    from_unconstrained,
    logistic_log_prob,
    to_unconstrained,
    torch_threads,
    trajectory_summary,
)
from camo_sbi.inference.npe import (
    _DTYPES,
    _seed_int,
    _simulate_summaries,
    check_sampling_settings,
    check_training_settings,
    point_estimate,
)
from camo_sbi.inference.npe_posterior import NpePosterior
from camo_sbi.inference.result import PosteriorResult, failed_at_prior_centre
from camo_sbi.task import SPACES

# a config with a ``rounds`` field (TSNPE) splits each task's budget over that many rounds

__all__ = ["KINDS", "Checkpoint", "FamilyConfig", "VectorFieldConfig", "run", "run_sequence", "train_vector_field"]

KINDS = ("likelihood", "posterior")
_U_EPS = 1e-6


@dataclass(frozen=True)
class FamilyConfig:
    """Settings every family shares (each module's config adds its own).

    Attributes:
        space, n_points, include_length: the summary, as `npe.NpeConfig`.
        hidden_features: width of the estimator's networks.
        training_batch_size, learning_rate, validation_fraction, stop_after_epochs, max_epochs:
            sbi training settings (early stopping on the validation loss).
        n_posterior_samples: SMC particles (likelihood families) or importance draws per round
            (posterior families).
        is_rounds, defensive_fraction: adaptive importance rounds and their share of mixture
            draws (posterior families; `npe_posterior.NpePosterior.sample_is`).
        smc_max_stages: tempering stages before SMC gives up (a fallback; likelihood families).
        point_estimate: "mean", "median" (weighted, coordinate-wise) or "mode".
        min_ess: below min(min_ess, N / 2) effective draws (of the weights, or of the distinct
            draws: `samplers.WeightedDraws.status`) the result is a fallback.
        chunk_size, sim_dtype, device, n_threads, scheduler: as `npe.NpeConfig`.
    """

    space: str = "joint"
    n_points: int = 20
    include_length: bool = True
    hidden_features: int = 50
    training_batch_size: int = 100
    learning_rate: float = 1e-3
    validation_fraction: float = 0.1
    stop_after_epochs: int = 20
    max_epochs: int = 200
    n_posterior_samples: int = 2000
    is_rounds: int = 3
    defensive_fraction: float = 0.2
    smc_max_stages: int = 100
    point_estimate: str = "mean"
    min_ess: float = 20.0
    chunk_size: int = 10000
    sim_dtype: str = "float32"
    device: str = "cpu"
    n_threads: int | None = 1
    scheduler: str | None = None

    def __post_init__(self):
        check_choice(self.space, SPACES, "space")
        check_positive_int(self.n_points, "n_points")
        check_bool(self.include_length, "include_length")
        check_positive_int(self.hidden_features, "hidden_features")
        check_training_settings(self)
        check_positive_int(self.n_posterior_samples, "n_posterior_samples", minimum=16)
        check_positive_int(self.smc_max_stages, "smc_max_stages")
        check_sampling_settings(self)


@dataclass(frozen=True)
class VectorFieldConfig(FamilyConfig):
    """FMPE's and NPSE's settings: `FamilyConfig` plus the MLP vector field (``hidden_features``
    wide, ``num_layers`` deep; smaller than sbi's 100 x 5, for cost) and the probability-flow ODE
    that gives each task's density (``ode_atol``, ``ode_rtol``, ``ode_exact``: exact trace or
    Hutchinson's estimate). Every density evaluation solves an ODE, so the importance sampler
    uses fewer draws by default (1000 per round, 2 rounds after the mixture's)."""

    hidden_features: int = 64
    num_layers: int = 3
    learning_rate: float = 5e-4
    training_batch_size: int = 200
    n_posterior_samples: int = 1000
    is_rounds: int = 2
    ode_atol: float = 1e-4
    ode_rtol: float = 1e-3
    ode_exact: bool = True

    def __post_init__(self):
        super().__post_init__()
        check_positive_int(self.num_layers, "num_layers")
        check_positive_float(self.ode_atol, "ode_atol")
        check_positive_float(self.ode_rtol, "ode_rtol")
        check_bool(self.ode_exact, "ode_exact")


def train_vector_field(kind: str, z, x, seed: int, config: VectorFieldConfig, **extra):
    """An FMPE or NPSE posterior q(z | x) of one task (`sbi_adapter.train_vector_field`)."""
    return sbi_adapter.train_vector_field(
        kind, z, x, seed=seed, hidden_features=config.hidden_features, num_layers=config.num_layers,
        training_batch_size=config.training_batch_size, learning_rate=config.learning_rate,
        validation_fraction=config.validation_fraction, stop_after_epochs=config.stop_after_epochs,
        max_epochs=config.max_epochs, atol=config.ode_atol, rtol=config.ode_rtol, exact=config.ode_exact,
        device=config.device, **extra)


class _LogisticBase:
    """The prior in logit coordinates (independent standard logistics) as an SMC base."""

    def __init__(self, dim: int):
        self.dim = dim

    def draw(self, n: int, generator: torch.Generator) -> torch.Tensor:
        u = torch.rand(n, self.dim, generator=generator, dtype=torch.float64).clamp(_U_EPS, 1 - _U_EPS)
        return torch.logit(u)

    def log_prob(self, z: torch.Tensor) -> torch.Tensor:
        return logistic_log_prob(z)


def _check(task, observations, budget, seed, config, config_cls):
    config, budget, seed, observations, prior = check_run_args(task, observations, budget, seed, config, config_cls)
    if prior.n_free == 0:
        raise ValueError("task.prior: every coordinate is fixed; there is nothing to infer")
    rounds = getattr(config, "rounds", 1)
    n_val = int(budget // rounds * config.validation_fraction)
    if n_val < 2 or budget // rounds - n_val < 2:
        raise ValueError(f"budget: {budget} simulations per task leave too few for training and validation "
                         f"(validation_fraction={config.validation_fraction}, {rounds} round(s))")
    return config, budget, seed, observations, prior


class Checkpoint(NamedTuple):
    """How a family's per-task estimator is saved and rebuilt (`task_checkpoint`), for a config
    with a ``workdir``: ``module_of(estimator)`` is the network saved, ``wrap(network)`` the
    estimator again, ``build(n_free, n_x, architecture)`` an untrained network of
    ``architecture(config)``."""

    module_of: Callable
    wrap: Callable
    build: Callable
    architecture: Callable


def _tasks(task, observations, budget: int, seed: int, config, train, method: str, checkpoint: Checkpoint | None):
    """Yield (estimator, observed summary, info) per task, in order: simulate, summarise, train
    (or read back a task an earlier run trained, with ``checkpoint`` and a ``workdir``)."""
    prior, sim, dtype = task.prior, task.simulator, _DTYPES[config.sim_dtype]
    lo, width = prior.low[prior.free_mask], (prior.high - prior.low)[prior.free_mask]
    workdir = getattr(config, "workdir", None) if checkpoint is not None else None
    for i, obs in enumerate(observations):
        key = None
        if workdir is not None:
            key = task_checkpoint.task_key(method, task, obs, index=i, budget=budget, seed=seed, config=config)
            stored = task_checkpoint.load_task(workdir, method, i, key, checkpoint.build)
            if stored is not None:  # trained by an earlier (killed) run with these very settings
                module, xo, info = stored
                charge(sim, int(info["n_simulations"]))  # run in that earlier process
                yield checkpoint.wrap(module), xo.float(), {**info, "resumed": True}
                continue
        counted_before = getattr(sim, "n_simulations", None)
        start = torch.as_tensor(obs.start, dtype=torch.float64).cpu()
        goal = torch.as_tensor(obs.goal, dtype=torch.float64).cpu()
        traj = torch.as_tensor(obs.trajectory(config.space), dtype=torch.float64).cpu()
        t_sim = 0.0

        def summaries(theta, key, start=start, goal=goal):
            nonlocal t_sim
            t0 = time.perf_counter()
            chunks = [(theta[s : s + config.chunk_size], (*key, c))
                      for c, s in enumerate(range(0, theta.shape[0], config.chunk_size))]
            feats = run_chunks(_simulate_summaries, chunks, simulator=sim, n_simulations=theta.shape[0],
                               scheduler=config.scheduler, start=start, goal=goal, dtype=dtype, config=config,
                               noise=task.noise)
            t_sim += time.perf_counter() - t0
            return torch.cat(feats)

        rounds = getattr(config, "rounds", 1)  # sequential: the first round gets what the later ones leave
        theta = prior.sample(budget - (rounds - 1) * (budget // rounds), np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0, i))))
        x = summaries(theta, (seed, 3, i))
        xo = trajectory_summary(traj, torch.tensor([traj.shape[0]]), n_points=config.n_points,
                                include_length=config.include_length)[0]
        finite = torch.isfinite(x).all(dim=1)
        keep = x[finite].std(dim=0) > 1e-8 * (1.0 + x[finite].abs().amax(dim=0))
        if not bool(keep.any()):
            raise RuntimeError(f"observations: task {i}'s simulations are all identical; nothing to learn")
        calls = 0

        def simulate(z, i=i, keep=keep):
            """Summaries (kept features) of parameters z (m, n_free) in logit coordinates (later rounds)."""
            nonlocal calls
            calls += 1
            th = prior.low.repeat(z.shape[0], 1)
            th[:, prior.free_mask] = from_unconstrained(z.double(), lo, width, "logit")[0]
            return summaries(th, (seed, 4, i, calls))[:, keep].float()

        z = to_unconstrained(theta[:, prior.free_mask], lo, width, "logit")
        with torch_threads(config.n_threads):
            est, info = train(z[finite], x[finite][:, keep], xo[keep], simulate, _seed_int(seed, 1, i), config,
                              budget=budget)
        info = {**info, "task": i, "n_features": int(keep.sum()), "n_invalid": int((~finite).sum())}
        info["time_simulate"] = t_sim
        info["n_simulations"] = budget if counted_before is None else int(sim.n_simulations - counted_before)
        if key is not None:
            task_checkpoint.save_task(workdir, method, i, key, checkpoint.module_of(est), xo[keep].float(), info,
                                      n_free=int(prior.n_free), architecture=checkpoint.architecture(config))
        yield est, xo[keep].float(), {**info, "resumed": False}


def _failed(task, why: str, method: str, infos, t_start) -> PosteriorResult:
    resumed = task_checkpoint.resumed_summary(infos)
    return failed_at_prior_centre(method, task.prior, len(infos), why,
                                  n_simulations=int(getattr(task.simulator, "n_simulations", 0)),
                                  wall_time=time.perf_counter() - t_start + resumed["resumed_seconds"],
                                  extras={"tasks": list(infos), **resumed})


def _likelihood_draws(prior, terms, config, seed):
    """SMC draws of log p(z) + sum_i term_i(z) and the theta density; terms: callables z -> (N,)."""
    lo, width = prior.low[prior.free_mask], (prior.high - prior.low)[prior.free_mask]

    @torch.no_grad()
    def log_target(z):
        with torch_threads(config.n_threads):
            total = logistic_log_prob(z)
            for term in terms:
                total = total + torch.nan_to_num(term(z), nan=-float("inf"))
        return total

    draws = samplers.smc(log_target, _LogisticBase(int(prior.n_free)), seed=_seed_int(seed, 2) % (2**32),
                         particles=config.n_posterior_samples, max_stages=config.smc_max_stages)
    free, logdet = from_unconstrained(draws.samples, lo, width, "logit")
    theta = prior.low.repeat(free.shape[0], 1)
    theta[:, prior.free_mask] = free

    @torch.no_grad()
    def density(t):
        t = torch.as_tensor(t, dtype=torch.float64)
        t = t.unsqueeze(0) if t.dim() == 1 else t
        inside = prior.contains(t)
        z = to_unconstrained(t[:, prior.free_mask], lo, width, "logit")
        lp = log_target(z) - from_unconstrained(z, lo, width, "logit")[1]
        return torch.where(inside, lp, torch.full_like(lp, -float("inf")))

    return draws.mapped(theta, draws.log_density - logdet), density


def _result(task, kind: str, method: str, estimators, x_obs, infos, config, seed: int,
            t_start: float) -> PosteriorResult:
    prior = task.prior
    t0 = time.perf_counter()
    try:
        if kind == "likelihood":
            draws, density = _likelihood_draws(prior, [lambda z, e=e, x=x: e(x, z) for e, x in
                                                       zip(estimators, x_obs, strict=True)], config, seed)
        else:
            posterior = NpePosterior(estimators, x_obs, prior.low, prior.high, theta_transform="logit",
                                     n_threads=config.n_threads)
            draws = posterior.sample_is(config.n_posterior_samples, _seed_int(seed, 2) % (2**32),
                                        is_rounds=config.is_rounds, defensive_fraction=config.defensive_fraction)
            density = posterior.log_prob
    except (RuntimeError, AssertionError, FloatingPointError) as exc:
        # no usable draw at all (a density NaN everywhere; an ODE solver giving up on a diverged
        # vector field): recorded as failed, never raised into a grid
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        return _failed(task, why, method, infos, t_start)
    extras = {"ess": draws.ess, "sampler": draws.sampler, "sampler_diagnostics": dict(draws.diagnostics),
              "tasks": list(infos), "time_simulate": sum(t["time_simulate"] for t in infos),
              "time_train": sum(t["time_train"] for t in infos), "time_sample": time.perf_counter() - t0,
              **task_checkpoint.resumed_summary(infos)}
    return PosteriorResult(
        method=method, samples=draws.samples.numpy(), weights=draws.weights.numpy(),
        estimate=point_estimate(draws, config.point_estimate, prior),
        n_simulations=int(getattr(task.simulator, "n_simulations", 0)),
        wall_time=time.perf_counter() - t_start + extras["resumed_seconds"],
        n_tasks=len(infos), extras=extras, status=draws.status(config.min_ess), density=density,
    )


def _accumulate(task, observations, budget, seed, config, config_cls, train, kind, method, checkpoint):
    """Check the arguments, then yield (config, estimators, summaries, infos, t_start) after each task."""
    check_choice(kind, KINDS, "kind")
    config, budget, seed, observations, _ = _check(task, observations, budget, seed, config, config_cls)
    t_start = time.perf_counter()
    ests, xs, infos = [], [], []
    for est, xo, info in _tasks(task, observations, budget, seed, config, train, method, checkpoint):
        ests.append(est)
        xs.append(xo)
        infos.append(info)
        yield config, ests, xs, infos, t_start


def run_sequence(task, observations, *, budget: int, seed: int, config, config_cls, train, kind: str, method: str,
                 checkpoint: Checkpoint | None = None):
    """Yield the result conditioned on the first 1, 2, ..., K tasks (each task trained once).

    ``train(z, x, x_obs, simulate, seed, config, budget=budget) -> (estimator, info)``: a
    ``"likelihood"`` estimator is a callable ``(x_obs, z) -> (N,)`` log term, a ``"posterior"``
    one a flow-like module (``log_prob``, ``sample``); ``info`` has ``time_train``.
    ``checkpoint``: how to save and rebuild an estimator (`Checkpoint`); with it and a config
    whose ``workdir`` is set, each trained task is saved there and a re-run reads it back.
    """
    for checked, ests, xs, infos, t_start in _accumulate(task, observations, budget, seed, config, config_cls,
                                                         train, kind, method, checkpoint):
        yield _result(task, kind, method, ests, xs, infos, checked, seed, t_start)


def run(task, observations, *, budget: int, seed: int, config, config_cls, train, kind: str,
        method: str, checkpoint: Checkpoint | None = None) -> PosteriorResult:
    """The result conditioned on every task in ``observations`` (the last of `run_sequence`)."""
    *_, last = _accumulate(task, observations, budget, seed, config, config_cls, train, kind, method, checkpoint)
    config, ests, xs, infos, t_start = last
    return _result(task, kind, method, ests, xs, infos, config, seed, t_start)
