"""Neural posterior estimation (sbi) per observed task, combined into the joint posterior.

sbi is used only through `camo_sbi.inference.sbi_adapter` (the one module importing sbi).

Design (same simulation design as CAMO, so budgets are equal):

1. Per observed task i, draw ``budget`` limit vectors from the prior and simulate them to THAT
   task's goal from its start in large batched ``simulate`` calls (never sbi's
   ``simulate_for_sbi`` with batch size 1). As in CAMO, each vector is widened to contain the
   task's observed start before simulating (part of the model, a no-op when the start is the
   prior's split point).
2. Summary x: the valid part of the trajectory (``config.space``) linearly resampled at
   ``n_points`` equally spaced times after the start (the start itself is observed, hence
   uninformative), flattened, plus the trajectory length. A fixed-size vector whatever the
   length; features that are constant over the task's simulations carry nothing (their z-score
   would divide by ~0): they are dropped, or with ``warm_start`` set to 0, in the observation
   too, so that every task's flow has the same input size. Optionally an MLP embedding net is
   trained jointly (``embedding="mlp"``).
3. Train a conditional flow q_i(z | x) (sbi NPE, single round = maximum likelihood, MAF or
   NSF) on the FREE coordinates only, in unconstrained coordinates z = logit of the position
   inside the prior box (``theta_transform="logit"``): the flow has no mass outside the box
   (no leakage correction needed). Option ``warm_start`` (off by default): task i > 0's flow
   starts from task i - 1's trained weights, with the z-scoring of its own data and less
   early-stopping patience (``warm_stop_after_epochs``); it stops after far fewer epochs, but
   the flows' errors are then no longer independent across tasks and they add up in the
   product (calibration measured in docs/guide/performance.md). Training is seeded inside
   ``torch.random.fork_rng``, so the same seed gives the same estimator and the caller's global
   torch RNG is untouched.
4. Combine: with a common prior p, p(theta | x_1..k) ∝ p(theta)^(1-k) ∏_i q_i(theta | x_i)
   (exact if each q_i is the exact posterior). In z coordinates p is the product of standard
   logistic densities; with ``theta_transform="none"``, p is uniform and the product is
   restricted to the box.
5. Sample the combination with `samplers.importance` (no MCMC tuning, deterministic, with an
   effective sample size to report): round 0 proposes from the equal mixture of the k flows,
   round 1 from a Gaussian approximation of the product, later rounds (``is_rounds`` in all)
   from a Gaussian fitted to the best round's weighted draws, each keeping a defensive share
   of flow-mixture draws. The product of k sharp per-task posteriors is much narrower than any
   of them, so round 0 alone is poor for k > 1; the adaptive rounds are what make the weights
   usable. With ``reuse_mixture_draws`` (default) round 0 draws only the defensive share from
   the flows and the adaptive rounds reuse those draws (drawing from a flow is its costly
   direction). A round whose proposal is the target (k = 1) ends the rounds. A sample with too
   small an ESS is a fallback (``min_ess``, the samplers' one rule).

Continual use: task i's simulations and training are seeded by (seed, i), and a warm start
reads task i - 1's flow only, so `run_sequence` trains each task once and its k-th result
equals `run` on the first k tasks.

The combined posterior itself (`npe_posterior.NpePosterior`: density, samplers, files) is
shared with `amortized`; the summaries and flow coordinates live in `flow_space`.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
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
from camo_sbi.budget import charge
from camo_sbi.distributed import parse_scheduler, run_chunks
from camo_sbi.inference import samplers, sbi_adapter, task_checkpoint
from camo_sbi.inference.contract import check_run_args
from camo_sbi.inference.flow_space import to_unconstrained, torch_threads, trajectory_summary
from camo_sbi.inference.npe_posterior import TRANSFORMS, NpePosterior
from camo_sbi.inference.result import PosteriorResult, weighted_median
from camo_sbi.priors import BoxPrior
from camo_sbi.task import SPACES, NoiseModel, contain

__all__ = ["NpeConfig", "check_sampling_settings", "check_training_settings", "fit", "point_estimate", "run", "run_sequence"]

_MODELS = ("maf", "nsf")
_EMBEDDINGS = ("none", "mlp")
_POINT_ESTIMATES = ("mean", "median", "mode")
_DTYPES = {"float32": torch.float32, "float64": torch.float64}

@renamed_fields(estimator="point_estimate", simulation_batch_size="chunk_size")
@dataclass(frozen=True)
class NpeConfig:
    """NPE settings.

    Attributes:
        space: "joint" (q) or "cartesian" (end-effector) trajectories summarised.
        n_points: resampled points per trajectory (after the start).
        include_length: append the trajectory length to the summary.
        embedding: "none" (summary fed to the flow, z-scored) or "mlp" (sbi FCEmbedding
            trained jointly, output ``embedding_dim``).
        embedding_dim: output size of the MLP embedding.
        density_estimator: "maf" or "nsf".
        hidden_features, num_transforms: flow size (sbi's ``posterior_nn``).
        theta_transform: "logit" (train in unconstrained coordinates) or "none" (raw theta;
            mass outside the box is discarded when sampling).
        training_batch_size, learning_rate, validation_fraction, stop_after_epochs, max_epochs:
            sbi training settings (early stopping on the validation loss).
        warm_start: train task i > 0's flow from task i - 1's trained weights (a warm start)
            instead of fresh ones; the summaries then keep every feature, those constant over
            the task's simulations set to 0 (in the observation too) rather than dropped, so
            every task's flow has the same input size. Faster, but not the default: its
            posteriors were measurably shifted (docs/guide/performance.md).
        warm_stop_after_epochs: ``stop_after_epochs`` of a warm-started flow (it starts near a
            posterior already, so it needs less patience); the first task keeps
            ``stop_after_epochs``.
        n_posterior_samples: importance samples returned (per IS round).
        is_rounds: adaptive importance-sampling rounds after the flow-mixture round (0: none).
        defensive_fraction: share of each adaptive round drawn from the flow mixture.
        reuse_mixture_draws: with k > 1 tasks, round 0 draws only that defensive share from the
            flows and every adaptive round reuses those draws and their densities (flow draws
            and evaluations are most of the sampling time); False: round 0 draws
            ``n_posterior_samples`` and each round its own defensive draws.
        point_estimate: "mean" (weighted), "median" (coordinate-wise weighted) or "mode"
            (the draw with the highest combined density). (Old names: ``estimator``, "map".)
        min_ess: the combined importance sample is a fallback (``status = "fallback: ..."``)
            below min(min_ess, N / 2) effective draws, of the weights or of the distinct draws
            (`samplers.WeightedDraws.status`); a count, not a share of the draws (why:
            docs/studies/design_measurements.md).
        chunk_size: prior draws per ``simulate`` call (old name: ``simulation_batch_size``): the chunks that
            ``scheduler`` distributes (the draws themselves are made up front, so the training
            data never depend on where the chunks run).
        sim_dtype: "float32" or "float64" for the simulations.
        workdir: None, or a directory (created) receiving ``npe_posterior_k{k}_seed{seed}.pt``
            (tensors) and its ``.pt.json`` metadata with the sha256 (reload with
            `npe_posterior.load_posterior`), and each task's flow as soon as it is trained
            (`task_checkpoint`): a run killed after task i, re-run with the same settings and
            workdir, reads tasks 0..i back instead of training them again (same numbers;
            their recorded simulations and seconds are still counted).
        device: torch device for training ("cpu").
        n_threads: torch intra-op threads while training and sampling (restored afterwards);
            None keeps the current setting. Small flows train fastest on one thread (OpenMP's
            busy-waiting on a loaded machine: docs/studies/design_measurements.md).
        scheduler: None (in-process), "local:N" or a Dask scheduler address: where the
            training-data simulation chunks run (see `camo_sbi.distributed`).
    """

    space: str = "joint"
    n_points: int = 20
    include_length: bool = True
    embedding: str = "none"
    embedding_dim: int = 32
    density_estimator: str = "maf"
    hidden_features: int = 50
    num_transforms: int = 5
    theta_transform: str = "logit"
    training_batch_size: int = 100
    learning_rate: float = 1e-3
    validation_fraction: float = 0.1
    stop_after_epochs: int = 20
    max_epochs: int = 200
    warm_start: bool = False
    warm_stop_after_epochs: int = 10
    n_posterior_samples: int = 10000
    is_rounds: int = 3
    defensive_fraction: float = 0.2
    reuse_mixture_draws: bool = True
    point_estimate: str = "mean"
    min_ess: float = 20.0
    chunk_size: int = 10000
    sim_dtype: str = "float32"
    workdir: str | os.PathLike | None = None
    device: str = "cpu"
    n_threads: int | None = 1
    scheduler: str | None = None

    def __post_init__(self):
        check_choice(self.space, SPACES, "space")
        check_positive_int(self.n_points, "n_points")
        check_bool(self.include_length, "include_length")
        check_choice(self.embedding, _EMBEDDINGS, "embedding")
        check_positive_int(self.embedding_dim, "embedding_dim")
        check_choice(self.density_estimator, _MODELS, "density_estimator")
        check_positive_int(self.hidden_features, "hidden_features")
        check_positive_int(self.num_transforms, "num_transforms")
        check_choice(self.theta_transform, TRANSFORMS, "theta_transform")
        check_training_settings(self)
        check_bool(self.warm_start, "warm_start")
        check_positive_int(self.warm_stop_after_epochs, "warm_stop_after_epochs")
        check_positive_int(self.n_posterior_samples, "n_posterior_samples", minimum=2)
        check_sampling_settings(self)
        check_bool(self.reuse_mixture_draws, "reuse_mixture_draws")
        check_workdir(self.workdir)


def check_sampling_settings(config) -> None:
    """Check a config's ``is_rounds``, ``defensive_fraction`` (< 1), ``point_estimate``, ``min_ess``,
    ``chunk_size``, ``sim_dtype``, ``n_threads``, ``device`` and ``scheduler`` (errors name the field)."""
    check_positive_int(config.is_rounds, "is_rounds", minimum=0)
    check_positive_float(config.defensive_fraction, "defensive_fraction")
    if config.defensive_fraction >= 1:
        raise ValueError(f"defensive_fraction: must be in (0, 1), got {config.defensive_fraction}")
    check_point_estimate(config.point_estimate, _POINT_ESTIMATES)
    check_positive_float(config.min_ess, "min_ess", allow_zero=True)
    check_positive_int(config.chunk_size, "chunk_size")
    check_choice(config.sim_dtype, _DTYPES, "sim_dtype")
    if config.n_threads is not None:
        check_positive_int(config.n_threads, "n_threads")
    if not isinstance(config.device, str):
        raise TypeError(f"device: expected a str, got {type(config.device).__name__}")
    try:
        torch.device(config.device)
    except RuntimeError as exc:
        raise ValueError(f"device: {exc}") from exc
    parse_scheduler(config.scheduler)


def check_training_settings(config) -> None:
    """Check a config's ``training_batch_size``, ``learning_rate``, ``validation_fraction``
    (< 0.5), ``stop_after_epochs`` and ``max_epochs`` (errors name the field)."""
    check_positive_int(config.training_batch_size, "training_batch_size", minimum=2)
    check_positive_float(config.learning_rate, "learning_rate")
    check_positive_float(config.validation_fraction, "validation_fraction")
    if config.validation_fraction >= 0.5:
        raise ValueError(f"validation_fraction: must be < 0.5, got {config.validation_fraction}")
    check_positive_int(config.stop_after_epochs, "stop_after_epochs")
    check_positive_int(config.max_epochs, "max_epochs")


# ----------------------------------------------------------------------------------------------
# training
# ----------------------------------------------------------------------------------------------


def _seed_int(*key: int) -> int:
    """A 63-bit integer seed from a SeedSequence keyed by ``key``."""
    ss = np.random.SeedSequence(key[0], spawn_key=tuple(key[1:]))
    return int(ss.generate_state(1, dtype=np.uint64)[0] & np.uint64(2**63 - 1))


def _train_flow(theta_z: torch.Tensor, x: torch.Tensor, config: NpeConfig, seed: int, init_from=None):
    """Train q(z | x) with sbi (through `sbi_adapter.train_npe`), from ``init_from``'s weights
    if given (a warm start, with ``warm_stop_after_epochs``); returns (estimator, info)."""
    warm = init_from is not None
    return sbi_adapter.train_npe(
        theta_z, x, seed=seed, density_estimator=config.density_estimator,
        hidden_features=config.hidden_features, num_transforms=config.num_transforms,
        embedding_dim=config.embedding_dim if config.embedding == "mlp" else None,
        training_batch_size=config.training_batch_size, learning_rate=config.learning_rate,
        validation_fraction=config.validation_fraction,
        stop_after_epochs=config.warm_stop_after_epochs if warm else config.stop_after_epochs,
        max_epochs=config.max_epochs, device=config.device, init_from=init_from,
    )


def flow_architecture(config) -> dict:
    """What `build_flow` needs to rebuild a config's per-task flow (NPE, TSNPE: sbi's ``posterior_nn``)."""
    return {"density_estimator": config.density_estimator, "hidden_features": config.hidden_features,
            "num_transforms": config.num_transforms,
            "embedding_dim": config.embedding_dim if getattr(config, "embedding", "none") == "mlp" else None}


def build_flow(n_free: int, n_x: int, architecture: dict):
    """An untrained per-task flow of ``architecture`` (`flow_architecture`), for a checkpoint's state dict."""
    emb = architecture["embedding_dim"]
    return sbi_adapter.new_npe_estimator(
        n_free, n_x, density_estimator=architecture["density_estimator"],
        hidden_features=int(architecture["hidden_features"]), num_transforms=int(architecture["num_transforms"]),
        embedding_dim=None if emb is None else int(emb))


