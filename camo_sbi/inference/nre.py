"""Neural ratio estimation, NRE-C (sbi ``NRE_C``, Miller et al. 2022), one ratio per task, sampled by SMC.

Per task i a classifier is trained (contrastive, ``num_classes`` classes, ``gamma`` the odds of
the joint class) whose logit estimates log r_i(x, z) = log p(x | z) / p(x) up to a constant; the
posterior over all tasks is log p(z) + sum_i log r_i(x_i, z) (each task's evidence p(x_i) is a
constant), sampled by tempered SMC from the prior. Shared machinery: `sbi_family`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

from camo_sbi._validation import check_choice, check_positive_float, check_positive_int
from camo_sbi.inference import sbi_adapter, sbi_family

__all__ = ["NreConfig", "run", "run_sequence"]


@dataclass(frozen=True)
class NreConfig(sbi_family.FamilyConfig):
    """`sbi_family.FamilyConfig` plus the classifier: ``classifier`` ("linear", "mlp" or
    "resnet"), ``num_classes`` (K of NRE-C), ``gamma`` (odds of the joint class); sbi's NRE
    learning rate 5e-4 and batch 200 by default."""

    classifier: str = "resnet"
    num_classes: int = 5
    gamma: float = 1.0
    learning_rate: float = 5e-4
    training_batch_size: int = 200

    def __post_init__(self):
        super().__post_init__()
        check_choice(self.classifier, ("linear", "mlp", "resnet"), "classifier")
        check_positive_int(self.num_classes, "num_classes")
        check_positive_float(self.gamma, "gamma")


def _train(z, x, x_obs, simulate, seed, config: NreConfig, budget):  # noqa: ARG001 - single round
    est, info = sbi_adapter.train_nre(
        z, x, seed=seed, classifier=config.classifier, hidden_features=config.hidden_features,
        num_classes=config.num_classes, gamma=config.gamma, training_batch_size=config.training_batch_size,
        learning_rate=config.learning_rate, validation_fraction=config.validation_fraction,
        stop_after_epochs=config.stop_after_epochs, max_epochs=config.max_epochs, device=config.device)
    return functools.partial(sbi_adapter.nre_log_ratio, est), info


_ARGS = {"config_cls": NreConfig, "train": _train, "kind": "likelihood", "method": "nre"}


def run(task, observations, *, budget: int, seed: int, config: NreConfig | None = None):
    """NRE-C conditioned on every task in ``observations``, ``budget`` simulations per task."""
    return sbi_family.run(task, observations, budget=budget, seed=seed, config=config, **_ARGS)


def run_sequence(task, observations, *, budget: int, seed: int, config: NreConfig | None = None):
    """Continual NRE-C: the result after each of the first 1, ..., K tasks (each trained once)."""
    return sbi_family.run_sequence(task, observations, budget=budget, seed=seed, config=config, **_ARGS)
