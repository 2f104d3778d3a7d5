"""The command line's edges, each timed against today's path (``--baseline``, a git revision) in the
same run, fresh processes, wall and CPU time (user + system of the child; on a shared machine
the CPU time is the better guide to an idle one):

    help          ``camo-sbi --help`` and ``camo-sbi compare --help`` (interpreter start included)
    re-run        ``compare`` of a finished small grid into the same --out, with the report
                  (``--model panda --methods camo,naive --budgets 200 --seeds 1 --tasks 2``)
    report        (with --report-run DIR) ``camo-sbi report DIR`` rebuilt from scratch (this tree:
                  ``--force``; a cached report takes the re-run's path above)
    quickstart    (with --quickstart, minutes) README command 1's main job: this tree
                  ``compare --seeds 1 --tasks 2 --out DIR``, the baseline ``compare --out DIR``

The baseline runs from a ``git archive`` of the revision (default: main before issue 28's
branch, 171667f) unpacked in a temporary directory and put first on PYTHONPATH, so both sides
use this venv's packages and kernel caches. Each timing is the median of ``--repeats`` runs;
the ratio is baseline / this tree.

    python benchmarks/bench_cli.py [--repeats 5] [--baseline 171667f] [--report-run DIR] [--quickstart]
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TINY = ["compare", "--model", "panda", "--methods", "camo,naive", "--budgets", "200", "--seeds", "1",
        "--tasks", "2"]


def _tree(rev: str, into: Path) -> Path:
    """``git archive REV`` unpacked under ``into`` (the baseline's source tree)."""
    data = subprocess.run(["git", "archive", "--format=tar", rev], cwd=ROOT, capture_output=True, check=True).stdout
    tar = into / "baseline.tar"
    tar.write_bytes(data)
    with tarfile.open(tar) as t:  # not named like an importable package (cwd is on sys.path)
        t.extractall(into / "baseline-src", filter="data")
    return into / "baseline-src"


def _run(argv: list[str], source: Path, cwd: Path) -> tuple[float, float]:
    """(wall s, child CPU s) of ``python -m camo_sbi.experiments.cli ARGV`` with ``source`` first on the path."""
    env = {**os.environ, "PYTHONPATH": str(source), "MPLBACKEND": "Agg"}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "camo_sbi.experiments.cli", *argv], cwd=cwd, env=env,
                         capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} ({source}) exited {res.returncode}:\n{res.stderr[-3000:]}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def _median(runs):
    return statistics.median(r[0] for r in runs), statistics.median(r[1] for r in runs)


def _row(name: str, new, old) -> None:
    print(f"| {name} | {new[0]:.2f} s ({new[1]:.2f} s CPU) | {old[0]:.2f} s ({old[1]:.2f} s CPU) | "
          f"**{old[0] / new[0]:.1f}x** ({old[1] / new[1]:.1f}x CPU) |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--baseline", default="171667f", help="git revision of today's path")
    ap.add_argument("--quickstart", action="store_true", help="also time README command 1's main job (minutes)")
    ap.add_argument("--report-run", type=Path, default=None, help="also time the report of this run directory")
    args = ap.parse_args()
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        old_src, new_src = _tree(args.baseline, tmp), ROOT
        tmp = tmp / "work"  # every command runs here: nothing importable in its current directory
        tmp.mkdir()
        print(f"load average {load:.1f} on {os.cpu_count()} cores; baseline {args.baseline}; "
              f"median of {args.repeats}")
        print("| target | this tree | baseline | ratio |\n|---|---|---|---|")
        for argv in (["--help"], ["compare", "--help"]):
            new = _median([_run(argv, new_src, tmp) for _ in range(args.repeats)])
            old = _median([_run(argv, old_src, tmp) for _ in range(args.repeats)])
            _row(f"`camo-sbi {' '.join(argv)}`", new, old)
        # a finished grid with its report, then re-runs into copies of it (each side its own copy,
        # so neither re-run finds the other's outputs)
        grid = tmp / "grid"
        _run([*TINY, "--out", str(grid)], new_src, tmp)
        runs = {"new": [], "old": []}
        for i in range(args.repeats):
            for side, src in (("new", new_src), ("old", old_src)):
                out = tmp / f"{side}{i}" / "grid"
                shutil.copytree(grid, out)
                runs[side].append(_run([*TINY, "--out", str(out)], src, tmp))
        _row("re-run of a finished 4-cell compare, with the report", _median(runs["new"]), _median(runs["old"]))
        if args.report_run is not None:
            new = _run(["report", str(args.report_run), "-o", str(tmp / "new.html"), "--force"], new_src, tmp)
            old = _run(["report", str(args.report_run), "-o", str(tmp / "old.html")], old_src, tmp)
            _row(f"`camo-sbi report` of {args.report_run.name} from scratch (one run)", new, old)
        if args.quickstart:
            new = _run(["compare", "--seeds", "1", "--tasks", "2", "--out", str(tmp / "qs-new")], new_src, tmp)
            old = _run(["compare", "--out", str(tmp / "qs-old")], old_src, tmp)
            _row("quickstart: README command 1's main job (one run)", new, old)
        print(f"load average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
