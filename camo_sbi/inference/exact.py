"""The exact likelihood of observed reaches, and the method that samples its posterior.

    log_likelihood(simulator, theta, observations, noise, space="joint") -> (B,)
    log_posterior(task, theta, observations, space="joint") -> (B,)
    run(task, observations, *, budget, seed, config) -> PosteriorResult      ("exact-likelihood")

NOT simulation-based inference. The toolkit's simulator is deterministic and its noise model
(`camo_sbi.task.NoiseModel`) adds i.i.d. Gaussian noise of standard deviation sigma to every
recorded value (sigma = ``noise.sigma(space)``: radians for joint angles, metres for
end-effector coordinates). So the likelihood of a recording given the limits theta is known in
closed form: a Gaussian around the deterministic simulation of each reach from its start to its
goal. Its posterior (the uniform prior box times this likelihood) is the best any method can
infer from the same reaches in the same space: the Bayes limit the simulation-based methods
are compared with (`camo-sbi reference`; the C2ST and MMD rows of ``compare --reference``).

How a reach's length enters (the simulated and recorded reaches need not have equal length).
A simulation of limits theta has ``length`` valid steps and holds its final posture afterwards
(the `Trajectories` convention: the controller has stopped). A recording has L samples. Let
``S_b`` = the simulated length for row b. The log-likelihood of one reach is

    - 1/(2 sigma^2) * sum_{t < max(L, S_b)} |x_obs[t] - x_sim[b, t]|^2  -  L d (log sigma + log(2 pi) / 2)

with both series extended by holding their last sample (the simulation past its horizon T when
L > T, the recording past L when S_b > L). For t < L this is exactly the Gaussian density of the
L d recorded values (a simulation that stopped early is at rest, as the model says). For
``L <= t < S_b`` (the simulated arm still moves after the recording ended) each extra step is
charged as if the recording had continued at rest at its last sample: an imputation, not data,
that makes a reach which runs on too long less likely, continuously in theta. It adds no
normalising constant (the density is over the L d recorded values only). At the true limits of
a synthetic subject S_b = L exactly (noise does not change a reach's length), so the
imputation never acts there; the one approximation is this continuous penalty in place of the
exact but discontinuous "likelihood zero unless S_b = L" (the length is recorded without
noise). Every reach starts from its recorded ``start`` (taken as exact: the simulator cannot
simulate from an uncertain start) and theta is widened to contain it (`task.contain`, as every
method does); ``x_obs[0]`` is compared like every other sample.

The method ``exact-likelihood`` samples this posterior by tempered SMC (`samplers.smc`) from the
prior box (as base) to the posterior, moving in theta's free coordinates (or, optionally, the
logit coordinates of the box, `flow_space`), then ``mcmc_steps`` sweeps of population MCMC
(`samplers.mcmc`) from its particles (`ExactConfig`). Each target evaluation simulates every
observed reach once per particle, through the task's counting simulator: its simulations are
counted (``n_simulations``) like any other method's, but the registry does not cap them
(`Capabilities.exact`): the exact likelihood is not an estimator of a budget, so it is exempt
from the budget comparisons: ``compare --reference`` runs it once, at the smallest of its
budgets (`registry.grid_budgets`), instead of repeating the same SMC per budget; the plain
``compare`` grid repeats it, so each budget's figures and tables hold it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import torch

from camo_sbi._validation import check_choice, check_positive_float, check_positive_int
from camo_sbi.inference import samplers
from camo_sbi.inference.contract import check_run_args
from camo_sbi.inference.flow_space import from_unconstrained, logistic_log_prob, torch_threads
from camo_sbi.inference.result import PosteriorResult, weighted_median
from camo_sbi.task import SPACES, NoiseModel, Observation, contain

__all__ = ["LABEL", "ExactConfig", "PriorBase", "log_likelihood", "log_posterior", "reach_log_likelihood", "run",
           "sample_posterior"]

LABEL = "not simulation-based: the exact likelihood's posterior (the Bayes limit with these data)"
"""How tables, the report and ``--help`` describe ``exact-likelihood``."""

_MCMC_KEEP = 4  # sweeps of the MCMC's second half kept (spread evenly): draws = 4 x chains
_CHUNK = 8192  # theta rows per simulate call (memory: rows x T x n float64 per reach)


@dataclass(frozen=True)
class ExactConfig:
    """Settings of ``exact-likelihood`` (the tempered SMC of `samplers.smc`).

    Attributes:
        space: the observation space whose recorded values the likelihood reads ("joint" or
            "cartesian"; the same space the other methods of a comparison read).
        coordinates: where the SMC moves: "box" (theta's free coordinates, `BoxBase`) or
            "logit" (the logit of the position in the prior box, `PriorBase`).
        particles: SMC particles (the posterior draws returned, weighted).
        moves: Metropolis-Hastings moves per SMC stage.
        mcmc_steps: after the SMC, a population MCMC (`samplers.mcmc`: random-walk and
            differential-evolution moves, which travel along a long narrow ridge) of this many
            sweeps, one chain per particle started at the SMC's particles resampled by weight;
            the draws are the chains' states at 4 sweeps spread over the second half (the
            first is burn-in), equally weighted (4 x particles draws). 0: the SMC's weighted
            particles as they are.
        max_stages: tempering stages before the run is declared failed (status "fallback").
        target_ess: the ESS fraction kept between stages.
        min_ess: the samplers' one fallback rule (`samplers.WeightedDraws.status`).
    """

    space: str = "joint"
    coordinates: str = "box"
    particles: int = 1000
    moves: int = 10
    mcmc_steps: int = 200
    max_stages: int = 300
    target_ess: float = 0.5
    min_ess: float = 100.0

    def __post_init__(self):
        check_choice(self.space, SPACES, "space")
        check_choice(self.coordinates, ("box", "logit"), "coordinates")
        check_positive_int(self.particles, "particles", minimum=16)
        check_positive_int(self.moves, "moves")
        check_positive_int(self.mcmc_steps, "mcmc_steps", minimum=0)
        check_positive_int(self.max_stages, "max_stages")
        check_positive_float(self.target_ess, "target_ess")
        if not self.target_ess < 1:
            raise ValueError(f"target_ess: must be in (0, 1), got {self.target_ess}")
        check_positive_float(self.min_ess, "min_ess", allow_zero=True)


def _sigma(noise: NoiseModel, space: str) -> float:
    if not isinstance(noise, NoiseModel):
        raise TypeError(f"noise: expected a NoiseModel, got {type(noise).__name__}")
    check_choice(space, SPACES, "space")
    s = noise.sigma(space)
    if not s > 0:
        raise ValueError(f"noise: the exact likelihood needs observation noise in the {space} space "
                         f"(a noise-free recording has a degenerate likelihood); got {noise}")
    return s


@torch.no_grad()
def reach_log_likelihood(sim_x: torch.Tensor, sim_length: torch.Tensor, obs_x: torch.Tensor,
                         sigma: float) -> torch.Tensor:
    """(B,) log-likelihood of one recorded reach ``obs_x`` (L, d) given simulations ``sim_x``
    (B, T, d) of valid lengths ``sim_length`` (B,), noise ``sigma`` (see the module docstring)."""
    sim_x = sim_x.to(torch.float64)
    obs_x = obs_x.to(torch.float64)
    B, T, d = sim_x.shape
    L = int(obs_x.shape[0])
    n = max(T, L)
    if n > T:  # the recording outlasts the simulator's horizon: the simulation holds its last posture
        sim_x = torch.cat([sim_x, sim_x[:, -1:].expand(B, n - T, d)], dim=1)
    if n > L:  # compared past its end only where the simulation still moves (imputed: at rest)
        obs_x = torch.cat([obs_x, obs_x[-1:].expand(n - L, d)])
    sq = ((sim_x - obs_x.unsqueeze(0)) ** 2).sum(-1)  # (B, n)
    steps = torch.arange(n).unsqueeze(0)
    used = steps < torch.clamp(sim_length.to(torch.int64).reshape(-1, 1), min=L)
    const = L * d * (math.log(sigma) + 0.5 * math.log(2 * math.pi))
    return -0.5 * (sq * used).sum(1) / sigma**2 - const


@torch.no_grad()
def log_likelihood(simulator, theta, observations, noise: NoiseModel, *, space: str = "joint") -> torch.Tensor:
    """(B,) float64 exact log-likelihood of ``observations`` given each row of ``theta`` (B, 2n).

    One simulation per row and reach (``simulator.simulate``, float64; a counting simulator
    counts them), from each reach's ``start`` to its ``goal`` with theta widened to contain the
    start. Reaches are independent given theta, so their log-likelihoods add. ValueError naming
    ``noise`` when sigma is 0 in ``space``, ``observations`` when a reach lacks ``space``.
    """
    sigma = _sigma(noise, space)
    theta = torch.as_tensor(theta, dtype=torch.float64)
    if theta.dim() != 2 or theta.shape[1] != 2 * simulator.n_joints:
        raise ValueError(f"theta: expected shape (B, {2 * simulator.n_joints}), got {tuple(theta.shape)}")
    obs = tuple(observations)
    if not obs:
        raise ValueError("observations: at least one observed reach is required")
    recorded = [_recorded(o, i, space) for i, o in enumerate(obs)]
    out = torch.zeros(theta.shape[0], dtype=torch.float64)
    for s in range(0, theta.shape[0], _CHUNK):
        rows = theta[s : s + _CHUNK]
        for o, x_obs in zip(obs, recorded, strict=True):
            traj = simulator.simulate(contain(rows, o.start), o.goal, o.start)
            x = traj.q if space == "joint" else traj.ee
            out[s : s + _CHUNK] += reach_log_likelihood(x, traj.length, x_obs, sigma)
    return out


def _recorded(o, i: int, space: str) -> torch.Tensor:
    """Reach ``i``'s recorded values in ``space`` (TypeError naming ``observations``, ValueError ``space``)."""
    if not isinstance(o, Observation):
        raise TypeError(f"observations: item {i} is a {type(o).__name__}, not an Observation")
    return o.trajectory(space)


