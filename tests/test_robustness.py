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


def test_summary_table_ratio():
    rows = [{"method": m, "condition": c, "metric": "cartesian_error_mm", "value": v, "seed": 0}
            for m, c, v in (("a", "clean", 2.0), ("a", "rate x3", 5.0), ("b", "clean", 1.0), ("b", "rate x3", 1.5))]
    t = summary_table(pd.DataFrame(rows)).set_index(["method", "condition"])
    assert t.loc[("a", "rate x3"), "error_ratio_to_clean"] == 2.5 and not t.loc[("a", "rate x3"), "within_2x_clean"]
    assert t.loc[("b", "rate x3"), "within_2x_clean"]
