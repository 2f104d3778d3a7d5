"""Neural posterior estimation (sbi) per observed task, combined into the joint posterior.

sbi is used only through `camo_sbi.inference.sbi_adapter` (the one module importing sbi).

Why one module of ~870 lines: training data, summaries, the combination rule and its two
samplers (importance sampling, population MCMC) are one method whose pieces share one
coordinate system (logit z of the prior box) and one feature mask; `amortized` reuses the
summary and the samplers from here, so splitting them would make modules that must change
together.

Design (same simulation design as CAMO, so budgets are equal):

1. Per observed task i, draw ``budget`` limit vectors from the prior and simulate them to THAT
   task's goal from its start in large batched ``simulate`` calls (never sbi's
   ``simulate_for_sbi`` with batch size 1). As in CAMO, each vector is widened to contain the
   task's observed start before simulating (part of the model, a no-op when the start is the
   prior's split point).
2. Summary x: the valid part of the trajectory (``config.space``) linearly resampled at
   ``n_points`` equally spaced times after the start (the start itself is observed, hence
   uninformative), flattened, plus the trajectory length. A fixed-size vector whatever the
   length; features that are constant over the task's simulations are dropped (their z-score
   would divide by ~0). Optionally an MLP embedding net is trained jointly (``embedding="mlp"``).
3. Train a conditional flow q_i(z | x) (sbi NPE, single round = maximum likelihood, MAF or
   NSF) on the FREE coordinates only, in unconstrained coordinates z = logit of the position
   inside the prior box (``theta_transform="logit"``): the flow has no mass outside the box
   (no leakage correction needed). Training is seeded inside ``torch.random.fork_rng``, so
   the same seed gives the same estimator and the caller's global torch RNG is untouched.
4. Combine: with a common prior p, p(theta | x_1..k) ∝ p(theta)^(1-k) ∏_i q_i(theta | x_i)
   (exact if each q_i is the exact posterior). In z coordinates p is the product of standard
   logistic densities; with ``theta_transform="none"``, p is uniform and the product is
   restricted to the box.
5. Sample the combination by importance sampling (no MCMC tuning, deterministic, with an
   effective sample size to report): round 0 proposes from the equal mixture of the k flows
   (stratified, n/k draws from each); round 1 from a Gaussian approximation of the product
   (each flow's draws moment-matched, precisions added, covariance inflated x2); later rounds
   (``is_rounds`` in all) from a Gaussian fitted to the best round's weighted draws (x1.5).
   Rounds >= 1 keep a defensive share (``defensive_fraction``) of flow-mixture draws so the
   weights stay bounded where the flows have mass. The round with the largest ESS is returned
   as weighted samples; every round's ESS is reported. The product of k sharp per-task
   posteriors is much narrower than any of them, so round 0 alone is poor for k > 1 (toy,
   3 tasks: ESS 1 of 4000; after the product round 2500); on the 14-D Panda with 5 tasks the
   ESS is ~1-2 % of the draws, hence 10000 draws by default.

Continual use: task i's simulations and training are seeded by (seed, i) only, so
`run_sequence` trains each task once and its k-th result equals `run` on the first k tasks.

`NpePosterior` holds the trained flows and observed summaries: ``log_prob``, ``sample``
(importance sampling, the per-task default), ``sample_mcmc`` (population MCMC) and
``sample_smc`` (tempered SMC; both used by `amortized`), ``save``; `load_posterior` reloads
it without retraining.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from camo_sbi._validation import (
    as_tensor,
    check_bool,
    check_choice,
    check_positive_float,
    check_positive_int,
)
from camo_sbi.distributed import parse_scheduler, run_chunks
from camo_sbi.inference import sbi_adapter
from camo_sbi.inference.contract import check_run_args
from camo_sbi.inference.result import (
    STATUS_OK,
    PosteriorResult,
    check_sample_shape,
    weighted_median,
)
from camo_sbi.priors import BoxPrior
from camo_sbi.task import SPACES, NoiseModel, contain

__all__ = [
    "ImportanceSample",
    "McmcSample",
    "SmcSample",
    "check_training_settings",
    "NpeConfig",
    "NpePosterior",
    "fit",
    "load_posterior",
    "point_estimate",
    "run",
    "run_sequence",
    "from_unconstrained",
    "logistic_log_prob",
    "summarize",
    "to_unconstrained",
    "torch_threads",
]

_MODELS = ("maf", "nsf")
_EMBEDDINGS = ("none", "mlp")
_TRANSFORMS = ("logit", "none")
_ESTIMATORS = ("mean", "median", "map")
_DTYPES = {"float32": torch.float32, "float64": torch.float64}
_FORMAT = "camo_sbi.npe.posterior/2"
# positions inside the box are clamped to [_U_EPS, 1 - _U_EPS] before the logit
_U_EPS = 1e-6
# log-prob evaluations per chunk (samples x tasks)
_CHUNK = 8192
# covariance inflation of the Gaussian importance proposals (product approximation, refits)
_IS_INFLATE_PRODUCT = 2.0
_IS_INFLATE = 1.5


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
        n_posterior_samples: importance samples returned (per IS round).
        is_rounds: adaptive importance-sampling rounds after the flow-mixture round (0: none).
        defensive_fraction: share of each adaptive round drawn from the flow mixture.
        estimator: point estimate: "mean" (weighted), "median" (coordinate-wise weighted) or
            "map" (sample with the highest combined density).
        simulation_batch_size: prior draws per ``simulate`` call: the chunks that
            ``scheduler`` distributes (the draws themselves are made up front, so the training
            data never depend on where the chunks run).
        sim_dtype: "float32" or "float64" for the simulations.
        workdir: None, or a directory (created) receiving ``npe_posterior_k{k}_seed{seed}.pt``
            (tensors) and its ``.pt.json`` metadata with the sha256 (reload with `load_posterior`).
        device: torch device for training ("cpu").
        n_threads: torch intra-op threads while training and sampling (restored afterwards);
            None keeps the current setting. Small flows train fastest on one thread: with
            OpenMP's busy-waiting, 2 threads were ~10x slower per batch on a loaded 2-core box.
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
    n_posterior_samples: int = 10000
    is_rounds: int = 3
    defensive_fraction: float = 0.2
    estimator: str = "mean"
    simulation_batch_size: int = 10000
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
        check_choice(self.theta_transform, _TRANSFORMS, "theta_transform")
        check_training_settings(self)
        check_positive_int(self.n_posterior_samples, "n_posterior_samples", minimum=2)
        check_positive_int(self.is_rounds, "is_rounds", minimum=0)
        check_positive_float(self.defensive_fraction, "defensive_fraction")
        if self.defensive_fraction >= 1:
            raise ValueError(f"defensive_fraction: must be in (0, 1), got {self.defensive_fraction}")
        check_choice(self.estimator, _ESTIMATORS, "estimator")
        check_positive_int(self.simulation_batch_size, "simulation_batch_size")
        check_choice(self.sim_dtype, _DTYPES, "sim_dtype")
        if self.workdir is not None and not isinstance(self.workdir, (str, os.PathLike)):
            raise TypeError(f"workdir: expected a path or None, got {type(self.workdir).__name__}")
        if self.n_threads is not None:
            check_positive_int(self.n_threads, "n_threads")
        if not isinstance(self.device, str):
            raise TypeError(f"device: expected a str, got {type(self.device).__name__}")
        try:
            torch.device(self.device)
        except RuntimeError as exc:
            raise ValueError(f"device: {exc}") from exc
        parse_scheduler(self.scheduler)


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
# summaries
# ----------------------------------------------------------------------------------------------


def summarize(traj, lengths, *, n_points: int = 20, include_length: bool = True) -> torch.Tensor:
    """Fixed-size summaries of padded trajectories.

    traj: (B, T, D) (steps >= length are padding) or (T, D); lengths: (B,) ints in [1, T]
    (or an int for a single trajectory). Returns (B, n_points * D [+ 1]) float64: the valid
    part linearly resampled at times (L - 1) * j / n_points, j = 1..n_points (the start,
    j = 0, is left out), flattened time-major, then the length L if ``include_length``.
    """
    x = as_tensor(traj, "traj", dtype=torch.float64)
    if x.dim() == 2:
        x = x.unsqueeze(0)
    if x.dim() != 3 or x.shape[1] < 1:
        raise ValueError(f"traj: expected shape (B, T, D), got {tuple(x.shape)}")
    B, T, D = x.shape
    L = torch.as_tensor(lengths).reshape(-1).to(device=x.device)
    if L.is_floating_point() or L.shape[0] != B:
        raise ValueError(f"lengths: expected {B} integer lengths, got {tuple(L.shape)} {L.dtype}")
    if bool(((L < 1) | (L > T)).any()):
        raise ValueError(f"lengths: must lie in [1, {T}]")
    n_points = check_positive_int(n_points, "n_points")
    last = (L - 1).to(torch.float64)
    pos = last[:, None] * (torch.arange(1, n_points + 1, dtype=torch.float64, device=x.device) / n_points)
    i0 = pos.floor().long().clamp(max=T - 1)
    i1 = torch.minimum(i0 + 1, (L - 1)[:, None].long())
    frac = (pos - i0.to(torch.float64)).unsqueeze(-1)
    x0 = torch.gather(x, 1, i0.unsqueeze(-1).expand(-1, -1, D))
    x1 = torch.gather(x, 1, i1.unsqueeze(-1).expand(-1, -1, D))
    feats = (x0 + frac * (x1 - x0)).reshape(B, n_points * D)
    if include_length:
        feats = torch.cat([feats, L.to(torch.float64)[:, None]], dim=1)
    return feats


def to_unconstrained(theta_free: torch.Tensor, lo: torch.Tensor, width: torch.Tensor,
                      transform: str) -> torch.Tensor:
    """Free coordinates (N, d) -> flow coordinates: logit of the position in the box, or as is."""
    theta_free = theta_free.to(torch.float64)
    if transform == "none":
        return theta_free
    return torch.logit(((theta_free - lo) / width).clamp(_U_EPS, 1 - _U_EPS))


def from_unconstrained(z: torch.Tensor, lo: torch.Tensor, width: torch.Tensor,
                       transform: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse of `to_unconstrained`: z (N, d) -> (free coordinates (N, d), log |d theta / d z| (N,))."""
    z = z.to(torch.float64)
    if transform == "none":
        return z, torch.zeros(z.shape[0], dtype=torch.float64)
    theta = lo + width * torch.sigmoid(z)
    logdet = (torch.log(width) + nn.functional.logsigmoid(z) + nn.functional.logsigmoid(-z)).sum(-1)
    return theta, logdet


