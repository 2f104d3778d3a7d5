"""Reusable check: a simulator's FK (pk reference and generated kernel) against PyBullet.

Usage from any test module::

    from tests._fk_check import assert_fk_matches_pybullet
    assert_fk_matches_pybullet(sim, n=100, seed=0)
"""

from __future__ import annotations

import os
import tempfile
import xml.etree.ElementTree as ET

import numpy as np
import torch

__all__ = ["assert_fk_matches_pybullet", "pybullet_fk"]


def _kinematics_only(urdf: str) -> str:
    """URDF text without <visual>/<collision> (mesh files need not exist for FK)."""
    root = ET.fromstring(urdf)
    for link in root.iter("link"):
        for tag in ("visual", "collision"):
            for el in link.findall(tag):
                link.remove(el)
    return ET.tostring(root, encoding="unicode")


def pybullet_fk(sim, q: np.ndarray) -> np.ndarray:
    """End-effector link-frame positions (B, 3) in the chain's base-link frame, from PyBullet.

    Uses a DIRECT client of its own (never the global default client) and
    ``getLinkState(..., computeForwardKinematics=True)[4]`` (worldLinkFramePosition, the
    URDF link frame, not the inertial frame). Joints not actuated by ``sim`` stay at 0.
    """
    import pybullet as p

    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "model.urdf")
        with open(path, "w") as fh:
            fh.write(_kinematics_only(sim.urdf))
        cid = p.connect(p.DIRECT)
        try:
            body = p.loadURDF(path, [0, 0, 0], [0, 0, 0, 1], useFixedBase=True, physicsClientId=cid)
            joint_index, link_index = {}, {}
            for i in range(p.getNumJoints(body, physicsClientId=cid)):
                info = p.getJointInfo(body, i, physicsClientId=cid)
                joint_index[info[1].decode()] = i
                link_index[info[12].decode()] = i
            idx = [joint_index[name] for name in sim.joint_names]
            ee = link_index[sim.end_effector]
            base = sim.spec.base_link
            out = np.empty((q.shape[0], 3))
            for b in range(q.shape[0]):
                for j, v in zip(idx, q[b], strict=True):
                    p.resetJointState(body, j, float(v), physicsClientId=cid)
                pos = np.array(p.getLinkState(body, ee, computeForwardKinematics=True, physicsClientId=cid)[4])
                if base in link_index:  # chain rooted below the URDF root: express in its frame
                    st = p.getLinkState(body, link_index[base], computeForwardKinematics=True, physicsClientId=cid)
                    R = np.array(p.getMatrixFromQuaternion(st[5], physicsClientId=cid)).reshape(3, 3)
                    pos = R.T @ (pos - np.array(st[4]))
                out[b] = pos
        finally:
            p.disconnect(physicsClientId=cid)
    return out


def assert_fk_matches_pybullet(sim, n: int = 100, seed: int = 0, atol: float = 1e-5) -> float:
    """Assert pk FK and kernel FK (float64) match PyBullet at ``n`` random configurations.

    Configurations are uniform inside ``sim.bounds``. Returns the max error (m).
    """
    from camo_sbi.simulators.kernel import kernel_fk

    rng = np.random.default_rng(seed)
    lim = sim.bounds.numpy()
    q = lim[:, 0] + (lim[:, 1] - lim[:, 0]) * rng.random((n, sim.n_joints))
    ref = pybullet_fk(sim, q)
    pk_fk = sim.forward_kinematics(torch.from_numpy(q)).numpy()
    kern = kernel_fk(sim.spec, q)
    err_pk = float(np.abs(pk_fk - ref).max())
    err_kernel = float(np.abs(kern - ref).max())
    assert err_pk <= atol, f"pk FK differs from pybullet by {err_pk:.3g} m"
    assert err_kernel <= atol, f"kernel FK differs from pybullet by {err_kernel:.3g} m"
    return max(err_pk, err_kernel)
