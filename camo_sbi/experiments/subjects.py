"""Ground-truth subjects: named restricted-limit profiles for each model."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # imported where limits are built: the CLI's --help lists the profiles below
    import torch

__all__ = ["HUMAN_PROFILES", "INFORMATIVE_PROFILES", "ONE_JOINT", "PANDA_PROFILES", "PAPER_JOINT", "build_model", "subject_names",
           "subject_theta"]

# Panda profiles: {joint index: fraction of the range kept on each side of the start posture}.
# Restricting a joint to a fraction f keeps lo = s - f (s - L), hi = s + f (U - s).
PANDA_PROFILES: dict[str, dict[int, float]] = {
    "shoulder_restricted": {0: 0.3, 1: 0.35},
    "elbow_restricted": {2: 0.4, 3: 0.3},
    "wrist_restricted": {4: 0.3, 5: 0.3, 6: 0.3},
    "mixed_restricted": {0: 0.5, 1: 0.5, 3: 0.5, 5: 0.5},
}


ONE_JOINT = "one_joint_restricted"
"""The authors' ground truth: ONE restricted joint, start +- 0.5 rad, every other joint at its
full range (their shoulder roll [pi/2 - 0.5, pi/2 + 0.5] around the start pi/2)."""
PAPER_JOINT = {"panda": "panda_joint1", "human": "shoulder_flexion"}
"""The joint the one-joint subject restricts: the first joint of the arm (the authors' shoulder roll)."""
_ONE_JOINT_HALF_WIDTH = 0.5
HUMAN_PROFILES = ("frozen_shoulder", "elbow_flexion_contracture", "restricted_wrist", "hemiparesis_mild")
"""The names of `camo_sbi.simulators.human.IMPAIRED_PROFILES` (defined there, with their limits),
repeated here so that ``--help`` lists them without importing the model (torch);
``tests/test_cli.py`` checks that the two agree."""


INFORMATIVE_PROFILES: dict[str, dict[str, dict[int, float]]] = {
    "informative_shoulder": {"panda": PANDA_PROFILES["shoulder_restricted"], "human": {2: 0.3, 3: 0.3}},
    "informative_elbow": {"panda": PANDA_PROFILES["elbow_restricted"], "human": {5: 0.3}},
}
"""The subjects of ``reproduce panda --setting informative``, per model, with the fraction rule
of `PANDA_PROFILES`: each restricted bound, relaxed alone, moves >= 1 mm of about half or more
of the reaches to goals from the nominal workspace (measured on 40 goals, seed 1: Panda shoulder
0.55-0.68 per bound, elbow 0.57-0.72; human shoulder flexion+abduction 0.50-0.65, elbow 0.53-0.68;
every run reports its own ``binding_test_fraction``)."""


def _fraction_limits(sim, fractions: dict[int, float]):
    import torch

    b = sim.bounds.to(torch.float64)
    s = sim.start.to(torch.float64)
    lo, hi = b[:, 0].clone(), b[:, 1].clone()
    for j, f in fractions.items():
        lo[j] = s[j] - f * (s[j] - b[j, 0])
        hi[j] = s[j] + f * (b[j, 1] - s[j])
    return torch.stack([lo, hi], dim=1).reshape(-1)


def build_model(model: str):
    """The simulator called ``model`` ("panda" or "human")."""
    from camo_sbi.simulators import human, panda

    if model == "panda":
        return panda()
    if model == "human":
        return human()
    raise ValueError(f"model: expected 'panda' or 'human', got {model!r}")


def subject_names(model: str) -> list[str]:
    if model == "panda":
        return list(PANDA_PROFILES)
    if model == "human":
        from camo_sbi.simulators import IMPAIRED_PROFILES

        return list(IMPAIRED_PROFILES)
    raise ValueError(f"model: expected 'panda' or 'human', got {model!r}")


def subject_theta(sim, model: str, name: str) -> torch.Tensor:
    """(2n,) float64 true limits of subject ``name`` for ``model`` (``ONE_JOINT`` for either model)."""
    import torch

    if name == ONE_JOINT:
        if model not in PAPER_JOINT:
            raise ValueError(f"model: expected one of {sorted(PAPER_JOINT)}, got {model!r}")
        b, s = sim.bounds.to(torch.float64), sim.start.to(torch.float64)
        lim = b.clone()
        j = list(sim.joint_names).index(PAPER_JOINT[model])
        lim[j, 0] = max(float(b[j, 0]), float(s[j]) - _ONE_JOINT_HALF_WIDTH)
        lim[j, 1] = min(float(b[j, 1]), float(s[j]) + _ONE_JOINT_HALF_WIDTH)
        return lim.reshape(-1)
    if name in INFORMATIVE_PROFILES:
        if model not in INFORMATIVE_PROFILES[name]:
            raise ValueError(f"model: expected one of {sorted(INFORMATIVE_PROFILES[name])}, got {model!r}")
        return _fraction_limits(sim, INFORMATIVE_PROFILES[name][model])
    if model == "human":
        from camo_sbi.simulators import impaired_limits

        return torch.as_tensor(impaired_limits(sim, name), dtype=torch.float64)
    if name not in PANDA_PROFILES:
        raise ValueError(f"subject: unknown Panda profile {name!r}; known: {', '.join(PANDA_PROFILES)}")
    return _fraction_limits(sim, PANDA_PROFILES[name])
