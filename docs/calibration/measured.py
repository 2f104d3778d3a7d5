"""Write camo_sbi/diagnostics/calibration_measured.csv from the measured calibration runs here.

    python docs/calibration/measured.py          # after re-running a `camo-sbi calibrate` below

Each folder of docs/calibration/ holds one `camo-sbi calibrate` run (its command in summary.txt
or COMMAND.txt); the package file keeps, per model and method, the pooled coverage deviation
that `camo_sbi.diagnostics.verdicts` turns into a verdict (`infer`'s limits.csv, the docs).
tests/test_docs_site.py checks that the package file equals what this script writes.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

from camo_sbi.diagnostics import verdicts

HERE = Path(__file__).resolve().parent
RUNS = ("panda", "human", "amortized-panda", "amortized-human")
"""The measured runs, in the order their models are listed (panda first)."""
TARGET = Path(verdicts.__file__).with_name(verdicts.MEASURED)


def measured_text() -> str:
    rows = []
    for run in RUNS:
        with open(HERE / run / "coverage.csv", newline="") as f:
            rows += verdicts.measured_rows(csv.DictReader(f), f"docs/calibration/{run}/coverage.csv")
    return verdicts.write_measured(rows)


def main() -> int:
    TARGET.write_text(measured_text())
    print(f"wrote {TARGET}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
