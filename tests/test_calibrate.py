"""`camo-sbi calibrate`: tiny end-to-end run, determinism, resume, option validation."""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
import pytest

from camo_sbi.diagnostics.calibration import central_interval_coverage, sbc_ranks
from camo_sbi.experiments import calibrate
from camo_sbi.experiments.models import ModelSpec

TINY = ["--model", "panda", "--methods", "camo,naive", "--subjects", "3", "--tasks", "1", "--budget", "40",
        "--sbc-draws", "20", "--config", 'camo={"keep_best": 20}']


def _args(*argv):
    p = argparse.ArgumentParser()
    calibrate.add_arguments(p)
    return p.parse_args(list(argv))


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("calib") / "run"
    assert calibrate.main(_args(*TINY, "--out", str(out))) == 0
    return out


def test_outputs_have_expected_columns(tiny_run):
    cov = pd.read_csv(tiny_run / "coverage.csv")
    # the columns camo_sbi.diagnostics.report reads, plus method
    assert {"task", "method", "coordinate", "alpha", "coverage", "n", "point_estimate"} <= set(cov.columns)
    assert set(cov["method"]) == {"camo", "naive"}
    overall = cov[cov["coordinate"] == "overall"]
    assert len(overall) == 2 * 19
    assert np.allclose(sorted(overall["alpha"].unique()), np.linspace(0.05, 0.95, 19))
    assert cov["coverage"].between(0, 1).all()
    # 3 subjects x 14 free coordinates pooled in "overall"; 3 subjects per coordinate
    assert set(overall["n"]) == {42}
    assert set(cov.loc[cov["coordinate"] != "overall", "n"]) == {3}
    assert cov.loc[cov["method"] == "naive", "point_estimate"].all()
    assert not cov.loc[cov["method"] == "camo", "point_estimate"].any()
    sbc = pd.read_csv(tiny_run / "sbc.csv")
    assert {"task", "method", "subject", "attempt", "coordinate", "rank", "n_draws"} <= set(sbc.columns)
    assert len(sbc) == 2 * 3 * 14
    assert sbc["rank"].between(0, 20).all()
    # the naive point estimate lies inside the true range: lower-limit ranks at 0, upper at L (or a tie)
    nv = sbc[sbc["method"] == "naive"]
    assert (nv.loc[nv["coordinate"].str.endswith("_lo"), "rank"] <= 20).all()
    assert (tiny_run / "coverage.png").stat().st_size > 1000
    assert "mean_abs_dev" in (tiny_run / "summary.txt").read_text()


def test_same_seed_same_coverage(tiny_run, tmp_path):
    out = tmp_path / "again"
    assert calibrate.main(_args(*TINY, "--out", str(out))) == 0
    assert (out / "coverage.csv").read_text() == (tiny_run / "coverage.csv").read_text()
    assert (out / "sbc.csv").read_text() == (tiny_run / "sbc.csv").read_text()


def test_resume_skips_finished_cells(tiny_run, tmp_path, monkeypatch):
    import shutil

    out = tmp_path / "resume"
    shutil.copytree(tiny_run, out)
    cells = sorted((out / "cells").glob("*.csv"))
    assert len(cells) == 6
    cells[0].unlink()
    calls = []
    real = calibrate.run_cell
    monkeypatch.setattr(calibrate, "run_cell", lambda cell, o: calls.append(cell.key) or real(cell, o))
    assert calibrate.main(_args(*TINY, "--out", str(out))) == 0
    assert calls == [cells[0].stem]
    assert (out / "coverage.csv").read_text() == (tiny_run / "coverage.csv").read_text()