def _check_run_args(task, observations, budget, seed, config):
    config, budget, seed, observations, prior = check_run_args(task, observations, budget, seed, config,
                                                               NpeConfig)
    if prior.n_free == 0:
        raise ValueError("task.prior: every coordinate is fixed; there is nothing to infer")
    n_val = int(budget * config.validation_fraction)
    if n_val < 2 or budget - n_val < 2:
        raise ValueError(
            f"budget: {budget} simulations per task leave too few for training and validation "
            f"(validation_fraction={config.validation_fraction})"
        )
    return observations, budget, seed, config


def _simulate_summaries(job, *, simulator, start, goal, dtype, config: NpeConfig,
                        noise: NoiseModel) -> torch.Tensor:
    """Summaries of one chunk of draws simulated to one task (in-process or on a Dask worker).

    ``job`` = (theta chunk, key of its noise stream): with observation noise the training
    trajectories are perturbed by the task's noise model (noise-augmented training data).
    """
    theta, key = job
    out = simulator.simulate(contain(theta, start).to(dtype), goal=goal.to(dtype), start=start.to(dtype))
    x = out.q if config.space == "joint" else out.ee
    if noise.sigma(config.space) > 0:
        x = noise.perturb(x, config.space, np.random.default_rng(key))
    return trajectory_summary(x, out.length, n_points=config.n_points, include_length=config.include_length)


