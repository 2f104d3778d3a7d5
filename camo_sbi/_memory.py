"""What a grid of runs costs in memory, known before anything is built (no torch: a
re-run of a finished grid imports none)."""

from __future__ import annotations

import os

__all__ = ["check_grid_fits", "physical_memory", "size_text"]


def physical_memory() -> int:
    """Bytes of physical memory of this machine (0 when unknown)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 0


def size_text(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if n < 1024 or unit == "PB":
            return f"{n:.3g} {unit}"
        n /= 1024
    return f"{n:.3g} PB"  # pragma: no cover


# lower bounds measured on this codebase (tracemalloc / ru_maxrss, 2026-12): a grid cell with its
# key takes ~1.25 KB, a worker process that imported torch and camo_sbi ~280 MB
_CELL_BYTES = 1000
_ROW_BYTES = 100  # one tidy result row (8 fields) in the combined table, far more in a DataFrame
_WORKER_BYTES = 200 * 2**20


def check_grid_fits(*, seeds: int, cells_per_seed: int, tasks: int, test_goals: int, n_joints: int = 1,
                    max_steps: int = 1, workers: int = 1, names: dict | None = None,
                    memory_bytes: int | None = None) -> int:
    """Refuse, before anything is built, a grid whose counts this machine cannot hold; returns
    the least memory it needs (bytes).

    The estimate is a lower bound: every cell (``seeds * cells_per_seed`` of them: subjects x
    methods x budgets x seeds) is held as a `Cell` (>= 1 KB) and leaves ``tasks`` result rows
    (>= 100 B each) in the combined table; each cell in flight holds its ``tasks + test_goals``
    reaches (``max_steps`` points of ``n_joints + 3`` float64); each extra worker process holds
    torch (>= 200 MB). ValueError naming the count whose reduction to 1 saves the most
    (``names`` maps seeds, tasks, test_goals and workers to the flag or key a user sets) when
    that alone exceeds the physical memory (``memory_bytes``).
    """
    names = {k: k for k in ("seeds", "tasks", "test_goals", "workers")} | dict(names or {})
    counts = {"seeds": seeds, "tasks": tasks, "test_goals": test_goals, "workers": workers}
    for key, v in counts.items():  # not _validation's check: it imports torch
        if isinstance(v, bool) or not isinstance(v, int):
            raise TypeError(f"{names[key]}: expected an integer, got {type(v).__name__}")
        if v < 1:
            raise ValueError(f"{names[key]}: must be >= 1, got {v}")

    def need(c: dict) -> int:
        cells = c["seeds"] * int(cells_per_seed)
        in_flight = min(c["workers"], cells)
        return (cells * (_CELL_BYTES + c["tasks"] * _ROW_BYTES)
                + in_flight * (c["tasks"] + c["test_goals"]) * int(max_steps) * (int(n_joints) + 3) * 8
                + (in_flight - 1) * _WORKER_BYTES)

    total = need(counts)
    avail = physical_memory() if memory_bytes is None else int(memory_bytes)
    if avail and total > avail:
        culprit = min(counts, key=lambda k: need({**counts, k: 1}))
        cells = seeds * int(cells_per_seed)
        raise ValueError(f"{names[culprit]}: {counts[culprit]} is too large: the grid ({cells} cells of {tasks} "
                         f"tasks and {test_goals} test goals, {workers} worker(s)) needs at least {size_text(total)} "
                         f"of memory, this machine has {size_text(avail)}; make {names[culprit]} smaller")
    return total
