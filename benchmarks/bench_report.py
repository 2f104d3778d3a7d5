"""`camo-sbi report RUN_DIR` from scratch in a fresh process: cold caches against warm ones.

    python benchmarks/bench_report.py RUN_DIR [--repeat 2]

RUN_DIR: a finished comparison (e.g. the quickstart's: ``camo-sbi compare --seeds 1 --tasks 2
--out runs/quickstart``, or ``bench_first_run.py --keep DIR``). Each arm writes the report to a
temporary file with ``--force`` (the report is never reused from its digest):

    cold     XDG_CACHE_HOME and MPLCONFIGDIR -> empty temp dirs (matplotlib's font cache and the
             chain kernel the predictive draws need start empty), as in a fresh clone
    cold+wu  the same after ``camo-sbi warmup`` in those caches (the warmup not timed)
    warm     the caches the cold arm filled (the plain reference timed in the same run)

Prints wall and the child's CPU time (getrusage), min over the repeats, the ratios against warm,
and the load average (the machine is shared: CPU time is the better guide to an idle one).
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CLI = str(Path(sys.executable).with_name("camo-sbi"))


def _timed(argv, env) -> tuple[float, float]:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run(argv, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed:\n{p.stderr[-3000:]}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dir")
    p.add_argument("--repeat", type=int, default=2)
    p.add_argument("--no-warmup-arm", action="store_true", help="skip the cold+wu arm")
    args = p.parse_args()
    rows: dict[str, list] = {"cold": [], "cold+wu": [], "warm": []}
    loads = []
    base = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "CAMO_SBI_KERNEL_CACHE")}
    for _ in range(args.repeat):
        tmp = Path(tempfile.mkdtemp(prefix="camo_report_"))
        loads.append(os.getloadavg()[0])
        env = {**base, "XDG_CACHE_HOME": str(tmp / "a"), "MPLCONFIGDIR": str(tmp / "a" / "mpl")}
        report = [CLI, "report", args.run_dir, "--force", "-o", str(tmp / "r.html")]
        rows["cold"].append(_timed(report, env))
        rows["warm"].append(_timed(report, env))
        if not args.no_warmup_arm:
            env_wu = {**base, "XDG_CACHE_HOME": str(tmp / "b"), "MPLCONFIGDIR": str(tmp / "b" / "mpl")}
            subprocess.run([CLI, "warmup"], env=env_wu, capture_output=True, check=True)
            rows["cold+wu"].append(_timed(report, env_wu))
        loads.append(os.getloadavg()[0])
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"camo-sbi report {args.run_dir} --force: {args.repeat} repeat(s), min; load average "
          f"{min(loads):.2f}..{max(loads):.2f} (2 cores, shared)")
    warm = min(r[0] for r in rows["warm"]), min(r[1] for r in rows["warm"])
    for k, v in rows.items():
        if v:
            w, c = min(r[0] for r in v), min(r[1] for r in v)
            print(f"  {k:8s} {w:7.1f} s wall {c:7.1f} s CPU   / warm: {w / warm[0]:.2f}x wall, {c / warm[1]:.2f}x CPU")


if __name__ == "__main__":
    main()
