"""The Franka Emika Panda, from the URDF shipped inside the pybullet wheel (``pybullet_data``).

The file is located at run time (never copied): ``pybullet_data.getDataPath()/franka_panda/panda.urdf``.
Chain: ``panda_link0`` -> ``panda_grasptarget`` (the point between the fingertips,
10.5 cm beyond the hand flange), arm joints ``panda_joint1`` .. ``panda_joint7``;
the finger joints are not on the path.
"""

from __future__ import annotations

import os

from camo_sbi.simulators.simulator import KinematicSimulator, from_urdf

__all__ = ["PANDA_JOINTS", "PANDA_READY", "panda", "panda_urdf_path"]

PANDA_JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))
#: the usual "ready" posture (elbow bent, hand pointing down), inside the URDF limits
PANDA_READY = (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785)
END_EFFECTOR = "panda_grasptarget"


def panda_urdf_path() -> str:
    """Absolute path of panda.urdf inside the installed pybullet_data package."""
    import pybullet_data

    path = os.path.join(pybullet_data.getDataPath(), "franka_panda", "panda.urdf")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"panda.urdf not found at {path} (is pybullet installed?)")
    return path


def panda(**kwargs) -> KinematicSimulator:
    """The 7-DOF Panda arm, end effector ``panda_grasptarget``, start at `PANDA_READY`.

    Keyword arguments go to `from_urdf` (``start``, ``controller``, ``backend``, ...).
    """
    kwargs.setdefault("start", PANDA_READY)
    kwargs.setdefault("joints", PANDA_JOINTS)
    return from_urdf(panda_urdf_path(), END_EFFECTOR, **kwargs)
