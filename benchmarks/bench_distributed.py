"""Speed-up of a Dask LocalCluster over in-process execution for a grid of independent cells.

    python benchmarks/bench_distributed.py [--scheduler local:2] [--seeds 4] [--budget 500]

The same `camo-sbi compare` grid (CAMO + naive on the Panda, ``--seeds`` seeds, ``--tasks``
observed tasks) runs twice into fresh directories: in-process, one cell after the other
(as ``compare`` without ``--scheduler``), then with its cells submitted to the cluster. One
warm-up cell runs first in each setting (numba / torch start-up) and is not timed; the
cluster's start-up is timed separately. The two tables must be identical (wall_time aside).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pandas as pd  # noqa: E402

from camo_sbi.distributed import dask_client, worker_count  # noqa: E402
from camo_sbi.experiments.compare import add_arguments, grid_cells, run_cell  # noqa: E402
from camo_sbi.experiments.grid import run_grid  # noqa: E402
from camo_sbi.experiments.store import ResultStore  # noqa: E402


def _table(out: Path) -> pd.DataFrame:
    df = ResultStore(out).table()
    df = df[df.metric != "wall_time"]
    return df.sort_values(["method", "seed", "n_tasks", "metric"]).reset_index(drop=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scheduler", default="local:2")
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--budget", type=int, default=500)
    ap.add_argument("--tasks", type=int, default=3)
    ap.add_argument("--methods", default="camo,naive")
    a = ap.parse_args(argv)
    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["--methods", a.methods, "--budgets", str(a.budget), "--seeds", str(a.seeds),
                         "--tasks", str(a.tasks), "--test-goals", "5"])
    specs = grid_cells(args)
    warm = grid_cells(p.parse_args(["--methods", "camo", "--budgets", "50", "--seeds", "1", "--tasks", "1",
                                    "--test-goals", "1", "--seed", "999"]))
    with tempfile.TemporaryDirectory(prefix="bench_distributed_") as tmp:
        tmp = Path(tmp)
        run_grid(run_cell, warm, ResultStore(tmp / "warm_inproc"), progress=False)
        t0 = time.perf_counter()
        run_grid(run_cell, specs, ResultStore(tmp / "inproc"), progress=False)
        t_in = time.perf_counter() - t0

        t0 = time.perf_counter()
        with dask_client(a.scheduler) as client:
            client.wait_for_workers(1)
            t_start = time.perf_counter() - t0
            # run_grid with the same spec reuses this open client
            run_grid(run_cell, warm, ResultStore(tmp / "warm_dask"), scheduler=a.scheduler, progress=False)
            t0 = time.perf_counter()
            run_grid(run_cell, specs, ResultStore(tmp / "dask"), scheduler=a.scheduler, progress=False)
            t_dask = time.perf_counter() - t0
            n_workers = worker_count(client)
        same = _table(tmp / "inproc").equals(_table(tmp / "dask"))
    print(f"grid: {len(specs)} cells ({a.methods}; budget {a.budget}, {a.tasks} tasks, {a.seeds} seeds)")
    print(f"in-process          : {t_in:8.2f} s")
    print(f"{a.scheduler:<20}: {t_dask:8.2f} s  ({n_workers} workers; cluster start-up {t_start:.2f} s not included)")
    print(f"speed-up            : {t_in / t_dask:8.2f}x")
    print(f"identical tables (wall_time aside): {same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
