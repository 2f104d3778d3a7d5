"""`camo-sbi reference` (a benchmark set of observations with reference posteriors) and
`camo-sbi compare --reference` (every method against them: C2ST and MMD rows)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from camo_sbi.experiments.cli import main

TINY = ["reference", "--model", "panda", "--setting", "informative", "--observations", "2", "--tasks", "1",
        "--test-goals", "2", "--draws", "100", "--moves", "1", "--mcmc-steps", "10"]


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--draws", "50"], "--draws: must be >= 100"),
        (["--observations", "0"], "--observations: must be >= 1"),
        (["--noise-joint-deg", "0"], "--noise-joint-deg: the exact likelihood needs noise > 0"),
        (["--noise-ee-mm", "-1"], "--noise-ee-mm"),
        (["--subjects", "nobody"], "nobody"),
        (["--scheduler", "nowhere"], "--scheduler"),
    ],
)
def test_reference_bad_options_exit_2(extra, needle, tmp_path, capsys):
    out = tmp_path / "bad"
    with pytest.raises(SystemExit) as exc:
        main([*TINY, *extra, "--out", str(out)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert needle in err, err
    assert not (out / "reference.json").exists()


def test_compare_reference_without_a_set_exits_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["compare", "--reference", str(tmp_path / "none"), "--methods", "naive", "--out", str(tmp_path / "c")])
    assert exc.value.code == 2
    assert "--reference:" in capsys.readouterr().err


@pytest.mark.slow
def test_reference_builds_verifies_and_compare_scores_every_method(tmp_path, capsys):
    refs = tmp_path / "refs"
    assert main([*TINY, "--out", str(refs)]) == 0
    prov = json.loads((refs / "reference.json").read_text())
    assert [e["observation"] for e in prov["observations"]] == [0, 1]
    assert {e["subject"] for e in prov["observations"]} == {"informative_shoulder", "informative_elbow"}
    assert prov["command"].startswith("camo-sbi reference") and prov["versions"]["torch"]
    for e in prov["observations"]:
        with np.load(refs / e["file"], allow_pickle=False) as z:
            assert z["reference"].shape == (100, 14) and z["lengths"].shape == (1,)
            assert e["check_ok"] == (float(z["check_c2st"]) <= 0.55)
    capsys.readouterr()
    assert main([*TINY, "--out", str(refs)]) == 0  # a re-run verifies instead of rebuilding
    assert "2 verified (sha256), 0 to build" in capsys.readouterr().out
    first = refs / prov["observations"][0]["file"]
    first.write_bytes(first.read_bytes() + b"x")
    with pytest.raises(SystemExit) as exc:
        main([*TINY, "--out", str(refs)])
    assert exc.value.code == 2 and "does not match its sha256" in capsys.readouterr().err
    # compare against the (intact) set: the other observation only, through a copy of the provenance
    prov["observations"] = prov["observations"][1:]
    (refs / "reference.json").write_text(json.dumps(prov))
    out = tmp_path / "cmp"
    assert main(["compare", "--reference", str(refs), "--methods", "camo-seq,exact-likelihood", "--budgets", "90,60",
                 "--config", 'exact-likelihood={"particles": 100, "moves": 1, "min_ess": 0}', "--out", str(out)]) == 0
    df = pd.read_csv(out / "results.csv")
    # exact-likelihood does not depend on the budget: run once, filed under the smallest budget
    assert set(df[df.method == "exact-likelihood"].budget) == {60} and set(df[df.method == "camo-seq"].budget) == {60, 90}
    df = df[df.budget == 60]
    c2 = df[df.metric == "c2st"].set_index("method")
    assert set(c2.index) == {"camo-seq", "exact-likelihood", "naive", "nominal", "oracle"}
    for m in ("naive", "nominal", "oracle"):  # point estimates: no number made up
        assert np.isnan(c2.loc[m, "value"]) and c2.loc[m, "c2st_status"].startswith("not a posterior")
    for m in ("camo-seq", "exact-likelihood"):
        assert 0.0 <= c2.loc[m, "value"] <= 1.0 and c2.loc[m, "c2st_status"] == "ok"
    assert not bool(c2.loc["exact-likelihood", "simulation_based"]) and bool(c2.loc["camo-seq", "simulation_based"])
    assert set(df[df.metric == "mmd"].method) == set(c2.index)
    # exact-likelihood sampled as the set did (its --mcmc-steps 10), under the --config given
    used = json.loads((out / "config.json").read_text())["config"]["exact-likelihood"]
    assert used == {"particles": 100, "moves": 1, "mcmc_steps": 10, "min_ess": 0}
    claims = pd.read_csv(out / "claims.csv")
    assert list(claims.method).count("camo-seq") == 2 and list(claims.method).count("exact-likelihood") == 1
    claims = claims[~claims.claim.str.endswith("at 90 simulations per reach")].set_index("method")  # no point estimate
    assert set(claims.index) == {"camo-seq", "exact-likelihood"}
    assert claims.loc["exact-likelihood", "claim"].startswith("the exact posterior is indistinguishable")
    assert claims.loc["camo-seq", "value"] == pytest.approx(c2.loc["camo-seq", "value"])
    assert bool(claims.loc["camo-seq", "holds"]) == (c2.loc["camo-seq", "value"] <= 0.65)  # one observation
    page = (out / "report.html").read_text()  # the report carries the reference metrics too
    assert "C2ST accuracy against the reference posterior" in page and "squared MMD to the reference" in page


def test_reference_claims_rule_on_a_hand_made_table():
    from camo_sbi.evaluation.claims import reference_claims

    def rows(method, values, sim=True, status="ok"):
        return [{"method": method, "budget": 1000, "seed": i, "n_tasks": 5, "metric": "c2st", "value": v,
                 "c2st_status": status, "simulation_based": sim} for i, v in enumerate(values)]

    df = pd.DataFrame(rows("npe", [0.60, 0.62, 0.61]) + rows("abc-smc", [0.60, 0.99, 0.62])
                      + rows("exact-likelihood", [0.50, 0.52, 0.51], sim=False)
                      + rows("naive", [float("nan")] * 3, status="not a posterior (a point estimate)"))
    t = reference_claims(df).set_index("method")
    assert list(t.index) == ["npe", "abc-smc", "exact-likelihood"]  # no row for a point estimate
    assert t.loc["npe", "holds"] and t.loc["npe", "value"] == pytest.approx(0.61)
    assert not t.loc["abc-smc", "holds"]  # its mean 0.737 is above 0.65
    assert t.loc["exact-likelihood", "holds"] and "C2ST <= 0.55" in t.loc["exact-likelihood", "claim"]
    df2 = pd.DataFrame(rows("npe", [0.60, 0.70]))  # mean 0.65, but the interval's top is 0.70
    assert not reference_claims(df2).holds.iloc[0]