def test_per_subject_rows_aggregate_to_library_coverage():
    """Averaging one-subject indicators equals central_interval_coverage over all subjects."""
    rng = np.random.default_rng(0)
    S, N, D = 6, 200, 3
    samples = rng.normal(size=(S, N, D))
    truths = rng.normal(size=(S, D))
    weights = [rng.random(N) for _ in range(S)]
    names = ["a_lo", "a_hi", "b_lo"]
    rows = []
    for s in range(S):
        for r in calibrate.subject_rows(samples[s], weights[s], truths[s], names, sbc_draws=10, seed=s):
            rows.append({**r, "cell": f"c{s}", "task": "t", "method": "m", "subject": s})
        rows += [{"cell": f"c{s}", "task": "t", "method": "m", "subject": s, "record": "meta", "name": k,
                  "alpha": np.nan, "value": v} for k, v in {"n_samples": N, "attempt": 0}.items()]
    cov, ranks = calibrate.aggregate(pd.DataFrame(rows), 10)
    ref = central_interval_coverage(list(samples), truths, weights=weights, names=names)
    ref["alpha"] = ref["alpha"].round(6)
    merged = cov.merge(ref, on=["coordinate", "alpha"], suffixes=("", "_ref"))
    assert len(merged) == len(ref)
    assert np.allclose(merged["coverage"], merged["coverage_ref"])
    assert (merged["n"] == merged["n_ref"]).all()
    ref_ranks = sbc_ranks([samples[0]], truths[:1], 10, np.random.default_rng(0), weights=[weights[0]])[0]
    got = ranks[ranks["subject"] == 0].set_index("coordinate").loc[names, "rank"].to_numpy()
    assert np.array_equal(got, ref_ranks.astype(int))


def test_point_mass_is_not_dropped():
    rows = calibrate.subject_rows(np.array([[0.5, 2.0]]), None, np.array([0.0, 3.0]), ["j_lo", "j_hi"],
                                  sbc_draws=10, seed=0)
    cov = [r for r in rows if r["record"] == "coverage"]
    assert len(cov) == 2 * 19 and all(r["value"] == 0.0 for r in cov)
    ranks = {r["name"]: r["value"] for r in rows if r["record"] == "rank"}
    assert ranks == {"j_lo": 0.0, "j_hi": 10.0}


def test_redraws_subject_deterministically(monkeypatch):
    import camo_sbi.scenarios.reaching as reaching

    real = reaching.make_reaching_task
    seen = []

    def flaky(sim, theta, **kw):
        seen.append(kw["seed"])
        if len(seen) <= 2:
            raise ValueError("true_theta: only 1 of 40 sampled goals were reachable")
        return real(sim, theta, **kw)

    monkeypatch.setattr(reaching, "make_reaching_task", flaky)
    sim = ModelSpec("panda").build()
    task, attempt = calibrate.draw_subject(sim, "panda", 4, n_tasks=1, seed=0)
    assert attempt == 2 and len(set(seen)) == 3
    monkeypatch.setattr(reaching, "make_reaching_task", real)
    task2, attempt2 = calibrate.draw_subject(sim, "panda", 4, n_tasks=1, seed=0)
    assert attempt2 == 0 and not np.allclose(task.true_theta, task2.true_theta)
    assert bool(task.prior.contains(task.true_theta))


@pytest.mark.parametrize(("argv", "option"), [
    (["--methods", "camo,bogus"], "--methods"),
    (["--methods", ""], "--methods"),
    (["--subjects", "0"], "--subjects"),
    (["--tasks", "0"], "--tasks"),
    (["--budget", "0"], "--budget"),
    (["--workers", "0"], "--workers"),
    (["--sbc-draws", "0"], "--sbc-draws"),
    (["--seed", "-1"], "--seed"),
    (["--config", "camo"], "--config"),
    (["--config", "camo={not json"], "--config"),
    (["--config", 'npe={"max_epochs": 5}'], "--config"),  # npe not in --methods
    (["--config", 'camo={"no_such_field": 1}'], "--config"),
    (["--methods", "abc-smc", "--budget", "50", "--config", 'abc-smc={"population_size": 80}'], "--budget"),
])
def test_bad_options_name_the_option(argv, option, tmp_path):
    args = _args("--methods", "camo", "--out", str(tmp_path / "bad"), *argv)
    with pytest.raises(ValueError, match=option):
        calibrate.main(args)
    assert not (tmp_path / "bad" / "coverage.csv").exists()


def test_bad_model_exits_2():
    with pytest.raises(SystemExit) as exc:
        _args("--model", "robot")
    assert exc.value.code == 2


def test_cli_exit_code_2(tmp_path, capsys):
    from camo_sbi.experiments import cli

    with pytest.raises(SystemExit) as exc:
        cli.main(["calibrate", "--subjects", "0", "--out", str(tmp_path)])
    assert exc.value.code == 2
    assert "--subjects" in capsys.readouterr().err
