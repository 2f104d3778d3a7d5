"""The claims tables: Holm, the paired tests and every claim's verdict on synthetic result tables."""

import numpy as np
import pandas as pd
import pytest

from camo_sbi.evaluation.claims import (
    CLAIM_COLUMNS,
    bootstrap_ci,
    holm,
    hrc_claims,
    manipulator_claims,
    paired_less,
)


def test_holm_hand_computed():
    # sorted p: 0.01 (x4 = 0.04), 0.02 (x3 = 0.06), 0.03 (x2 = 0.06), 0.5 (x1 = 0.5)
    np.testing.assert_allclose(holm([0.03, 0.01, 0.5, 0.02]), [0.06, 0.04, 0.5, 0.06])
    np.testing.assert_allclose(holm([0.9, 0.8]), [1.0, 1.0])  # 2 x 0.8 capped at 1; monotone after it
    assert np.isnan(holm([0.1, np.nan])[1])


def test_paired_less_and_bootstrap():
    rng = np.random.default_rng(0)
    d = rng.normal(-1.0, 0.5, size=30)
    assert paired_less(d) < 1e-6 and paired_less(-d) > 0.99
    assert paired_less(np.zeros(10)) == 1.0  # no evidence at all
    lo, hi = bootstrap_ci(d)
    assert lo < d.mean() < hi and hi - lo < 0.5
    assert bootstrap_ci(d) == bootstrap_ci(d)  # fixed seed: reproducible


def _manipulator_table(camo_offset: float, n_runs: int = 30, seed: int = 0) -> pd.DataFrame:
    """A synthetic reproduce-panda table: errors fall with tasks; CAMO = naive + offset."""
    rng = np.random.default_rng(seed)
    rows = []
    for run in range(n_runs):
        for k in range(1, 6):
            base = 100.0 / k + 50.0 + rng.normal(0, 1)
            vals = {"naive": base, "nominal": 60.0 + rng.normal(0, 1),
                    "camo-js": base + camo_offset + rng.normal(0, 0.5) - (20 if k >= 3 else 0),
                    "camo-cs": base + camo_offset + rng.normal(0, 0.5) - (20 if k >= 3 else 0)}
            for m, v in vals.items():
                for metric in ("cartesian_error_mm", "joint_error_deg"):
                    rows.append({"run": run, "method": m, "n_tasks": k, "metric": metric, "value": v})
    return pd.DataFrame(rows)


def test_manipulator_claims_verdicts():
    df = _manipulator_table(camo_offset=-30.0)
    c = manipulator_claims(df, setting="toolkit")
    assert list(c.columns) == list(CLAIM_COLUMNS)
    below = c[c.claim.str.startswith("CAMO is below") & c.statistic.str.startswith("cartesian_error_mm")]
    assert set(below.baseline) == {"naive", "nominal"}
    # below naive at every k: yes; below nominal at every k: no (150 - 30 > 60 at k = 1)
    assert below[below.baseline == "naive"].holds.all()
    assert not below[below.baseline == "nominal"].holds.any()
    equiv = c[c.claim.str.startswith("CS is as good as JS")]
    assert len(equiv) == 1 and bool(equiv.holds.iloc[0])
    conv = c[c.claim == "CAMO converges within 3 tasks"]
    assert len(conv) == 2 and conv.holds.all()  # 100/k levels off and the -20 step comes at k = 3
    assert (c.p_value >= c.p_raw).all()  # Holm never lowers a p-value


def test_manipulator_claims_a_method_that_does_not_beat_naive():
    c = manipulator_claims(_manipulator_table(camo_offset=+25.0), setting="toolkit")
    fig3 = c[c.claim.str.contains("Fig. 3") & (c.baseline == "naive")]
    assert len(fig3) == 2 and not fig3.holds.any()
    below = c[c.claim.str.startswith("CAMO is below") & (c.baseline == "naive")]
    assert not below.holds.any()


def test_hrc_claims_verdicts():
    rng = np.random.default_rng(1)
    rows = []
    for prior in ("strong", "weak"):
        for run in range(10):
            for k in (1, 2, 3):
                vals = {"camo-js": (0.9 + rng.normal(0, 0.01), 0.99, 0.94),
                        "naive": (1.0, 0.5 + 0.1 * k, 0.6 + rng.normal(0, 0.02)),
                        "nominal": (0.5, 1.0, 0.6 + rng.normal(0, 0.02)),
                        "majority": (0.0, 0.0, 0.0)}
                for m, (p, r, f) in vals.items():
                    for metric, v in (("precision", p), ("recall", r), ("f1", f)):
                        rows.append({"run": run, "prior": prior, "method": m, "n_tasks": k, "metric": metric,
                                     "value": v})
    c = hrc_claims(pd.DataFrame(rows))
    level = c[c.claim.str.startswith("precision about 0.85")]
    assert len(level) == 4 and level.holds.all()
    better = c[c.claim.str.startswith("CAMO allocates better")]
    assert len(better) == 4 and better.holds.all()
    majority = c[c.claim.str.startswith("the naive method stays")]
    assert len(majority) == 2 and not majority.holds.any()  # naive's F1 is far above the majority's 0


@pytest.mark.parametrize("table", [pd.DataFrame(columns=["run", "method", "n_tasks", "metric", "value"])])
def test_empty_tables_give_empty_claims(table):
    assert manipulator_claims(table.astype({"n_tasks": int}), setting="x").empty