def _train_tasks(task, observations, budget: int, seed: int, config: NpeConfig):
    """Yield (estimator, observed summary, info) per task, in order (arguments checked).

    Task i's draws and training are seeded by (seed, i); with ``warm_start`` its training
    starts from task i - 1's estimator, so it depends on the tasks before it only (continual
    `run_sequence` == `run` on the first k tasks).
    """
    prior, sim, dtype = task.prior, task.simulator, _DTYPES[config.sim_dtype]
    lo_free = prior.low[prior.free_mask]
    width_free = (prior.high - prior.low)[prior.free_mask]
    previous, previous_key = None, None
    for i, obs in enumerate(observations):
        key = None
        if config.workdir is not None:
            key = task_checkpoint.task_key("npe", task, obs, index=i, budget=budget, seed=seed, config=config,
                                           previous=previous_key if config.warm_start else None)
            stored = task_checkpoint.load_task(config.workdir, "npe", i, key, build_flow)
            if stored is not None:  # trained by an earlier (killed) run with these very settings
                est, xo, info = stored
                charge(sim, budget)  # those simulations were run, in that earlier process
                previous, previous_key = (est if config.warm_start else None), key
                yield est, xo.float(), {**info, "resumed": True}
                continue
        start = torch.as_tensor(obs.start, dtype=torch.float64).cpu()
        goal = torch.as_tensor(obs.goal, dtype=torch.float64).cpu()
        traj_obs = torch.as_tensor(obs.trajectory(config.space), dtype=torch.float64).cpu()
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0, i)))
        theta = prior.sample(budget, rng)
        t0 = time.perf_counter()
        chunks = [(theta[s : s + config.chunk_size], (seed, 3, i, c))
                  for c, s in enumerate(range(0, budget, config.chunk_size))]
        feats = run_chunks(_simulate_summaries, chunks, simulator=sim, n_simulations=budget,
                           scheduler=config.scheduler, start=start, goal=goal, dtype=dtype, config=config,
                           noise=task.noise)
        t_sim = time.perf_counter() - t0
        x = torch.cat(feats)
        xo = trajectory_summary(traj_obs, torch.tensor([traj_obs.shape[0]]), n_points=config.n_points,
                       include_length=config.include_length)[0]
        finite = torch.isfinite(x).all(dim=1)
        keep = x[finite].std(dim=0) > 1e-8 * (1.0 + x[finite].abs().amax(dim=0))
        if not bool(keep.any()):
            raise RuntimeError(f"observations: task {i}'s simulations are all identical; nothing to learn")
        z = to_unconstrained(theta[:, prior.free_mask], lo_free, width_free, config.theta_transform)
        if config.warm_start:  # the same input size for every task: constant features set to 0
            x, xo = x.masked_fill(~keep, 0.0), xo.masked_fill(~keep, 0.0)
        else:
            x, xo = x[:, keep], xo[keep]
        with torch_threads(config.n_threads):
            est, info = _train_flow(z, x, config, _seed_int(seed, 1, i), init_from=previous)
        if config.warm_start:
            previous = est
        info.update(task=i, n_features=int(keep.sum()), n_invalid=int((~finite).sum()),
                    time_simulate=t_sim, warm_start=bool(config.warm_start and i > 0))
        if key is not None:
            task_checkpoint.save_task(config.workdir, "npe", i, key, est, xo.float(), info,
                                      n_free=int(prior.n_free), architecture=flow_architecture(config))
        previous_key = key
        yield est, xo.float(), {**info, "resumed": False}


