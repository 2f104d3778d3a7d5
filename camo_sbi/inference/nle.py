"""Neural likelihood estimation (sbi ``NLE_A``), one likelihood per observed task, sampled by SMC.

Per task i a conditional flow q_i(x | z) of the summary given the limits (in the prior box's
logit coordinates z) is trained on that task's ``budget`` prior simulations; the posterior over
all tasks is log p(z) + sum_i log q_i(x_i | z) (independent tasks: exact if each q_i is), sampled
by tempered SMC from the prior. Shared machinery (simulation, summaries, combination, statuses,
continual use): `sbi_family`.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass

from camo_sbi._validation import check_choice, check_positive_int, check_workdir
from camo_sbi.inference import sbi_adapter, sbi_family

__all__ = ["NleConfig", "run", "run_sequence"]


@dataclass(frozen=True)
class NleConfig(sbi_family.FamilyConfig):
    """`sbi_family.FamilyConfig` plus the likelihood flow: ``density_estimator`` ("maf" or
    "nsf") and ``num_transforms``; ``workdir``: None, or a folder where each task's trained flow
    is saved as soon as it is trained, so that a killed run resumes at its next task
    (`task_checkpoint`; same numbers, the earlier tasks' simulations and seconds still counted)."""

    density_estimator: str = "maf"
    num_transforms: int = 5
    workdir: str | os.PathLike | None = None

    def __post_init__(self):
        super().__post_init__()
        check_choice(self.density_estimator, sbi_adapter.FLOW_KINDS, "density_estimator")
        check_positive_int(self.num_transforms, "num_transforms")
        check_workdir(self.workdir)


def _train(z, x, x_obs, simulate, seed, config: NleConfig, budget):  # noqa: ARG001 - single round
    est, info = sbi_adapter.train_nle(
        z, x, seed=seed, density_estimator=config.density_estimator, hidden_features=config.hidden_features,
        num_transforms=config.num_transforms, training_batch_size=config.training_batch_size,
        learning_rate=config.learning_rate, validation_fraction=config.validation_fraction,
        stop_after_epochs=config.stop_after_epochs, max_epochs=config.max_epochs, device=config.device)
    return _wrap(est), info


def _wrap(flow):
    """The likelihood term ``(x_obs, z) -> (N,)`` of a trained flow."""
    return functools.partial(sbi_adapter.nle_log_likelihood, flow)


def _build(n_free: int, n_x: int, architecture: dict):
    return sbi_adapter.new_nle_estimator(n_free, n_x, density_estimator=architecture["density_estimator"],
                                         hidden_features=int(architecture["hidden_features"]),
                                         num_transforms=int(architecture["num_transforms"]))


_CHECKPOINT = sbi_family.Checkpoint(
    module_of=lambda term: term.args[0], wrap=_wrap, build=_build,
    architecture=lambda c: {"density_estimator": c.density_estimator, "hidden_features": c.hidden_features,
                            "num_transforms": c.num_transforms})
_ARGS = {"config_cls": NleConfig, "train": _train, "kind": "likelihood", "method": "nle",
         "checkpoint": _CHECKPOINT}


def run(task, observations, *, budget: int, seed: int, config: NleConfig | None = None):
    """NLE conditioned on every task in ``observations``, ``budget`` simulations per task."""
    return sbi_family.run(task, observations, budget=budget, seed=seed, config=config, **_ARGS)


def run_sequence(task, observations, *, budget: int, seed: int, config: NleConfig | None = None):
    """Continual NLE: the result after each of the first 1, ..., K tasks (each trained once)."""
    return sbi_family.run_sequence(task, observations, budget=budget, seed=seed, config=config, **_ARGS)
