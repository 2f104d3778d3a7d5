"""The one grid runner of the experiment commands: a typed `Cell` and `run_grid`.

compare, calibrate, robustness and ``reproduce panda`` describe their grids as `Cell` objects
and hand them to `run_grid`, which

* skips the cells already finished in the `ResultStore` (an interrupted or repeated run resumes);
* runs the others in-process (``workers=1``), in spawned worker processes that die with the
  parent (``workers=N``, `camo_sbi.experiments.processes`) or on Dask (``scheduler``,
  `camo_sbi.distributed`), a cell whose Dask worker dies being retried;
* writes each finished cell's rows atomically through the store, in the process that ran it;
* shows a tqdm progress bar.

Every input of a cell (its seeds included) is in the cell, so results do not depend on where
or in which order it ran: any number of workers gives the same table. A method that raises
inside a cell does not reach this runner: the commands' cell functions run methods with
``errors="record"`` (`camo_sbi.inference.registry.run_method`), which turns the exception into
a ``"failed: ..."`` result, so its rows carry that status and the grid goes on. A cell function
that itself raises (a bug, a full disk) stops the grid with that exception: cells already
finished stay in the store, cells in flight are lost, and the next run computes only what is
missing. Kill or SIGTERM
behaves the same way.

A cell's ``key`` (the name of its file under ``cells/``) is `store.cell_key` of its key
fields, exactly as each command computed it before this module existed, so run folders made
by older versions resume. The key fields are the shared fields (``subject``, ``seed``,
``budget``, ``tasks`` and ``method`` when set), the command-specific ``extras`` and
``model_key``, the entries through which a command names its model in the key (these differ
between commands for historical reasons and are kept as they were; so does the budget's name
in the key, ``budget_key``: ``reproduce panda`` has always called it ``samples``).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

__all__ = ["Cell", "init_worker", "pending", "run_grid"]

_SHARED = ("subject", "seed", "budget", "tasks", "method")


def _check_int(value, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{name}: expected an int, got {type(value).__name__}")
    if value < minimum:
        raise ValueError(f"{name}: must be >= {minimum}, got {value}")
    return value


@dataclass(frozen=True, eq=True)
class Cell:
    """One grid cell: everything needed to run it in any process, and its stable key.

    Attributes:
        model: the picklable `ModelSpec` (workers rebuild the simulator from it).
        subject: the subject's profile name (or a synthetic subject's index).
        seed: the cell's seed (compare/robustness: the seed index; calibrate: the run's seed).
        budget: simulations per observed task.
        tasks: observed tasks.
        method: the method the cell runs, or None for a cell running several (``extras``).
        extras: command-specific key fields (read-only mapping; values as they enter the key).
        model_key: ``(name, value)`` entries naming the model in the key.
        budget_key: the name of ``budget`` in the key ("budget"; ``reproduce panda``: "samples").
        key: `cell_key` of every key field (computed, not passed).
    """

    model: Any
    subject: str | int
    seed: int
    budget: int
    tasks: int
    method: str | None = None
    extras: Mapping[str, Any] = field(default_factory=dict)
    model_key: tuple[tuple[str, str], ...] = ()
    budget_key: str = "budget"
    key: str = field(init=False, compare=False)

    def __post_init__(self):
        from camo_sbi.experiments.models import ModelSpec
        from camo_sbi.experiments.store import cell_key

        if not isinstance(self.model, ModelSpec):
            raise TypeError(f"model: expected a ModelSpec, got {type(self.model).__name__}")
        if isinstance(self.subject, bool) or not isinstance(self.subject, (str, int)):
            raise TypeError(f"subject: expected a str or int, got {type(self.subject).__name__}")
        _check_int(self.seed, "seed", 0)
        _check_int(self.budget, "budget", 1)
        _check_int(self.tasks, "tasks", 1)
        if self.method is not None and not isinstance(self.method, str):
            raise TypeError(f"method: expected a str or None, got {type(self.method).__name__}")
        if not isinstance(self.extras, Mapping):
            raise TypeError(f"extras: expected a mapping, got {type(self.extras).__name__}")
        extras = dict(self.extras)
        try:
            model_key = tuple((str(k), str(v)) for k, v in self.model_key)
        except (TypeError, ValueError):
            raise TypeError("model_key: expected (name, value) pairs") from None
        if not isinstance(self.budget_key, str) or not self.budget_key:
            raise TypeError(f"budget_key: expected a non-empty str, got {self.budget_key!r}")
        names = [*self._shared(), *extras, *(k for k, _ in model_key)]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"extras: key field(s) {dup} given twice (shared fields, extras and model_key)")
        if any(not isinstance(k, str) for k in extras):
            raise TypeError("extras: keys must be str")
        object.__setattr__(self, "extras", MappingProxyType(extras))
        object.__setattr__(self, "model_key", model_key)
        object.__setattr__(self, "key", cell_key(self.key_fields()))

    def _shared(self) -> dict[str, str]:
        """{name in the key: attribute} of the shared fields this cell keys on."""
        return {(self.budget_key if k == "budget" else k): k for k in _SHARED if k != "method" or self.method is not None}

    def key_fields(self) -> dict[str, Any]:
        """The fields the key is computed from (`store.cell_key`)."""
        shared = {name: getattr(self, k) for name, k in self._shared().items()}
        return {**shared, **self.extras, **dict(self.model_key)}

    @property
    def label(self) -> str:
        """A short description for the progress bar."""
        parts = [self.method or str(self.extras.get("methods", ""))]
        if "condition" in self.extras:
            parts.append(str(self.extras["condition"]))
        return " ".join([*parts, f"subject={self.subject}", f"b={self.budget}", f"s={self.seed}"])

    def __hash__(self) -> int:
        return hash(self.key)

    # MappingProxyType does not pickle: send the extras as a plain dict
    def __getstate__(self):
        return {**self.__dict__, "extras": dict(self.extras)}

    def __setstate__(self, state):
        for k, v in state.items():
            object.__setattr__(self, k, MappingProxyType(v) if k == "extras" else v)


def init_worker() -> None:
    """Start-up of a worker process or Dask worker: one numba and one torch thread per worker."""
    import torch

    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
    torch.set_num_threads(1)


def _run_and_store(fn: Callable, cell: Cell, out: str) -> str:
    """Run ``fn(cell, out)`` and write its rows as the cell's file (atomic); returns the key."""
    from camo_sbi.experiments.store import ResultStore

    try:
        rows = fn(cell, out)
    except BaseException as exc:
        exc.add_note(f"in grid cell {cell.key}")
        raise
    ResultStore(out).put(cell.key, rows)
    return cell.key


