"""Worker processes that die with their parent: the ``--workers N`` runner.

`run_in_processes` runs grid cells in N spawned processes (`ProcessPoolExecutor`). A worker
must never outlive the command that started it (it would keep writing into ``--out`` after
the parent was killed, while a new run may already hold the directory), so:

* each worker asks the Linux kernel for SIGKILL when its parent dies
  (``prctl(PR_SET_PDEATHSIG, SIGKILL)``; covers ``kill -9`` of the parent), checks right away
  that the parent did not die before that call, and runs a watchdog thread that kills the
  worker when ``os.getppid()`` changes (the fallback where prctl is unavailable);
* workers ignore SIGINT (Ctrl-C reaches the whole process group; the parent handles it);
* when the parent leaves the runner with an exception (a failing cell, Ctrl-C, SIGTERM
  turned into an exception by the CLI) it kills its workers before re-raising: the cells
  already finished are saved, the ones in flight are recomputed by the next run.

Workers stay in the parent's process group, so ``timeout``/SLURM signals sent to the group
reach them directly as well.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context

__all__ = ["kill_workers", "run_in_processes", "set_parent_death_signal"]

_PR_SET_PDEATHSIG = 1
WATCHDOG_INTERVAL = 0.5
"""Seconds between the watchdog's checks of the parent pid."""


def set_parent_death_signal(sig: int = signal.SIGKILL) -> bool:
    """Ask Linux to send ``sig`` to this process when its parent dies; False where unsupported."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch_parent(parent_pid: int) -> None:
    while True:
        if os.getppid() != parent_pid:
            os.kill(os.getpid(), signal.SIGKILL)
        time.sleep(WATCHDOG_INTERVAL)


def _init_worker(parent_pid: int, initializer=None, initargs=()) -> None:
    """Worker start-up: die with the parent (prctl + watchdog), ignore Ctrl-C, then ``initializer``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    set_parent_death_signal(signal.SIGKILL)
    if os.getppid() != parent_pid:  # the parent died before prctl took effect
        os.kill(os.getpid(), signal.SIGKILL)
    threading.Thread(target=_watch_parent, args=(parent_pid,), name="camo-sbi-parent-watchdog",
                     daemon=True).start()
    if initializer is not None:
        initializer(*initargs)


def kill_workers(executor: ProcessPoolExecutor, timeout: float = 5.0) -> None:
    """SIGKILL every live worker process of ``executor`` and reap them (at most ``timeout`` s each)."""
    procs = list((getattr(executor, "_processes", None) or {}).values())
    for p in procs:
        try:
            p.kill()
        except (OSError, ValueError):  # already gone / already closed
            pass
    for p in procs:
        try:
            p.join(timeout)
        except (OSError, ValueError, AssertionError):
            pass


def run_in_processes(cell_fn, specs: list, out, workers: int, *, on_done, initializer=None) -> list:
    """Run ``cell_fn(spec, str(out))`` for every spec in ``workers`` spawned processes; returns
    the values ``cell_fn`` returned, in completion order.

    Each cell writes its own rows atomically; ``on_done()`` is called as cells finish and the
    first failing cell's exception is re-raised once the workers are killed (cells in flight
    are lost, finished ones are saved). ``cell_fn`` and ``initializer`` (run once in each
    worker) must be module-level functions. Workers die with the parent (module docstring).
    """
    ex = ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_init_worker,
                             initargs=(os.getpid(), initializer))
    results = []
    try:
        for f in as_completed([ex.submit(cell_fn, spec, str(out)) for spec in specs]):
            results.append(f.result())
            on_done()
    except BaseException:  # a failing cell, Ctrl-C, SIGTERM (via the CLI): stop the workers now
        kill_workers(ex)
        ex.shutdown(wait=False, cancel_futures=True)
        raise
    else:
        ex.shutdown(wait=True)
    return results
