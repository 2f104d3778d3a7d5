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


def _series_table(curves: dict, n_runs: int = 12, seed: int = 0) -> pd.DataFrame:
    """Cartesian errors after 1..K tasks per method: ``curves[m]`` (K,) plus small run noise."""
    rng = np.random.default_rng(seed)
    rows = []
    for run in range(n_runs):
        for m, curve in curves.items():
            for k, v in enumerate(curve, start=1):
                rows.append({"run": run, "method": m, "n_tasks": k, "metric": "cartesian_error_mm",
                             "value": v + rng.normal(0, 0.05)})
    return pd.DataFrame(rows)


def test_convergence_claim_on_rising_falling_and_flat_series():
    """Converged after 3 tasks: within the tolerance of the final error AND no later rise beyond
    it, and the error fell at all. A rising series never holds (the DH arm's camo-js went from
    2.58 mm after 3 tasks to 3.22 mm after 10, and was once counted as converged)."""
    K = 10
    curves = {
        "camo-js": np.linspace(2.0, 2.6, K),  # rising throughout
        "camo-cs": np.r_[4.0, 3.0, 2.58, np.linspace(2.6, 3.22, K - 3)],  # falls, then rises after task 3
        "camo-seq": np.r_[10.0, 4.0, 2.0, np.full(K - 3, 2.0)],  # falls and levels off by task 3
        "camo-seq-cs": np.r_[10.0, 8.0, 6.0, np.linspace(5.0, 2.0, K - 3)],  # still falling after task 3
        "camo-hull": np.full(K, 3.0),  # flat: never learned
    }
    c = manipulator_claims(_series_table(curves), setting="paper")
    conv = c[c.claim == "CAMO converges within 3 tasks"].set_index("method")
    assert conv.loc["camo-seq", "holds"]
    for m in ("camo-js", "camo-cs", "camo-seq-cs", "camo-hull"):
        assert not conv.loc[m, "holds"], m
    assert conv.loc["camo-cs", "value"] > 0.5  # the rise after task 3 is in the gap
    assert set(conv.variant) >= {"the authors' JS, as their code runs it", "Algorithm 1 as written, JS"}


def test_convergence_gap_definition():
    from camo_sbi.evaluation.claims import convergence_gap

    e = np.array([[5.0, 3.0, 2.0, 2.0, 2.0],   # converged at 3: gap 0
                  [5.0, 3.0, 2.0, 2.5, 2.0],   # returns to 2 but rose by 0.5 in between
                  [5.0, 3.0, 2.0, 1.5, 1.0],   # still falling: |2 - 1|
                  [1.0, 2.0, 3.0, 4.0, 5.0]])  # rising: both parts
    np.testing.assert_allclose(convergence_gap(e, 3), [0.0, 0.5, 1.0, 2.0])
    with pytest.raises(ValueError, match="^errors:"):
        convergence_gap(e, 6)


def test_paper_claims_are_attributed_to_the_authors_variants():
    df = _manipulator_table(camo_offset=-30.0)
    df = pd.concat([df, df[df.method == "camo-js"].assign(method="camo-seq"),
                    df[df.method == "camo-cs"].assign(method="camo-seq-cs")])
    c = manipulator_claims(df, setting="paper")
    equiv = c[c.claim.str.startswith("CS is as good as JS")]
    assert set(zip(equiv.method, equiv.baseline, strict=True)) == {("camo-cs", "camo-js"), ("camo-seq-cs", "camo-seq")}
    v = dict(zip(c.method, c.variant, strict=True))
    assert v["camo-seq"].startswith("the authors' JS") and v["camo-seq-cs"].startswith("the authors' CS")
    assert v["camo-js"].startswith("Algorithm 1 as written")


def test_bootstrap_ci_is_scipy_s_percentile_bootstrap_of_the_same_resamples():
    """scipy.stats.bootstrap draws the same (10000, n) resample indices as the hand-written percentile
    bootstrap it replaced; the two intervals agree to rounding (the README's intervals are unchanged)."""
    from camo_sbi.evaluation.claims import _BOOT

    rng = np.random.default_rng(3)
    for n in (2, 5, 30):
        x = rng.normal(2.0, 10.0, size=n)
        means = x[np.random.default_rng(0).integers(0, n, size=(_BOOT, n))].mean(axis=1)
        expected = np.quantile(means, [0.025, 0.975])
        np.testing.assert_allclose(bootstrap_ci(x), expected, rtol=1e-12, atol=1e-12)
    assert all(np.isnan(bootstrap_ci([1.0])))