def _posterior(prior: BoxPrior, estimators, x_obs, infos, config: NpeConfig, budget: int,
               seed: int) -> NpePosterior:
    meta = {"config": {k: (str(v) if isinstance(v, os.PathLike) else v) for k, v in asdict(config).items()},
            "budget": budget, "seed": seed, "tasks": list(infos)}
    return NpePosterior(list(estimators), list(x_obs), prior.low, prior.high,
                        theta_transform=config.theta_transform, n_threads=config.n_threads, info=meta)


def fit(task, observations, *, budget: int, seed: int, config: NpeConfig | None = None):
    """Simulate ``budget`` prior draws per observed task, train one flow per task.

    Returns (`NpePosterior`, info dict: ``time_simulate`` and per-task training summaries).
    """
    observations, budget, seed, config = _check_run_args(task, observations, budget, seed, config)
    ests, xs, infos = [], [], []
    for est, xo, info in _train_tasks(task, observations, budget, seed, config):
        ests.append(est)
        xs.append(xo)
        infos.append(info)
    posterior = _posterior(task.prior, ests, xs, infos, config, budget, seed)
    return posterior, {"time_simulate": sum(i["time_simulate"] for i in infos), "tasks": infos}


def point_estimate(draws: samplers.WeightedDraws, kind: str, prior: BoxPrior) -> np.ndarray:
    """(2n,) point estimate of weighted draws in theta coordinates: "mean", "median"
    (coordinate-wise) or "mode" (the draw with the highest density); known coordinates set exactly."""
    check_point_estimate(kind, _POINT_ESTIMATES)
    theta, w = draws.samples.numpy(), draws.weights.numpy()
    if kind == "mean":
        estimate = w @ theta
    elif kind == "median":
        estimate = weighted_median(theta, w)
    else:
        estimate = theta[int(np.argmax(draws.log_density.numpy()))]
    return prior.with_known(torch.from_numpy(estimate)).numpy()  # exact, not a mean of constants


