"""Truncated sequential NPE (TSNPE, Deistler et al. 2022; sbi ``NPE_C`` with ``RestrictedPrior``).

Per task i, the ``budget`` simulations are spent in ``rounds`` rounds: the first on prior
draws, each later one on draws from the prior truncated to the current posterior's
highest-density region (all but ``quantile`` of its mass, `sbi_adapter.train_tsnpe`), the flow
q_i(z | x_i) retrained on everything so far. Truncation only removes prior mass the posterior
does not have, so q_i stays an estimate of the posterior under the full prior and the tasks
combine as per-task NPE's flows do, p(z)^(1-k) prod_i q_i(z | x_i) (`npe_posterior.NpePosterior`).
Sequential within a task, continual over tasks. Shared machinery: `sbi_family`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from camo_sbi._validation import (
    check_choice,
    check_positive_float,
    check_positive_int,
    check_workdir,
)
from camo_sbi.inference import npe, sbi_adapter, sbi_family

__all__ = ["TsnpeConfig", "run", "run_sequence"]


@dataclass(frozen=True)
class TsnpeConfig(sbi_family.FamilyConfig):
    """`sbi_family.FamilyConfig` plus the flow (``density_estimator``, ``num_transforms``) and the
    truncation: ``rounds`` (budget per task split evenly; the first round gets the remainder),
    ``quantile`` (posterior mass left out of the truncated region), ``support_samples``
    (posterior draws that set the threshold, and prior draws that measure its acceptance),
    ``min_acceptance`` (below it the truncated prior is drawn by SIR from the posterior instead
    of by rejection from the prior); ``workdir``: None, or a folder where each task's last-round
    flow is saved as soon as it is trained, so that a killed run resumes at its next task
    (`task_checkpoint`; same numbers, the earlier tasks' simulations and seconds still counted)."""

    density_estimator: str = "maf"
    num_transforms: int = 5
    rounds: int = 3
    quantile: float = 1e-4
    support_samples: int = 10000
    min_acceptance: float = 1e-3
    workdir: str | os.PathLike | None = None

    def __post_init__(self):
        super().__post_init__()
        check_choice(self.density_estimator, sbi_adapter.FLOW_KINDS, "density_estimator")
        check_positive_int(self.num_transforms, "num_transforms")
        check_positive_int(self.rounds, "rounds")
        check_positive_float(self.quantile, "quantile")
        if self.quantile >= 1:
            raise ValueError(f"quantile: must be in (0, 1), got {self.quantile}")
        check_positive_int(self.support_samples, "support_samples", minimum=100)
        check_positive_float(self.min_acceptance, "min_acceptance")
        check_workdir(self.workdir)


def _train(z, x, x_obs, simulate, seed, config: TsnpeConfig, budget):
    return sbi_adapter.train_tsnpe(
        z, x, x_obs, simulate, rounds=config.rounds, round_size=budget // config.rounds, seed=seed,
        quantile=config.quantile, support_samples=config.support_samples, min_acceptance=config.min_acceptance,
        density_estimator=config.density_estimator, hidden_features=config.hidden_features,
        num_transforms=config.num_transforms, training_batch_size=config.training_batch_size,
        learning_rate=config.learning_rate, validation_fraction=config.validation_fraction,
        stop_after_epochs=config.stop_after_epochs, max_epochs=config.max_epochs, device=config.device)


_CHECKPOINT = sbi_family.Checkpoint(module_of=lambda flow: flow, wrap=lambda flow: flow, build=npe.build_flow,
                                    architecture=npe.flow_architecture)
_ARGS = {"config_cls": TsnpeConfig, "train": _train, "kind": "posterior", "method": "tsnpe",
         "checkpoint": _CHECKPOINT}


def run(task, observations, *, budget: int, seed: int, config: TsnpeConfig | None = None):
    """TSNPE conditioned on every task in ``observations``, ``budget`` simulations per task."""
    return sbi_family.run(task, observations, budget=budget, seed=seed, config=config, **_ARGS)


def run_sequence(task, observations, *, budget: int, seed: int, config: TsnpeConfig | None = None):
    """Continual TSNPE: the result after each of the first 1, ..., K tasks (each task once)."""
    return sbi_family.run_sequence(task, observations, budget=budget, seed=seed, config=config, **_ARGS)
