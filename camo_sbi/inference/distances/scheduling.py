"""Running the chunks of a kernel on a shared thread pool.

A chunk kernel is ``fn(c, n_chunks, *args)``: a ``nogil`` numba function that handles a fixed
share of the work (blocks c, c + n_chunks, ...) and writes its results into arrays of ``args``,
so results never depend on which thread runs a chunk or when.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

__all__ = ["default_workers", "run_chunks"]

_POOL: ThreadPoolExecutor | None = None
_POOL_SIZE = 0
_POOL_LOCK = threading.Lock()


def default_workers() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def run_chunks(fn, n_chunks: int, *args) -> None:
    """fn(c, n_chunks, *args) for c in range(n_chunks), chunk 0 in the calling thread.

    The kernels are ``nogil``: the chunks run truly in parallel on a shared thread pool. Each
    chunk's work depends only on (c, n_chunks), never on thread timing.
    """
    global _POOL, _POOL_SIZE
    if n_chunks > 1:
        with _POOL_LOCK:
            if _POOL is None or _POOL_SIZE < n_chunks - 1:
                if _POOL is not None:
                    _POOL.shutdown(wait=False)
                _POOL = ThreadPoolExecutor(max_workers=n_chunks - 1, thread_name_prefix="dtw")
                _POOL_SIZE = n_chunks - 1
            pool = _POOL
        futures = [pool.submit(fn, c, n_chunks, *args) for c in range(1, n_chunks)]
    fn(0, n_chunks, *args)
    if n_chunks > 1:
        for f in futures:
            f.result()