def _result(task, posterior: NpePosterior, config: NpeConfig, budget: int, seed: int,
            t_start: float) -> PosteriorResult:
    """Sample the combined posterior and package it (saved to the workdir if any).

    Status: `samplers.WeightedDraws.status` with ``config.min_ess``.
    """
    t0 = time.perf_counter()
    draws = posterior.sample_is(config.n_posterior_samples, _seed_int(seed, 2) % (2**32),
                             is_rounds=config.is_rounds, defensive_fraction=config.defensive_fraction,
                             reuse_mixture_draws=config.reuse_mixture_draws)
    t_sample = time.perf_counter() - t0
    estimate = point_estimate(draws, config.point_estimate, task.prior)
    path = None
    if config.workdir is not None:
        path = posterior.save(Path(config.workdir) / f"npe_posterior_k{posterior.n_tasks}_seed{seed}.pt")
    tasks = posterior.info["tasks"]
    extras = {
        "ess": draws.ess,
        "ess_rounds": list(draws.diagnostics["ess_rounds"]),
        "tasks": tasks,
        "time_simulate": sum(t["time_simulate"] for t in tasks),
        "time_train": sum(t["time_train"] for t in tasks),
        "time_sample": t_sample,
        "posterior_path": None if path is None else str(path),
        **task_checkpoint.resumed_summary(tasks),
    }
    return PosteriorResult(
        method="npe", samples=draws.samples.numpy(), weights=draws.weights.numpy(), estimate=estimate,
        n_simulations=int(getattr(task.simulator, "n_simulations", budget * posterior.n_tasks)),
        wall_time=time.perf_counter() - t_start + extras["resumed_seconds"], n_tasks=posterior.n_tasks,
        extras=extras,
        status=draws.status(config.min_ess), density=posterior.log_prob,
    )


