"""Amortized NPE: one flow per body model, trained once, for any person's reaches.

Two forms (`TrainConfig.form`):

- ``"set"`` (default): q(theta | {x_1..x_k}), k = 1..max_set reaches, one conditional flow
  behind a permutation-invariant set embedding (`SetFlow`: mean, max and min of the
  standardised reach features and the mean of a per-reach MLP). Inference is ONE flow sample
  (`AmortizedEstimator.sample_set`), exact draws of the trained posterior, no combining.
- ``"per-reach"``: q(theta | x) for one reach, combined over a person's reaches by sbi's
  i.i.d. NPE rule and sampled by MCMC, SMC or importance sampling (``AmortizedConfig.combine``).

    est = train(simulator, model="panda", config=TrainConfig(simulations=200_000), seed=0)
    est.save("panda.pt");  est = load_estimator("panda.pt")
    run_method("npe-amortized", task, budget=1, seed=0, config={"estimator_path": "panda.pt"})

**Training** (once per body model, `train`): ``simulations`` independent triples

- limits theta ~ the model's box prior ``BoxPrior(sim.bounds, sim.start)`` (split at the
  default start, so every draw contains it);
- a goal drawn INDEPENDENTLY of theta: the end-effector position FK(q') of a configuration
  q' uniform inside the limits theta' of a second, independent prior draw. Its distribution
  is the marginal (over the prior) of the experiments' goal design, which draws goals inside
  the subject's TRUE limits and keeps them only if reachable (`camo_sbi.scenarios.reaching`).
  That selection makes an experiment's goals informative about theta (a goal is only asked
  where the person can go); the estimator ignores this information, as CAMO and per-task NPE
  do: it models p(trajectory | theta, goal) with the goal as a given condition. Goals are
  never filtered by reachability under the training theta (that would couple them to theta).
- the start: the model's default start posture, the start of every experiment and the
  prior's split point. Under the model rule ("observed postures bound the limits") a start
  outside theta's limits is impossible, so a start drawn independently of theta would need a
  prior that is not split at it; we keep the start fixed instead and REFUSE tasks whose
  reaches start elsewhere or whose prior is not this box (strong priors, other starts):
  retrain for those. The start is therefore constant in training and not a network input.

The set form draws ``max_set`` such reaches (independent goals, same limits) for each of
``simulations // max_set`` limit vectors; every training epoch sees a new random subset of
each (size uniform on 1..max_set), so one flow covers every set size.

Each triple is simulated once (large batched ``simulate`` calls), optionally perturbed with
the observation-noise model (`NoiseModel.perturb`, seeded), and summarised per space exactly
as per-task NPE does (`trajectory_summary`: the valid part resampled at ``n_points`` times after
the start, plus the length), with the goal prepended: condition x = [goal (3), summary].
Features constant over the training set are dropped. One conditional flow q(z | x) per
requested space (joint and/or Cartesian, from the SAME simulations, so training cost is
paid once) is trained by maximum likelihood in the logit coordinates z of the prior box
(no mass outside the box), inputs and conditions standardised with stored statistics.

**Inference, set form** (`run`, no simulation): ``n_posterior_samples`` draws of
q(theta | the person's N <= max_set reaches) and their log densities in one pass of the flow
(sbi's ``sample_and_log_prob``), equally weighted.

**Inference, per-reach form** (`run`, no simulation): for reaches x_1..x_N of one person,
p(theta | x_1..N) ∝ p(theta)^(1-N) ∏_i q(theta | x_i) (sbi's i.i.d. NPE rule, exact when q
is the exact per-reach posterior), held by `npe_posterior.NpePosterior` (the same flow with N
conditions; its log target in the logit coordinates z, with the prior pushed to z as
standard logistic densities, serves every sampler of `samplers`). ``combine="mcmc"``
(default): `samplers.mcmc`, a population MCMC in z whose chains start from a Gaussian
approximation of the product, one batched flow call over half the chains x N reaches per
half-sweep; equally weighted draws (``weights`` None). ``combine="smc"``: `samplers.smc`,
tempered SMC from the mixture of the N flows to the product. ``combine="is"``:
`samplers.importance`, the importance sampler of per-task NPE. Every sampler's result passes
the samplers' one fallback rule (`samplers.WeightedDraws.status` with ``min_ess``: MCMC
chains that barely moved, SMC that did not reach the product, too small an ESS), and the
registry warns about every fallback.

Why the set form is the default, and what each form and sampler measured (calibration,
time per person, the per-reach samplers' failure to converge): `docs/studies/amortized_measurements.md`
and docs/user-guide/amortized.md.

Modules: this one holds the inference settings, `train`, `run` and the sbi diagnostics;
`amortized_estimator` the training settings (`TrainConfig`), the estimator object and its file
(format, fingerprint check, `load_estimator`); `amortized_flows` the networks;
`amortized_data` the model fingerprint and the training set.
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass

import torch

from camo_sbi._validation import (
    InputError,
    check_choice,
    check_point_estimate,
    check_positive_float,
    check_positive_int,
    renamed_fields,
)
from camo_sbi.budget import unwrap_simulator
from camo_sbi.inference import npe, samplers, sbi_adapter
from camo_sbi.inference.amortized_data import (
    fingerprint_differences,
    model_fingerprint,
    seed_int,
    simulate_training_set,
)
from camo_sbi.inference.amortized_estimator import (
    FAST_SET_TRAINING,
    FORMAT,
    FORMS,
    AmortizedEstimator,
    TrainConfig,
    load_estimator,
    payload_sha256,
)
from camo_sbi.inference.amortized_flows import SET_EMBEDDING, SetFlow, new_flow
from camo_sbi.inference.contract import check_run_args
from camo_sbi.inference.flow_space import logistic_log_prob, to_unconstrained, torch_threads
from camo_sbi.inference.result import PosteriorResult
from camo_sbi.priors import BoxPrior
from camo_sbi.task import SPACES

__all__ = [
    "FAST_SET_TRAINING",
    "FORMAT",
    "FORMS",
    "AmortizedConfig",
    "AmortizedEstimator",
    "TrainConfig",
    "load_estimator",
    "model_fingerprint",
    "payload_sha256",
    "run",
    "simulate_training_set",
    "sbi_diagnostics",
    "train",
]

COMBINE = ("mcmc", "is", "smc")  # samplers of the per-reach form's product posterior


@renamed_fields(estimator="estimator_path")
@dataclass(frozen=True)
class AmortizedConfig:
    """npe-amortized settings at inference.

    Attributes:
        estimator_path: path of a trained estimator file (`train` + `AmortizedEstimator.save`, or
            ``camo-sbi amortize``). Required.
        space: the observation space read ("joint" or "cartesian"); the file must hold a flow
            for it.
        combine: how the per-reach form's product posterior is sampled; None (default): the
            estimator's own way, one flow sample for a set-form estimator and "mcmc" for a
            per-reach one. Giving it for a set-form estimator is a ValueError (nothing is
            combined there). "mcmc" (population MCMC, `samplers.mcmc`, equally weighted draws),
            "smc" (tempered SMC, `samplers.smc`, ``smc_particles`` weighted draws) or "is"
            (importance sampling, `samplers.importance`, weighted draws). None of
            them converges on the Panda's 5-reach target within seconds; what was measured,
            and why MCMC stays the default: docs/studies/amortized_measurements.md.
        n_posterior_samples: draws returned by the set form's flow, MCMC (at most this many,
            mcmc_chains per kept sweep) and IS; SMC returns ``smc_particles``.
        is_rounds, defensive_fraction: the importance sampler (combine="is").
        mcmc_chains, mcmc_steps, mcmc_burn_in, mcmc_de_fraction: the population MCMC
            (combine="mcmc"): chains, sweeps, discarded adaptation sweeps, share of
            differential-evolution moves. The chains do not reach the target's typical set at
            the default sweeps: the draws are wide because they are unconverged
            (docs/studies/amortized_measurements.md).
        smc_particles, smc_moves, smc_target_ess, smc_inflate, smc_base,
            smc_independent_fraction, smc_max_stages: the tempered SMC (combine="smc"):
            particles; Metropolis moves per stage; the ESS share kept per stage; covariance
            inflation of the Gaussian proposals; base "mixture" (the N flows) or "gaussian"
            (the Gaussian product); share of independent Gaussian proposals among the moves;
            stages before the fallback (moves against calibration and time:
            docs/studies/amortized_measurements.md).
        min_acceptance: an MCMC acceptance rate below it (or more than half of the chains never
            moving after burn-in) sets ``status = "fallback: ..."``.
        point_estimate: "mean", "median" or "mode" (`npe.point_estimate`; old name of the mode: "map").
        min_ess: the samplers' one fallback rule (`samplers.WeightedDraws.status`): weighted
            draws (combine="is" or "smc") with an effective sample size (of the weights, or of the
            distinct draws) below min(min_ess, N / 2) are reported as ``status = "fallback: ..."``.
        n_threads: torch intra-op threads while sampling (None: unchanged).
    """

    estimator_path: str | os.PathLike | None = None
    space: str = "joint"
    combine: str | None = None
    n_posterior_samples: int = 10_000
    is_rounds: int = 3
    defensive_fraction: float = 0.2
    mcmc_chains: int = 128
    mcmc_steps: int = 300
    mcmc_burn_in: int = 150
    mcmc_de_fraction: float = 0.2
    smc_particles: int = 512
    smc_moves: int = 2
    smc_target_ess: float = 0.5
    smc_inflate: float = 2.0
    smc_base: str = "mixture"
    smc_independent_fraction: float = 0.5
    smc_max_stages: int = 50
    point_estimate: str = "mean"
    min_ess: float = 20.0
    min_acceptance: float = 0.01
    n_threads: int | None = 1

    def __post_init__(self):
        if self.estimator_path is not None and not isinstance(self.estimator_path, (str, os.PathLike)):
            raise TypeError(f"estimator_path: expected a path, got {type(self.estimator_path).__name__}")
        check_choice(self.space, SPACES, "space")
        if self.combine is not None:
            check_choice(self.combine, COMBINE, "combine")
        check_positive_int(self.n_posterior_samples, "n_posterior_samples", minimum=2)
        check_positive_int(self.mcmc_chains, "mcmc_chains", minimum=8)
        check_positive_int(self.mcmc_steps, "mcmc_steps")
        check_positive_int(self.mcmc_burn_in, "mcmc_burn_in", minimum=0)
        if self.mcmc_burn_in >= self.mcmc_steps:
            raise ValueError(f"mcmc_burn_in: must be < mcmc_steps ({self.mcmc_steps}), got {self.mcmc_burn_in}")
        check_positive_float(self.mcmc_de_fraction, "mcmc_de_fraction", allow_zero=True)
        if self.mcmc_de_fraction > 1:
            raise ValueError(f"mcmc_de_fraction: must be in [0, 1], got {self.mcmc_de_fraction}")
        check_positive_float(self.min_acceptance, "min_acceptance", allow_zero=True)
        check_positive_int(self.smc_particles, "smc_particles", minimum=16)
        check_positive_int(self.smc_moves, "smc_moves")
        check_positive_float(self.smc_target_ess, "smc_target_ess")
        if self.smc_target_ess >= 1:
            raise ValueError(f"smc_target_ess: must be in (0, 1), got {self.smc_target_ess}")
        check_positive_float(self.smc_inflate, "smc_inflate")
        check_choice(self.smc_base, ("mixture", "gaussian"), "smc_base")
        check_positive_float(self.smc_independent_fraction, "smc_independent_fraction", allow_zero=True)
        if self.smc_independent_fraction > 1:
            raise ValueError(f"smc_independent_fraction: must be in [0, 1], got {self.smc_independent_fraction}")
        check_positive_int(self.smc_max_stages, "smc_max_stages")
        check_positive_int(self.is_rounds, "is_rounds", minimum=0)
        check_positive_float(self.defensive_fraction, "defensive_fraction")
        if self.defensive_fraction >= 1:
            raise ValueError(f"defensive_fraction: must be in (0, 1), got {self.defensive_fraction}")
        check_point_estimate(self.point_estimate, ("mean", "median", "mode"))
        check_positive_float(self.min_ess, "min_ess", allow_zero=True)
        if self.n_threads is not None:
            check_positive_int(self.n_threads, "n_threads")


def train(simulator, *, model: str, config: TrainConfig | None = None, seed: int,
          progress: bool = False) -> AmortizedEstimator:
    """Simulate ``config.simulations`` training triples for ``simulator`` and train one flow per space.

    ``model``: the name recorded in the file (e.g. "panda"). The simulator is used directly
    (never through a budget counter); the cost is recorded in ``metadata``
    (``training_simulations``, ``training_time`` = simulation + training seconds).
    Deterministic given ``seed``; the global torch RNG is untouched.
    """
    config = TrainConfig() if config is None else config
    if not isinstance(config, TrainConfig):
        raise TypeError(f"config: expected a TrainConfig, got {type(config).__name__}")
    if not isinstance(model, str) or not model:
        raise ValueError(f"model: expected a non-empty name, got {model!r}")
    seed = check_positive_int(seed, "seed", minimum=0)
    sim = unwrap_simulator(simulator)
    prior = BoxPrior(sim.bounds, sim.start)
    if prior.n_free == 0:
        raise ValueError("simulator: every limit is fixed by its bounds and start; nothing to infer")
    t0 = time.perf_counter()
    data = simulate_training_set(sim, prior, config, seed, progress=progress)
    lo, w = prior.low[prior.free_mask], (prior.high - prior.low)[prior.free_mask]
    z = to_unconstrained(data["theta"][:, prior.free_mask], lo, w, "logit").float()
    flows, features, training = {}, {}, {}
    for k, space in enumerate(config.spaces):
        x = data["x"][space]
        reaches = x.reshape(-1, x.shape[-1])
        finite = torch.isfinite(x).reshape(x.shape[0], -1).all(dim=1)
        fr = torch.isfinite(reaches).all(dim=1)
        keep = reaches[fr].std(dim=0) > 1e-8 * (1.0 + reaches[fr].abs().amax(dim=0))
        flow = new_flow(config, z.shape[1], int(keep.sum()), seed_int(seed, 3, k))
        flow.set_statistics(z[finite], reaches[fr][:, keep].float())
        if config.form == "set":
            sets = x[finite][..., keep]
            gen = torch.Generator().manual_seed(seed_int(seed, 11, k))
            size = torch.randint(1, config.max_set + 1, (sets.shape[0], 1), generator=gen)
            valid = torch.argsort(torch.rand(sets.shape[:2], generator=gen), dim=1).argsort(dim=1) < size
            xk = SetFlow.pack(sets, valid)  # stored flags: the validation sets; training redraws them
        else:
            xk = x[finite][:, keep].float()
        with torch_threads(config.n_threads):
            info = sbi_adapter.fit_density_estimator(
                flow, z[finite], xk, seed=seed_int(seed, 4, k),
                batch_size=max(2, config.training_batch_size // config.reaches_per_theta),
                learning_rate=config.learning_rate, validation_fraction=config.validation_fraction,
                stop_after_epochs=config.stop_after_epochs, max_epochs=config.max_epochs,
                max_seconds=config.max_train_seconds, progress=progress, desc=f"training {space}",
                balance=config.balance, prior_log_prob=logistic_log_prob, lr_schedule=config.lr_schedule)
        info.pop("training_loss")
        info["n_invalid"] = int((~finite).sum())
        flows[space] = flow
        features[space] = {"keep": keep.tolist(), "n_kept": int(keep.sum()),
                           "n_reaches": int(x[finite].reshape(-1, x.shape[-1]).shape[0])}
        training[space] = info
    total = time.perf_counter() - t0
    from importlib.metadata import version

    metadata = {
        "format": FORMAT,
        "model": model,
        "fingerprint": model_fingerprint(sim),
        "prior": {"low": prior.low.tolist(), "high": prior.high.tolist()},
        "settings": config.to_json(),
        "seed": seed,
        "features": features,
        "training": training,
        "training_simulations": int(data["theta"].shape[0] * config.reaches_per_theta),
        **({"set_embedding": SET_EMBEDDING} if config.form == "set" else {}),
        "time_simulate": data["time_simulate"],
        "training_time": total,
        "versions": {"camo_sbi": version("camo_sbi"), "torch": torch.__version__,
                     "sbi": ".".join(map(str, sbi_adapter.sbi_version()))},
    }
    return AmortizedEstimator(metadata, flows)


# ----------------------------------------------------------------------------------- the run contract


def run(task, observations, *, budget: int, seed: int, config: AmortizedConfig | None = None) -> PosteriorResult:
    """The combined posterior of ``observations`` from a trained estimator; simulates nothing.

    ``budget`` is accepted for the common contract and unused (the cost was paid in training:
    ``extras["training_simulations"]``, ``extras["training_time"]``). extras also hold
    ``sampler`` ("mcmc", "smc", "is" or "flow" for the set form), ``time_load``,
    ``time_sample``, ``estimator_path``; with MCMC ``acceptance``, ``stuck_fraction``,
    ``chains``, ``steps``, ``burn_in``, ``step_scale``; with SMC ``ess``, ``stages``,
    ``acceptance``, ``particles``, ``flow_calls``; with IS ``ess``, ``ess_rounds``.
    """
    config, budget, seed, observations, prior = check_run_args(task, observations, budget, seed, config,
                                                               AmortizedConfig)
    t0 = time.perf_counter()
    if config.estimator_path is None:
        raise InputError("estimator_path: npe-amortized needs a trained estimator file, config={'estimator_path': FILE}; "
                         "train one with `camo-sbi amortize --model M --out FILE`")
    try:
        est = load_estimator(config.estimator_path)
    except ValueError as exc:  # a missing, damaged or foreign file: the caller's input, never a method failure
        raise InputError(str(exc)) from exc
    t_load = time.perf_counter() - t0
    est.check_task(task, observations, config.space)
    if est.form == "set" and config.combine is not None:
        raise InputError(f"combine: {config.combine!r} applies to per-reach estimators; {est.path or 'this'} is a "
                         f"set-form estimator, sampled directly (leave combine unset)")
    combine = config.combine or "mcmc"
    t1 = time.perf_counter()
    sample_seed = seed_int(seed, 5) % (2**32)
    if est.form == "set":
        theta, lp = est.sample_set(observations, config.space, config.n_posterior_samples, sample_seed,
                                   n_threads=config.n_threads)
        n = theta.shape[0]
        draws = samplers.WeightedDraws(theta, torch.full((n,), 1.0 / n, dtype=torch.float64), lp, float(n), "flow")
    else:
        posterior = est.posterior(observations, config.space, n_threads=config.n_threads)
        if combine == "mcmc":
            draws = posterior.sample_mcmc(config.n_posterior_samples, sample_seed, chains=config.mcmc_chains,
                                          steps=config.mcmc_steps, burn_in=config.mcmc_burn_in,
                                          de_fraction=config.mcmc_de_fraction, min_acceptance=config.min_acceptance)
        elif combine == "smc":
            draws = posterior.sample_smc(sample_seed, particles=config.smc_particles, moves=config.smc_moves,
                                         target_ess=config.smc_target_ess, inflate=config.smc_inflate,
                                         base=config.smc_base, independent_fraction=config.smc_independent_fraction,
                                         max_stages=config.smc_max_stages)
        else:
            draws = posterior.sample_is(config.n_posterior_samples, sample_seed, is_rounds=config.is_rounds,
                                        defensive_fraction=config.defensive_fraction)
    t_sample = time.perf_counter() - t1
    estimate = npe.point_estimate(draws, config.point_estimate, prior)
    extras = {"time_load": t_load, "time_sample": t_sample, "estimator_path": est.path,
              "training_simulations": est.training_simulations, "training_time": est.training_time,
              "space": config.space, "form": est.form, "sampler": draws.sampler}
    diag = draws.diagnostics
    if draws.sampler == "mcmc":
        extras.update({k: diag[k] for k in ("acceptance", "stuck_fraction", "chains", "steps", "burn_in",
                                            "step_scale")})
    elif draws.sampler == "smc":
        extras.update(ess=draws.ess, stages=len(diag["betas"]) - 1, acceptance=diag["acceptance"],
                      particles=diag["particles"], flow_calls=diag["flow_calls"])
    elif draws.sampler == "is":
        extras.update(ess=draws.ess, ess_rounds=list(diag["ess_rounds"]))
    status = draws.status(config.min_ess)
    if status != "ok" and est.form != "set":
        status = status.replace("fallback: ", f"fallback: combining {len(observations)} reaches: ", 1)
    weights = draws.weights.numpy() if draws.sampler in ("is", "smc") else None
    return PosteriorResult(method="npe-amortized", samples=draws.samples.numpy(), weights=weights, estimate=estimate,
                           n_simulations=0, wall_time=time.perf_counter() - t0, n_tasks=len(observations),
                           extras=extras, status=status)


# ----------------------------------------------------------------------------------- sbi diagnostics


def sbi_diagnostics(estimator: AmortizedEstimator, simulator, space: str, *, n: int = 500,
                    num_posterior_samples: int = 500, seed: int = 0) -> dict:
    """sbi's SBC (`run_sbc` + `check_sbc`) and TARP (`run_tarp` + `check_tarp`) of the per-reach posterior.

    The case where they apply: one amortized posterior q(theta | x) checked on ``n`` fresh
    (theta, x) pairs from the training distribution (theta ~ prior, goal ~ the design,
    noise as trained). Costs ``n`` simulations (reported as ``simulations``), uncounted by
    any budget. Returns SBC KS p-values and C2ST per free coordinate, C2ST of the
    data-averaged posterior vs the prior, TARP's ECP curve, ATC and KS p-value.
    """
    if not isinstance(estimator, AmortizedEstimator):
        raise TypeError(f"estimator: expected an AmortizedEstimator, got {type(estimator).__name__}")
    if space not in estimator.flows:
        raise ValueError(f"space: the estimator has flows for {list(estimator.flows)} only, not {space!r}")
    diff = fingerprint_differences(estimator.metadata["fingerprint"], model_fingerprint(simulator))
    if diff:
        raise ValueError(f"simulator: differs from the estimator's model in {', '.join(diff)}")
    n = check_positive_int(n, "n", minimum=10)
    sim = unwrap_simulator(simulator)
    n_sims = n * estimator.settings.reaches_per_theta
    prior = BoxPrior(sim.bounds, sim.start)
    settings = dataclasses.replace(estimator.settings, spaces=(space,))
    data = simulate_training_set(sim, prior, settings, seed_int(seed, 6), n=n_sims)
    keep = torch.tensor(estimator.metadata["features"][space]["keep"], dtype=torch.bool)
    x = data["x"][space][..., keep].float()
    if estimator.form == "set":  # sets of 1..max_set reaches, sizes drawn uniformly (seeded)
        gen = torch.Generator().manual_seed(seed_int(seed, 12))
        size = torch.randint(1, settings.max_set + 1, (x.shape[0], 1), generator=gen)
        valid = torch.arange(settings.max_set)[None] < size
        x = SetFlow.pack(x, valid)
    theta = data["theta"][:, prior.free_mask].float()
    post = estimator.single_reach_posterior(space)
    ranks, dap = sbi_adapter.run_sbc(theta, x, post, num_posterior_samples=num_posterior_samples,
                                     seed=seed_int(seed, 7))
    checks = sbi_adapter.check_sbc(ranks, prior.sample(n, seed_int(seed, 8))[:, prior.free_mask], dap,
                                   num_posterior_samples=num_posterior_samples, seed=seed_int(seed, 9))
    ecp, alpha = sbi_adapter.run_tarp(theta, x, post, num_posterior_samples=num_posterior_samples,
                                      seed=seed_int(seed, 10))
    atc, ks = sbi_adapter.check_tarp(ecp, alpha)
    return {"n": n, "simulations": n_sims, "form": estimator.form, "space": space, "num_posterior_samples": num_posterior_samples,
            "sbc_ks_pvals": checks["ks_pvals"], "sbc_c2st_ranks": checks["c2st_ranks"],
            "c2st_dap": checks["c2st_dap"][0], "tarp_ecp": ecp.tolist(), "tarp_alpha": alpha.tolist(),
            "tarp_atc": atc, "tarp_ks_pvalue": ks}
