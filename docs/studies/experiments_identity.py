"""Compare two folders of `reproduce` runs made by two versions of the code (issue 37: reproduce
panda and reproduce hrc moved onto the grid runner). For each experiment folder present in both:
the cell file names (the cell keys), results.csv with the timing rows left out (metric
`wall_time` / `compile_time` / `design_wall_time` / `import_time`: they differ between any two runs) and claims.csv, exactly.

    python docs/studies/experiments_identity.py BASE_DIR BRANCH_DIR

Prints one line per experiment and exits 1 if any differs. See experiments_identity.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd

TIMINGS = ("wall_time", "compile_time", "design_wall_time", "import_time")


def compare(a: Path, b: Path) -> list[str]:
    problems = []
    ca, cb = sorted(p.name for p in (a / "cells").iterdir()), sorted(p.name for p in (b / "cells").iterdir())
    if ca != cb:
        problems.append(f"cell names differ ({len(ca)} vs {len(cb)})")
    ra, rb = (pd.read_csv(d / "results.csv") for d in (a, b))
    ra, rb = (df[~df.metric.isin(TIMINGS)].reset_index(drop=True) for df in (ra, rb))
    try:
        pd.testing.assert_frame_equal(ra, rb, check_exact=True)
    except AssertionError as exc:
        problems.append(f"results.csv differs: {str(exc).splitlines()[0]}")
    try:
        pd.testing.assert_frame_equal(pd.read_csv(a / "claims.csv"), pd.read_csv(b / "claims.csv"), check_exact=True)
    except AssertionError as exc:
        problems.append(f"claims.csv differs: {str(exc).splitlines()[0]}")
    n = len(ra)
    return problems or [f"identical: {len(ca)} cells, {n} rows (timings aside), claims.csv"]


def main(argv=None) -> int:
    base, branch = (Path(x) for x in (argv or sys.argv[1:]))
    bad = False
    for d in sorted(p for p in base.iterdir() if (p / "results.csv").exists()):
        other = branch / d.name
        if not (other / "results.csv").exists():
            print(f"{d.name}: missing in {branch}")
            bad = True
            continue
        lines = compare(d, other)
        bad |= not lines[0].startswith("identical")
        print(f"{d.name}: " + "; ".join(lines))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
