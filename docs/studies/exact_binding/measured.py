"""Write camo_sbi/diagnostics/untouched_measured.csv from the binding-bound rows here.

    python docs/studies/exact_binding/measured.py     # after re-running exact_binding_bounds.py

Each ``{model}_s{seed}.csv`` (exact-likelihood, naive, camo-seq) and ``{model}_s{seed}_others.csv``
(every other posterior method, on the very same runs) holds `docs/studies/exact_binding_bounds.py`'s
rows. The package file keeps, per model and method, how many of the untouched binding bounds
(no training reach touched them) the method's 90% interval covered, pooled over the seeds run;
`camo_sbi.diagnostics.verdicts.untouched_verdict` turns it into the verdict that `infer`'s
limits.csv and report carry. tests/test_docs_site.py checks that the package file equals what
this script writes.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

from camo_sbi.diagnostics import verdicts

HERE = Path(__file__).resolve().parent
MODELS = ("panda", "human")
TARGET = Path(verdicts.__file__).with_name(verdicts.UNTOUCHED_MEASURED)


def measured_text() -> str:
    out = []
    for model in MODELS:
        files = sorted(HERE.glob(f"{model}_s*.csv"))
        rows = []
        for f in files:
            with open(f, newline="") as fh:
                rows += list(csv.DictReader(fh))
        source = " ".join(f"docs/studies/exact_binding/{f.name}" for f in files)
        out += verdicts.untouched_rows(rows, source)
    return verdicts.write_untouched(out)


def main() -> int:
    TARGET.write_text(measured_text())
    print(f"wrote {TARGET}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
