"""The machinery of the `camo_sbi.inference.distances` package rather than its numbers.

Its import paths, and the guard that keeps numba's on-disk cache in step with the kernel
modules.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import textwrap
from pathlib import Path

from numba.core.dispatcher import Dispatcher

from camo_sbi.inference import distances
from camo_sbi.inference.distances import chunks, numba_cache

# ----------------------------------------------------------------------------------------------
# import paths and numba's cache
# ----------------------------------------------------------------------------------------------


def test_public_names_and_import_paths():
    assert set(distances.__all__) == {"dtw_distances", "l2_distance"}
    from camo_sbi.inference.distances import _candidate_bounds, l2_distance  # noqa: F401


def test_the_cache_guard_sees_every_kernel_and_its_digest_is_current():
    mods = distances.KERNEL_MODULES
    assert chunks in mods and len(mods) == 5
    caches = numba_cache._caches(mods)
    # every kernel of the package is under the guard (numba still exposes its cache)
    kernels = [
        v
        for m in mods
        for v in vars(m).values()
        if isinstance(v, Dispatcher) and v.py_func.__module__ == m.__name__
    ]
    assert len(caches) == len(kernels) >= 16
    digest = numba_cache.sources_digest(mods)
    for path in {c.cache_path for c in caches}:
        assert (Path(path) / numba_cache.STAMP_NAME).read_text() == digest
    assert not numba_cache.flush_if_changed(mods)  # nothing changed since the import


_CALLEE = """
from numba import njit

@njit(cache=True)
def f():
    return {value}
"""
_CALLER = """
from numba import njit
from pkg.a import f

@njit(cache=True)
def g():
    return f()
"""
_MAIN = """
import importlib.util, sys
sys.path.insert(0, {root!r})
spec = importlib.util.spec_from_file_location("numba_cache", {guard!r})
guard = importlib.util.module_from_spec(spec)
spec.loader.exec_module(guard)
import pkg.a, pkg.b
flushed = guard.flush_if_changed((pkg.a, pkg.b))
print(pkg.b.g(), flushed)
"""


def test_the_cache_guard_drops_a_cached_caller_when_its_callee_module_changes(tmp_path):
    """numba alone would return the old callee's value from g's cache (numba issue #1833)."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "b.py").write_text(_CALLER)
    guard = importlib.util.find_spec("camo_sbi.inference.distances.numba_cache").origin
    main = tmp_path / "main.py"
    main.write_text(_MAIN.format(root=str(tmp_path), guard=guard))

    def run(value):
        (pkg / "a.py").write_text(textwrap.dedent(_CALLEE.format(value=value)))
        res = subprocess.run([sys.executable, str(main)], capture_output=True, text=True)
        assert res.returncode == 0, res.stderr
        return res.stdout.split()

    assert run(1) == ["1", "True"]  # first run: no digest yet
    assert run(1) == ["1", "False"]  # unchanged: the caches are used as they are
    assert run(22) == ["22", "True"]  # only a.py changed: g's cache is dropped