def run(task, observations, *, budget: int, seed: int, config: NpeConfig | None = None) -> PosteriorResult:
    """NPE conditioned on every task in ``observations``, ``budget`` simulations per task.

    Returns importance-weighted samples of the combined posterior; ``extras``: ``ess``,
    ``ess_rounds``, per-task training summaries (epochs, validation loss, seconds),
    ``time_simulate``, ``time_train``, ``time_sample``, ``posterior_path`` (with a workdir).
    """
    observations, budget, seed, config = _check_run_args(task, observations, budget, seed, config)
    t_start = time.perf_counter()
    posterior, _ = fit(task, observations, budget=budget, seed=seed, config=config)
    return _result(task, posterior, config, budget, seed, t_start)


def run_sequence(task, observations, *, budget: int, seed: int, config: NpeConfig | None = None):
    """Continual NPE: yield the result conditioned on the first 1, 2, ..., K tasks.

    Each task is simulated and trained once; the k-th result equals ``run`` on the first k
    tasks (same seeds), at the cost of K trainings instead of K (K + 1) / 2.
    """
    observations, budget, seed, config = _check_run_args(task, observations, budget, seed, config)
    t_start = time.perf_counter()
    ests, xs, infos = [], [], []
    for est, xo, info in _train_tasks(task, observations, budget, seed, config):
        ests.append(est)
        xs.append(xo)
        infos.append(info)
        posterior = _posterior(task.prior, ests, xs, infos, config, budget, seed)
        yield _result(task, posterior, config, budget, seed, t_start)
