"""How far today's DTW code is from its golden values (tests/data/dtw_golden.npz) on this CPU,
or on another CPU emulated through the compilers' own switches (docs/guide/reproducibility.md):

    NUMBA_CACHE_DIR=$(mktemp -d) NUMBA_CPU_NAME=generic ATEN_CPU_CAPABILITY=default \\
        .venv/bin/python docs/studies/golden_drift.py

Prints how many finite values differ from the golden ones and the largest relative difference
(the tests allow 1e-12).
"""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from tests.test_distances import _GOLDEN, _GOLDEN_CASES, _check_golden_case  # noqa: E402

golden = dict(np.load(_GOLDEN))
worst, differ, total = 0.0, 0, 0


def check(got, want, what):
    global worst, differ, total
    got, want = np.asarray(got), np.asarray(want)
    m = np.isfinite(want) & np.isfinite(got)
    differ += int((got[m] != want[m]).sum())
    total += int(m.sum())
    if m.any():
        worst = max(worst, float((np.abs(got[m] - want[m]) / np.maximum(np.abs(want[m]), 1e-300)).max()))


for case in _GOLDEN_CASES:
    _check_golden_case(golden, case, check, lambda got, want, full, kw, what: check(got, want, what))
print(f"values differing from golden: {differ} of {total}; max relative difference {worst:.3g}")
