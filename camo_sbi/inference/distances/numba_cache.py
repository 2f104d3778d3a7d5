"""Keeps numba's on-disk cache of kernels split across modules in step with their sources.

numba caches a jitted function together with every jitted function it calls, but decides
whether that cache is stale from the caller's own source file only (numba issue #1833): after an
edit of ``bounds.py`` alone, the cached kernels of ``chunks.py`` would go on running the old
bounds. `flush_if_changed` keeps a digest of the sources of all the given modules beside the
cache of each and, when it differs, empties the caches of all their kernels once (they are
compiled again on their next call).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from numba.core.dispatcher import Dispatcher

__all__ = ["STAMP_NAME", "flush_if_changed", "sources_digest"]

STAMP_NAME = "kernel-sources.sha256"


def sources_digest(modules) -> str:
    """sha256 of the names and source bytes of ``modules`` (any order)."""
    h = hashlib.sha256()
    for m in sorted(modules, key=lambda m: m.__name__):
        h.update(m.__name__.encode() + b"\0" + Path(m.__file__).read_bytes() + b"\0")
    return h.hexdigest()


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