@torch.no_grad()
def log_posterior(task, theta, observations=None, *, space: str = "joint") -> torch.Tensor:
    """(B,) unnormalised log posterior: ``task.prior.log_prob`` plus `log_likelihood` (the task's
    simulator and noise); rows outside the prior box are -inf and are not simulated."""
    theta = torch.as_tensor(theta, dtype=torch.float64)
    theta = theta.unsqueeze(0) if theta.dim() == 1 else theta
    lp = task.prior.log_prob(theta)
    inside = torch.isfinite(lp)
    if bool(inside.any()):
        obs = task.observations if observations is None else observations
        lp[inside] = lp[inside] + log_likelihood(task.simulator, theta[inside], obs, task.noise, space=space)
    return lp


class BoxBase:
    """The uniform prior box itself, in theta's free coordinates: the SMC's base, with
    ``draw(n, generator)``, ``log_prob(z)`` (0 inside the box, -inf outside: the constant
    log-volume is dropped) and ``theta(z)``. Moves stay linear in theta, so a posterior
    concentrated along a line of theta (a joint's mid-range pinned by the controller's
    centring term, its width free) stays a line; moves leaving the box are rejected."""

    def __init__(self, prior):
        self.prior = prior
        self.lo = prior.low[prior.free_mask]
        self.width = (prior.high - prior.low)[prior.free_mask]

    @property
    def dim(self) -> int:
        return int(self.lo.shape[0])

    def draw(self, n: int, generator: torch.Generator) -> torch.Tensor:
        return self.lo + self.width * torch.rand(n, self.dim, generator=generator, dtype=torch.float64)

    def log_prob(self, z: torch.Tensor) -> torch.Tensor:
        inside = ((z >= self.lo) & (z <= self.lo + self.width)).all(-1)
        return torch.where(inside, 0.0, -math.inf).to(torch.float64)

    def theta(self, z: torch.Tensor) -> torch.Tensor:
        return self.prior.expand(z)


