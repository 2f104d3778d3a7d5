"""Amortized NPE: one flow per body model, trained once, for any person's reaches.

Two forms (`TrainConfig.form`):

- ``"set"`` (default): q(theta | {x_1..x_k}), k = 1..max_set reaches, one conditional flow
  behind a permutation-invariant set embedding (`_SetFlow`: mean, max and min of the
  standardised reach features and the mean of a per-reach MLP). Inference is ONE flow sample
  (`AmortizedEstimator.sample_set`), exact draws of the trained posterior, no combining.
- ``"per-reach"``: q(theta | x) for one reach, combined over a person's reaches by sbi's
  i.i.d. NPE rule and sampled by MCMC, SMC or importance sampling (``AmortizedConfig.combine``).

    est = train(simulator, model="panda", config=TrainConfig(simulations=200_000), seed=0)
    est.save("panda.pt");  est = load_estimator("panda.pt")
    run_method("npe-amortized", task, budget=1, seed=0, config={"estimator": "panda.pt"})

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
as per-task NPE does (`npe.summarize`: the valid part resampled at ``n_points`` times after
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
is the exact per-reach posterior), held by `npe.NpePosterior` (the same flow with N
conditions; its log target in the logit coordinates z, with the prior pushed to z as
standard logistic densities, serves every sampler). ``combine="mcmc"`` (default):
`npe.NpePosterior.sample_mcmc`, a population MCMC in z: 128 chains started from a Gaussian
approximation of the product, 300 sweeps (150 of adaptation, discarded), each half of the
population moved by random-walk Metropolis with the other half's covariance (or a
differential-evolution move), one batched flow call over half the chains x N reaches per
half-sweep; equally weighted draws (``weights`` None). An acceptance rate below
``min_acceptance`` or more than half of the chains never moving sets ``status =
"fallback: ..."``. ``combine="smc"``: `npe.NpePosterior.sample_smc`, tempered SMC from the
mixture of the N flows to the product (512 weighted particles, 2 Metropolis moves per
stage); a run that does not reach the product within its stage limit is a fallback.
``combine="is"``: the importance sampler of per-task NPE (`npe.NpePosterior.sample`); an
effective sample size below ``min_ess`` sets the fallback status (every fallback is warned
about by the registry).

Why the set form is the default, and what each form and sampler measured (calibration,
time per person, the per-reach samplers' failure to converge): `docs/studies/amortized_measurements.md`
and the README's "Amortized inference" section.

Why one module of ~1000 lines: training, the file format and its fingerprint check, and
inference are one estimator's life cycle; they share the metadata schema (a change to the
training settings changes what a file stores and what inference checks), so they change
together. The samplers themselves live in `npe` (`NpePosterior`), beside per-task NPE's
importance sampler.

**Files**: one ``torch.save`` dict {"format", "metadata" (JSON text), "state_dict"} read with
``torch.load(weights_only=True)``; the metadata (format version, model name and fingerprint:
joint names, bounds, start, URDF and controller; prior box; spaces; summary settings; noise;
feature masks; training cost; the sha256 of the payload, `payload_sha256`, verified before
anything is built) is checked against every task before use. Loading rebuilds each NSF as
`sbi_adapter.NsfReader` from the metadata and loads only its weights: no sbi import, the same
draws (MAF flows, sbi embedding nets and one-input flows are rebuilt through sbi).
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from camo_sbi._io import atomic_write_bytes
from camo_sbi._validation import (
    check_bool,
    check_choice,
    check_positive_float,
    check_positive_int,
)
from camo_sbi.budget import unwrap_simulator
from camo_sbi.inference import npe, sbi_adapter
from camo_sbi.inference.contract import check_run_args
from camo_sbi.inference.result import STATUS_OK, PosteriorResult
from camo_sbi.priors import BoxPrior
from camo_sbi.task import SPACES, NoiseModel

__all__ = [
    "AmortizedConfig",
    "AmortizedEstimator",
    "FAST_SET_TRAINING",
    "FORMAT",
    "TrainConfig",
    "load_estimator",
    "model_fingerprint",
    "payload_sha256",
    "run",
    "simulate_training_set",
    "train",
]

FORMAT = "camo_sbi.amortized/2"  # /2: the metadata carries the payload's sha256
_FORMAT_1 = "camo_sbi.amortized/1"
_DTYPES = {"float32": torch.float32, "float64": torch.float64}
FORMS = ("set", "per-reach")
COMBINE = ("mcmc", "is", "smc")  # samplers of the per-reach form's product posterior
_START_TOL = 1e-6  # radians: an observed start this close to the estimator's counts as the same
_BOX_TOL = 1e-9


# ----------------------------------------------------------------------------------- configs

# The optimiser settings a TrainConfig takes when they are left None, per form: for now the same
# for both. FAST_SET_TRAINING is the faster set-form alternative of
# benchmarks/bench_amortized_train.py (`camo-sbi amortize --fast`): it reaches the default's
# validation loss several times sooner but is more over-confident, so it is NOT the default
# (the numbers: README, "Measured performance"); on the per-reach MAF toy of
# tests/test_amortized.py it moved an upper limit 5.6 posterior sd off.
_OPTIMISER_DEFAULTS = {
    "set": {"training_batch_size": 512, "learning_rate": 1e-3, "lr_schedule": "constant", "max_epochs": 40},
    "per-reach": {"training_batch_size": 512, "learning_rate": 1e-3, "lr_schedule": "constant", "max_epochs": 40},
}
FAST_SET_TRAINING = {"training_batch_size": 2048, "learning_rate": 3e-3, "lr_schedule": "cosine", "max_epochs": 30}


@dataclass(frozen=True)
class TrainConfig:
    """How an amortized estimator is trained (all of it is stored in the file's metadata).

    Attributes:
        simulations: simulated reaches (one trajectory each).
        form: "set" (default: one flow q(theta | set of 1..max_set reaches) behind a
            permutation-invariant set embedding, `_SetFlow`; the simulations are max_set
            reaches of each of simulations // max_set limit vectors; inference is one flow
            sample) or "per-reach" (one flow q(theta | one reach), combined over a person's
            reaches by the i.i.d. rule and sampled by `AmortizedConfig.combine`). Measured on
            the Panda and the human at 200k simulations (README, "Amortized inference"): the
            set form is calibrated (mean |coverage - alpha| 0.016 and 0.017), the per-reach
            product is not (0.047 too wide from unconverged MCMC, 0.285 over-confident from SMC).
        max_set: the largest set of reaches the "set" form is trained on (and accepts).
        spaces: observation spaces to train a flow for ("joint", "cartesian" or both; the
            same simulations serve every space).
        noise: observation-noise model applied to the simulated trajectories (seeded).
        n_points, include_length: the trajectory summary (`npe.summarize`).
        density_estimator: "nsf" (default; sbi's neural spline flow, coupling layers: one pass
            per transform to sample) or "maf" (sbi's masked autoregressive flow: sampling takes
            one pass per coordinate and transform, ~4x slower here; and in nflows' MADE the
            first coordinate of each transform does not see the condition: on the 2-limit toy
            of the tests, with its seed and 3 transforms, one limit came out the same for every
            set of reaches, at its prior). The per-reach measurements were made with "maf".
        hidden_features, num_transforms: flow size.
        embedding_dim, embedding_hidden: None, or an MLP embedding of the condition (3 layers of
            ``embedding_hidden`` units, ``embedding_dim`` outputs) trained with the flow.
        training_batch_size, learning_rate, lr_schedule, validation_fraction, stop_after_epochs,
        max_epochs: maximum-likelihood training with early stopping (a batch holds
            ``training_batch_size`` reaches: for the set form that many // max_set sets;
            ``lr_schedule`` "cosine" lowers the rate along a half cosine over ``max_epochs``,
            "constant" keeps it). Left None, training_batch_size, learning_rate, lr_schedule
            and max_epochs take the form's defaults (`_OPTIMISER_DEFAULTS`: 512 reaches, 1e-3,
            constant, 40 epochs for both forms; 200 000 Panda simulations took 14.7 min, set
            form, NSF, fresh clone). ``FAST_SET_TRAINING`` (2048, 3e-3, cosine, 30 epochs)
            reaches the same validation loss sooner but calibrates worse
            (`benchmarks/bench_amortized_train.py`, README "Measured performance"), so it is
            an option (`amortize --fast`), not the default.
            `dataclasses.replace` keeps resolved values: replace ``form`` on a config built
            with the other form's defaults and they stay.
        max_train_seconds: per space, stop after the epoch that crosses it (None: no limit).
        simulation_batch_size: trajectories per ``simulate`` call.
        sim_dtype: "float32" or "float64" for the simulations.
        n_threads: torch intra-op threads while training (None: unchanged).
        balance: > 0 adds balanced NPE's penalty (Delaunoy et al. 2023) with this weight to
            the training loss (`sbi_adapter.fit_density_estimator`); 0 (default): plain
            maximum likelihood.
    """

    simulations: int = 200_000
    form: str = "set"
    max_set: int = 10
    spaces: tuple[str, ...] = ("joint",)
    noise: NoiseModel = field(default_factory=NoiseModel)
    n_points: int = 20
    include_length: bool = True
    density_estimator: str = "nsf"
    hidden_features: int = 64
    num_transforms: int = 5
    embedding_dim: int | None = None
    embedding_hidden: int = 128
    training_batch_size: int | None = None
    learning_rate: float | None = None
    validation_fraction: float = 0.05
    stop_after_epochs: int = 8
    max_epochs: int | None = None
    max_train_seconds: float | None = None
    simulation_batch_size: int = 10_000
    sim_dtype: str = "float32"
    n_threads: int | None = 1
    balance: float = 0.0
    lr_schedule: str | None = None

    def __post_init__(self):
        check_positive_int(self.simulations, "simulations", minimum=10)
        check_positive_float(self.balance, "balance", allow_zero=True)
        check_choice(self.form, FORMS, "form")
        for name, value in _OPTIMISER_DEFAULTS[self.form].items():  # None: the form's measured default
            if getattr(self, name) is None:
                object.__setattr__(self, name, value)
        check_choice(self.lr_schedule, sbi_adapter.LR_SCHEDULES, "lr_schedule")
        check_positive_int(self.max_set, "max_set", minimum=2)
        if self.form == "set" and self.simulations < 10 * self.max_set:
            raise ValueError(f"simulations: the set form needs at least {10 * self.max_set} (10 sets of "
                             f"max_set={self.max_set} reaches), got {self.simulations}")
        spaces = (self.spaces,) if isinstance(self.spaces, str) else tuple(self.spaces)
        if not spaces or len(set(spaces)) != len(spaces):
            raise ValueError(f"spaces: expected one or more distinct spaces of {SPACES}, got {self.spaces!r}")
        for s in spaces:
            check_choice(s, SPACES, "spaces")
        object.__setattr__(self, "spaces", spaces)
        if not isinstance(self.noise, NoiseModel):
            raise TypeError(f"noise: expected a NoiseModel, got {type(self.noise).__name__}")
        check_positive_int(self.n_points, "n_points")
        check_bool(self.include_length, "include_length")
        check_choice(self.density_estimator, sbi_adapter.FLOW_KINDS, "density_estimator")
        check_positive_int(self.hidden_features, "hidden_features")
        check_positive_int(self.num_transforms, "num_transforms")
        if self.embedding_dim is not None:
            check_positive_int(self.embedding_dim, "embedding_dim")
        check_positive_int(self.embedding_hidden, "embedding_hidden")
        npe.check_training_settings(self)
        if self.max_train_seconds is not None:
            check_positive_float(self.max_train_seconds, "max_train_seconds")
        check_positive_int(self.simulation_batch_size, "simulation_batch_size")
        check_choice(self.sim_dtype, _DTYPES, "sim_dtype")
        if self.n_threads is not None:
            check_positive_int(self.n_threads, "n_threads")

    @property
    def reaches_per_theta(self) -> int:
        """Simulated reaches per training limit vector: max_set for the set form, 1 per reach."""
        return self.max_set if self.form == "set" else 1

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["spaces"] = list(self.spaces)
        return d

    @classmethod
    def from_json(cls, d: dict) -> TrainConfig:
        d = dict(d)
        d["noise"] = NoiseModel(**d["noise"])
        d["spaces"] = tuple(d["spaces"])
        d.setdefault("balance", 0.0)  # files written before the setting existed
        d.setdefault("lr_schedule", "constant")
        return cls(**d)


@dataclass(frozen=True)
class AmortizedConfig:
    """npe-amortized settings at inference.

    Attributes:
        estimator: path of a trained estimator file (`train` + `AmortizedEstimator.save`, or
            ``camo-sbi amortize``). Required.
        space: the observation space read ("joint" or "cartesian"); the file must hold a flow
            for it.
        combine: how the per-reach form's product posterior is sampled; None (default): the
            estimator's own way, one flow sample for a set-form estimator and "mcmc" for a
            per-reach one. Giving it for a set-form estimator is a ValueError (nothing is
            combined there). "mcmc" (
            population MCMC, `npe.NpePosterior.sample_mcmc`, equally weighted draws), "smc"
            (tempered SMC, `npe.NpePosterior.sample_smc`, ``smc_particles`` weighted draws) or
            "is" (the importance sampler of `npe.NpePosterior.sample`, weighted draws). None of
            them converges on the Panda's 5-reach target within seconds; see the module
            docstring for what was measured and why MCMC stays the default.
        n_posterior_samples: draws returned by the set form's flow, MCMC (at most this many,
            mcmc_chains per kept sweep) and IS; SMC returns ``smc_particles``.
        is_rounds, defensive_fraction: the importance sampler (combine="is").
        mcmc_chains, mcmc_steps, mcmc_burn_in, mcmc_de_fraction: the population MCMC
            (combine="mcmc"): chains, sweeps, discarded adaptation sweeps, share of
            differential-evolution moves. Measured (Panda, `camo-sbi calibrate --subjects 50
            --tasks 5`, 2 loaded cores): 300 / 150 sweeps: mean |coverage - alpha| 0.047
            (under-confident), 5.5 s per subject; 100 / 50 sweeps: 0.079 (under-confident),
            2.0 s. The chains have not reached the target's typical set at 300 sweeps (see the
            module docstring): the draws are wide because they are unconverged.
        smc_particles, smc_moves, smc_target_ess, smc_inflate, smc_base,
            smc_independent_fraction, smc_max_stages: the tempered SMC (combine="smc"):
            particles; Metropolis moves per stage; the ESS share kept per stage; covariance
            inflation of the Gaussian proposals; base "mixture" (the N flows) or "gaussian"
            (the Gaussian product); share of independent Gaussian proposals among the moves;
            stages before the fallback. Measured (same setting): 2 moves 0.285
            (over-confident), ~0.6 s per person; 3 moves 0.266; 40 moves 0.229, ~15 s.
        min_acceptance: an MCMC acceptance rate below it (or more than half of the chains never
            moving after burn-in) sets ``status = "fallback: ..."``.
        point_estimate: "mean", "median" or "map" (`npe.point_estimate`).
        min_ess: an importance sample (combine="is") with a smaller effective sample size is
            reported as ``status = "fallback: ..."``.
        n_threads: torch intra-op threads while sampling (None: unchanged).
    """

    estimator: str | os.PathLike | None = None
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
        if self.estimator is not None and not isinstance(self.estimator, (str, os.PathLike)):
            raise TypeError(f"estimator: expected a path, got {type(self.estimator).__name__}")
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
        check_choice(self.point_estimate, ("mean", "median", "map"), "point_estimate")
        check_positive_float(self.min_ess, "min_ess", allow_zero=True)
        if self.n_threads is not None:
            check_positive_int(self.n_threads, "n_threads")


# ----------------------------------------------------------------------------------- model identity


def model_fingerprint(simulator) -> dict:
    """What identifies a body model: joint names, bounds, default start, URDF, end effector, controller."""
    sim = unwrap_simulator(simulator)
    cfg = getattr(sim, "config", None)
    if dataclasses.is_dataclass(cfg):
        cfg = {k: (v if isinstance(v, (int, float, str, bool)) or v is None else repr(v))
               for k, v in dataclasses.asdict(cfg).items()}
    elif cfg is not None:
        cfg = repr(cfg)
    urdf = getattr(sim, "urdf", "") or ""
    return {
        "joint_names": list(sim.joint_names),
        "bounds": torch.as_tensor(sim.bounds, dtype=torch.float64).tolist(),
        "start": torch.as_tensor(sim.start, dtype=torch.float64).tolist(),
        "urdf_sha256": hashlib.sha256(urdf.encode()).hexdigest(),
        "end_effector": getattr(sim, "end_effector", None),
        "controller": cfg,
        "max_steps": getattr(sim, "max_steps", None) or (cfg.get("max_steps") if isinstance(cfg, dict) else None),
    }


def _controller_defaults() -> dict:
    from camo_sbi.simulators.controller import ControllerConfig

    return {f.name: f.default for f in dataclasses.fields(ControllerConfig)
            if f.default is not dataclasses.MISSING and isinstance(f.default, (int, float, str, bool))}


def _fingerprint_differences(a: dict, b: dict) -> list[str]:
    """Fields of the current fingerprint ``b`` on which the stored fingerprint ``a`` differs.

    A controller setting that a stored file does not name did not exist when the file was
    written; it counts as that setting's default, which is the behaviour the controller had
    before the setting was added (``derivative_gain=0``, ``early_stop=True``).
    """
    out = []
    for k in sorted(b):
        va, vb = a.get(k), b.get(k)
        if k == "controller" and isinstance(va, dict) and isinstance(vb, dict):
            va = {**{n: d for n, d in _controller_defaults().items() if n in vb}, **va}
        if k in ("bounds", "start") and va is not None and vb is not None:
            ta, tb = torch.tensor(va, dtype=torch.float64), torch.tensor(vb, dtype=torch.float64)
            if ta.shape != tb.shape or not torch.allclose(ta, tb, atol=1e-9, rtol=0):
                out.append(k)
        elif va != vb:
            out.append(k)
    return out


# ----------------------------------------------------------------------------------- the flow


class _Flow(nn.Module):
    """An sbi flow q(z' | x') on standardised coordinates, exposed on raw ones.

    z' = (z - z_mean) / z_std, x' = (x - x_mean) / x_std (statistics of the training set,
    stored as buffers); ``log_prob`` includes the Jacobian of the z standardisation. Same
    interface as an sbi density estimator: ``log_prob(input, condition)``, ``sample(shape,
    condition)``, ``loss(input, condition)``.
    """

    def __init__(self, net: nn.Module, n_inputs: int, n_conditions: int):
        super().__init__()
        self.net = net
        self.register_buffer("z_mean", torch.zeros(n_inputs))
        self.register_buffer("z_std", torch.ones(n_inputs))
        self.register_buffer("x_mean", torch.zeros(n_conditions))
        self.register_buffer("x_std", torch.ones(n_conditions))

    def set_statistics(self, z: torch.Tensor, x: torch.Tensor) -> None:
        self.z_mean.copy_(z.mean(0))
        self.z_std.copy_(z.std(0).clamp_min(1e-6))
        self.x_mean.copy_(x.mean(0))
        self.x_std.copy_(x.std(0).clamp_min(1e-6))

    def _x(self, condition):
        return (condition.to(torch.float32) - self.x_mean) / self.x_std

    def log_prob(self, input, condition):  # noqa: A002 - sbi's argument name
        zs = (input.to(torch.float32) - self.z_mean) / self.z_std
        return self.net.log_prob(zs, self._x(condition)) - torch.log(self.z_std).sum()

    def loss(self, input, condition):  # noqa: A002
        return -self.log_prob(input, condition)

    def sample(self, sample_shape, condition):
        return self.net.sample(torch.Size(sample_shape), self._x(condition)) * self.z_std + self.z_mean


class _SetFlow(nn.Module):
    """q(z | {x_1..x_k}): a permutation-invariant set embedding feeding an sbi flow; trained jointly.

    The embedding of a set of k reaches (features standardised with stored statistics, x'):
    Linear([mean x', max x', min x', mean phi(x'), k / K]), with phi a per-reach MLP. The
    raw pooled features come first because a limit shows in the extreme postures over the
    reaches; a DeepSet of the MLP features alone (mean-pooled, the first design) learned
    nothing in 8 epochs at 200k Panda simulations (loss 28.3 nats, the prior's 28.0) and, on
    3000 sets, reached 27.9 where these pooled features reach 20.3
    (``benchmarks/ablate_set_embedding.py``).

    Conditions are packed as (B, K * (F + 1)): K = max_set reaches of F raw features, each
    followed by a validity flag (1: a reach of the set, 0: padding). In training mode ``loss``
    redraws every example's subset (size uniform on 1..K among its valid reaches) from the global
    torch RNG, which `sbi_adapter.fit_density_estimator` seeds inside ``fork_rng``: each epoch sees
    new sets. In eval mode (validation, inference) the stored flags are used.
    """

    def __init__(self, net: nn.Module, n_inputs: int, n_features: int, max_set: int, hidden: int = 128,
                 embed: int = 64):
        super().__init__()
        self.net, self.n_features, self.max_set = net, n_features, max_set
        self.phi = nn.Sequential(nn.Linear(n_features, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, embed))
        self.rho = nn.Linear(3 * n_features + embed + 1, embed)
        self.register_buffer("z_mean", torch.zeros(n_inputs))
        self.register_buffer("z_std", torch.ones(n_inputs))
        self.register_buffer("x_mean", torch.zeros(n_features))
        self.register_buffer("x_std", torch.ones(n_features))

    set_statistics = _Flow.set_statistics

    @staticmethod
    def pack(sets: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """(B, K, F) reaches and (B, K) bool validity -> (B, K * (F + 1)) float32 conditions."""
        return torch.cat([sets.to(torch.float32), valid.to(torch.float32).unsqueeze(-1)], -1).flatten(1)

    def _unpack(self, condition):
        c = condition.to(torch.float32).reshape(condition.shape[0], self.max_set, self.n_features + 1)
        return c[..., :-1], c[..., -1] > 0.5

    def embed(self, condition) -> torch.Tensor:
        sets, valid = self._unpack(condition)
        if self.training:  # a new random subset of each example's valid reaches
            k = torch.randint(1, self.max_set + 1, (sets.shape[0], 1))
            k = torch.minimum(k, valid.sum(1, keepdim=True))
            rank = torch.argsort(torch.argsort(torch.rand(valid.shape) + (~valid).float(), dim=1), dim=1)
            valid = rank < k
        xs = (sets - self.x_mean) / self.x_std
        v = valid.unsqueeze(-1)
        w = v.to(torch.float32)
        n = w.sum(1).clamp_min(1.0)
        pooled = [(xs * w).sum(1) / n, torch.where(v, xs, -1e4).amax(1), torch.where(v, xs, 1e4).amin(1),
                  (self.phi(xs) * w).sum(1) / n, w.sum(1) / self.max_set]
        return self.rho(torch.cat(pooled, -1))

    def log_prob(self, input, condition):  # noqa: A002
        zs = (input.to(torch.float32) - self.z_mean) / self.z_std
        return self.net.log_prob(zs, self.embed(condition)) - torch.log(self.z_std).sum()

    def loss(self, input, condition):  # noqa: A002
        return -self.log_prob(input, condition)

    def sample(self, sample_shape, condition):
        return self.net.sample(torch.Size(sample_shape), self.embed(condition)) * self.z_std + self.z_mean

    def sample_and_log_prob(self, sample_shape, condition):
        """Draws (raw z) and their log densities in one pass of the flow (sbi's
        ``sample_and_log_prob``; a MAF's inverse yields its log-determinant, so no second pass)."""
        zs, lp = self.net.sample_and_log_prob(torch.Size(sample_shape), self.embed(condition))
        return zs * self.z_std + self.z_mean, lp - torch.log(self.z_std).sum()


_SET_EMBED = 64
# the set embedding's architecture, written to a set-form file's metadata; files of an
# earlier (or later) embedding are refused with a message, never half-loaded
_SET_EMBEDDING = "pooled-mean-max-min-phi/1"


def _new_flow(settings: TrainConfig, n_inputs: int, n_conditions: int, seed: int, *,
              reader: bool = False) -> nn.Module:
    """The untrained flow of ``settings.form``; ``n_conditions``: features per reach.

    ``reader``: the NSF built as `sbi_adapter.NsfReader` (inference only, no sbi import; the
    weights must then be loaded), else sbi's trainable flow."""
    is_set = settings.form == "set"
    if reader:
        net = sbi_adapter.NsfReader(n_inputs, _SET_EMBED if is_set else n_conditions,
                                    hidden_features=settings.hidden_features,
                                    num_transforms=settings.num_transforms)
    else:
        net = sbi_adapter.build_flow(settings.density_estimator, n_inputs, _SET_EMBED if is_set else n_conditions,
                                     hidden_features=settings.hidden_features,
                                     num_transforms=settings.num_transforms,
                                     embedding_dim=None if is_set else settings.embedding_dim,
                                     embedding_hidden=settings.embedding_hidden, seed=seed)
    if not is_set:
        return _Flow(net, n_inputs, n_conditions)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed + 1)
        return _SetFlow(net, n_inputs, n_conditions, settings.max_set, settings.embedding_hidden, _SET_EMBED)


# ----------------------------------------------------------------------------------- summaries


def _conditions(traj: torch.Tensor, lengths: torch.Tensor, goals: torch.Tensor, settings: TrainConfig) -> torch.Tensor:
    """(B, 3 + summary) float64: the goal, then `npe.summarize` of the trajectory."""
    s = npe.summarize(traj, lengths, n_points=settings.n_points, include_length=settings.include_length)
    return torch.cat([torch.as_tensor(goals, dtype=torch.float64).reshape(-1, 3), s], dim=1)


def _seed(seed: int, *key: int) -> int:
    return int(np.random.SeedSequence(seed, spawn_key=key).generate_state(1, np.uint64)[0] >> np.uint64(1))


def design_goals(simulator, prior: BoxPrior, n: int, seed: int) -> torch.Tensor:
    """(n, 3) float64 training goals, independent of the training limits (see the module docstring):
    FK of configurations uniform inside the limits of independent prior draws."""
    sim = unwrap_simulator(simulator)
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(1,)))
    theta_goal = prior.sample(n, rng)
    u = torch.from_numpy(rng.random((n, sim.n_joints)))
    q = theta_goal[:, 0::2] + (theta_goal[:, 1::2] - theta_goal[:, 0::2]) * u
    return torch.cat([sim.forward_kinematics(q[s : s + 20000]).to(torch.float64)
                      for s in range(0, n, 20000)])


