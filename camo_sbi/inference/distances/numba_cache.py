"""Keeps numba's on-disk cache of kernels split across modules in step with their sources.

numba caches a jitted function together with every jitted function it calls, but decides
whether that cache is stale from the caller's own source file only (numba issue #1833): after an
edit of ``bounds.py`` alone, the cached kernels of ``chunks.py`` would go on running the old
bounds. `flush_if_changed` keeps a digest of the sources of all the given modules beside the
cache of each and, when it differs, empties the caches of all their kernels once (they are
compiled again on their next call).

`use_private_cache` decides where that cache lives before anything is compiled: numba unpickles
its cache files, so only a private directory of this user is used (`camo_sbi._io.check_private_dir`):
``NUMBA_CACHE_DIR`` when set, else ``$XDG_CACHE_HOME/camo_sbi/numba`` (``~/.cache/...``), created
with mode 0700; never the installed package's ``__pycache__``. When that directory is not private
(world- or group-writable, another user's, a symbolic link) or cannot be created, the kernels are
compiled in memory on every run, with one `NumbaCacheWarning`. Inside it a module's kernels are
filed under its package's dotted name and the sha256 of the sources of the modules given
together (`PackageLocator`: ``camo_sbi.inference.distances-<digest>``), not under a digest of
the source file's absolute path as numba's own locator does: a second clone or install of the
same sources in the same user account loads the kernels the first one compiled (compiling
happens once per user, not once per clone), and checkouts of different sources (worktrees of
two branches) keep apart caches instead of flushing each other's on every switch.
"""

from __future__ import annotations

import hashlib
import os
import warnings
from pathlib import Path

from numba.core import config as numba_config
from numba.core.caching import NullCache, UserProvidedCacheLocator
from numba.core.dispatcher import Dispatcher

from camo_sbi._compiling import announce_compiling
from camo_sbi._io import make_private_dir

__all__ = ["STAMP_NAME", "NumbaCacheWarning", "PackageLocator", "cache_root", "flush_if_changed",
           "sources_digest", "use_private_cache"]


class NumbaCacheWarning(RuntimeWarning):
    """numba's cache directory is not private: camo_sbi's kernels are compiled in memory instead."""

STAMP_NAME = "kernel-sources.sha256"


def sources_digest(modules) -> str:
    """sha256 of the names and source bytes of ``modules`` (any order)."""
    h = hashlib.sha256()
    for m in sorted(modules, key=lambda m: m.__name__):
        h.update(m.__name__.encode() + b"\0" + Path(m.__file__).read_bytes() + b"\0")
    return h.hexdigest()


