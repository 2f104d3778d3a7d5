"""Running the chunks of a kernel on threads: `ChunkRunner` owns a pool, `run_chunks` shares one.

Used by the simulators' generated kernels and the DTW kernels alike (one pool per process).

A chunk kernel is ``fn(c, n_chunks, *args)``: a ``nogil`` numba function that handles a fixed
share of the work (blocks c, c + n_chunks, ...) and writes its results into arrays of ``args``,
so results never depend on which thread runs a chunk or when. Chunk 0 runs in the calling
thread, chunks 1 .. n_chunks - 1 on the runner's threads, all truly in parallel.

Lifetime, as mujoco's ``rollout.Rollout`` owns its pool: a `ChunkRunner` is never shut down
under a caller. `ChunkRunner.close` only refuses new runs; the pool shuts down when the runs in
progress have finished. `run_chunks` (used by `dtw_distances`) shares one default runner per
process; a call that needs more threads than it has replaces it with a larger new one and closes
the old one that way. A caller takes the default runner, and is counted as using it, under the
same lock under which it is replaced, so a runner in use always keeps its pool.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import wait as wait_all

from camo_sbi._validation import check_positive_int

__all__ = ["ChunkRunner", "default_workers", "run_chunks"]


def default_workers() -> int:
    """Threads a kernel runs on: ``NUMBA_NUM_THREADS`` if set (worker processes set it to 1), else
    the number of CPUs this process may run on (at least 1)."""
    env = os.environ.get("NUMBA_NUM_THREADS")
    if env and env.strip().isdigit() and int(env) >= 1:
        return int(env)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


class ChunkRunner:
    """Owns a thread pool of ``threads`` threads that runs up to ``threads + 1`` chunks at once.

    Safe to share between threads: concurrent `run` calls share the pool. Use as a context
    manager, or call `close` (idempotent) when done::

        with ChunkRunner(3) as runner:
            runner.run(kernel, 4, *args)   # kernel(c, 4, *args) for c = 0, 1, 2, 3
    """

    def __init__(self, threads: int):
        self.threads = check_positive_int(threads, "threads")
        self._pool = ThreadPoolExecutor(max_workers=self.threads, thread_name_prefix="camo_sbi")
        self._lock = threading.Lock()
        self._runs = 0  # runs in progress
        self._closed = False

    @property
    def closed(self) -> bool:
        """True once `close` was called (runs in progress may still be finishing)."""
        return self._closed

    def run(self, fn, n_chunks: int, *args) -> None:
        """fn(c, n_chunks, *args) for c in range(n_chunks), chunk 0 in the calling thread.

        Returns when every chunk has finished; re-raises the first chunk's exception, if any.
        Raises RuntimeError if the runner is closed, ValueError if n_chunks > threads + 1.
        """
        self._enter()
        try:
            self._run(fn, n_chunks, *args)
        finally:
            self._leave()

    def close(self) -> None:
        """Refuse new runs; the pool shuts down as soon as no run is in progress."""
        with self._lock:
            self._closed = True
            idle = self._runs == 0
        if idle:
            self._pool.shutdown(wait=False)

    def __enter__(self) -> ChunkRunner:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"ChunkRunner(threads={self.threads}, {state}, runs in progress: {self._runs})"

    def _enter(self) -> None:
        with self._lock:
            if self._closed:
                raise RuntimeError("ChunkRunner: closed, cannot start a run")
            self._runs += 1

    def _leave(self) -> None:
        with self._lock:
            self._runs -= 1
            last = self._closed and self._runs == 0
        if last:
            self._pool.shutdown(wait=False)

    def _run(self, fn, n_chunks: int, *args) -> None:
        """`run` for a caller already counted by `_enter`."""
        n_chunks = check_positive_int(n_chunks, "n_chunks")
        if n_chunks - 1 > self.threads:
            raise ValueError(f"n_chunks: at most {self.threads + 1} here, got {n_chunks}")
        futures = [self._pool.submit(fn, c, n_chunks, *args) for c in range(1, n_chunks)]
        try:
            fn(0, n_chunks, *args)
        finally:
            wait_all(futures)  # the chunks write into shared arrays: never return before them
        for f in futures:
            f.result()


_default: ChunkRunner | None = None
_default_lock = threading.Lock()


def _take_default(threads: int) -> ChunkRunner:
    """The shared runner, with at least ``threads`` threads, counted as in use by the caller."""
    global _default
    with _default_lock:
        if _default is None or _default.threads < threads:
            old, _default = _default, ChunkRunner(threads)
            if old is not None:
                old.close()  # its pool ends when its last run does
        _default._enter()
        return _default


def run_chunks(fn, n_chunks: int, *args) -> None:
    """fn(c, n_chunks, *args) for c in range(n_chunks): chunk 0 in the calling thread, the
    others on the shared default runner (grown when needed); see `ChunkRunner.run`."""
    if n_chunks <= 1:
        fn(0, n_chunks, *args)
        return
    runner = _take_default(n_chunks - 1)
    try:
        runner._run(fn, n_chunks, *args)
    finally:
        runner._leave()