def simulate_training_set(simulator, prior: BoxPrior, settings: TrainConfig, seed: int, *,
                          n: int | None = None, progress: bool = False) -> dict:
    """Simulate ``n`` (default ``settings.simulations``) training triples; no count is charged.

    Returns {"theta": (n, 2n) float64, "x": {space: (n, D) float64 conditions},
    "time_simulate": seconds (FK of the goals + simulation + summaries)}. Seeded by ``seed``:
    limits, goals and noise come from independent streams. The "set" form simulates
    ``max_set`` reaches (independent goals) of each of n // max_set limit vectors: "theta" is
    (n // max_set, 2n) and "x" (n // max_set, max_set, D).
    """
    from tqdm import tqdm

    sim = unwrap_simulator(simulator)
    n = settings.simulations if n is None else check_positive_int(n, "n")
    r = settings.reaches_per_theta
    m = n // r
    n = m * r
    t0 = time.perf_counter()
    theta_m = prior.sample(m, np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0,))))
    theta = theta_m.repeat_interleave(r, dim=0)
    goals = design_goals(sim, prior, n, seed)
    start = torch.as_tensor(sim.start, dtype=torch.float64)
    noise_gen = torch.Generator().manual_seed(_seed(seed, 2))
    dtype = _DTYPES[settings.sim_dtype]
    parts = {s: [] for s in settings.spaces}
    b = settings.simulation_batch_size
    for s in tqdm(range(0, n, b), desc="simulating", unit="batch", disable=not progress, leave=False):
        out = sim.simulate(theta[s : s + b].to(dtype), goals[s : s + b].to(dtype), start.to(dtype))
        for space in settings.spaces:
            traj = out.q if space == "joint" else out.ee
            traj = settings.noise.perturb(traj.to(torch.float64), space, noise_gen)
            parts[space].append(_conditions(traj, out.length, goals[s : s + b], settings))
    x = {k: torch.cat(v) for k, v in parts.items()}
    if r > 1:
        x = {k: v.reshape(m, r, -1) for k, v in x.items()}
    return {"theta": theta_m, "x": x, "time_simulate": time.perf_counter() - t0}


