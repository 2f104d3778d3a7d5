"""Flow-matching posterior estimation (sbi ``FMPE``), one posterior per task, combined as NPE's flows.

Per task i a conditional vector field is trained by flow matching on that task's ``budget``
prior simulations (in the prior box's logit coordinates z); its probability-flow ODE gives a
density q_i(z | x_i) and draws. The tasks combine as per-task NPE's flows do,
p(z)^(1-k) prod_i q_i(z | x_i) (`npe_posterior.NpePosterior`), sampled by adaptive importance
sampling from the mixture of the q_i. Shared machinery: `sbi_family`.
"""

from __future__ import annotations

from dataclasses import dataclass

from camo_sbi.inference import sbi_family

__all__ = ["FmpeConfig", "run", "run_sequence"]


@dataclass(frozen=True)
class FmpeConfig(sbi_family.VectorFieldConfig):
    """`sbi_family.VectorFieldConfig` as it is."""


def _train(z, x, x_obs, simulate, seed, config: FmpeConfig, budget):  # noqa: ARG001 - single round
    return sbi_family.train_vector_field("fmpe", z, x, seed, config)


_ARGS = {"config_cls": FmpeConfig, "train": _train, "kind": "posterior", "method": "fmpe"}


def run(task, observations, *, budget: int, seed: int, config: FmpeConfig | None = None):
    """FMPE conditioned on every task in ``observations``, ``budget`` simulations per task."""
    return sbi_family.run(task, observations, budget=budget, seed=seed, config=config, **_ARGS)


def run_sequence(task, observations, *, budget: int, seed: int, config: FmpeConfig | None = None):
    """Continual FMPE: the result after each of the first 1, ..., K tasks (each trained once)."""
    return sbi_family.run_sequence(task, observations, budget=budget, seed=seed, config=config, **_ARGS)