def cache_root() -> Path:
    """Where numba caches camo_sbi's distance kernels: ``NUMBA_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/camo_sbi/numba`` (default ``~/.cache/camo_sbi/numba``)."""
    env = os.environ.get("NUMBA_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "camo_sbi" / "numba"


_SUBDIRS: dict[str, str] = {}
"""module name -> its cache subdirectory, set by `use_private_cache` before numba locates a cache."""


class PackageLocator(UserProvidedCacheLocator):
    """numba's locator for ``numba.config.CACHE_DIR``, with a module's kernels filed under its
    package's dotted name and the digest of the sources given to `use_private_cache` together
    (``CACHE_DIR/camo_sbi.inference.distances-<16 hex>``) instead of a digest of the source's
    absolute path: the same sources in another directory (a fresh clone, a reinstall) find the
    same cache, other sources another one. numba still stamps each index with the sha256 of the
    source file (`flush_if_changed` covers kernels split across modules)."""

    def __init__(self, py_func, py_file):
        super().__init__(py_func, py_file)
        package = py_func.__module__.rpartition(".")[0] or py_func.__module__
        self._cache_path = os.path.join(numba_config.CACHE_DIR, _SUBDIRS.get(py_func.__module__, package))


def _dispatchers(modules) -> list:
    return [v for m in modules for v in vars(m).values()
            if isinstance(v, Dispatcher) and v.py_func.__module__ == m.__name__
            and getattr(getattr(v, "_cache", None), "cache_path", None)]


def use_private_cache(modules) -> Path | None:
    """Point numba's on-disk cache of every cached kernel of ``modules`` at `cache_root`, or, when
    that is not a private directory of this user, switch their caching off (one `NumbaCacheWarning`:
    compiled in memory, nothing read or written). Returns the directory used, or None.
    Call it at import, before any kernel runs (and before `flush_if_changed`)."""
    announce_compiling()
    dispatchers = _dispatchers(modules)
    if not dispatchers:
        return None
    root = cache_root()
    reason = make_private_dir(root, subdirs=())
    digest = sources_digest(modules)[:16]
    for m in modules:
        _SUBDIRS[m.__name__] = f"{m.__name__.rpartition('.')[0] or m.__name__}-{digest}"
    if reason is None:
        saved = {k: getattr(numba_config, k) for k in ("CACHE_DIR", "CACHE_LOCATOR_CLASSES")
                 if hasattr(numba_config, k)}
        try:
            numba_config.CACHE_DIR = str(root)
            if "CACHE_LOCATOR_CLASSES" in saved:  # (a numba without it: its own locator for CACHE_DIR)
                numba_config.CACHE_LOCATOR_CLASSES = f"{__name__}.{PackageLocator.__name__}"
            for d in dispatchers:
                d.enable_caching()  # located by PackageLocator (numba imports it by that name)
        finally:
            for k, v in saved.items():
                setattr(numba_config, k, v)
        # the per-source subdirectory numba uses inside it must be private too
        paths = {Path(d._cache.cache_path) for d in dispatchers}
        reason = next((f"{p} {r}" for p in sorted(paths) if (r := _check_subdir(root, p)) is not None), None)
        if reason is None:
            return root
    else:
        reason = f"{root} {reason}"
    for d in dispatchers:
        d._cache = NullCache()
    if reason not in _warned:
        _warned.add(reason)
        warnings.warn(f"numba cache {reason}; compiling camo_sbi's numba kernels in memory without caching "
                      "(set NUMBA_CACHE_DIR to a private directory, mode 700)", NumbaCacheWarning, stacklevel=2)
    return None


_warned: set[str] = set()


def _check_subdir(root: Path, path: Path) -> str | None:
    """Each existing directory from ``root`` down to ``path`` must be private (created 0700 here)."""
    from camo_sbi._io import check_private_dir

    rel = path.relative_to(root)
    d = root
    for part in rel.parts:
        d = d / part
        if not os.path.lexists(d):
            try:
                os.mkdir(d, 0o700)
            except FileExistsError:
                pass
            except OSError as exc:
                return f"cannot be created ({exc.strerror or exc})"
        why = check_private_dir(d, subdirs=())
        if why is not None:
            return why
    return None


def _caches(modules) -> list:
    """numba's on-disk caches of the jitted functions defined in ``modules`` (with cache=True)."""
    out = []
    for m in modules:
        for v in vars(m).values():
            if isinstance(v, Dispatcher) and v.py_func.__module__ == m.__name__:
                cache = getattr(v, "_cache", None)
                if getattr(cache, "cache_path", None):
                    out.append(cache)
    return out


def _read(path: str) -> str | None:
    try:
        return Path(path).read_text()
    except OSError:
        return None


def flush_if_changed(modules) -> bool:
    """Empty the caches of every kernel of ``modules`` if any of their sources changed since
    the last call (or the digest is missing); True if it did. Call it at import, before any
    kernel runs. Nothing to do (False) when the kernels are not cached (e.g. NUMBA_DISABLE_JIT).
    """
    caches = _caches(modules)
    if not caches:
        return False
    digest = sources_digest(modules)
    stamps = sorted({os.path.join(c.cache_path, STAMP_NAME) for c in caches})
    if all(_read(p) == digest for p in stamps):
        return False
    for c in caches:
        c.flush()  # an empty index: the next call compiles and saves again
    for p in stamps:  # only after the flush: a process that sees the new digest sees new caches
        tmp = f"{p}.{os.getpid()}.tmp"
        Path(tmp).write_text(digest)
        os.replace(tmp, p)
    return True
