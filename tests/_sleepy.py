"""Module-level cells and initializers for the process-hygiene tests in test_faults.py.

Spawned workers import this module, so it stays light (no torch, no numba).
"""

from __future__ import annotations

import os
import time
from pathlib import Path


def sleepy_cell(spec: dict, out: str) -> str:
    """Mark ``started-<name>-<pid>`` in ``out``, sleep ``spec["seconds"]`` (default 600), mark ``finished-<name>``."""
    Path(out, f"started-{spec['name']}-{os.getpid()}").touch()
    if spec.get("fail"):
        raise ValueError(f"cell {spec['name']} failed")
    time.sleep(spec.get("seconds", 600))
    Path(out, f"finished-{spec['name']}").touch()
    return spec["name"]


def without_death_signal() -> None:
    """Initializer that clears PR_SET_PDEATHSIG again: only the watchdog thread is left."""
    from camo_sbi.experiments.processes import set_parent_death_signal

    set_parent_death_signal(0)


PARENT = """
import sys
from camo_sbi.experiments.processes import run_in_processes
from tests import _sleepy
init = getattr(_sleepy, sys.argv[2]) if sys.argv[2] else None
specs = [{"name": n} for n in "abcd"]
run_in_processes(_sleepy.sleepy_cell, specs, sys.argv[1], 2, on_done=lambda: None, initializer=init)
"""
"""A parent process (``python -c PARENT OUT INITIALIZER``) running four sleeping cells on two workers."""
