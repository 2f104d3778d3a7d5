"""Batched kinematic simulators behind one signature (see `base.Simulator`)."""

from camo_sbi.simulators.base import Simulator, Trajectories, limits_to_theta, theta_to_limits
from camo_sbi.simulators.controller import ControllerConfig
from camo_sbi.simulators.human import IMPAIRED_PROFILES, human, impaired_limits
from camo_sbi.simulators.panda import panda
from camo_sbi.simulators.simulator import KinematicSimulator, from_urdf, sample_goals

__all__ = [
    "ControllerConfig",
    "IMPAIRED_PROFILES",
    "KinematicSimulator",
    "Simulator",
    "Trajectories",
    "from_urdf",
    "human",
    "impaired_limits",
    "limits_to_theta",
    "panda",
    "sample_goals",
    "theta_to_limits",
]
