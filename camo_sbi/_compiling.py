"""One line when camo_sbi's numba kernels are compiled rather than loaded from their cache.

The first time in a process that numba compiles one of camo_sbi's kernels, `announce_compiling`'s
listener logs one line for each of three kinds (the package's small kernels: the DTW of small
calls and the KDE; the pruned DTW cascade that larger calls use; a body model's generated chain
kernels), e.g.

    compiling camo_sbi's kernels (once, about <COMPILE_SECONDS> s; later runs load them from ...)

through the ``camo_sbi`` logger at the warning level: the CLI shows it unless -q, and with no
handler configured Python prints it on stderr. A kernel loaded from numba's cache fires no
``numba:compile`` event, so a warm run prints nothing. ``camo-sbi warmup`` compiles ahead.
Only a top-level compilation is classified: the kernels a kernel calls compile inside its event.
"""

from __future__ import annotations

import logging
import os
import threading

__all__ = ["COMPILE_SECONDS", "announce_compiling"]

COMPILE_SECONDS = {"package": 2, "cascade": 12, "chain": 3}
"""About how long a first compile takes on 2 cores (CPU seconds, measured in
docs/guide/performance.md): the package's small kernels (a quickstart compiles only these); the
pruned DTW cascade (`camo_sbi.inference.distances.chunks`' entry points for large calls); one
chain's kernel in one precision."""

CASCADE = frozenset({"dtw_chunk", "coarse_chunk", "fine_bounds"})
"""The entry points of the pruned DTW cascade (their callees compile inside their events)."""

_WHAT = {"package": "camo_sbi's DTW and KDE kernels",
         "cascade": "camo_sbi's pruned DTW kernels for large batches",
         "chain": "a body model's chain kernels"}

_state = {"installed": False, "said": set()}
_depth = threading.local()
_lock = threading.Lock()
log = logging.getLogger("camo_sbi.compiling")


def _cache_home() -> str:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join("~", ".cache")
    return os.path.join(base, "camo_sbi")


def _kind(module: str, name: str) -> str | None:
    if module.startswith("camo_sbi_kernel_"):
        return "chain"
    if not module.startswith("camo_sbi"):
        return None
    return "cascade" if module.startswith("camo_sbi.inference.distances") and name in CASCADE else "package"


def _on_compile(module: str, name: str = "") -> None:
    kind = _kind(module, name)
    if kind is None:
        return
    with _lock:
        if kind in _state["said"]:
            return
        _state["said"].add(kind)
    log.warning("compiling %s (once, about %d s; later runs load them from %s; `camo-sbi warmup` compiles "
                "them ahead)", _WHAT[kind], COMPILE_SECONDS[kind], _cache_home())


def announce_compiling() -> None:
    """Install, once per process, the listener that logs the notice at the first compilation of a
    camo_sbi kernel of each kind (numba's ``numba:compile`` event; loading from the cache fires none)."""
    with _lock:
        if _state["installed"]:
            return
        _state["installed"] = True
    from numba.core import event

    class _Notice(event.Listener):
        def on_start(self, ev):
            depth = getattr(_depth, "n", 0)
            _depth.n = depth + 1
            if depth == 0:
                f = getattr((ev.data or {}).get("dispatcher"), "py_func", None)
                _on_compile(getattr(f, "__module__", "") or "", getattr(f, "__name__", "") or "")

        def on_end(self, ev):
            _depth.n = max(getattr(_depth, "n", 1) - 1, 0)

    event.register("numba:compile", _Notice())
