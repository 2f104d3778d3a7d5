"""One line when camo_sbi's numba kernels are compiled rather than loaded from their cache.

The first time in a process that numba compiles one of camo_sbi's kernels, `announce_compiling`'s
listener logs one line for each of the two kinds (the package's DTW and KDE kernels; a body
model's generated chain kernels), e.g.

    compiling camo_sbi's kernels (once, about <COMPILE_SECONDS> s; later runs load them from ...)

through the ``camo_sbi`` logger at the warning level: the CLI shows it unless -q, and with no
handler configured Python prints it on stderr. A kernel loaded from numba's cache fires no
``numba:compile`` event, so a warm run prints nothing. ``camo-sbi warmup`` compiles ahead.
"""

from __future__ import annotations

import logging
import os
import threading

__all__ = ["COMPILE_SECONDS", "announce_compiling"]

COMPILE_SECONDS = {"package": 20, "chain": 3}
"""About how long a first compile takes on 2 cores (CPU seconds, measured in
docs/guide/performance.md): the package's kernels of a quickstart run; one chain's kernel."""

_state = {"installed": False, "said": set()}
_lock = threading.Lock()
log = logging.getLogger("camo_sbi.compiling")


def _cache_home() -> str:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join("~", ".cache")
    return os.path.join(base, "camo_sbi")


def _on_compile(module: str) -> None:
    if not module.startswith("camo_sbi"):
        return
    kind = "chain" if module.startswith("camo_sbi_kernel_") else "package"
    with _lock:
        if kind in _state["said"]:
            return
        _state["said"].add(kind)
    what = "a body model's chain kernels" if kind == "chain" else "camo_sbi's DTW and KDE kernels"
    n = COMPILE_SECONDS[kind]
    log.warning("compiling %s (once, about %d s; later runs load them from %s; `camo-sbi warmup` compiles "
                "them ahead)", what, n, _cache_home())


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
            d = (ev.data or {}).get("dispatcher")
            _on_compile(getattr(getattr(d, "py_func", None), "__module__", "") or "")

        def on_end(self, ev):
            pass

    event.register("numba:compile", _Notice())
