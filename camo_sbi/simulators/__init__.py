"""Batched kinematic simulators behind one signature (see `base.Simulator`), and the registry of
body models (`registry`).

The names below are imported on first use (PEP 562), so that the command line can read the
model registry (``--model`` choices, profile lists in ``--help``) without importing torch.
``camo_sbi.simulators.human`` and ``.panda`` stay the builder functions, as they were when this
package imported them eagerly, even after their modules of the same name are imported.
"""

import sys
import types
from importlib import import_module

_WHERE = {
    "Simulator": "base", "Trajectories": "base", "limits_to_theta": "base", "theta_to_limits": "base",
    "ControllerConfig": "controller",
    "IMPAIRED_PROFILES": "human", "human": "human", "impaired_limits": "human",
    "panda": "panda",
    "KinematicSimulator": "simulator", "from_urdf": "simulator", "sample_goals": "simulator",
}

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


def __getattr__(name: str):
    if name in _WHERE:
        value = getattr(import_module(f"camo_sbi.simulators.{_WHERE[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'camo_sbi.simulators' has no attribute {name!r}")


class _Package(types.ModuleType):
    def __setattr__(self, name, value):
        # importing the submodule `human` (or `panda`) sets the package attribute to the module:
        # keep the function of that name instead, as the eager package did
        if name in _WHERE and isinstance(value, types.ModuleType) and value.__name__ == f"{__name__}.{name}":
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package


def __dir__():
    return sorted({*globals(), *__all__})