def pending(cells: Iterable[Cell], store) -> list[Cell]:
    """The cells of ``cells`` not finished (and intact) in ``store``."""
    return [c for c in cells if not store.done(c.key)]


def run_grid(fn: Callable[[Cell, str], Iterable[Mapping]], cells: Iterable[Cell], store, workers: int = 1,
             scheduler: str | None = None, *, progress: str | bool = "grid", threads: int | None = None,
             retries: int | None = None) -> list[str]:
    """Run ``fn(cell, out)`` for every cell not finished in ``store``; store its rows.

    Args:
        fn: a module-level function (it is pickled to workers) returning the cell's tidy rows;
            ``out`` is ``str(store.out)`` (for the cell's side files: work directories, posteriors).
        cells: the grid; cells already finished in ``store`` are skipped.
        store: the `ResultStore` the rows are written to (each cell atomically, where it ran).
        workers: processes (1: in this process). Ignored with ``scheduler``.
        scheduler: a Dask scheduler spec (`camo_sbi.distributed.parse_scheduler`), or None.
        progress: the progress bar's description, or False for no bar.
        threads: in-process only, torch threads while the cells run (restored after); None: unchanged.
        retries: Dask only, how often a cell whose worker dies is resubmitted (default
            `camo_sbi.distributed.DEFAULT_RETRIES`).

    Returns:
        the keys of the cells run, in completion order.

    The first cell whose ``fn`` raises stops the grid with its exception (a note names the cell);
    finished cells stay stored, the next run computes the rest.
    """
    from tqdm import tqdm

    from camo_sbi.distributed import DEFAULT_RETRIES, dask_client, map_unordered, parse_scheduler

    if not callable(fn):
        raise TypeError(f"fn: expected a callable, got {type(fn).__name__}")
    cells = list(cells)
    bad = next((c for c in cells if not isinstance(c, Cell)), None)
    if bad is not None:
        raise TypeError(f"cells: expected Cell objects, got {type(bad).__name__}")
    _check_int(workers, "workers", 1)
    if threads is not None:
        _check_int(threads, "threads", 1)
    try:
        remote = parse_scheduler(scheduler) is not None
    except ValueError as exc:
        raise ValueError(f"scheduler: {exc}") from None
    out = str(store.out)
    todo = pending(cells, store)
    task = functools.partial(_run_and_store, fn)
    bar = tqdm(total=len(todo), desc=progress if isinstance(progress, str) else "grid", unit="cell",
               disable=progress is False)
    done: list[str] = []

    def finished(key: str) -> None:
        done.append(key)
        bar.update()

    try:
        if remote:
            with dask_client(scheduler) as client:
                client.run(init_worker)
                for key in map_unordered(task, todo, client, retries=DEFAULT_RETRIES if retries is None else retries,
                                         out=out):
                    finished(key)
        elif workers == 1:
            _in_process(task, todo, out, bar, finished, threads)
        else:
            from camo_sbi.experiments.processes import run_in_processes

            done.extend(run_in_processes(task, todo, out, workers, on_done=bar.update, initializer=init_worker))
    finally:
        bar.close()
    return done


def _in_process(task, todo, out, bar, finished, threads) -> None:
    saved = None
    if threads is not None:
        import torch

        saved = torch.get_num_threads()
        torch.set_num_threads(threads)
    try:
        for cell in todo:
            bar.set_postfix_str(cell.label)
            finished(task(cell, out))
    finally:
        if saved is not None:
            import torch

            torch.set_num_threads(saved)