def logistic_log_prob(z: torch.Tensor) -> torch.Tensor:
    """(N,) log density in logit coordinates z of the uniform box prior: z = logit(u), u ~ U(0, 1),
    a standard logistic per coordinate."""
    return (nn.functional.logsigmoid(z) + nn.functional.logsigmoid(-z)).sum(-1)


@contextlib.contextmanager
def torch_threads(n: int | None):
    """torch's intra-op thread count set to ``n`` for the block (None: unchanged)."""
    old = torch.get_num_threads()
    if n is not None and n != old:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if torch.get_num_threads() != old:
            torch.set_num_threads(old)


# ----------------------------------------------------------------------------------------------
# the combined posterior
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ImportanceSample:
    """Weighted draws from `NpePosterior.sample`.

    theta: (N, 2n) float64; weights: (N,) normalised; log_prob: (N,) combined log density
    (theta coordinates, unnormalised); ess: effective sample size of the returned round;
    ess_rounds: ESS of every round (round 0 = flow mixture).
    """

    theta: np.ndarray
    weights: np.ndarray
    log_prob: np.ndarray
    ess: float
    ess_rounds: list[float]


@dataclass(frozen=True)
class McmcSample:
    """Equally weighted draws from `NpePosterior.sample_mcmc`.

    theta: (N, 2n) float64; weights: (N,) uniform (1 / N, for code reading weighted draws);
    log_prob: (N,) combined log density (theta coordinates, unnormalised); acceptance: the
    acceptance rate after burn-in; stuck_fraction: share of chains that never moved after
    burn-in; chains, steps, burn_in: the run's size; step_scale: the adapted random-walk scale.
    """

    theta: np.ndarray
    weights: np.ndarray
    log_prob: np.ndarray
    acceptance: float
    stuck_fraction: float
    chains: int
    steps: int
    burn_in: int
    step_scale: float


