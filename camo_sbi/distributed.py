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
import socket
import struct
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from urllib.parse import urlsplit

__all__ = ["CONNECT_TIMEOUT", "DEFAULT_RETRIES", "connect_early", "dask_client", "get_client", "local_scheduler", "map_ordered", "map_unordered", "parse_scheduler",
           "run_chunks", "worker_count"]

DEFAULT_RETRIES = 2
CONNECT_TIMEOUT = 10.0  # seconds to reach a scheduler address before giving up

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


_MAX_HANDSHAKE = 2**24  # bytes: a scheduler's handshake message is a few hundred


def _probe_tcp(address: str) -> None:
    """For a ``tcp://`` address, check within CONNECT_TIMEOUT that a Dask scheduler answers
    before handing the address to dask, whose handshake read neither times out on a silent peer
    nor bounds the length it allocates. On connection a scheduler writes its handshake first,
    framed as dask's messages are: an 8-byte length (native order, ``struct`` "Q"), then that many
    bytes; anything else (a refusal, silence, a closed connection, an HTTP reply) is an OSError."""
    url = urlsplit(address)
    if url.scheme.lower() != "tcp" or not url.hostname:
        return  # tls://, ucx://, ...: dask's own connect (and its timeout) alone
    deadline = time.monotonic() + CONNECT_TIMEOUT
    with socket.create_connection((url.hostname, url.port or 8786), timeout=CONNECT_TIMEOUT) as sock:
        header = b""
        while len(header) < 8:
            sock.settimeout(max(deadline - time.monotonic(), 0.01))
            try:
                chunk = sock.recv(8 - len(header))
            except TimeoutError:
                raise TimeoutError(f"no Dask handshake from {address} within {CONNECT_TIMEOUT:g} s") from None
            if not chunk:
                raise ConnectionError(f"{address} closed the connection without a Dask handshake")
            header += chunk
    (n,) = struct.unpack("Q", header)
    if not 0 < n <= _MAX_HANDSHAKE:
        raise ConnectionError(f"{address} answered {header!r}, not a Dask handshake")


def _start(spec: str):
    kind, value = parse_scheduler(spec)
    distributed = _import_distributed()
    if kind == "local":
        # single-threaded workers: torch / OpenMP threads would only oversubscribe the cores
        cluster = distributed.LocalCluster(n_workers=value, threads_per_worker=1, processes=True,
                                           dashboard_address=None)
        return distributed.Client(cluster), cluster
    try:
        _probe_tcp(value)
        return distributed.Client(value, timeout=CONNECT_TIMEOUT), None
    except Exception as exc:  # noqa: BLE001 - a wrong peer surfaces from dask's comm layer in many ways
        # nothing listening: OSError after the timeout; something else listening (an HTTP proxy on
        # the route): dask read its reply as a frame length (MemoryError "3.07 EiB"), a silent one
        # made it wait forever. All are the address's fault: one line naming it.
        detail = (str(exc).splitlines() or [""])[0][:200]
        raise ValueError(f"scheduler: cannot connect to a Dask scheduler at {value!r} within {CONNECT_TIMEOUT:g} s "
                         f"({type(exc).__name__}{': ' + detail if detail else ''}); is `dask scheduler` running "
                         f"there?") from None


def _close(client, cluster) -> None:
    try:
        client.close()
    finally:
        if cluster is not None:
            cluster.close()


@contextmanager
def local_scheduler() -> Iterator[None]:
    """Run the dask graphs built inside this block in this process (dask's synchronous scheduler).

    Inside a Dask worker, xarray otherwise takes a *distributed* write lock named after its write
    target, which an in-memory buffer cannot have ("Semaphore or Lock <BytesIO> not known"); a
    write that stays in this process needs no cluster lock. Without dask: nothing to do."""
    try:
        import dask
    except ImportError:  # dask is an optional dependency
        yield
        return
    with dask.config.set(scheduler="synchronous"):
        yield


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


def connect_early(spec: str | None) -> None:
    """Connect now to a scheduler *address* (`get_client`: the client is reused by the run), so an
    unreachable or wrong address is refused before a run folder or a cell is touched; ``local:N``
    and in-process start later, as before. ValueError naming ``scheduler`` otherwise."""
    parsed = parse_scheduler(spec)
    if parsed is not None and parsed[0] == "address":
        get_client(spec)


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

