"""The robustness study: conditions, pairing, coverage and the summary table."""

import numpy as np
import pandas as pd
import pytest
import torch

from camo_sbi.experiments.cli import main
from camo_sbi.experiments.robustness import coverage90, summary_table
from camo_sbi.inference.result import PosteriorResult
from camo_sbi.priors import BoxPrior


def test_coverage90_hand_computed():
    prior = BoxPrior(torch.tensor([[-1.0, 1.0], [-1.0, 1.0]]), torch.zeros(2), fixed={1: (-0.5, 0.5)})
    samples = np.stack([np.linspace(-0.9, -0.1, 101), np.linspace(0.1, 0.9, 101), np.full(101, -0.5),
                        np.full(101, 0.5)], axis=1)
    res = PosteriorResult("x", samples, None, samples[50], 0, 0.0, 1)
    # 90% intervals: lo in [-0.86, -0.14], hi in [0.14, 0.86]; truth lo inside, hi outside
    assert coverage90(res, torch.tensor([-0.5, 0.95, -0.5, 0.5]), prior) == 0.5
    point = PosteriorResult("p", samples[:1], None, samples[0], 0, 0.0, 1)
    assert coverage90(point, torch.tensor(samples[0]), prior) == 1.0


def test_robustness_command_small(tmp_path):
    out = tmp_path / "rob"
    argv = ["robustness", "--methods", "camo-js,naive,nominal,oracle", "--seeds", "1", "--tasks", "2",
            "--test-goals", "3", "--budget", "100", "--out", str(out)]
    assert main(argv) == 0
    df = pd.read_csv(out / "results.csv")
    table = pd.read_csv(out / "robustness.csv")
    assert set(df.condition) == {"clean", "noise 1deg/5mm", "noise 3deg/15mm", "rate x3", "taller 5%",
                                 "shorter 5%"}
    assert set(table.method) == {"camo-js", "naive", "nominal", "oracle"}
    assert (table[table.condition == "clean"].error_ratio_to_clean.dropna() == 1.0).all()
    err = df[df.metric == "cartesian_error_mm"].set_index(["method", "condition"]).value
    # the oracle is exact on clean, noisy and resampled data (it ignores the observations) ...
    for cond in ("clean", "noise 1deg/5mm", "rate x3"):
        assert err[("oracle", cond)] == 0.0
    # ... but a mis-sized model mispredicts even with the true limits
    assert err[("oracle", "taller 5%")] > 1.0 and err[("oracle", "shorter 5%")] > 1.0
    assert (out / "robustness.png").stat().st_size > 1000
    # a rerun resumes (nothing recomputed) and other settings are refused
    assert main(argv) == 0
    with pytest.raises(SystemExit):
        main([*argv[:-2], "--budget", "50", "--out", str(out)])


@pytest.mark.slow  # in the slow tier for the default tier's 4-minute budget (issue 28)
def test_robustness_body_scale_free(tmp_path):
    """--body-scale free: s estimated from the observed body's joint and end-effector recordings
    (within 0.01 of 1.10 / 0.95), and the oracle, on the rescaled model, predicts the mis-sized body's
    reaches far better than on the model's own size."""
    out = tmp_path / "rob"
    argv = ["robustness", "--methods", "oracle", "--seeds", "1", "--tasks", "2", "--test-goals", "3", "--budget",
            "20", "--conditions", "clean,taller 10%,shorter 5%"]
    assert main([*argv, "--body-scale", "free", "--out", str(out)]) == 0
    assert main([*argv, "--out", str(tmp_path / "fixed")]) == 0
    df = pd.read_csv(out / "results.csv").set_index(["condition", "metric"]).value
    assert abs(df[("taller 10%", "body_scale")] - 1.10) < 0.01 and abs(df[("shorter 5%", "body_scale")] - 0.95) < 0.01
    fixed = pd.read_csv(tmp_path / "fixed" / "results.csv").set_index(["condition", "metric"]).value
    assert "body_scale" not in set(pd.read_csv(tmp_path / "fixed" / "results.csv").metric)
    for cond in ("taller 10%", "shorter 5%"):
        assert df[(cond, "cartesian_error_mm")] < 0.2 * fixed[(cond, "cartesian_error_mm")]


def test_summary_table_ratio():
    rows = [{"method": m, "condition": c, "metric": "cartesian_error_mm", "value": v, "seed": 0}
            for m, c, v in (("a", "clean", 2.0), ("a", "rate x3", 5.0), ("b", "clean", 1.0), ("b", "rate x3", 1.5))]
    t = summary_table(pd.DataFrame(rows)).set_index(["method", "condition"])
    assert t.loc[("a", "rate x3"), "error_ratio_to_clean"] == 2.5 and not t.loc[("a", "rate x3"), "within_2x_clean"]
    assert t.loc[("b", "rate x3"), "within_2x_clean"]
