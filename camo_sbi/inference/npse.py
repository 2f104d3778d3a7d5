"""Neural posterior score estimation (sbi ``NPSE``), one posterior per task, combined as NPE's flows.

Per task i a score network is trained by denoising score matching (``sde_type``: "ve", "vp" or
"subvp") on that task's ``budget`` prior simulations (in the prior box's logit coordinates z).
Its density q_i(z | x_i) and its draws both come from the probability-flow ODE (sbi's
``sample_with="ode"``; the SDE sampler's draws would not follow the density the importance
weights divide by). The tasks combine as per-task NPE's flows do (`npe_posterior.NpePosterior`).
A score model whose ODE density is NaN everywhere gives a ``failed`` result, never an exception.
Shared machinery: `sbi_family`.
"""

from __future__ import annotations

from dataclasses import dataclass

from camo_sbi._validation import check_choice
from camo_sbi.inference import sbi_family

__all__ = ["NpseConfig", "run", "run_sequence"]


@dataclass(frozen=True)
class NpseConfig(sbi_family.VectorFieldConfig):
    """`sbi_family.VectorFieldConfig` plus ``sde_type`` ("ve", sbi's default; "vp"; "subvp")."""

    sde_type: str = "ve"

    def __post_init__(self):
        super().__post_init__()
        check_choice(self.sde_type, ("ve", "vp", "subvp"), "sde_type")


def _train(z, x, x_obs, simulate, seed, config: NpseConfig, budget):  # noqa: ARG001 - single round
    return sbi_family.train_vector_field("npse", z, x, seed, config, sde_type=config.sde_type)


_ARGS = {"config_cls": NpseConfig, "train": _train, "kind": "posterior", "method": "npse"}


def run(task, observations, *, budget: int, seed: int, config: NpseConfig | None = None):
    """NPSE conditioned on every task in ``observations``, ``budget`` simulations per task."""
    return sbi_family.run(task, observations, budget=budget, seed=seed, config=config, **_ARGS)


def run_sequence(task, observations, *, budget: int, seed: int, config: NpseConfig | None = None):
    """Continual NPSE: the result after each of the first 1, ..., K tasks (each trained once)."""
    return sbi_family.run_sequence(task, observations, budget=budget, seed=seed, config=config, **_ARGS)