class PriorBase:
    """The uniform prior box in logit coordinates z of its free coordinates (a standard logistic
    per coordinate): the SMC's base, with ``draw(n, generator)``, ``log_prob(z)`` and
    ``theta(z)`` -> (N, 2n) limits (known coordinates at their values)."""

    def __init__(self, prior):
        self.prior = prior
        self.lo = prior.low[prior.free_mask]
        self.width = (prior.high - prior.low)[prior.free_mask]

    @property
    def dim(self) -> int:
        return int(self.lo.shape[0])

    def draw(self, n: int, generator: torch.Generator) -> torch.Tensor:
        u = torch.rand(n, self.dim, generator=generator, dtype=torch.float64).clamp(1e-12, 1 - 1e-12)
        return torch.logit(u)

    def log_prob(self, z: torch.Tensor) -> torch.Tensor:
        return logistic_log_prob(z)

    def theta(self, z: torch.Tensor) -> torch.Tensor:
        free, _ = from_unconstrained(z, self.lo, self.width, "logit")
        return self.prior.expand(free)


def sample_posterior(task, observations, *, seed, config: ExactConfig | None = None) -> samplers.WeightedDraws:
    """Weighted draws of the exact posterior (in theta coordinates) by tempered SMC from the prior.

    The target in logit coordinates is the base (the prior pushed to z) times the likelihood,
    so tempering from base to target tempers the likelihood alone. ``seed``: int or
    torch.Generator. Returns `samplers.WeightedDraws` with ``samples`` (N, 2n) theta.
    """
    config = ExactConfig() if config is None else config
    base = (BoxBase if config.coordinates == "box" else PriorBase)(task.prior)
    if base.dim == 0:
        raise ValueError("task.prior: every coordinate is fixed; nothing to infer")
    obs = tuple(observations)

    def target(z):
        lp = base.log_prob(z)
        inside = torch.isfinite(lp)
        if bool(inside.any()):  # rows outside the box are not simulated
            lp[inside] = lp[inside] + log_likelihood(task.simulator, base.theta(z[inside]), obs, task.noise,
                                                     space=config.space)
        return lp

    gen = torch.Generator().manual_seed(int(seed)) if not isinstance(seed, torch.Generator) else seed
    with torch_threads(1):  # small tensors: torch's thread pool only adds contention
        draws = samplers.smc(target, base, seed=gen, particles=config.particles, moves=config.moves,
                             max_stages=config.max_stages, target_ess=config.target_ess)
        if config.mcmc_steps and draws.failure is None:
            idx = torch.multinomial(draws.weights, config.particles, replacement=True, generator=gen)
            chains = config.particles + config.particles % 2
            mc = samplers.mcmc(target, draws.samples[idx], _MCMC_KEEP * chains, seed=gen, chains=chains,
                               steps=config.mcmc_steps, burn_in=config.mcmc_steps // 2, de_fraction=0.5)
            draws = replace(mc, diagnostics={**mc.diagnostics, "betas": draws.diagnostics["betas"],
                                             "smc_acceptance": draws.diagnostics["acceptance"]})
    return draws.mapped(base.theta(draws.samples), draws.log_density)


def run(task, observations, *, budget: int, seed: int, config: ExactConfig | None = None) -> PosteriorResult:
    """The run contract: the exact posterior's draws; ``budget`` is not used (the registry counts
    the simulations without capping them: see the module docstring). A task without noise in
    ``config.space`` has a degenerate likelihood: the result is then "failed: ..." (prior draws,
    no simulation), so a grid of such tasks records why instead of stopping.

    Estimate: the weighted coordinate-wise median. Status: `samplers.WeightedDraws.status`
    with ``config.min_ess`` (a run whose tempering did not reach the posterior is a fallback).
    ``extras``: ``ess``, ``stages``, ``acceptance``, ``label``. ``density``: `log_posterior`
    on the unwrapped simulator (each call simulates every reach per row, outside the count).
    """
    t0 = time.perf_counter()
    config, budget, seed, observations, prior = check_run_args(task, observations, budget, seed, config,
                                                               ExactConfig)
    if task.noise.sigma(config.space) == 0:  # a grid of noise-free tasks goes on; the rows say why
        return _failed(task, prior, observations, seed, config, t0,
                       f"no observation noise in the {config.space} space: the exact likelihood is degenerate")
    draws = sample_posterior(task, observations, seed=seed, config=config)
    theta, w = draws.samples.numpy(), draws.weights.numpy()
    estimate = prior.with_known(torch.from_numpy(weighted_median(theta, w))).numpy()
    from camo_sbi.budget import unwrap_simulator

    plain = task.with_simulator(unwrap_simulator(task.simulator))
    return PosteriorResult(
        method="exact-likelihood", samples=theta, weights=w, estimate=estimate,
        n_simulations=int(getattr(task.simulator, "n_simulations", 0)), wall_time=time.perf_counter() - t0,
        n_tasks=len(observations),
        extras={"ess": draws.ess, "stages": len(draws.diagnostics["betas"]) - 1,
                "acceptance": draws.diagnostics["acceptance"], "label": LABEL},
        status=draws.status(config.min_ess),
        density=lambda th: log_posterior(plain, th, observations, space=config.space),
    )


def _failed(task, prior, observations, seed, config, t0, reason: str) -> PosteriorResult:
    """A "failed: reason" result: prior draws (labelled failed, never passed off as a posterior)."""
    theta = prior.sample(config.particles, seed).numpy()
    return PosteriorResult(method="exact-likelihood", samples=theta, weights=None, estimate=prior.outer_theta().numpy(),
                           n_simulations=0, wall_time=time.perf_counter() - t0, n_tasks=len(observations),
                           extras={"label": LABEL}, status=f"failed: {reason}")