@dataclass(frozen=True)
class SmcSample:
    """Weighted draws from `NpePosterior.sample_smc`.

    theta: (N, 2n) float64; weights: (N,) normalised; log_prob: (N,) combined log density
    (theta coordinates, unnormalised); ess: effective sample size of the weights; betas: the
    tempering schedule (0 ... 1); reached: whether b = 1 was reached within the stage limit
    with the target ESS; acceptance: mean Metropolis acceptance over the moves; particles;
    flow_calls: batched flow evaluations (each particles x k rows).
    """

    theta: np.ndarray
    weights: np.ndarray
    log_prob: np.ndarray
    ess: float
    betas: list[float]
    reached: bool
    acceptance: float
    particles: int
    flow_calls: int


class NpePosterior:
    """p(theta | x_1..k) ∝ p(theta)^(1-k) ∏_i q_i(theta | x_i) from per-task flows.

    Args:
        estimators: k trained sbi density estimators q_i(z | x) over the free coordinates.
        x_obs: k observed summaries (1-D tensors; each estimator's own feature set).
        low, high: (2n,) prior box; coordinates with low == high are fixed.
        theta_transform: "logit" or "none" (coordinates the estimators model).
        info: free-form metadata (config, training summaries) saved along.
        n_threads: torch intra-op threads used by ``log_prob`` and ``sample`` (restored
            afterwards), so results do not depend on the caller's thread setting; None: as is.
    """

    def __init__(self, estimators, x_obs, low, high, *, theta_transform: str = "logit", info=None,
                 n_threads: int | None = 1):
        if len(estimators) != len(x_obs) or not estimators:
            raise ValueError("estimators: need one estimator per observed summary (at least one)")
        check_choice(theta_transform, _TRANSFORMS, "theta_transform")
        self.estimators = [e.eval() for e in estimators]
        self.x_obs = [torch.as_tensor(x, dtype=torch.float32).reshape(1, -1) for x in x_obs]
        self.low = torch.as_tensor(low, dtype=torch.float64).cpu()
        self.high = torch.as_tensor(high, dtype=torch.float64).cpu()
        self.free_mask = self.high > self.low
        self.theta_transform = theta_transform
        self.info = dict(info or {})
        self.n_threads = None if n_threads is None else check_positive_int(n_threads, "n_threads")
        self._lo = self.low[self.free_mask]
        self._w = (self.high - self.low)[self.free_mask]

    @property
    def n_tasks(self) -> int:
        return len(self.estimators)

    @property
    def dim(self) -> int:
        return int(self.low.shape[0])

    @property
    def n_free(self) -> int:
        return int(self.free_mask.sum())

    # coordinates -------------------------------------------------------------------------

    def to_unconstrained(self, theta_free: torch.Tensor) -> torch.Tensor:
        """(N, n_free) free coordinates -> (N, n_free) flow coordinates z."""
        return to_unconstrained(theta_free, self._lo, self._w, self.theta_transform)

    def from_unconstrained(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """z (N, n_free) -> (free coordinates (N, n_free), log |d theta / d z| (N,))."""
        return from_unconstrained(z, self._lo, self._w, self.theta_transform)

    def _theta(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """z (N, n_free) -> (full theta (N, 2n) with the fixed coordinates set, log |d theta / d z| (N,))."""
        theta_free, logdet = self.from_unconstrained(z)
        theta = self.low.repeat(theta_free.shape[0], 1)
        theta[:, self.free_mask] = theta_free
        return theta, logdet

    def _prior_log_prob_z(self, z: torch.Tensor) -> torch.Tensor:
        if self.theta_transform == "none":
            inside = ((z >= self._lo) & (z <= self._lo + self._w)).all(-1)
            lp = torch.full((z.shape[0],), -float(torch.log(self._w).sum()), dtype=torch.float64)
            return torch.where(inside, lp, torch.full_like(lp, -math.inf))
        return logistic_log_prob(z)

    # densities ---------------------------------------------------------------------------

    @torch.no_grad()
    def task_log_probs(self, z: torch.Tensor) -> torch.Tensor:
        """(k, N) log q_i(z | x_i) in flow coordinates (NaN mapped to -inf).

        When every task shares one flow (the amortized estimator), one call per chunk
        evaluates all k conditions at once (input (n, k, d), condition (k, F)).
        """
        z = torch.as_tensor(z, dtype=torch.float32)
        out = torch.empty(self.n_tasks, z.shape[0], dtype=torch.float64)
        k = self.n_tasks
        with torch_threads(self.n_threads):
            if k > 1 and all(e is self.estimators[0] for e in self.estimators) \
                    and len({x.shape for x in self.x_obs}) == 1:
                x = torch.cat(self.x_obs)
                step = max(1, _CHUNK // k)
                for s in range(0, z.shape[0], step):
                    zc = z[s : s + step]
                    lp = self.estimators[0].log_prob(zc.unsqueeze(1).expand(-1, k, -1), condition=x)
                    out[:, s : s + zc.shape[0]] = lp.reshape(zc.shape[0], k).T.double()
                return torch.nan_to_num(out, nan=-math.inf)
            for i, (est, x) in enumerate(zip(self.estimators, self.x_obs, strict=True)):
                for s in range(0, z.shape[0], _CHUNK):
                    zc = z[s : s + _CHUNK]
                    lp = est.log_prob(zc.unsqueeze(1), condition=x).reshape(-1).double()
                    out[i, s : s + zc.shape[0]] = lp
        return torch.nan_to_num(out, nan=-math.inf)

    def _log_target_z(self, z: torch.Tensor, lq: torch.Tensor) -> torch.Tensor:
        lp = self._prior_log_prob_z(z)
        out = lq.sum(0) + (1 - self.n_tasks) * torch.where(torch.isfinite(lp), lp, torch.zeros_like(lp))
        # outside the prior's support the target is zero, whatever the power of the prior
        return torch.where(torch.isfinite(lp), out, torch.full_like(out, -math.inf))

    @torch.no_grad()
    def log_prob(self, theta) -> torch.Tensor:
        """(B,) unnormalised log p(theta | x_1..k) for theta (B, 2n) or (2n,), -inf outside the box.

        Density with respect to the free coordinates; exact normalisation only for k = 1.
        """
        t = as_tensor(theta, "theta", dtype=torch.float64).cpu()
        t = t.unsqueeze(0) if t.dim() == 1 else t
        if t.dim() != 2 or t.shape[1] != self.dim:
            raise ValueError(f"theta: expected shape (B, {self.dim}), got {tuple(t.shape)}")
        inside = ((t >= self.low - 1e-9) & (t <= self.high + 1e-9)).all(-1)
        z = self.to_unconstrained(t[:, self.free_mask])
        _, logdet = self.from_unconstrained(z)
        lp = self._log_target_z(z, self.task_log_probs(z)) - logdet
        return torch.where(inside, lp, torch.full_like(lp, -math.inf))

    # sampling ----------------------------------------------------------------------------

    @torch.no_grad()
    def _sample_flows(self, counts: list[int]) -> torch.Tensor:
        parts = [est.sample((c,), condition=x).reshape(c, -1).double()
                 for est, x, c in zip(self.estimators, self.x_obs, counts, strict=True) if c > 0]
        return torch.cat(parts)

    @staticmethod
    def _mixture_counts(n: int, k: int) -> list[int]:
        return [n // k + (1 if i < n % k else 0) for i in range(k)]

    def _product_gaussian(self, z: torch.Tensor, counts: list[int]):
        """Gaussian approximation of the target from each flow's own draws (moment matching):
        precision sum_i P_i - (k - 1) P_prior (the prior term dropped if that is not positive
        definite), mean the precision-weighted combination. None if degenerate."""
        k, d = self.n_tasks, self.n_free
        eye = torch.eye(d, dtype=torch.float64)
        prec_sum, shift = torch.zeros(d, d, dtype=torch.float64), torch.zeros(d, dtype=torch.float64)
        s = 0
        for c in counts:
            zi = z[s : s + c]
            s += c
            if c < d + 2:
                return None
            mu_i = zi.mean(0)
            p_i = torch.linalg.inv(torch.cov(zi.T).reshape(d, d) + 1e-9 * eye)
            prec_sum += p_i
            shift += p_i @ mu_i
        if self.theta_transform == "logit":
            # standard logistic prior: variance pi^2 / 3, mean 0
            prec = prec_sum - (k - 1) * (3.0 / math.pi**2) * eye
            if bool((torch.linalg.eigvalsh(prec) <= 0).any()):
                prec = prec_sum
        else:
            prec = prec_sum
        try:
            cov = torch.linalg.inv(prec)
            return cov @ shift, 0.5 * (cov + cov.T)
        except RuntimeError:
            return None

    def _pool_and_product(self, init_draws: int):
        """Stratified flow-mixture draws (at least d + 2 per flow) and the Gaussian product of
        them (`_product_gaussian`; None if k = 1 or degenerate): the start of MCMC and SMC."""
        k, d = self.n_tasks, self.n_free
        counts = self._mixture_counts(max(init_draws, k * (d + 2)), k)
        pool = self._sample_flows(counts)
        return pool, (self._product_gaussian(pool, counts) if k > 1 else None)

    def sample(self, sample_shape=(), seed: int | None = None, *, n_proposals: int | None = None) -> torch.Tensor:
        """Equally weighted draws, shape (*sample_shape, 2n), like sbi's ``posterior.sample``.

        Sampling-importance-resampling: ``sample_is`` draws ``n_proposals`` weighted draws
        (default: max(prod(sample_shape), 1000)) and they are resampled by weight. ``seed``:
        an int; None draws a fresh nondeterministic seed (never the global random state).
        The weighted draws themselves, with their effective sample size, come from ``sample_is``.
        """
        shape = check_sample_shape(sample_shape)
        if seed is None:
            seed = int(np.random.SeedSequence().generate_state(1)[0])
        seed = check_positive_int(seed, "seed", minimum=0)
        n = int(np.prod(shape, dtype=np.int64))
        m = max(n, 1000) if n_proposals is None else check_positive_int(n_proposals, "n_proposals", minimum=2)
        draws = self.sample_is(m, seed)
        idx = np.random.default_rng(seed).choice(len(draws.weights), size=n, replace=True, p=draws.weights)
        return torch.from_numpy(np.ascontiguousarray(draws.theta[idx])).reshape(*shape, self.dim)

    @torch.no_grad()
    def sample_is(self, n: int, seed: int, *, is_rounds: int = 2, defensive_fraction: float = 0.2) -> ImportanceSample:
        """``n`` weighted draws per round by importance sampling (see the module docstring).

        Round 0 proposes from the equal mixture of the k flows. Round 1 (k > 1) proposes from
        a Gaussian approximation of the product (each flow's draws moment-matched, precisions
        added), later rounds from a Gaussian fitted to the best round's weighted draws; both
        with inflated covariance and a defensive share of flow-mixture draws. Returns the
        round with the largest ESS. Deterministic given ``seed``; the global torch RNG is
        restored afterwards.
        """
        n = check_positive_int(n, "n", minimum=2)
        seed = check_positive_int(seed, "seed", minimum=0)
        is_rounds = check_positive_int(is_rounds, "is_rounds", minimum=0)
        k, d = self.n_tasks, self.n_free
        gen = torch.Generator().manual_seed(seed)
        best, ess_rounds, product = None, [], None
        eye = torch.eye(d, dtype=torch.float64)
        with torch.random.fork_rng(devices=[]), torch_threads(self.n_threads):
            torch.manual_seed(seed)
            for r in range(is_rounds + 1):
                if r == 0:
                    counts = self._mixture_counts(n, k)
                    z = self._sample_flows(counts)
                    lq = self.task_log_probs(z)
                    log_mix = torch.tensor([math.log(c / n) if c else -math.inf for c in counts],
                                           dtype=torch.float64)
                    log_r = torch.logsumexp(lq + log_mix[:, None], dim=0)
                    if k > 1:
                        product = self._product_gaussian(z, counts)
                else:
                    if r == 1 and product is not None:
                        mu, cov = product
                        cov = _IS_INFLATE_PRODUCT * cov
                    elif best is not None:
                        w = torch.from_numpy(best["weights"])
                        mu = w @ best["z"]
                        zc = best["z"] - mu
                        cov = _IS_INFLATE * ((zc * w[:, None]).T @ zc)
                    else:
                        break
                    cov = 0.5 * (cov + cov.T) + 1e-9 * eye
                    gauss = torch.distributions.MultivariateNormal(mu, covariance_matrix=cov)
                    n_def = max(int(round(defensive_fraction * n)), k)
                    n_gauss = n - n_def
                    counts = self._mixture_counts(n_def, k)
                    eps = torch.randn(n_gauss, d, generator=gen, dtype=torch.float64)
                    z = torch.cat([mu + eps @ gauss.scale_tril.T, self._sample_flows(counts)])
                    lq = self.task_log_probs(z)
                    log_mix = torch.tensor([math.log(c / n) if c else -math.inf for c in counts],
                                           dtype=torch.float64)
                    log_def = torch.logsumexp(lq + log_mix[:, None], dim=0)
                    log_r = torch.logaddexp(log_def, math.log(n_gauss / n) + gauss.log_prob(z))
                log_t = self._log_target_z(z, lq)
                log_w = torch.nan_to_num(log_t - log_r, nan=-math.inf)
                if not bool(torch.isfinite(log_w).any()):
                    ess_rounds.append(0.0)
                    continue
                w = torch.softmax(log_w, dim=0)
                ess = float(1.0 / (w**2).sum())
                ess_rounds.append(ess)
                if best is None or ess > best["ess"]:
                    best = {"z": z, "weights": w.numpy(), "log_t": log_t, "ess": ess}
        if best is None:
            raise RuntimeError("sample: every importance weight is zero (the flows put no mass in the box)")
        theta, logdet = self._theta(best["z"])
        return ImportanceSample(theta.numpy(), best["weights"], (best["log_t"] - logdet).numpy(),
                                best["ess"], ess_rounds)

    @torch.no_grad()
    def sample_mcmc(self, n: int, seed: int, *, chains: int = 128, steps: int = 100, burn_in: int = 50,
                    init_draws: int = 512, de_fraction: float = 0.2,
                    target_acceptance: float = 0.25) -> McmcSample:
        """``n`` equally weighted draws of the combined posterior by population MCMC in z.

        Target: the log density of `log_prob` in flow coordinates z (`_log_target_z`). ``chains``
        chains start from a Gaussian approximation of the product (`_product_gaussian` of
        ``init_draws`` flow-mixture draws; from those draws themselves if it is degenerate) and
        take ``steps`` sweeps. A sweep updates the two halves of the population in turn, each
        half with ONE batched flow evaluation (chains / 2 x k conditions). A chain proposes a
        random-walk Metropolis move z + s L eps (L L^T: the covariance of the OTHER half, which
        stays fixed during the update, so each update leaves the product of the targets
        invariant, as in emcee's split ensemble), or with probability ``de_fraction`` a
        differential-evolution move z + g (z_a - z_b) + s L eps / 100 (a, b two distinct chains
        of the other half, g = 2.38 / sqrt(2 d), g = 1 every tenth move). During the first
        ``burn_in`` sweeps (discarded) the scale s is adapted toward ``target_acceptance``, then
        frozen. The draws are the states of every chain at ``ceil(n / chains)`` sweeps spread
        over the post-burn-in ones (at most ``n``). Deterministic given ``seed``; the global
        torch RNG is restored afterwards.
        """
        n = check_positive_int(n, "n", minimum=2)
        seed = check_positive_int(seed, "seed", minimum=0)
        chains = check_positive_int(chains, "chains", minimum=8)
        steps = check_positive_int(steps, "steps")
        burn_in = check_positive_int(burn_in, "burn_in", minimum=0)
        if burn_in >= steps:
            raise ValueError(f"burn_in: must be < steps ({steps}), got {burn_in}")
        d = self.n_free
        gen = torch.Generator().manual_seed(seed)
        with torch.random.fork_rng(devices=[]), torch_threads(self.n_threads):
            torch.manual_seed(seed)
            pool, product = self._pool_and_product(init_draws)
            if product is not None:
                mu, cov = product
                z = mu + torch.randn(chains, d, generator=gen, dtype=torch.float64) @ _cholesky(cov).T
            else:
                z = pool[torch.randint(pool.shape[0], (chains,), generator=gen)]
            lt = self._log_target_z(z, self.task_log_probs(z))
            halves = (torch.arange(0, chains, 2), torch.arange(1, chains, 2))
            log_s = math.log(2.38 / math.sqrt(d))
            g_de = 2.38 / math.sqrt(2 * d)
            n_keep = min(math.ceil(n / chains), steps - burn_in)
            keep_at = set(torch.linspace(burn_in, steps - 1, n_keep).round().long().tolist())
            kept, kept_lt = [], []
            accepted = proposed = 0
            moved = torch.zeros(chains, dtype=torch.bool)
            for t in range(steps):
                for h in (0, 1):
                    idx, other = halves[h], halves[1 - h]
                    zo, m, mo = z[other], idx.shape[0], other.shape[0]
                    step = math.exp(log_s) * torch.randn(m, d, generator=gen, dtype=torch.float64) \
                        @ _cholesky(torch.cov(zo.T).reshape(d, d)).T
                    a = torch.randint(mo, (m,), generator=gen)
                    b = (a + 1 + torch.randint(mo - 1, (m,), generator=gen)) % mo
                    g = torch.where(torch.rand(m, generator=gen, dtype=torch.float64) < 0.1, 1.0, g_de)
                    de = g[:, None] * (zo[a] - zo[b]) + 0.01 * step
                    use_de = torch.rand(m, generator=gen, dtype=torch.float64) < de_fraction
                    prop = z[idx] + torch.where(use_de[:, None], de, step)
                    lt_prop = self._log_target_z(prop, self.task_log_probs(prop))
                    log_u = torch.log(torch.rand(m, generator=gen, dtype=torch.float64))
                    acc = torch.nan_to_num(lt_prop - lt[idx], nan=-math.inf) > log_u
                    z[idx[acc]] = prop[acc]
                    lt[idx[acc]] = lt_prop[acc]
                    if t < burn_in:
                        log_s += (float(acc.double().mean()) - target_acceptance) / math.sqrt(t + 1)
                    else:
                        accepted += int(acc.sum())
                        proposed += m
                        moved[idx[acc]] = True
                if t in keep_at:
                    kept.append(z.clone())
                    kept_lt.append(lt.clone())
        zs, lts = torch.cat(kept)[:n], torch.cat(kept_lt)[:n]
        theta, logdet = self._theta(zs)
        m = theta.shape[0]
        return McmcSample(theta.numpy(), np.full(m, 1.0 / m), (lts - logdet).numpy(),
                          acceptance=accepted / max(proposed, 1), stuck_fraction=float((~moved).double().mean()),
                          chains=chains, steps=steps, burn_in=burn_in, step_scale=math.exp(log_s))

    @torch.no_grad()
    def sample_smc(self, seed: int, *, particles: int = 512, base: str = "mixture", init_draws: int = 512,
                   inflate: float = 2.0, target_ess: float = 0.5, moves: int = 3, independent_fraction: float = 0.5,
                   max_stages: int = 50, target_acceptance: float = 0.3) -> SmcSample:
        """Weighted draws of the combined posterior by tempered sequential Monte Carlo in z.

        Base r: ``"mixture"`` (default), the equal mixture of the k flows, sampled exactly
        (``particles`` stratified draws) and evaluated from the same k flow densities the
        target needs (no extra flow call); or ``"gaussian"``, the Gaussian approximation of the
        product (`_product_gaussian` of ``init_draws`` flow draws), covariance x ``inflate``.
        Bridge: pi_b(z) ∝ r(z)^(1-b) t(z)^b, b from 0 to 1 (t: the target of `log_prob` in z,
        `_log_target_z`). Each stage picks the next b by bisection so that the incremental
        weights keep an effective sample size of ``target_ess`` x ``particles``; if b = 1 keeps
        it, the run ends with those weighted particles. Otherwise the particles are resampled
        (systematic) and take ``moves`` Metropolis-Hastings steps targeting pi_b; each particle
        proposes, with probability ``independent_fraction``, an independent draw from a
        Gaussian fitted to the weighted particles (covariance x ``inflate``), else a random-walk
        step (covariance s^2 x the weighted particle covariance, s adapted toward
        ``target_acceptance`` between moves). One batched flow call (particles x k
        conditions) per move. If ``max_stages`` stages do not reach b = 1, the last stage jumps
        to b = 1 and ``reached`` is False (the caller reports a fallback). Deterministic given
        ``seed``; the global torch RNG is restored afterwards.
        """
        seed = check_positive_int(seed, "seed", minimum=0)
        particles = check_positive_int(particles, "particles", minimum=16)
        check_choice(base, ("mixture", "gaussian"), "base")
        init_draws = check_positive_int(init_draws, "init_draws", minimum=2)
        inflate = check_positive_float(inflate, "inflate")
        target_ess = check_positive_float(target_ess, "target_ess")
        if target_ess >= 1:
            raise ValueError(f"target_ess: must be in (0, 1), got {target_ess}")
        moves = check_positive_int(moves, "moves")
        independent_fraction = check_positive_float(independent_fraction, "independent_fraction", allow_zero=True)
        if independent_fraction > 1:
            raise ValueError(f"independent_fraction: must be in [0, 1], got {independent_fraction}")
        max_stages = check_positive_int(max_stages, "max_stages")
        k, d = self.n_tasks, self.n_free
        gen = torch.Generator().manual_seed(seed)
        eye = torch.eye(d, dtype=torch.float64)
        log_mix = torch.tensor([-math.log(k)] * k, dtype=torch.float64)[:, None]
        n_evals = 0
        with torch.random.fork_rng(devices=[]), torch_threads(self.n_threads):
            torch.manual_seed(seed)
            if base == "mixture":
                gauss = None
                z = self._sample_flows(self._mixture_counts(particles, k))
            else:
                pool, product = self._pool_and_product(init_draws)
                if product is None:
                    product = pool.mean(0), torch.cov(pool.T).reshape(d, d)
                mu, cov = product
                gauss = torch.distributions.MultivariateNormal(mu, scale_tril=_cholesky(inflate * cov))
                z = mu + torch.randn(particles, d, generator=gen, dtype=torch.float64) @ gauss.scale_tril.T

            def densities(zz):
                lq = self.task_log_probs(zz)
                lr = torch.logsumexp(lq + log_mix, dim=0) if gauss is None else gauss.log_prob(zz)
                return lr, self._log_target_z(zz, lq)

            log_r, lt = densities(z)
            n_evals += 1
            beta, betas, acc_rates, log_s = 0.0, [0.0], [], math.log(2.38 / math.sqrt(d))
            log_w = torch.zeros(particles, dtype=torch.float64)
            for stage in range(max_stages):
                delta = torch.nan_to_num(lt - log_r, nan=-math.inf, posinf=-math.inf)
                delta = torch.where(torch.isfinite(log_r), delta, torch.full_like(delta, -math.inf))

                def ess_at(b, log_w=log_w, beta=beta, delta=delta):
                    w = torch.softmax(log_w + (b - beta) * delta, dim=0)
                    return float(1.0 / (w**2).sum()) if bool(torch.isfinite(w).all()) else 0.0

                reached = ess_at(1.0) >= target_ess * particles
                if reached or stage == max_stages - 1:
                    log_w = log_w + (1.0 - beta) * delta
                    beta = 1.0
                    betas.append(beta)
                    break
                lo_b, hi_b = beta, 1.0
                for _ in range(40):
                    mid = 0.5 * (lo_b + hi_b)
                    lo_b, hi_b = (mid, hi_b) if ess_at(mid) >= target_ess * particles else (lo_b, mid)
                new_beta = max(lo_b, beta + 1e-6)
                log_w = log_w + (new_beta - beta) * delta
                beta = new_beta
                betas.append(beta)
                w = torch.softmax(log_w, dim=0)
                if not bool(torch.isfinite(w).all()):
                    break  # no particle has a finite target density: reported below, never NaN
                mean = w @ z
                zc = z - mean
                pcov = (zc * w[:, None]).T @ zc + 1e-9 * eye
                scale = _cholesky(pcov)
                fit = torch.distributions.MultivariateNormal(mean, scale_tril=_cholesky(inflate * pcov))
                u = (torch.arange(particles, dtype=torch.float64)
                     + torch.rand(1, generator=gen, dtype=torch.float64)) / particles
                idx = torch.searchsorted(torch.cumsum(w, 0), u).clamp_max(particles - 1)
                z, log_r, lt = z[idx], log_r[idx], lt[idx]
                log_w = torch.zeros(particles, dtype=torch.float64)
                for _ in range(moves):
                    indep = torch.rand(particles, generator=gen, dtype=torch.float64) < independent_fraction
                    rw = z + math.exp(log_s) * torch.randn(particles, d, generator=gen, dtype=torch.float64) @ scale.T
                    ind = mean + torch.randn(particles, d, generator=gen, dtype=torch.float64) @ fit.scale_tril.T
                    prop = torch.where(indep[:, None], ind, rw)
                    lr_p, lt_p = densities(prop)
                    n_evals += 1
                    cur = (1 - beta) * log_r + beta * lt
                    new = (1 - beta) * lr_p + beta * lt_p
                    # independence proposals: Hastings correction fit(z) / fit(z')
                    corr = torch.where(indep, fit.log_prob(z) - fit.log_prob(prop), torch.zeros_like(cur))
                    log_u = torch.log(torch.rand(particles, generator=gen, dtype=torch.float64))
                    acc = torch.nan_to_num(new - cur + corr, nan=-math.inf) > log_u
                    z = torch.where(acc[:, None], prop, z)
                    log_r = torch.where(acc, lr_p, log_r)
                    lt = torch.where(acc, lt_p, lt)
                    acc_rates.append(float(acc.double().mean()))
                    if bool((~indep).any()):
                        log_s += float(acc[~indep].double().mean()) - target_acceptance
        w = torch.softmax(log_w, dim=0)
        if bool(torch.isfinite(w).all()):
            ess = float(1.0 / (w**2).sum())
        else:  # every weight zero: no posterior reached; the last particles, equally weighted
            w, ess, reached = torch.full((particles,), 1.0 / particles, dtype=torch.float64), 0.0, False
        theta, logdet = self._theta(z)
        return SmcSample(theta.numpy(), w.numpy(), (lt - logdet).numpy(), ess=ess, betas=betas, reached=reached,
                         acceptance=float(np.mean(acc_rates)) if acc_rates else float("nan"),
                         particles=particles, flow_calls=n_evals)

    # persistence -------------------------------------------------------------------------

    def save(self, path) -> Path:
        """Write the flows' weights (tensors only) to ``path`` and their description to ``path`` + ".json".

        The JSON metadata holds the format, the architecture settings, the sizes, the sampler's
        settings, ``info`` and the sha256 of the weights file; `load_posterior` checks that digest,
        loads the weights with ``torch.load(weights_only=True)`` (no code can run) and rebuilds the
        networks from the metadata. Both files are written atomically, the metadata last.
        """
        import hashlib
        import io
        import json

        from camo_sbi._io import atomic_write_bytes, atomic_write_text

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        buf = io.BytesIO()
        torch.save({"format": _FORMAT,
                    "state_dict": {f"{k}.{name}": t.detach().cpu() for k, e in enumerate(self.estimators)
                                   for name, t in e.state_dict().items()},
                    "x_obs": [x.detach().cpu() for x in self.x_obs],
                    "low": self.low, "high": self.high}, buf)
        data = buf.getvalue()
        config = self.info.get("config", {})
        meta = {"format": _FORMAT, "weights": path.name, "sha256": hashlib.sha256(data).hexdigest(),
                "bytes": len(data), "n_tasks": self.n_tasks, "n_free": self.n_free,
                "n_x": [int(x.shape[1]) for x in self.x_obs],
                "architecture": {k: config.get(k, getattr(NpeConfig, k)) for k in _ARCH_KEYS},
                "theta_transform": self.theta_transform, "n_threads": self.n_threads, "info": self.info}
        atomic_write_bytes(path, data)
        atomic_write_text(_meta_path(path), json.dumps(meta, indent=1, default=str))
        return path


_ARCH_KEYS = ("density_estimator", "hidden_features", "num_transforms", "embedding", "embedding_dim")


def _meta_path(path: Path) -> Path:
    return path.with_name(path.name + ".json")


def _cholesky(cov: torch.Tensor) -> torch.Tensor:
    """Lower Cholesky factor of a (jittered, symmetrised) covariance; its diagonal's root if not PD."""
    d = cov.shape[0]
    cov = 0.5 * (cov + cov.T) + 1e-9 * torch.eye(d, dtype=cov.dtype)
    factor, info = torch.linalg.cholesky_ex(cov)
    return factor if int(info) == 0 else torch.diag(cov.diagonal().clamp_min(1e-12).sqrt())


def load_posterior(path) -> NpePosterior:
    """Reload a posterior written by `NpePosterior.save` (no retraining).

    Nothing in the files is run: the weights file must match the sha256 in its metadata
    (``path`` + ".json"), is read with ``torch.load(weights_only=True)`` (tensors only) and the
    networks are rebuilt from the metadata. ValueError ``path: <file>: ...`` naming the file
    for a missing, damaged, foreign or mismatched file (the CLI exits 2).
    """
    import hashlib
    import io
    import json

    path = Path(path)
    meta_path = _meta_path(path)
    if not path.is_file():
        raise ValueError(f"path: no such file {str(path)!r}")
    try:
        meta = json.loads(meta_path.read_text())
        if not isinstance(meta, dict):
            raise ValueError("not a JSON object")
    except FileNotFoundError:
        raise ValueError(f"path: {path}: its metadata {meta_path.name} is missing (not a camo_sbi NPE posterior "
                         f"{_FORMAT}); nothing was loaded") from None
    except (OSError, ValueError) as exc:
        raise ValueError(f"path: {meta_path}: unreadable metadata ({exc})") from None
    if meta.get("format") != _FORMAT:
        raise ValueError(f"path: {path}: is not a camo_sbi NPE posterior ({_FORMAT}; found {meta.get('format')!r})")
    data = path.read_bytes()
    if hashlib.sha256(data).hexdigest() != meta.get("sha256"):
        raise ValueError(f"path: {path}: sha256 differs from its metadata {meta_path.name} (damaged or replaced); "
                         "nothing was loaded")
    try:
        blob = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
        arch = meta["architecture"]
        n_x, n_free = [int(v) for v in meta["n_x"]], int(meta["n_free"])
        estimators = []
        for k, nx in enumerate(n_x):
            est = sbi_adapter.new_npe_estimator(
                n_free, nx, density_estimator=arch["density_estimator"], hidden_features=int(arch["hidden_features"]),
                num_transforms=int(arch["num_transforms"]),
                embedding_dim=int(arch["embedding_dim"]) if arch["embedding"] == "mlp" else None)
            prefix = f"{k}."
            est.load_state_dict({name[len(prefix):]: t for name, t in blob["state_dict"].items()
                                 if name.startswith(prefix)}, strict=True)
            estimators.append(est)
        return NpePosterior(estimators, blob["x_obs"], blob["low"], blob["high"],
                            theta_transform=meta["theta_transform"], info=meta.get("info"),
                            n_threads=meta.get("n_threads", 1))
    except Exception as exc:  # noqa: BLE001 - a refused pickle, a missing key, weights that do not fit
        raise ValueError(f"path: {path}: cannot be loaded as a camo_sbi NPE posterior "
                         f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None


# ----------------------------------------------------------------------------------------------
# training
# ----------------------------------------------------------------------------------------------


def _seed_int(*key: int) -> int:
    """A 63-bit integer seed from a SeedSequence keyed by ``key``."""
    ss = np.random.SeedSequence(key[0], spawn_key=tuple(key[1:]))
    return int(ss.generate_state(1, dtype=np.uint64)[0] & np.uint64(2**63 - 1))


def _train_flow(theta_z: torch.Tensor, x: torch.Tensor, config: NpeConfig, seed: int):
    """Train q(z | x) with sbi (through `sbi_adapter.train_npe`); returns (estimator, info)."""
    return sbi_adapter.train_npe(
        theta_z, x, seed=seed, density_estimator=config.density_estimator,
        hidden_features=config.hidden_features, num_transforms=config.num_transforms,
        embedding_dim=config.embedding_dim if config.embedding == "mlp" else None,
        training_batch_size=config.training_batch_size, learning_rate=config.learning_rate,
        validation_fraction=config.validation_fraction, stop_after_epochs=config.stop_after_epochs,
        max_epochs=config.max_epochs, device=config.device,
    )


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
    return summarize(x, out.length, n_points=config.n_points, include_length=config.include_length)


def _train_tasks(task, observations, budget: int, seed: int, config: NpeConfig):
    """Yield (estimator, observed summary, info) per task, in order (arguments checked).

    Task i's draws and training are seeded by (seed, i) only, so its estimator does not
    depend on the other tasks (continual `run_sequence` == `run` on the first k tasks).
    """
    prior, sim, dtype = task.prior, task.simulator, _DTYPES[config.sim_dtype]
    lo_free = prior.low[prior.free_mask]
    width_free = (prior.high - prior.low)[prior.free_mask]
    for i, obs in enumerate(observations):
        start = torch.as_tensor(obs.start, dtype=torch.float64).cpu()
        goal = torch.as_tensor(obs.goal, dtype=torch.float64).cpu()
        traj_obs = torch.as_tensor(obs.trajectory(config.space), dtype=torch.float64).cpu()
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0, i)))
        theta = prior.sample(budget, rng)
        t0 = time.perf_counter()
        chunks = [(theta[s : s + config.simulation_batch_size], (seed, 3, i, c))
                  for c, s in enumerate(range(0, budget, config.simulation_batch_size))]
        feats = run_chunks(_simulate_summaries, chunks, simulator=sim, n_simulations=budget,
                           scheduler=config.scheduler, start=start, goal=goal, dtype=dtype, config=config,
                           noise=task.noise)
        t_sim = time.perf_counter() - t0
        x = torch.cat(feats)
        xo = summarize(traj_obs, torch.tensor([traj_obs.shape[0]]), n_points=config.n_points,
                       include_length=config.include_length)[0]
        finite = torch.isfinite(x).all(dim=1)
        keep = x[finite].std(dim=0) > 1e-8 * (1.0 + x[finite].abs().amax(dim=0))
        if not bool(keep.any()):
            raise RuntimeError(f"observations: task {i}'s simulations are all identical; nothing to learn")
        z = to_unconstrained(theta[:, prior.free_mask], lo_free, width_free, config.theta_transform)
        with torch_threads(config.n_threads):
            est, info = _train_flow(z, x[:, keep], config, _seed_int(seed, 1, i))
        info.update(task=i, n_features=int(keep.sum()), n_invalid=int((~finite).sum()),
                    time_simulate=t_sim)
        yield est, xo[keep].float(), info


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


#: a combined importance sample with an effective sample size below min(NPE_MIN_ESS, N / 2)
#: gets status "fallback: low effective sample size (ESS x of N)". Measured: human, budget
#: 500, seeds 0-1, after 1-5 tasks: ESS 10000, 1958 / 1393, 517 / 910, 4.5 / 768, 9.2 / 7.9
#: of 10000 (the degenerate runs are a handful of draws, the others hundreds); Panda, budget
#: 2000, 5 tasks: 50-230 of 10000 (a usable posterior: tests/test_npe.py::test_panda_slow).
#: A share of the draws (e.g. 1 %) would flag those Panda runs: the count is what matters.
NPE_MIN_ESS = 20


def point_estimate(draws: ImportanceSample, kind: str, prior: BoxPrior) -> np.ndarray:
    """(2n,) point estimate of weighted draws: "mean", "median" (coordinate-wise) or "map"
    (the draw with the highest combined density); known coordinates set exactly."""
    check_choice(kind, _ESTIMATORS, "estimator")
    if kind == "mean":
        estimate = draws.weights @ draws.theta
    elif kind == "median":
        estimate = weighted_median(draws.theta, draws.weights)
    else:
        estimate = draws.theta[int(np.argmax(draws.log_prob))]
    return prior.with_known(torch.from_numpy(estimate)).numpy()  # exact, not a mean of constants


def _result(task, posterior: NpePosterior, config: NpeConfig, budget: int, seed: int,
            t_start: float) -> PosteriorResult:
    """Sample the combined posterior and package it (saved to the workdir if any).

    Status "fallback: low effective sample size ..." below ``NPE_MIN_ESS`` (see there).
    """
    t0 = time.perf_counter()
    draws = posterior.sample_is(config.n_posterior_samples, _seed_int(seed, 2) % (2**32),
                             is_rounds=config.is_rounds, defensive_fraction=config.defensive_fraction)
    t_sample = time.perf_counter() - t0
    w = draws.weights
    estimate = point_estimate(draws, config.estimator, task.prior)
    path = None
    if config.workdir is not None:
        path = posterior.save(Path(config.workdir) / f"npe_posterior_k{posterior.n_tasks}_seed{seed}.pt")
    tasks = posterior.info["tasks"]
    extras = {
        "ess": draws.ess,
        "ess_rounds": draws.ess_rounds,
        "tasks": tasks,
        "time_simulate": sum(t["time_simulate"] for t in tasks),
        "time_train": sum(t["time_train"] for t in tasks),
        "time_sample": t_sample,
        "posterior_path": None if path is None else str(path),
    }
    status = STATUS_OK
    if draws.ess < min(NPE_MIN_ESS, 0.5 * len(w)):
        status = (f"fallback: low effective sample size (ESS {draws.ess:.1f} of {len(w)} importance draws, "
                  f"below {min(NPE_MIN_ESS, 0.5 * len(w)):g})")
    return PosteriorResult(
        method="npe", samples=draws.theta, weights=w, estimate=estimate,
        n_simulations=int(getattr(task.simulator, "n_simulations", budget * posterior.n_tasks)),
        wall_time=time.perf_counter() - t_start, n_tasks=posterior.n_tasks, extras=extras, status=status,
        density=posterior.log_prob,
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
