"""The README's command 1 in a fresh clone: cold (every cache empty) against warm.

    python benchmarks/bench_first_run.py [--repeat 1] [--warmup] [--keep DIR]

Runs ``camo-sbi compare --seeds 1 --tasks 2 --out DIR`` (the README's command 1, install
excluded) in a fresh process:

    cold      XDG_CACHE_HOME and MPLCONFIGDIR -> empty temp dirs (numba's cache of the package's
              kernels, the generated chain kernels and matplotlib's font cache all start empty),
              NUMBA_CACHE_DIR and CAMO_SBI_KERNEL_CACHE unset, the package's own ``__pycache__``
              removed (a fresh clone has none)
    warm      the same caches again, a new output directory (the plain reference timed in the
              same run: everything cached, nothing re-used from the first run's results)

With ``--warmup`` the cold arm runs ``camo-sbi warmup`` first (timed apart and added to the
cold total: the README runs both). Wall time and the children's CPU time (getrusage) are
printed with the ratios cold / warm; the machine's load average is printed beside them.
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

ROOT = Path(__file__).resolve().parents[1]
CLI = str(Path(sys.executable).with_name("camo-sbi"))


def _clear_pycache() -> None:
    for d in (ROOT / "camo_sbi").rglob("__pycache__"):
        shutil.rmtree(d, ignore_errors=True)


def _timed(argv: list[str], env: dict) -> tuple[float, float, str]:
    """(wall s, CPU s of the child, its stderr) of one fresh process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run(argv, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed ({p.returncode}):\n{p.stderr[-3000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, p.stderr


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeat", type=int, default=1, help="cold/warm pairs (min taken)")
    p.add_argument("--warmup", action="store_true", help="run `camo-sbi warmup` before the cold run")
    p.add_argument("--keep", help="keep the last cold run's output here (e.g. for bench_report)")
    args = p.parse_args()
    rows: dict[str, list[tuple[float, float]]] = {"cold": [], "warmup": [], "warm": []}
    loads = []
    for _ in range(args.repeat):
        tmp = Path(tempfile.mkdtemp(prefix="camo_first_"))
        env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "CAMO_SBI_KERNEL_CACHE")}
        env.update(XDG_CACHE_HOME=str(tmp / "cache"), MPLCONFIGDIR=str(tmp / "mpl"))
        _clear_pycache()
        loads.append(os.getloadavg()[0])
        if args.warmup:
            w, c, _ = _timed([CLI, "warmup"], env)
            rows["warmup"].append((w, c))
        w, c, err = _timed([CLI, "compare", "--seeds", "1", "--tasks", "2", "--out", str(tmp / "cold")], env)
        notices = [ln for ln in err.splitlines() if "compiling" in ln]
        rows["cold"].append((w, c))
        w, c, _ = _timed([CLI, "compare", "--seeds", "1", "--tasks", "2", "--out", str(tmp / "warm")], env)
        rows["warm"].append((w, c))
        loads.append(os.getloadavg()[0])
        if args.keep:
            shutil.rmtree(args.keep, ignore_errors=True)
            shutil.copytree(tmp / "cold", args.keep)
        shutil.rmtree(tmp, ignore_errors=True)
    best = {k: (min(r[0] for r in v), min(r[1] for r in v)) for k, v in rows.items() if v}
    print(f"README command 1, {args.repeat} cold/warm pair(s), min; load average {min(loads):.2f}..{max(loads):.2f} "
          f"(2 cores, shared)")
    for k, (w, c) in best.items():
        print(f"  {k:8s} {w:7.1f} s wall  {c:7.1f} s CPU")
    cw, cc = best["cold"]
    if "warmup" in best:
        cw, cc = cw + best["warmup"][0], cc + best["warmup"][1]
        print(f"  {'cold total (warmup + compare)':30s} {cw:7.1f} s wall  {cc:7.1f} s CPU")
    print(f"  cold / warm: {cw / best['warm'][0]:.2f}x wall, {cc / best['warm'][1]:.2f}x CPU "
          f"(target: <= 40 s wall, <= 1.5x CPU)")
    print(f"  compile notices on the cold run's stderr: {notices or 'none'}")


if __name__ == "__main__":
    main()
