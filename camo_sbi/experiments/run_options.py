"""The options the experiment commands share, declared once: ``--seed``, ``--workers``,
``--scheduler``, ``--wait`` and ``--out``.

Light on purpose (argparse and pathlib only): every command's parser is built at start-up.
``--workers`` and ``--scheduler`` are the grid runner's (`camo_sbi.experiments.grid.run_grid`);
with neither a command runs in-process. None of them but ``--seed`` changes a result
(`rundir.RUNTIME_OPTIONS`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["add_run_options"]

WORKERS_HELP = "parallel worker processes (without --scheduler); the same table with any number"
SCHEDULER_HELP = ("run the cells on Dask: 'local:N' (a LocalCluster with N worker processes) or a scheduler "
                  "address 'tcp://host:8786'; default: in-process / --workers")
WAIT_HELP = "if another run holds --out, wait for it instead of stopping"


def add_run_options(p: argparse.ArgumentParser, *, out: str | None, out_help: str | None = None,
                    seed_help: str = "base seed", grid: bool = True) -> None:
    """``--seed``; with ``grid`` ``--workers`` and ``--scheduler``; ``--wait``; ``--out`` (default
    ``out``, or required when ``out`` is None)."""
    p.add_argument("--seed", type=int, default=0, help=seed_help)
    if grid:
        p.add_argument("--workers", type=int, default=1, help=WORKERS_HELP)
        p.add_argument("--scheduler", default=None, help=SCHEDULER_HELP)
    p.add_argument("--wait", action="store_true", help=WAIT_HELP)
    if out is None:
        p.add_argument("--out", type=Path, required=True, help=out_help)
    else:
        p.add_argument("--out", type=Path, default=Path(out), help=out_help)