# ----------------------------------------------------------------------------------- the estimator


class AmortizedEstimator:
    """Per-reach flows q(theta | goal, trajectory) for one body model, one per space.

    Build with `train`, reload with `load_estimator`. ``metadata`` holds everything needed
    to check a task against it and to rebuild the flows; ``flows`` maps a space to its flow.
    """

    def __init__(self, metadata: dict, flows: dict[str, _Flow]):
        self.metadata = metadata
        self.flows = {k: f.eval() for k, f in flows.items()}
        self.settings = TrainConfig.from_json(metadata["settings"])
        self.low = torch.tensor(metadata["prior"]["low"], dtype=torch.float64)
        self.high = torch.tensor(metadata["prior"]["high"], dtype=torch.float64)
        self.free_mask = self.high > self.low
        self.start = torch.tensor(metadata["fingerprint"]["start"], dtype=torch.float64)
        self.noise = NoiseModel(**metadata["settings"]["noise"])
        self.path: str | None = None

    @property
    def model(self) -> str:
        return self.metadata["model"]

    @property
    def spaces(self) -> tuple[str, ...]:
        return tuple(self.flows)

    @property
    def training_simulations(self) -> int:
        return int(self.metadata["training_simulations"])

    @property
    def training_time(self) -> float:
        return float(self.metadata["training_time"])

    # -- use

    def check_task(self, task, observations, space: str) -> None:
        """ValueError (naming what differs) unless ``task`` is one this estimator was trained for."""
        name = self.path or "the estimator"
        if space not in self.flows:
            raise ValueError(f"space: {name} has flows for {list(self.flows)} only, not {space!r}; "
                             f"train one with --space {space}")
        diff = _fingerprint_differences(self.metadata["fingerprint"], model_fingerprint(task.simulator))
        if diff:
            raise ValueError(f"estimator: {name} was trained for model {self.model!r}; the task's simulator "
                             f"differs in {', '.join(diff)}")
        prior = task.prior
        if (prior.low.shape != self.low.shape or not torch.allclose(prior.low, self.low, atol=_BOX_TOL, rtol=0)
                or not torch.allclose(prior.high, self.high, atol=_BOX_TOL, rtol=0)):
            raise ValueError(f"task.prior: differs from the prior {name} was trained under (the model's full "
                             f"range split at its default start, no fixed joints); retrain for this prior")
        for i, o in enumerate(observations):
            if not torch.allclose(o.start, self.start, atol=_START_TOL, rtol=0):
                raise ValueError(f"observations: reach {i} starts at {o.start.tolist()}, but {name} was trained "
                                 f"for reaches from the model's default start {self.start.tolist()}")
        if task.noise != self.noise:
            raise ValueError(f"task.noise: the task's observation noise {task.noise} differs from the noise "
                             f"{name} was trained with ({self.noise}); retrain with --noise-joint-deg / "
                             f"--noise-ee-mm matching the recordings")
        if self.form == "set":
            self._check_set_size(len(observations))

    def _check_set_size(self, n: int) -> None:
        k = self.settings.max_set
        if n > k:
            raise ValueError(f"observations: {n} reaches, but the set estimator {self.path or ''} was "
                             f"trained on sets of at most max_set={k}; pass at most {k} or retrain")

    def conditions(self, observations, space: str) -> torch.Tensor:
        """(N, D) float32 network conditions of observed reaches (kept features only)."""
        keep = torch.tensor(self.metadata["features"][space]["keep"], dtype=torch.bool)
        rows = []
        for o in observations:
            traj = o.trajectory(space).to(torch.float64)
            rows.append(_conditions(traj, torch.tensor([traj.shape[0]]), o.goal, self.settings)[0, keep])
        return torch.stack(rows).float()

    @property
    def form(self) -> str:
        return self.settings.form

    def set_condition(self, observations, space: str) -> torch.Tensor:
        """(1, K * (F + 1)) the packed set condition of 1..max_set observed reaches (set form)."""
        x = self.conditions(observations, space)
        k = self.settings.max_set
        self._check_set_size(x.shape[0])
        sets = torch.zeros(1, k, x.shape[1])
        sets[0, : x.shape[0]] = x
        valid = torch.arange(k)[None] < x.shape[0]
        return _SetFlow.pack(sets, valid)

    @torch.no_grad()
    def sample_set(self, observations, space: str, n: int, seed: int, *, n_threads: int | None = 1):
        """(n, 2n) float64 draws of q(theta | the set of reaches) and their log densities (theta coordinates)."""
        flow = self.flows[space]
        lo, w = self.low[self.free_mask], (self.high - self.low)[self.free_mask]
        # everything under n_threads: small element-wise ops on the default threads cost up to
        # 100x more on a busy machine (measured: logsigmoid of (1000, 14) 49 ms vs 0.07 ms)
        with torch.random.fork_rng(devices=[]), npe.torch_threads(n_threads):
            cond = self.set_condition(observations, space)
            torch.manual_seed(seed)
            z, lp = flow.sample_and_log_prob((n,), cond)
            z, lp = z.reshape(n, -1), lp.reshape(-1).double()
            free, logdet = npe.from_unconstrained(z, lo, w, "logit")
            theta = self.low.repeat(n, 1)
            theta[:, self.free_mask] = free
            return theta, lp - logdet

    def posterior(self, observations, space: str, *, n_threads: int | None = 1) -> npe.NpePosterior:
        """The combined posterior of the reaches (`npe.NpePosterior`, the same flow N times)."""
        x = self.conditions(observations, space)
        flow = self.flows[space]
        return npe.NpePosterior([flow] * x.shape[0], list(x), self.low, self.high,
                                theta_transform="logit",
                                n_threads=n_threads, info={"estimator": self.path, "space": space})

    def single_reach_posterior(self, space: str, *, chunk: int = 256) -> _SingleReach:
        """q(theta_free | x) for batches of raw conditions: sbi's ``sample_batched`` interface."""
        return _SingleReach(self, space, chunk)

    # -- persistence

    def to_bytes(self) -> bytes:
        state = {f"{space}.{k}": v.detach().cpu().clone() for space, f in self.flows.items()
                 for k, v in f.state_dict().items()}
        metadata = {**self.metadata, "sha256": payload_sha256(self.metadata, state)}
        buf = io.BytesIO()
        torch.save({"format": FORMAT, "metadata": json.dumps(metadata, sort_keys=True),
                    "state_dict": state}, buf)
        return buf.getvalue()

    def save(self, path) -> Path:
        """Write the estimator atomically to ``path`` (state dict + JSON metadata in one file)."""
        path = Path(path)
        atomic_write_bytes(path, self.to_bytes())
        return path

    def describe(self) -> str:
        m = self.metadata
        form = (f"set form (sets of 1..{self.settings.max_set} reaches)" if self.form == "set"
                else "per-reach form (combined by the i.i.d. rule)")
        lines = [f"amortized estimator for model {m['model']!r}: {form}, {self.settings.density_estimator} flow, "
                 f"spaces {', '.join(self.flows)}, {m['training_simulations']} training simulations, "
                 f"{m['training_time']:.1f} s to train",
                 f"  noise: {self.noise}; summary: {self.settings.n_points} points + length, goal prepended"]
        for space, info in m["training"].items():
            lines.append(f"  {space}: {m['features'][space]['n_kept']} features, {info['epochs']} epochs "
                         f"({info['stopped']}), best validation loss {info['best_validation_loss']:.3f}, "
                         f"{info['time_train']:.1f} s")
        return "\n".join(lines)


