"""Shared fixtures: simulator factories (Panda, a tiny 3-joint URDF with a prismatic joint,
the human model) and the PyBullet FK check (`tests._fk_check.assert_fk_matches_pybullet`)."""

from __future__ import annotations

import pytest

from camo_sbi import _compiling
from camo_sbi.simulators import from_urdf, human, panda
from tests._fk_check import assert_fk_matches_pybullet

# The one-line "compiling ... (once, about N s ...)" notice goes to stderr at a process's first
# compilation of each kind: in a test worker that is whichever test compiles first (caches are
# empty in a fresh clone on CI), and tests asserting a command's exact stderr lines would see it
# there. Said already for the tests; tests/test_warmup.py resets this to test the notice itself.
_compiling._state["said"].update(("package", "chain"))

__all__ = ["SIMULATOR_FACTORIES", "TINY_URDF", "assert_fk_matches_pybullet", "tiny"]

#: revolute (z) -> prismatic (x, tilted origin) -> revolute about a skew axis -> fixed tool
TINY_URDF = """<?xml version="1.0"?>
<robot name="tiny">
  <link name="base"><inertial><mass value="0.5"/><inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <link name="l1"><inertial><mass value="0.5"/><inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <link name="l2"><inertial><mass value="0.5"/><inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <link name="l3"><inertial><mass value="0.5"/><inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <link name="tip"><inertial><mass value="0.5"/><inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <joint name="j1" type="revolute">
    <parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0.1" rpy="0 0 0"/>
    <axis xyz="0 0 1"/>
    <limit lower="-2.5" upper="2.5" effort="1" velocity="1"/>
  </joint>
  <joint name="j2" type="prismatic">
    <parent link="l1"/><child link="l2"/>
    <origin xyz="0.05 0 0.2" rpy="0.3 -0.2 0.1"/>
    <axis xyz="1 0 0"/>
    <limit lower="-0.1" upper="0.3" effort="1" velocity="1"/>
  </joint>
  <joint name="j3" type="revolute">
    <parent link="l2"/><child link="l3"/>
    <origin xyz="0.3 0.02 0" rpy="1.5707963267948966 0 0.4"/>
    <axis xyz="0 0.6 0.8"/>
    <limit lower="-2.0" upper="2.0" effort="1" velocity="1"/>
  </joint>
  <joint name="tool" type="fixed">
    <parent link="l3"/><child link="tip"/>
    <origin xyz="0.25 0 0.05" rpy="0 0.5 0"/>
  </joint>
</robot>
"""


def tiny(**kwargs):
    """3-joint chain (revolute, prismatic, revolute) with end effector ``tip``."""
    kwargs.setdefault("start", [0.2, 0.1, -0.3])
    return from_urdf(TINY_URDF, "tip", **kwargs)


#: name -> zero-argument factory; add a model here and every contract test covers it
SIMULATOR_FACTORIES = {"panda": panda, "tiny": tiny, "human": human}

_built: dict = {}


def build_simulator(name: str):
    """Session-cached simulator built by ``SIMULATOR_FACTORIES[name]``."""
    if name not in _built:
        _built[name] = SIMULATOR_FACTORIES[name]()
    return _built[name]


@pytest.fixture(params=list(SIMULATOR_FACTORIES))
def any_sim(request):
    return build_simulator(request.param)


@pytest.fixture
def panda_sim():
    return build_simulator("panda")


@pytest.fixture
def fk_check():
    """The reusable PyBullet FK assertion as a fixture."""
    return assert_fk_matches_pybullet
