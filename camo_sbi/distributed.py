"""Optional Dask execution: the only module importing ``dask`` / ``distributed`` (lazily).

A *scheduler spec* selects where work runs:

- ``None`` (or ``""``): in-process, no Dask at all;
- ``"local:N"``: a `distributed.LocalCluster` with N worker processes, one thread each;
- ``"tcp://host:port"`` (any ``scheme://`` address): an existing cluster (``dask scheduler`` +
  ``dask worker``, or a dask-jobqueue ``SLURMCluster``).

Work is split into chunks whose random streams are derived from the seed and the chunk
index, never from the worker, and results are gathered in submission order, so the numbers
do not depend on the number of workers (or on Dask being used). Tasks are retried by Dask
(``retries``) when a worker dies, so finished work is never lost.
"""

from __future__ import annotations

import atexit
import re
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager

__all__ = ["DEFAULT_RETRIES", "dask_client", "get_client", "map_ordered", "map_unordered", "parse_scheduler",
           "run_chunks", "worker_count"]

DEFAULT_RETRIES = 2

_LOCAL = re.compile(r"^local:(\d+)$")
_ADDRESS = re.compile(r"^[a-z][a-z0-9+.-]*://\S+$", re.IGNORECASE)
_CLIENTS: dict[str, tuple[object, object | None]] = {}  # spec -> (client, cluster or None)


def parse_scheduler(spec: str | None) -> None | tuple[str, int] | tuple[str, str]:
    """``None`` (in-process), ``("local", n)`` or ``("address", addr)``; ValueError otherwise."""
    if spec is None:
        return None
    if not isinstance(spec, str):
        raise ValueError(f"scheduler: expected None, 'local:N' or 'tcp://host:port', got {type(spec).__name__}")
    text = spec.strip()
    if not text:
        return None
    m = _LOCAL.match(text)
    if m:
        n = int(m.group(1))
        if n < 1:
            raise ValueError(f"scheduler: 'local:N' needs N >= 1, got {spec!r}")
        return ("local", n)
    if _ADDRESS.match(text):
        return ("address", text)
    raise ValueError(f"scheduler: expected 'local:N' (N >= 1) or an address like 'tcp://host:8786', got {spec!r}")


def _import_distributed():
    try:
        import distributed
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("scheduler: Dask is not installed; pip install 'camo_sbi[dask]'") from exc
    return distributed


def _start(spec: str):
    kind, value = parse_scheduler(spec)
    distributed = _import_distributed()
    if kind == "local":
        # single-threaded workers: torch / OpenMP threads would only oversubscribe the cores
        cluster = distributed.LocalCluster(n_workers=value, threads_per_worker=1, processes=True,
                                           dashboard_address=None)
        return distributed.Client(cluster), cluster
    return distributed.Client(value), None


def _close(client, cluster) -> None:
    try:
        client.close()
    finally:
        if cluster is not None:
            cluster.close()


@contextmanager
def dask_client(spec: str | None) -> Iterator[object | None]:
    """A `distributed.Client` for ``spec`` for the duration of the block (None: in-process).

    ``local:N`` starts a LocalCluster that is closed on exit; an address connects to an
    existing cluster (which stays up). Inside the block, `get_client` with the same spec
    (e.g. from a method whose config carries ``scheduler``) reuses this client.
    """
    if parse_scheduler(spec) is None:
        yield None
        return
    key = spec.strip()
    if key in _CLIENTS:  # already open (an outer block or get_client): reuse, leave it open
        yield _CLIENTS[key][0]
        return
    client, cluster = _start(key)
    _CLIENTS[key] = (client, cluster)
    try:
        yield client
    finally:
        _CLIENTS.pop(key, None)
        _close(client, cluster)


def get_client(spec: str | None):
    """The client for ``spec`` (None for in-process), started once per process and reused.

    Clients started here (not inside a `dask_client` block) are closed at interpreter exit.
    """
    if parse_scheduler(spec) is None:
        return None
    key = spec.strip()
    if key not in _CLIENTS:
        _CLIENTS[key] = _start(key)
    return _CLIENTS[key][0]


@atexit.register
def _close_all() -> None:  # pragma: no cover - interpreter shutdown
    while _CLIENTS:
        _, (client, cluster) = _CLIENTS.popitem()
        try:
            _close(client, cluster)
        except Exception:
            pass


def map_ordered(fn: Callable, items: Iterable, client=None, *, retries: int = DEFAULT_RETRIES,
                **shared) -> list:
    """``[fn(item, **shared) for item in items]``, on ``client``'s workers if it is not None.

    Results come back in the order of ``items`` whatever worker ran them; a task whose
    worker dies is resubmitted up to ``retries`` times. ``fn`` and ``shared`` must pickle.
    """
    items = list(items)
    if client is None:
        return [fn(item, **shared) for item in items]
    futures = client.map(fn, items, pure=False, retries=retries, **shared)
    return client.gather(futures)


def map_unordered(fn: Callable, items: Iterable, client=None, *, retries: int = DEFAULT_RETRIES,
                  **shared) -> Iterator:
    """Yield ``fn(item, **shared)`` for every item as each finishes (in order when in-process).

    On a client each item is one task, resubmitted up to ``retries`` times if its worker dies.
    """
    items = list(items)
    if client is None:
        for item in items:
            yield fn(item, **shared)
        return
    from distributed import as_completed

    futures = [client.submit(fn, item, pure=False, retries=retries, **shared) for item in items]
    for future in as_completed(futures):
        yield future.result()


def run_chunks(fn: Callable, jobs: Iterable, *, simulator, n_simulations: int, scheduler: str | None,
               **shared) -> list:
    """The one Dask path every method uses: ``[fn(job, simulator=..., **shared) for job in jobs]``.

    In-process (``scheduler`` None) every chunk calls the given, budget-counting simulator,
    which counts (and refuses) each call before it simulates. On Dask, ``n_simulations``
    (what the chunks will simulate in total) is charged to the counting wrappers FIRST,
    before anything runs, and the workers get the unwrapped simulator. Results come back
    in the order of ``jobs``.
    """
    client = get_client(scheduler)
    if client is None:
        return map_ordered(fn, jobs, None, simulator=simulator, **shared)
    # imported here, not at the top: parsing --scheduler needs neither numpy nor torch
    from camo_sbi.budget import charge, unwrap_simulator

    charge(simulator, n_simulations)
    return map_ordered(fn, jobs, client, simulator=unwrap_simulator(simulator), **shared)


def worker_count(client) -> int:
    """Number of workers currently connected (1 for in-process)."""
    if client is None:
        return 1
    return max(len(client.scheduler_info().get("workers", {})), 1)