class _SingleReach:
    """sbi-style posterior of ONE condition row (one reach, or one packed set for the set form):
    ``sample_batched((n,), x)`` -> (n, B, n_free) theta draws."""

    def __init__(self, est: AmortizedEstimator, space: str, chunk: int):
        self._flow = est.flows[space]
        self._lo = est.low[est.free_mask]
        self._w = (est.high - est.low)[est.free_mask]
        self._chunk = chunk

    @torch.no_grad()
    def sample_batched(self, sample_shape, x, show_progress_bars: bool = False, **kwargs):
        n = int(torch.Size(sample_shape).numel())
        x = torch.as_tensor(x, dtype=torch.float32)
        out = []
        for s in range(0, x.shape[0], self._chunk):
            z = self._flow.sample((n,), x[s : s + self._chunk]).to(torch.float64)
            out.append(npe.from_unconstrained(z.reshape(-1, z.shape[-1]), self._lo, self._w,
                                              "logit")[0].reshape(z.shape))
        return torch.cat(out, dim=1).float()


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
    z = npe.to_unconstrained(data["theta"][:, prior.free_mask], lo, w, "logit").float()
    flows, features, training = {}, {}, {}
    for k, space in enumerate(config.spaces):
        x = data["x"][space]
        reaches = x.reshape(-1, x.shape[-1])
        finite = torch.isfinite(x).reshape(x.shape[0], -1).all(dim=1)
        fr = torch.isfinite(reaches).all(dim=1)
        keep = reaches[fr].std(dim=0) > 1e-8 * (1.0 + reaches[fr].abs().amax(dim=0))
        flow = _new_flow(config, z.shape[1], int(keep.sum()), _seed(seed, 3, k))
        flow.set_statistics(z[finite], reaches[fr][:, keep].float())
        if config.form == "set":
            sets = x[finite][..., keep]
            gen = torch.Generator().manual_seed(_seed(seed, 11, k))
            size = torch.randint(1, config.max_set + 1, (sets.shape[0], 1), generator=gen)
            valid = torch.argsort(torch.rand(sets.shape[:2], generator=gen), dim=1).argsort(dim=1) < size
            xk = _SetFlow.pack(sets, valid)  # stored flags: the validation sets; training redraws them
        else:
            xk = x[finite][:, keep].float()
        with npe.torch_threads(config.n_threads):
            info = sbi_adapter.fit_density_estimator(
                flow, z[finite], xk, seed=_seed(seed, 4, k),
                batch_size=max(2, config.training_batch_size // config.reaches_per_theta),
                learning_rate=config.learning_rate, validation_fraction=config.validation_fraction,
                stop_after_epochs=config.stop_after_epochs, max_epochs=config.max_epochs,
                max_seconds=config.max_train_seconds, progress=progress, desc=f"training {space}",
                balance=config.balance, prior_log_prob=npe.logistic_log_prob, lr_schedule=config.lr_schedule)
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
        **({"set_embedding": _SET_EMBEDDING} if config.form == "set" else {}),
        "time_simulate": data["time_simulate"],
        "training_time": total,
        "versions": {"camo_sbi": version("camo_sbi"), "torch": torch.__version__,
                     "sbi": ".".join(map(str, sbi_adapter.sbi_version()))},
    }
    return AmortizedEstimator(metadata, flows)


