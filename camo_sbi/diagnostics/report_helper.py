"""One helper process for a report: the work that holds the GIL, beside the figures.

`write_report` starts a `Helper` (``python -m camo_sbi.diagnostics.report_helper``, one
child process) before it imports anything heavy, and hands it, as soon as the posteriors are
loaded, the two jobs of the report that do not draw: the simulations of the
posterior-predictive reaches (`camo_sbi.diagnostics.report.predictive_paths`: torch, and numba compiling the chain kernel
on a first run) and the classifier two-sample tests of the posterior comparison (`camo_sbi.diagnostics.report.c2st_accuracy`).
Both hold the GIL (numba's compiler; scikit-learn's random forests on a few hundred draws are
mostly Python), so threads cannot overlap them with the figures; a second process can, on a
second core, and the report's own process then never imports torch. The jobs are the very same
calls as in the report's process (the same functions, arguments and seeds), so the figures and
numbers do not depend on where they ran.

A plain child process, not multiprocessing's ``spawn``: that would run the caller's
``__main__`` script again in the child (a script calling `write_report` without a
``__main__`` guard would build its report twice). Jobs and results travel pickled over the
child's stdin and stdout (the child's own prints go to stderr); jobs run in the order given.

Nothing here may fail a report: a helper that cannot start, dies, or fails a job makes
`Helper.result` return None, and the report does that job itself.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import subprocess
import sys

__all__ = ["Helper"]


# the jobs, by name -> (module, function), imported in the helper only (this module imports neither)
_JOBS = {"predictive_paths": ("camo_sbi.diagnostics.report", "predictive_paths"),
         "c2st": ("camo_sbi.diagnostics.report", "c2st_accuracy")}


def _run(name: str, args):
    import importlib

    module, function = _JOBS[name]
    return getattr(importlib.import_module(module), function)(*args)


class Helper:
    """The helper process of one report: `submit` a job by name, `result` waits for it.

    ``Helper(enabled=False)``, or a child that cannot start, runs nothing: `submit` returns
    None and `result(None)` is None (the caller does the job itself)."""

    def __init__(self, enabled: bool = True):
        self._proc = None
        self._next = 0
        self._done: dict[int, object] = {}
        if enabled:
            with contextlib.suppress(OSError, ValueError):
                self._proc = subprocess.Popen([sys.executable, "-m", __name__], stdin=subprocess.PIPE,
                                              stdout=subprocess.PIPE, env={**os.environ, "PYTHONWARNINGS": "ignore"})

    def submit(self, name: str, *args) -> int | None:
        """Queue job ``name`` (`compile_kernel` or `c2st`) with ``args``; its id, or None."""
        if self._proc is None or name not in _JOBS:
            return None
        try:
            pickle.dump((self._next, name, args), self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            self._proc.stdin.flush()
        except (OSError, ValueError, pickle.PicklingError):
            self._stop()
            return None
        self._next += 1
        return self._next - 1

    def result(self, job: int | None):
        """Job ``job``'s value once the helper finished it; None when there is no such job, it
        failed, or the helper is gone."""
        while job is not None and job not in self._done and self._proc is not None:
            try:
                jid, ok, value = pickle.load(self._proc.stdout)
            except Exception:  # noqa: BLE001 - EOF or garbage: the helper is gone
                self._stop()
                break
            self._done[jid] = value if ok else None
        return self._done.pop(job, None) if job is not None else None

    def _stop(self) -> None:
        if self._proc is not None:
            proc, self._proc = self._proc, None
            with contextlib.suppress(OSError, ValueError):
                proc.stdin.close()
            with contextlib.suppress(OSError):
                proc.kill()
            proc.wait()
            proc.stdout.close()

    def close(self) -> None:
        """Stop the helper (a job nobody waited for is abandoned)."""
        self._stop()

    def __enter__(self) -> Helper:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _serve() -> None:
    """The child: read (id, name, args) jobs from stdin (a thread, so the parent never blocks
    writing), run them in order, write (id, ok, value) to the original stdout."""
    import queue
    import threading

    out = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    sys.stdout = sys.stderr  # anything a library prints goes to stderr, not into the results
    jobs: queue.Queue = queue.Queue()

    def read():
        while True:
            try:
                jobs.put(pickle.load(sys.stdin.buffer))
            except Exception:  # noqa: BLE001 - EOF: the report is done
                jobs.put(None)
                return

    threading.Thread(target=read, daemon=True).start()
    # import what the jobs need while the report loads its posteriors (it sends the first job then)
    with contextlib.suppress(Exception):
        import importlib

        for module in ("camo_sbi.diagnostics.report", "camo_sbi.diagnostics.calibration",
                       "camo_sbi.simulators.kernel", "camo_sbi.simulators.registry"):
            importlib.import_module(module)
    while (job := jobs.get()) is not None:
        jid, name, args = job
        try:
            reply = (jid, True, _run(name, args))
        except Exception as exc:  # noqa: BLE001 - the report redoes the job and reports its error
            reply = (jid, False, repr(exc))
        pickle.dump(reply, out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()


if __name__ == "__main__":
    _serve()
