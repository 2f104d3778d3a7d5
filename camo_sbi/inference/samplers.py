"""Samplers of an unnormalised log density: importance sampling, population MCMC, tempered SMC.

Each is a plain function of a ``log_target(z)`` callable, (N, d) float64 tensor -> (N,) float64
log density (unnormalised; -inf where the target is zero, NaN read as -inf), plus the
proposal or starting points it needs, and returns one type, `WeightedDraws`. Estimators
(per-task NPE, amortized NPE, or a new likelihood- or ratio-based method) build the target;
the samplers know nothing of flows, tasks or priors. This module is the one place in
camo_sbi that implements them.

Proposals:

- `Mixture`: k equally weighted components (e.g. k per-task flows), sampled stratified
  (``counts``) through ``sample(counts)`` and evaluated through ``log_probs(z)`` (k, N).
  Its ``product`` is the Gaussian approximation of the product of the components (each
  component's draws moment-matched, precisions added, minus k - 1 times an isotropic prior
  precision ``prior_precision`` when that stays positive definite): the start of the adaptive
  importance rounds, of the MCMC chains and of the Gaussian SMC base.
- `Gaussian`: a mean and a lower Cholesky factor; ``draw(n, generator)`` and ``log_prob(z)``.

Randomness: every draw the samplers make comes from a ``torch.Generator`` seeded by their
``seed`` argument; a proposal's own ``sample`` (e.g. an sbi flow) may use the global torch
RNG, which the caller then forks and seeds (as `npe_posterior.NpePosterior` does).

One fallback rule (`WeightedDraws.status`): a sample is a fallback when its sampler reported
a failure (SMC did not reach the target; MCMC chains barely moved) or when its effective
sample size (of the normalised weights) is below ``min(min_ess, N / 2)``: ``min_ess`` is the
one setting (per-task NPE and amortized NPE both name it so), and the N / 2 cap keeps a small
equally weighted sample acceptable. MCMC draws are equally weighted, so their ESS is N (it
does not measure autocorrelation; their failure test is the acceptance rate).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

import numpy as np
import torch

from camo_sbi._validation import check_choice, check_positive_float, check_positive_int

__all__ = ["Gaussian", "Mixture", "WeightedDraws", "cholesky", "importance", "mcmc", "smc"]

SAMPLERS = ("is", "mcmc", "smc", "flow")
# covariance inflation of the Gaussian importance proposals (product approximation, refits)
_IS_INFLATE_PRODUCT = 2.0
_IS_INFLATE = 1.5
_DRAWS_NAME = {"is": "importance draws", "mcmc": "MCMC draws", "smc": "SMC particles", "flow": "flow draws"}


@dataclass(frozen=True, eq=False)  # tensors: compare fields with torch.equal, not ==
class WeightedDraws:
    """Weighted draws of a target.

    samples: (N, d) float64; weights: (N,) float64, normalised (uniform for MCMC and exact
    flow draws); log_density: (N,) float64 unnormalised log target at the samples; ess:
    effective sample size of the weights, 1 / sum w^2; sampler: "is", "mcmc", "smc" or
    "flow"; failure: None, or what went wrong in the sampler (read by `status`);
    diagnostics: the sampler's own numbers (read-only mapping): IS ``ess_rounds``; MCMC
    ``acceptance``, ``stuck_fraction``, ``chains``, ``steps``, ``burn_in``, ``step_scale``;
    SMC ``betas``, ``reached``, ``acceptance``, ``particles``, ``flow_calls``.
    """

    samples: torch.Tensor
    weights: torch.Tensor
    log_density: torch.Tensor
    ess: float
    sampler: str
    failure: str | None = None
    diagnostics: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        check_choice(self.sampler, SAMPLERS, "sampler")
        object.__setattr__(self, "diagnostics", MappingProxyType(dict(self.diagnostics)))

    def __len__(self) -> int:
        return int(self.weights.shape[0])

    def mapped(self, samples: torch.Tensor, log_density: torch.Tensor) -> WeightedDraws:
        """The same draws in other coordinates (e.g. theta from z, with the log-Jacobian applied)."""
        return replace(self, samples=samples, log_density=log_density, diagnostics=dict(self.diagnostics))

    def distinct_ess(self) -> float:
        """The effective sample size with identical draws merged (their weights summed).

        Resampling copies particles, so a population that has collapsed onto a few points keeps
        uniform weights, and with them ``ess`` = N; merged, its weights say how many points it
        really holds (1 for a single point). Equals ``ess`` when every draw is distinct.
        """
        return self._merged()[1]

    def _merged(self) -> tuple[int, float]:
        """(distinct points, `distinct_ess`)."""
        points, inverse = torch.unique(self.samples, dim=0, return_inverse=True)
        merged = torch.zeros(points.shape[0], dtype=torch.float64)
        merged.index_add_(0, inverse.reshape(-1), self.weights.to(torch.float64))
        total = float(merged.sum())
        return int(points.shape[0]), (total**2 / float((merged**2).sum()) if total > 0 else 0.0)

    def status(self, min_ess: float) -> str:
        """"ok", or "fallback: ..." under the module's one rule: a sampler failure, or an ESS below
        min(min_ess, N / 2), of the weights or of the distinct draws (`distinct_ess`)."""
        min_ess = check_positive_float(min_ess, "min_ess", allow_zero=True)
        if self.failure is not None:
            return f"fallback: {self.failure}"
        n = len(self)
        threshold = min(min_ess, 0.5 * n)
        if not self.ess >= threshold:
            return (f"fallback: low effective sample size (ESS {self.ess:.1f} of {n} {_DRAWS_NAME[self.sampler]}, "
                    f"below {threshold:g})")
        points, distinct = self._merged()
        if not distinct >= threshold:
            return (f"fallback: collapsed onto {points} distinct point(s) (ESS {distinct:.1f} of {n} "
                    f"{_DRAWS_NAME[self.sampler]} with identical draws merged, below {threshold:g})")
        return "ok"


def cholesky(cov: torch.Tensor) -> torch.Tensor:
    """Lower Cholesky factor of a (jittered, symmetrised) covariance; its diagonal's root if not PD."""
    d = cov.shape[0]
    cov = 0.5 * (cov + cov.T) + 1e-9 * torch.eye(d, dtype=cov.dtype)
    factor, info = torch.linalg.cholesky_ex(cov)
    return factor if int(info) == 0 else torch.diag(cov.diagonal().clamp_min(1e-12).sqrt())


