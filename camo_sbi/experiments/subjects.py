"""Ground-truth subjects of the registered body models, for the studies.

The profiles themselves (the Panda's and the human's, the one-joint and the informative
subjects) are defined with the models in `camo_sbi.simulators.registry`; these are the
studies' names for reading them (a model registered there has its subjects here too).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from camo_sbi.simulators.registry import ONE_JOINT, get_model

if TYPE_CHECKING:
    import torch

__all__ = ["ONE_JOINT", "build_model", "informative_names", "subject_names", "subject_theta"]


def build_model(model: str):
    """The simulator called ``model`` (a registered name), with its default settings."""
    from camo_sbi.simulators import registry

    return registry.build_model(model)


def subject_names(model: str) -> list[str]:
    """The named profiles of ``model`` (ValueError naming ``model`` if it is not registered)."""
    return list(get_model(model).profiles)


def informative_names(model: str) -> list[str]:
    """The subjects of the informative design for ``model`` (empty if it has none)."""
    return list(get_model(model).informative)


def subject_theta(sim, model: str, name: str) -> torch.Tensor:
    """(2n,) float64 true limits of subject ``name`` of ``model``: a profile, ``ONE_JOINT`` (models
    with a paper joint) or an informative subject."""
    from camo_sbi.simulators import registry

    return registry.subject_theta(sim, model, name)