def payload_sha256(metadata: dict, state: dict) -> str:
    """sha256 of an estimator file's payload: its metadata (without the "sha256" entry, as sorted
    JSON) and every tensor of its state dict (key, dtype, shape and raw bytes, in key order)."""
    h = hashlib.sha256(json.dumps({k: v for k, v in metadata.items() if k != "sha256"}, sort_keys=True).encode())
    for key in sorted(state):
        t = state[key].detach().cpu().contiguous()
        h.update(f"\n{key}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def _uses_reader(settings: TrainConfig, n_inputs: int) -> bool:
    """Whether a loaded flow is evaluated by `sbi_adapter.NsfReader`: an NSF of 2+ inputs (sbi builds
    a one-input NSF differently) without an sbi embedding net."""
    return (settings.density_estimator == "nsf" and n_inputs > 1
            and (settings.form == "set" or settings.embedding_dim is None))


def from_bytes(data: bytes, name: str = "estimator") -> AmortizedEstimator:
    """Rebuild an estimator from `AmortizedEstimator.to_bytes` (``torch.load(weights_only=True)``).

    The payload's sha256 (`payload_sha256`, stored in the metadata) is verified before anything
    is built: a damaged or edited file is a ValueError naming it. NSF flows are rebuilt as
    `sbi_adapter.NsfReader` (same weights, same draws, no sbi import); others through sbi.
    """
    try:
        blob = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling error means "not our file"
        raise ValueError(f"estimator: {name} is not a camo_sbi amortized estimator or is damaged "
                         f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from exc
    if not isinstance(blob, dict) or blob.get("format") not in (FORMAT, _FORMAT_1):
        found = blob.get("format") if isinstance(blob, dict) else type(blob).__name__
        raise ValueError(f"estimator: {name} has format {found!r}, expected {FORMAT!r} (retrain it with this "
                         f"version of camo_sbi)")
    missing = [k for k in ("metadata", "state_dict") if k not in blob]
    if missing or not isinstance(blob["metadata"], str) or not isinstance(blob["state_dict"], dict):
        raise ValueError(f"estimator: {name} has no valid {' or '.join(missing) or 'metadata and state_dict'} "
                         f"entry (damaged, or not written by `camo-sbi amortize`)")
    if blob["format"] == _FORMAT_1:
        raise ValueError(f"estimator: {name} has format {_FORMAT_1!r}, written before estimator files carried a "
                         f"checksum; retrain it with `camo-sbi amortize` (format {FORMAT!r})")
    try:
        meta = json.loads(blob["metadata"])
    except ValueError as exc:
        raise ValueError(f"estimator: {name}'s metadata is not valid JSON (damaged file)") from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        found = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise ValueError(f"estimator: {name}'s metadata has format {found!r}, expected {FORMAT!r}")
    stored = meta.get("sha256")
    if not isinstance(stored, str) or stored != payload_sha256(meta, blob["state_dict"]):
        raise ValueError(f"estimator: {name} fails its sha256 check (stored {str(stored)[:12]}..., the payload "
                         f"differs): the file is damaged or was edited; retrain it or restore a copy")
    settings = TrainConfig.from_json(meta["settings"])
    if settings.form == "set" and meta.get("set_embedding") != _SET_EMBEDDING:
        raise ValueError(f"estimator: {name} is a set-form estimator with set embedding "
                         f"{meta.get('set_embedding', 'the first, experimental DeepSet')!r}, this version reads "
                         f"{_SET_EMBEDDING!r} only; retrain it with `camo-sbi amortize`")
    n_in = int(sum(1 for lo, hi in zip(meta["prior"]["low"], meta["prior"]["high"], strict=True) if hi > lo))
    flows = {}
    for k, space in enumerate(settings.spaces):
        prefix = f"{space}."
        state = {key[len(prefix):]: v for key, v in blob["state_dict"].items() if key.startswith(prefix)}
        flow = _new_flow(settings, n_in, meta["features"][space]["n_kept"], _seed(meta["seed"], 3, k),
                         reader=_uses_reader(settings, n_in))
        try:
            flow.load_state_dict(state, strict=True)
        except RuntimeError as exc:
            raise ValueError(f"estimator: {name}'s {space} weights do not fit its metadata ({exc})") from exc
        flows[space] = flow
    return AmortizedEstimator(meta, flows)


_CACHE: dict[tuple, AmortizedEstimator] = {}


def load_estimator(path) -> AmortizedEstimator:
    """Load an estimator file (cached per process by path, size and modification time)."""
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"estimator: expected a path, got {type(path).__name__}")
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"estimator: no such file {str(p)!r} (train one with `camo-sbi amortize`)")
    st = p.stat()
    key = (str(p.resolve()), st.st_size, st.st_mtime_ns)
    if key not in _CACHE:
        est = from_bytes(p.read_bytes(), repr(str(p)))
        est.path = str(p)
        _CACHE.clear()  # one estimator at a time is what every caller needs
        _CACHE[key] = est
    return _CACHE[key]


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
    if config.estimator is None:
        raise ValueError("estimator: npe-amortized needs a trained estimator file, config={'estimator': FILE}; "
                         "train one with `camo-sbi amortize --model M --out FILE`")
    est = load_estimator(config.estimator)
    t_load = time.perf_counter() - t0
    est.check_task(task, observations, config.space)
    if est.form == "set" and config.combine is not None:
        raise ValueError(f"combine: {config.combine!r} applies to per-reach estimators; {est.path or 'this'} is a "
                         f"set-form estimator, sampled directly (leave combine unset)")
    combine = config.combine or "mcmc"
    t1 = time.perf_counter()
    if est.form == "set":
        theta, lp = est.sample_set(observations, config.space, config.n_posterior_samples, _seed(seed, 5) % (2**32),
                                   n_threads=config.n_threads)
        n = theta.shape[0]
        draws = npe.ImportanceSample(theta.numpy(), np.full(n, 1.0 / n), lp.numpy(), float(n), [float(n)])
    else:
        posterior = est.posterior(observations, config.space, n_threads=config.n_threads)
        if combine == "mcmc":
            draws = posterior.sample_mcmc(config.n_posterior_samples, _seed(seed, 5) % (2**32),
                                          chains=config.mcmc_chains, steps=config.mcmc_steps,
                                          burn_in=config.mcmc_burn_in, de_fraction=config.mcmc_de_fraction)
        elif combine == "smc":
            draws = posterior.sample_smc(_seed(seed, 5) % (2**32), particles=config.smc_particles,
                                         moves=config.smc_moves, target_ess=config.smc_target_ess,
                                         inflate=config.smc_inflate, base=config.smc_base,
                                         independent_fraction=config.smc_independent_fraction,
                                         max_stages=config.smc_max_stages)
        else:
            draws = posterior.sample_is(config.n_posterior_samples, _seed(seed, 5) % (2**32),
                                     is_rounds=config.is_rounds, defensive_fraction=config.defensive_fraction)
    t_sample = time.perf_counter() - t1
    estimate = npe.point_estimate(draws, config.point_estimate, prior)
    status = STATUS_OK
    extras = {"time_load": t_load, "time_sample": t_sample, "estimator_path": est.path,
              "training_simulations": est.training_simulations, "training_time": est.training_time,
              "space": config.space, "form": est.form}
    weights = None
    if est.form == "set":
        extras["sampler"] = "flow"
    elif combine == "mcmc":
        extras.update(sampler="mcmc", acceptance=draws.acceptance, stuck_fraction=draws.stuck_fraction,
                      chains=draws.chains, steps=draws.steps, burn_in=draws.burn_in, step_scale=draws.step_scale)
        if not draws.acceptance >= config.min_acceptance or draws.stuck_fraction > 0.5:
            status = (f"fallback: MCMC combining {len(observations)} reaches barely moved (acceptance "
                      f"{draws.acceptance:.4f}, min_acceptance {config.min_acceptance:g}; "
                      f"{draws.stuck_fraction:.0%} of {draws.chains} chains never moved after burn-in)")
    elif combine == "smc":
        extras.update(sampler="smc", ess=draws.ess, stages=len(draws.betas) - 1, acceptance=draws.acceptance,
                      particles=draws.particles, flow_calls=draws.flow_calls)
        weights = draws.weights
        if not draws.reached or not draws.ess >= config.min_ess:
            status = (f"fallback: SMC combining {len(observations)} reaches did not reach the posterior "
                      f"({len(draws.betas) - 1} stages, final ESS {draws.ess:.1f} of {draws.particles})")
    else:
        extras.update(sampler="is", ess=draws.ess, ess_rounds=draws.ess_rounds)
        weights = draws.weights
        if not draws.ess >= config.min_ess or not math.isfinite(draws.ess):
            status = (f"fallback: degenerate importance weights combining {len(observations)} reaches (ESS "
                      f"{draws.ess:.1f} of {config.n_posterior_samples} < min_ess {config.min_ess:g})")
    return PosteriorResult(method="npe-amortized", samples=draws.theta, weights=weights, estimate=estimate,
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
    diff = _fingerprint_differences(estimator.metadata["fingerprint"], model_fingerprint(simulator))
    if diff:
        raise ValueError(f"simulator: differs from the estimator's model in {', '.join(diff)}")
    n = check_positive_int(n, "n", minimum=10)
    sim = unwrap_simulator(simulator)
    n_sims = n * estimator.settings.reaches_per_theta
    prior = BoxPrior(sim.bounds, sim.start)
    settings = dataclasses.replace(estimator.settings, spaces=(space,))
    data = simulate_training_set(sim, prior, settings, _seed(seed, 6), n=n_sims)
    keep = torch.tensor(estimator.metadata["features"][space]["keep"], dtype=torch.bool)
    x = data["x"][space][..., keep].float()
    if estimator.form == "set":  # sets of 1..max_set reaches, sizes drawn uniformly (seeded)
        gen = torch.Generator().manual_seed(_seed(seed, 12))
        size = torch.randint(1, settings.max_set + 1, (x.shape[0], 1), generator=gen)
        valid = torch.arange(settings.max_set)[None] < size
        x = _SetFlow.pack(x, valid)
    theta = data["theta"][:, prior.free_mask].float()
    post = estimator.single_reach_posterior(space)
    ranks, dap = sbi_adapter.run_sbc(theta, x, post, num_posterior_samples=num_posterior_samples,
                                     seed=_seed(seed, 7))
    checks = sbi_adapter.check_sbc(ranks, prior.sample(n, _seed(seed, 8))[:, prior.free_mask], dap,
                                   num_posterior_samples=num_posterior_samples, seed=_seed(seed, 9))
    ecp, alpha = sbi_adapter.run_tarp(theta, x, post, num_posterior_samples=num_posterior_samples,
                                      seed=_seed(seed, 10))
    atc, ks = sbi_adapter.check_tarp(ecp, alpha)
    return {"n": n, "simulations": n_sims, "form": estimator.form, "space": space, "num_posterior_samples": num_posterior_samples,
            "sbc_ks_pvals": checks["ks_pvals"], "sbc_c2st_ranks": checks["c2st_ranks"],
            "c2st_dap": checks["c2st_dap"][0], "tarp_ecp": ecp.tolist(), "tarp_alpha": alpha.tolist(),
            "tarp_atc": atc, "tarp_ks_pvalue": ks}