@dataclass(frozen=True, eq=False)
class Gaussian:
    """N(mean, L L^T): mean (d,) float64, scale_tril L (d, d) lower triangular."""

    mean: torch.Tensor
    scale_tril: torch.Tensor

    @classmethod
    def from_covariance(cls, mean: torch.Tensor, cov: torch.Tensor) -> Gaussian:
        """Through `cholesky` (jittered; the diagonal if not positive definite)."""
        return cls(mean, cholesky(cov))

    def draw(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """(n, d) float64 draws from ``generator``."""
        eps = torch.randn(n, self.mean.shape[0], generator=generator, dtype=torch.float64)
        return self.mean + eps @ self.scale_tril.T

    def log_prob(self, z: torch.Tensor) -> torch.Tensor:
        return torch.distributions.MultivariateNormal(self.mean, scale_tril=self.scale_tril).log_prob(z)


@dataclass(frozen=True)
class Mixture:
    """k equally weighted components in d dimensions, sampled stratified.

    sample: counts (k ints) -> (sum counts, d) float64, component i's draws in block i;
    log_probs: (N, d) -> (k, N) float64 component log densities; prior_precision: the
    isotropic precision of a prior shared by the components (each a posterior under it),
    taken out k - 1 times in `product`; 0: none.
    """

    sample: Callable[[list[int]], torch.Tensor]
    log_probs: Callable[[torch.Tensor], torch.Tensor]
    n_components: int
    dim: int
    prior_precision: float = 0.0

    def counts(self, n: int) -> list[int]:
        """Stratified draws per component for ``n`` draws (the first n % k get one more)."""
        k = self.n_components
        return [n // k + (1 if i < n % k else 0) for i in range(k)]

    def draw(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:  # noqa: ARG002
        """(n, d) stratified draws (the components' own random state, not ``generator``)."""
        return self.sample(self.counts(n))

    def log_prob(self, z: torch.Tensor) -> torch.Tensor:
        """(N,) log density of the equal mixture."""
        k = self.n_components
        log_mix = torch.tensor([-math.log(k)] * k, dtype=torch.float64)[:, None]
        return torch.logsumexp(self.log_probs(z) + log_mix, dim=0)

    def product(self, z: torch.Tensor, counts: list[int]):
        """(mean, covariance) of the Gaussian approximation of the product of the components
        from their stratified draws ``z`` (``counts`` per component); None if degenerate."""
        k, d = self.n_components, self.dim
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
        if self.prior_precision:
            prec = prec_sum - (k - 1) * self.prior_precision * eye
            if bool((torch.linalg.eigvalsh(prec) <= 0).any()):
                prec = prec_sum
        else:
            prec = prec_sum
        try:
            cov = torch.linalg.inv(prec)
            return cov @ shift, 0.5 * (cov + cov.T)
        except RuntimeError:
            return None

    def pool_and_product(self, init_draws: int):
        """Stratified draws (at least d + 2 per component) and their `product` (None if k = 1 or
        degenerate): the start of MCMC and of the Gaussian SMC base."""
        k, d = self.n_components, self.dim
        counts = self.counts(max(init_draws, k * (d + 2)))
        pool = self.sample(counts)
        return pool, (self.product(pool, counts) if k > 1 else None)


def _generator(seed) -> torch.Generator:
    if isinstance(seed, torch.Generator):
        return seed
    return torch.Generator().manual_seed(check_positive_int(seed, "seed", minimum=0))


def _check_callable(f, name: str) -> None:
    if not callable(f):
        raise TypeError(f"{name}: expected a callable, got {type(f).__name__}")


# ----------------------------------------------------------------------------------- importance sampling

REUSE_MIN_PER_DIM = 25
"""With ``reuse_mixture_draws``: the fewest round-0 draws per component and dimension (the
Gaussian product is fitted from their means and covariances)."""


@torch.no_grad()
def importance(log_target, proposal: Mixture, n: int, *, seed, rounds: int = 2,
               defensive_fraction: float = 0.2, reuse_mixture_draws: bool = False) -> WeightedDraws:
    """``n`` weighted draws per round by adaptive importance sampling; the round with the largest ESS.

    Round 0 proposes from ``proposal`` (n stratified draws). Round 1 (k > 1 components)
    proposes from ``proposal.product`` of round 0's draws (covariance x2), later rounds (up
    to ``rounds``) from a Gaussian fitted to the best round's weighted draws (x1.5); both keep
    a defensive share ``defensive_fraction`` of mixture draws so the weights stay bounded
    where the components have mass. ``diagnostics["ess_rounds"]``: every round's ESS.
    A round whose ESS is n (its proposal is the target: k = 1, or weights all equal) ends the
    rounds, since no later round can have a larger one.

    ``reuse_mixture_draws`` (k > 1 only): round 0 makes only the defensive share of stratified
    mixture draws, or `REUSE_MIN_PER_DIM` x d per component if that is more (what the
    Gaussian product is fitted from), at most n; the defensive share of them, with their
    densities, is the defensive part of every later round (as adaptive multiple importance
    sampling reuses past draws): far fewer component draws and evaluations per round. Round 0's
    own sample, when smaller than n, is returned only if no later round has a finite weight. RuntimeError if every weight of every round is zero. ``seed``:
    int or torch.Generator.
    """
    _check_callable(log_target, "log_target")
    if not isinstance(proposal, Mixture):
        raise TypeError(f"proposal: expected a samplers.Mixture, got {type(proposal).__name__}")
    n = check_positive_int(n, "n", minimum=2)
    rounds = check_positive_int(rounds, "rounds", minimum=0)
    defensive_fraction = check_positive_float(defensive_fraction, "defensive_fraction")
    if defensive_fraction >= 1:
        raise ValueError(f"defensive_fraction: must be in (0, 1), got {defensive_fraction}")
    gen = _generator(seed)
    k, d = proposal.n_components, proposal.dim
    best, ess_rounds, product = None, [], None
    eye = torch.eye(d, dtype=torch.float64)
    reuse = bool(reuse_mixture_draws) and k > 1 and rounds > 0
    n_def = max(int(round(defensive_fraction * n)), k)
    pool = None  # reused mixture draws: (z, component log densities, log target, counts)
    for r in range(rounds + 1):
        log_t = None
        if r == 0:
            n0 = min(n, max(n_def, k * REUSE_MIN_PER_DIM * d)) if reuse else n
            counts = proposal.counts(n0)
            z = proposal.sample(counts)
            lq = proposal.log_probs(z)
            log_mix = torch.tensor([math.log(c / n0) if c else -math.inf for c in counts], dtype=torch.float64)
            log_r = torch.logsumexp(lq + log_mix[:, None], dim=0)
            if k > 1:
                product = proposal.product(z, counts)
            if reuse:  # the defensive share: the first draws of each component's block
                log_t = log_target(z)
                starts = [sum(counts[:i]) for i in range(k)]
                def_counts = proposal.counts(n_def)
                idx = torch.cat([torch.arange(s0, s0 + c) for s0, c in zip(starts, def_counts, strict=True)])
                pool = (z[idx], lq[:, idx], log_t[idx], def_counts)
        else:
            if r == 1 and product is not None:
                mu, cov = product
                cov = _IS_INFLATE_PRODUCT * cov
            elif best is not None:
                w = best["weights"]
                mu = w @ best["z"]
                zc = best["z"] - mu
                cov = _IS_INFLATE * ((zc * w[:, None]).T @ zc)
            else:
                break
            cov = 0.5 * (cov + cov.T) + 1e-9 * eye
            gauss = torch.distributions.MultivariateNormal(mu, covariance_matrix=cov)
            n_gauss = n - n_def
            eps = torch.randn(n_gauss, d, generator=gen, dtype=torch.float64)
            z_gauss = mu + eps @ gauss.scale_tril.T
            if pool is None:
                counts = proposal.counts(n_def)
                z = torch.cat([z_gauss, proposal.sample(counts)])
                lq = proposal.log_probs(z)
            else:  # the target is pointwise: the pool's log target is reused as it is
                lq_gauss = proposal.log_probs(z_gauss)
                log_t = torch.cat([log_target(z_gauss), pool[2]])
                z, lq, counts = torch.cat([z_gauss, pool[0]]), torch.cat([lq_gauss, pool[1]], dim=1), pool[3]
            log_mix = torch.tensor([math.log(c / n) if c else -math.inf for c in counts], dtype=torch.float64)
            log_def = torch.logsumexp(lq + log_mix[:, None], dim=0)
            log_r = torch.logaddexp(log_def, math.log(n_gauss / n) + gauss.log_prob(z))
        if log_t is None:
            log_t = log_target(z)
        log_w = torch.nan_to_num(log_t - log_r, nan=-math.inf, neginf=-math.inf)  # -inf stays -inf (not -1.8e308)
        if not bool(torch.isfinite(log_w).any()):
            ess_rounds.append(0.0)
            continue
        w = torch.softmax(log_w, dim=0)
        ess = float(1.0 / (w**2).sum())
        ess_rounds.append(ess)
        # with reused draws round 0's sample is smaller than n: the fallback only
        smaller = best is not None and best["z"].shape[0] < z.shape[0]
        if best is None or ess > best["ess"] or smaller:
            best = {"z": z, "weights": w, "log_t": log_t, "ess": ess}
        if ess >= n * (1.0 - 1e-9):  # the proposal is the target: no later round can do better
            break
    if best is None:
        raise RuntimeError("importance: every importance weight is zero (the proposal puts no mass where the "
                           "target has)")
    return WeightedDraws(best["z"], best["weights"], best["log_t"], best["ess"], "is",
                         diagnostics={"ess_rounds": ess_rounds})


# ----------------------------------------------------------------------------------- population MCMC


@torch.no_grad()
def mcmc(log_target, init, n: int, *, seed, chains: int = 128, steps: int = 100, burn_in: int = 50,
         de_fraction: float = 0.2, target_acceptance: float = 0.25, min_acceptance: float = 0.0) -> WeightedDraws:
    """At most ``n`` equally weighted draws by population MCMC.

    ``init``: a `Gaussian` the ``chains`` starting points are drawn from, or an (M, d) tensor
    of candidates they are picked from at random. Each of ``steps`` sweeps updates the two
    halves of the population in turn, each half with ONE batched ``log_target`` call. A chain
    proposes a random-walk Metropolis move z + s L eps (L L^T: the covariance of the OTHER
    half, fixed during the update, so each update leaves the product of the targets invariant,
    as in emcee's split ensemble), or with probability ``de_fraction`` a
    differential-evolution move z + g (z_a - z_b) + s L eps / 100 (a, b two distinct chains of
    the other half, g = 2.38 / sqrt(2 d), g = 1 every tenth move). During the first
    ``burn_in`` sweeps (discarded) s is adapted toward ``target_acceptance``, then frozen. The
    draws are every chain's state at ``ceil(n / chains)`` sweeps spread over the rest. A
    failure (see `WeightedDraws.status`): acceptance below ``min_acceptance`` or more than
    half of the chains never moving after burn-in. ``seed``: int or torch.Generator.
    """
    _check_callable(log_target, "log_target")
    if not isinstance(init, (Gaussian, torch.Tensor)) or (isinstance(init, torch.Tensor) and init.dim() != 2):
        raise TypeError(f"init: expected a samplers.Gaussian or an (M, d) tensor, got {type(init).__name__}")
    n = check_positive_int(n, "n", minimum=2)
    chains = check_positive_int(chains, "chains", minimum=8)
    steps = check_positive_int(steps, "steps")
    burn_in = check_positive_int(burn_in, "burn_in", minimum=0)
    if burn_in >= steps:
        raise ValueError(f"burn_in: must be < steps ({steps}), got {burn_in}")
    de_fraction = check_positive_float(de_fraction, "de_fraction", allow_zero=True)
    if de_fraction > 1:
        raise ValueError(f"de_fraction: must be in [0, 1], got {de_fraction}")
    target_acceptance = check_positive_float(target_acceptance, "target_acceptance")
    if target_acceptance >= 1:
        raise ValueError(f"target_acceptance: must be in (0, 1), got {target_acceptance}")
    min_acceptance = check_positive_float(min_acceptance, "min_acceptance", allow_zero=True)
    gen = _generator(seed)
    if isinstance(init, Gaussian):
        d = int(init.mean.shape[0])
        z = init.draw(chains, gen)
    else:
        d = int(init.shape[1])
        z = init.to(torch.float64)[torch.randint(init.shape[0], (chains,), generator=gen)]
    lt = log_target(z)
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
                @ cholesky(torch.cov(zo.T).reshape(d, d)).T
            a = torch.randint(mo, (m,), generator=gen)
            b = (a + 1 + torch.randint(mo - 1, (m,), generator=gen)) % mo
            g = torch.where(torch.rand(m, generator=gen, dtype=torch.float64) < 0.1, 1.0, g_de)
            de = g[:, None] * (zo[a] - zo[b]) + 0.01 * step
            use_de = torch.rand(m, generator=gen, dtype=torch.float64) < de_fraction
            prop = z[idx] + torch.where(use_de[:, None], de, step)
            lt_prop = log_target(prop)
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
    m = zs.shape[0]
    acceptance, stuck = accepted / max(proposed, 1), float((~moved).double().mean())
    failure = None
    if not acceptance >= min_acceptance or stuck > 0.5:
        failure = (f"MCMC barely moved (acceptance {acceptance:.4f}, min_acceptance {min_acceptance:g}; "
                   f"{stuck:.0%} of {chains} chains never moved after burn-in)")
    return WeightedDraws(zs, torch.full((m,), 1.0 / m, dtype=torch.float64), lts, float(m), "mcmc", failure,
                         {"acceptance": acceptance, "stuck_fraction": stuck, "chains": chains, "steps": steps,
                          "burn_in": burn_in, "step_scale": math.exp(log_s)})


# ----------------------------------------------------------------------------------- tempered SMC


@torch.no_grad()
def smc(log_target, base, *, seed, particles: int = 512, inflate: float = 2.0, target_ess: float = 0.5,
        moves: int = 3, independent_fraction: float = 0.5, max_stages: int = 50,
        target_acceptance: float = 0.3) -> WeightedDraws:
    """``particles`` weighted draws by tempered sequential Monte Carlo from ``base`` to the target.

    ``base``: a `Mixture` or a `Gaussian` (anything with ``draw(n, generator)`` and
    ``log_prob(z)``), drawn exactly. Bridge pi_b ∝ r^(1-b) t^b, b from 0 to 1. Each stage
    picks the next b by bisection so that the incremental weights keep an ESS of
    ``target_ess`` x ``particles``; if b = 1 keeps it, the run ends with those weighted
    particles. Otherwise the particles are resampled (systematic) and take ``moves``
    Metropolis-Hastings steps targeting pi_b: with probability ``independent_fraction`` an
    independent draw from a Gaussian fitted to the weighted particles (covariance x
    ``inflate``), else a random-walk step (s^2 x their covariance, s adapted toward
    ``target_acceptance``). One ``base.log_prob`` and one ``log_target`` call per move. If
    ``max_stages`` stages do not reach b = 1, the last stage jumps to b = 1 and the run is a
    failure (``diagnostics["reached"]`` False); with no finite target density at all the
    particles come back equally weighted with ESS 0. ``seed``: int or torch.Generator.
    """
    _check_callable(log_target, "log_target")
    if not (callable(getattr(base, "draw", None)) and callable(getattr(base, "log_prob", None))):
        raise TypeError(f"base: expected a samplers.Mixture or Gaussian, got {type(base).__name__}")
    particles = check_positive_int(particles, "particles", minimum=16)
    inflate = check_positive_float(inflate, "inflate")
    target_ess = check_positive_float(target_ess, "target_ess")
    if target_ess >= 1:
        raise ValueError(f"target_ess: must be in (0, 1), got {target_ess}")
    moves = check_positive_int(moves, "moves")
    independent_fraction = check_positive_float(independent_fraction, "independent_fraction", allow_zero=True)
    if independent_fraction > 1:
        raise ValueError(f"independent_fraction: must be in [0, 1], got {independent_fraction}")
    max_stages = check_positive_int(max_stages, "max_stages")
    target_acceptance = check_positive_float(target_acceptance, "target_acceptance")
    gen = _generator(seed)
    n_evals = 0
    z = base.draw(particles, gen)
    d = int(z.shape[1])
    eye = torch.eye(d, dtype=torch.float64)

    def densities(zz):
        return base.log_prob(zz), log_target(zz)

    log_r, lt = densities(z)
    n_evals += 1
    beta, betas, acc_rates, log_s = 0.0, [0.0], [], math.log(2.38 / math.sqrt(d))
    log_w = torch.zeros(particles, dtype=torch.float64)
    reached = False
    for stage in range(max_stages):
        delta = torch.nan_to_num(lt - log_r, nan=-math.inf, posinf=-math.inf, neginf=-math.inf)
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
        scale = cholesky(pcov)
        fit = torch.distributions.MultivariateNormal(mean, scale_tril=cholesky(inflate * pcov))
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
    failure = None if reached else (f"SMC did not reach the target ({len(betas) - 1} stages, final ESS "
                                    f"{ess:.1f} of {particles})")
    acceptance = float(np.mean(acc_rates)) if acc_rates else float("nan")
    return WeightedDraws(z, w, lt, ess, "smc", failure,
                         {"betas": betas, "reached": reached, "acceptance": acceptance, "particles": particles,
                          "flow_calls": n_evals})
