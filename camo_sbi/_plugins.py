"""Methods and body models from other installed packages, through entry points.

A package adds a method or a body model to every command (``--help``, ``--methods``,
``--model``, worker processes, Dask workers) by declaring an entry point in its
``pyproject.toml``::

    [project.entry-points."camo_sbi.methods"]
    my-method = "my_package.my_method"          # a module whose import calls registry.register(...)

    [project.entry-points."camo_sbi.models"]
    my-arm = "my_package.bodies:my_arm"         # or an object: a MethodSpec / ModelDef, or a
                                                # function returning one (or a list, or None)

The entry points of a group are read the first time a registry is looked up (`load`), in each
process on its own: a worker process or a Dask worker is a fresh interpreter that reads them
again, so it knows the same methods and models as the command that started it as long as
both run in the same environment. Reading the installed packages' metadata costs a few
milliseconds; a plug-in's module is imported only then, so ``camo-sbi --help`` imports what
its plug-ins import.

A plug-in that fails to load (an ImportError, a name already taken) is reported as a warning
naming the entry point and its distribution, and the others still load; the command goes on
without it (a method it provided is then "unknown", naming the known ones).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from importlib import metadata

__all__ = ["GROUPS", "load"]

GROUPS = ("camo_sbi.methods", "camo_sbi.models")
_LOADED: set[str] = set()
_FOUND: list = []  # every installed entry point, read once for both groups (one scan of the metadata)


def load(group: str, register: Callable, kind: type) -> None:
    """Load the entry points of ``group`` once per process: each entry point's object is imported;
    a ``kind`` instance is passed to ``register``, a callable is called and what it returns
    (a ``kind``, several, or None when it registered by itself) is registered."""
    if group not in GROUPS:
        raise ValueError(f"group: expected one of {GROUPS}, got {group!r}")
    if group in _LOADED:
        return
    _LOADED.add(group)  # before loading: a plug-in that looks the registry up does not recurse
    if not _FOUND:
        _FOUND.append(metadata.entry_points())
    for ep in _FOUND[0].select(group=group):
        where = f"{group} entry point {ep.name!r} ({ep.value}" + (f", from {ep.dist.name}" if ep.dist else "") + ")"
        try:
            obj = ep.load()
            if isinstance(obj, kind):
                register(obj)
            elif callable(obj) and not isinstance(obj, type):
                made = obj()
                for item in (made if isinstance(made, list | tuple) else [] if made is None else [made]):
                    if not isinstance(item, kind):
                        raise TypeError(f"returned {type(item).__name__}, not a {kind.__name__}")
                    register(item)
        except Exception as exc:  # noqa: BLE001 - one broken plug-in must not stop the others
            warnings.warn(f"plug-in: {where} failed to load: {type(exc).__name__}: {exc}", RuntimeWarning,
                          stacklevel=2)
