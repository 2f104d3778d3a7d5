"""The `camo-sbi` command line: `reproduce panda` and `compare`, tidy tables, resumption, bad options."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from camo_sbi.experiments.cli import main

REPRO = ["reproduce", "panda", "--runs", "2", "--tasks", "2", "--test-goals", "3", "--samples", "200"]
PREDICTION = {"cartesian_error_mm", "joint_error_deg", "eq2_cartesian", "eq2_joint", "reference_cartesian",
              "reference_joint"}
# limit_error_binding_deg / limit_error_free_deg appear when some bound binds / does not
# wall_time and compile_time (numba compiling on first use) are timings: they differ between runs
TIMINGS = ("wall_time", "compile_time", "import_time")
BINDING = {"binding_test_fraction", "binding_test_reaches", "binding_train_fraction", "binding_train_reaches",
           "binding_test_bound_min_fraction"}
PANDA_JOINTS = [f"panda_joint{i}" for i in range(1, 8)]
PER_JOINT = {f"limit_error_deg_{j}" for j in PANDA_JOINTS}  # the scorer's per-joint limit errors
REPRO_METRICS = PREDICTION | BINDING | PER_JOINT | {"limit_error_deg", "n_simulations", *TIMINGS}
LIMIT_GROUPS = {"limit_error_binding_deg", "limit_error_free_deg"}
BASELINES = ("naive", "nominal", "oracle")

COMPARE = ["compare", "--model", "panda", "--methods", "camo,naive", "--budgets", "100", "--seeds", "2",
           "--tasks", "2", "--test-goals", "3", "--no-report"]
COMPARE_METRICS = PREDICTION | BINDING | PER_JOINT | {"limit_error_deg", "n_simulations", *TIMINGS}
PPC = {"ppc_cartesian_error_mm", "pp_mean_cartesian_error_mm"}  # posterior methods only
MODEL_CHECK = {"model_check_p", "model_check_flagged"}  # the model check (issue 33) of the final posterior
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _run(args, out) -> int:
    return main([*args, "--out", str(out)])


def _compare(out, *extra) -> pd.DataFrame:
    assert _run([*COMPARE, *extra], out) == 0
    return pd.read_csv(Path(out) / "results.csv")


def _without_wall_time(df: pd.DataFrame) -> pd.DataFrame:
    return df[~df.metric.isin(TIMINGS)].reset_index(drop=True)


def _sorted(df: pd.DataFrame, keys) -> pd.DataFrame:
    return df.sort_values(list(keys)).reset_index(drop=True)


def _assert_png(path: Path):
    assert path.is_file(), path
    data = path.read_bytes()
    assert len(data) > 1000 and data[:8] == PNG_MAGIC, path


# ------------------------------------------------------------------------------ reproduce panda


@pytest.fixture(scope="module")
def repro(tmp_path_factory):
    out = tmp_path_factory.mktemp("repro") / "a"
    assert _run(REPRO, out) == 0
    return out, pd.read_csv(out / "results.csv")


def _metric_sets(df, keys):
    """{key: set of metrics}; the optional limit groups are the same for every method of a key."""
    return df.groupby(keys).metric.apply(set)


@pytest.mark.slow  # two spawned worker processes, each importing torch and compiling its kernels
def test_reproduce_panda_with_two_workers_gives_the_same_table(repro, tmp_path):
    """The runs are grid cells (`run_grid`): --workers 2 writes the same cells, the same table
    (timings aside) and the same claims as in-process."""
    out, ref = repro
    assert _run([*REPRO, "--workers", "2"], tmp_path / "w2") == 0
    two = pd.read_csv(tmp_path / "w2" / "results.csv")
    assert sorted(p.name for p in (tmp_path / "w2" / "cells").iterdir()) == \
        sorted(p.name for p in (out / "cells").iterdir())
    keep = lambda df: df[~df.metric.isin(TIMINGS)].reset_index(drop=True)  # noqa: E731
    pd.testing.assert_frame_equal(keep(two), keep(ref), check_exact=True)
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "w2" / "claims.csv"), pd.read_csv(out / "claims.csv"),
                                  check_exact=True)


def test_reproduce_writes_every_row_once(repro):
    out, df = repro
    assert list(df.columns) == ["run", "model", "subject", "method", "n_tasks", "metric", "value", "status"]
    methods = ("camo-js", "camo-cs", "camo-hull", "camo-seq", *BASELINES)
    got = list(zip(df.run, df.method, df.n_tasks, df.metric, strict=True))
    assert len(got) == len(set(got))  # no duplicated row
    sets = _metric_sets(df, ["run", "method", "n_tasks"])
    assert set(sets.index) == {(r, m, k) for r in (0, 1) for m in methods for k in (1, 2)}
    for (r, _, _), metrics in sets.items():
        assert REPRO_METRICS <= metrics <= REPRO_METRICS | LIMIT_GROUPS
        assert metrics == sets[(r, "oracle", 1)]  # every method scored on the same bounds
    assert set(df.status) == {"ok"}
    assert set(df.model) == {"panda"}
    # subjects are cycled over the runs: two runs, two different profiles
    assert df.groupby("run").subject.nunique().eq(1).all() and df.subject.nunique() == 2
    v = df.set_index(["run", "method", "n_tasks", "metric"]).value
    assert v.notna().all()
    # counted budgets: CAMO draws --samples per observed task, the naive baseline simulates nothing
    for r in (0, 1):
        for k in (1, 2):
            assert v[(r, "camo-js", k, "n_simulations")] == 200 * k
            assert v[(r, "camo-cs", k, "n_simulations")] == 200 * k
            assert v[(r, "camo-hull", k, "n_simulations")] == 200 * k
            assert v[(r, "camo-seq", k, "n_simulations")] == 200 * k
            for b in BASELINES:
                assert v[(r, b, k, "n_simulations")] == 0
    errs = df[df.metric.isin(PREDICTION | {"limit_error_deg"})]
    assert (errs.value >= 0).all() and (errs[errs.method != "oracle"].value > 0).any()
    # the oracle (the true limits) predicts every held-out reach exactly: a pipeline check
    assert (errs[errs.method == "oracle"].value == 0).all()


def test_reproduce_writes_both_figures_and_config(repro):
    out, _ = repro
    _assert_png(out / "fig2_cartesian_error_vs_tasks.png")
    _assert_png(out / "fig3_final_error.png")
    _assert_png(out / "limit_error_vs_tasks.png")
    claims = pd.read_csv(out / "claims.csv")
    assert list(claims.columns) == ["claim", "setting", "method", "variant", "baseline", "statistic", "value",
                                    "ci_low", "ci_high", "p_value", "p_raw", "test", "holds", "binding_test_reaches_min",
                                    "few_reaches"]
    assert set(claims.baseline) >= {"naive", "nominal"} and set(claims.setting) == {"toolkit"}
    assert (out / "config.json").is_file()
    assert len(list((out / "cells").glob("*.csv"))) == 2  # one cell per run


def test_reproduce_informative_setting(tmp_path, capsys):
    """Issue 23: goals from the nominal workspace, at least half of the test goals binding, the
    reachability scores, and claims of every method against naive and nominal on both metrics."""
    out = tmp_path / "inf"
    assert _run(["reproduce", "panda", "--setting", "informative", "--design", "random", "--runs", "2",
                 "--tasks", "2", "--test-goals", "4", "--samples", "100", "--methods", "camo-js"], out) == 0
    df = pd.read_csv(out / "results.csv")
    v = df.pivot_table(index=["run", "method", "n_tasks"], columns="metric", values="value")
    assert (v["binding_test_fraction"] >= 0.5).all() and (v["binding_test_reaches"] >= 2).all()
    assert {"reachability_f1", "reachability_precision", "reachability_recall", "limit_error_binding_deg"} <= set(
        v.columns)
    assert (v.xs("oracle", level="method")["reachability_f1"] == 1).all()
    claims = pd.read_csv(out / "claims.csv")
    assert set(claims.method) == {"camo-js"} and set(claims.baseline) == {"naive", "nominal"}
    assert claims.claim.str.contains("cartesian_error_mm").sum() == 2
    assert claims.claim.str.contains("limit_error_binding_deg").sum() == 2
    assert "binding reaches" in capsys.readouterr().out


def test_reproduce_same_seed_same_table(repro, tmp_path):
    _, df = repro
    assert _run(REPRO, tmp_path / "b") == 0
    df2 = pd.read_csv(tmp_path / "b" / "results.csv")
    pd.testing.assert_frame_equal(_without_wall_time(df2), _without_wall_time(df))


def test_reproduce_other_seed_other_table(repro, tmp_path):
    _, df = repro
    assert _run([*REPRO, "--runs", "1", "--methods", "naive", "--seed", "1"], tmp_path / "c") == 0
    df2 = pd.read_csv(tmp_path / "c" / "results.csv")
    a = df[(df.run == 0) & (df.method == "naive") & (df.metric == "cartesian_error_mm")].value.to_numpy()
    b = df2[(df2.method == "naive") & (df2.metric == "cartesian_error_mm")].value.to_numpy()
    assert a.shape == b.shape == (2,) and not (a == b).all()
    assert set(df2.method) == {"naive", "nominal", "oracle"}  # the baselines come with every table


def test_reproduce_rerun_skips_finished_cells(repro):
    out, df = repro
    cells = sorted((out / "cells").glob("*.csv"))
    mtimes = [p.stat().st_mtime_ns for p in cells]
    assert _run(REPRO, out) == 0
    df2 = pd.read_csv(out / "results.csv")
    # identical including wall_time: nothing was recomputed, and no row was duplicated
    pd.testing.assert_frame_equal(df2, df)
    assert [p.stat().st_mtime_ns for p in sorted((out / "cells").glob("*.csv"))] == mtimes


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--methods", "foo"], "--methods"),
        (["--methods", "camo-js,bar"], "--methods"),
        (["--runs", "0"], "--runs"),
        (["--tasks", "0"], "--tasks"),
        (["--test-goals", "-1"], "--test-goals"),
        (["--samples", "0"], "--samples"),
        (["--runs", "two"], "--runs"),
        (["--model", "robot"], "--model"),
        (["--sampling", "sobol"], "--sampling"),
        (["--subjects", "nobody"], "nobody"),
        (["--design", "active"], "--design: active design needs --setting informative"),
        (["--setting", "informative", "--design", "active", "--design-method", "naive"],
         "--design-method: naive returns no posterior draws to design with"),
    ],
)
def test_reproduce_bad_options_exit_2(extra, needle, tmp_path, capsys):
    out = tmp_path / "bad"
    with pytest.raises(SystemExit) as exc:
        _run([*REPRO, *extra], out)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert needle in err, err
    assert not (out / "results.csv").exists()


# ------------------------------------------------------------------------------ compare


@pytest.fixture(scope="module")
def compare_table(tmp_path_factory):
    out = tmp_path_factory.mktemp("compare") / "w1"
    return out, _compare(out)


def test_compare_in_a_fresh_directory(tmp_path):
    """A first run into a new directory must work (no folder pre-created by the caller)."""
    out = tmp_path / "fresh"
    assert _run(["compare", "--methods", "naive", "--seeds", "1", "--tasks", "1", "--test-goals", "2",
                 "--budgets", "10", "--no-report"], out) == 0
    assert (out / "results.csv").is_file()


def test_compare_row_for_every_cell(compare_table):
    out, df = compare_table
    assert list(df.columns) == ["task", "subject", "method", "budget", "seed", "n_tasks", "metric", "value",
                                "status"]
    got = list(zip(df.method, df.seed, df.n_tasks, df.metric, strict=True))
    assert len(got) == len(set(got))
    sets = _metric_sets(df, ["method", "seed", "n_tasks"])
    # the baselines are added to every grid: naive, nominal, oracle
    assert set(sets.index) == {(m, s, k) for m in ("camo", *BASELINES) for s in (0, 1) for k in (1, 2)}
    for (m, s, k), metrics in sets.items():
        # the posterior's predictive scores; the model check (issue 33) of its final posterior
        extra = (PPC | (MODEL_CHECK if k == 2 else set())) if m == "camo" else set()
        assert COMPARE_METRICS | extra <= metrics <= COMPARE_METRICS | extra | LIMIT_GROUPS
        assert metrics - extra == sets[("oracle", s, 1)]
    assert set(df.budget) == {100} and set(df.task) == {"panda"} and df.subject.nunique() == 1
    assert df.value.notna().all()
    v = df.set_index(["method", "seed", "n_tasks", "metric"]).value
    for s in (0, 1):
        for k in (1, 2):
            assert v[("camo", s, k, "n_simulations")] == 100 * k
            assert v[("naive", s, k, "n_simulations")] == 0
    oracle = df[(df.method == "oracle") & df.metric.isin(PREDICTION)]
    assert len(oracle) and (oracle.value == 0).all()
    assert len(list((out / "cells").glob("*.csv"))) == 8
    for name in ("error_vs_tasks.png", "wall_time.png"):
        _assert_png(out / name)
    assert not (out / "error_vs_budget.png").exists()  # one budget: no error-vs-budget figure


def test_compare_methods_see_the_same_task(compare_table):
    """Per seed the observations are shared by all methods; across seeds they differ."""
    _, df = compare_table
    naive = df[(df.method == "naive") & (df.metric == "cartesian_error_mm")].set_index(["seed", "n_tasks"]).value
    assert naive[(0, 2)] != naive[(1, 2)]


def test_compare_rerun_returns_same_table(compare_table):
    out, df = compare_table
    df2 = _compare(out)
    pd.testing.assert_frame_equal(df2, df)  # including wall_time: finished cells were skipped


@pytest.mark.slow  # in the slow tier for the default tier's 4-minute budget (issue 28)
def test_compare_parallel_workers_same_table(compare_table, tmp_path):
    _, df = compare_table
    df2 = _compare(tmp_path / "w2", "--workers", "2")
    keys = ["method", "seed", "n_tasks", "metric"]
    a, b = _sorted(_without_wall_time(df), keys), _sorted(_without_wall_time(df2), keys)
    pd.testing.assert_frame_equal(b, a, check_exact=True)


@pytest.mark.slow  # in the slow tier for the default tier's 4-minute budget (issue 28)
def test_compare_interrupted_run_resumes_without_duplicates(compare_table, tmp_path):
    _, ref = compare_table
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "camo_sbi.experiments.cli", *COMPARE, "--out", str(out)]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    cells = out / "cells"
    try:
        deadline = time.monotonic() + 300  # a hang guard, not a timing assertion
        while not (cells.is_dir() and any(cells.glob("*.csv"))):
            if proc.poll() is not None:
                pytest.fail(f"compare exited ({proc.returncode}) before writing a cell:\n"
                            f"{proc.stderr.read().decode()[-3000:]}")
            if time.monotonic() > deadline:
                pytest.fail("no cell written within 300 s")
            time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    done = sorted(cells.glob("*.csv"))
    assert 1 <= len(done) < 8, "the run was not interrupted mid-grid"
    keys = ["method", "seed", "n_tasks", "metric"]
    for p in done:  # every finished cell is complete: its rows are exactly the reference cell's
        part = pd.read_csv(p)
        (method,), (seed,) = set(part.method), set(part.seed)
        want = ref[(ref.method == method) & (ref.seed == seed)]
        pd.testing.assert_frame_equal(_sorted(_without_wall_time(part), keys), _sorted(_without_wall_time(want), keys))
    assert not (out / "results.csv").exists()

    df = _compare(out)
    counts = df.groupby(keys).size()
    assert (counts == 1).all() and len(counts) == len(ref)
    # and the resumed table equals an uninterrupted run (wall_time aside)
    pd.testing.assert_frame_equal(_sorted(_without_wall_time(df), keys), _sorted(_without_wall_time(ref), keys))


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--methods", "foo"], "method"),
        (["--methods", "camo,foo"], "method"),
        (["--methods", ","], "--methods"),
        (["--budgets", "0"], "--budgets"),
        (["--budgets", "ten"], "--budgets"),
        (["--seeds", "0"], "--seeds"),
        (["--tasks", "0"], "--tasks"),
        (["--workers", "0"], "--workers"),
        (["--model", "robot"], "--model"),
        (["--space", "polar"], "--space"),
        (["--subjects", "nobody"], "nobody"),
    ],
)
def test_compare_bad_options_exit_2(extra, needle, tmp_path, capsys):
    out = tmp_path / "bad"
    with pytest.raises(SystemExit) as exc:
        _run([*COMPARE, *extra], out)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert needle in err, err
    assert not (out / "results.csv").exists()
    assert not (out / "cells").exists() or not any((out / "cells").iterdir())


@pytest.mark.slow
def test_compare_with_abc_smc_and_npe(tmp_path):
    """The pyabc and sbi methods run through the same grid (slow: NPE trains a flow per k, minutes)."""
    out = tmp_path / "sbi"
    args = ["--methods", "abc-smc,npe", "--seeds", "1"]
    df = _compare(out, *args)
    got = list(zip(df.method, df.n_tasks, df.metric, strict=True))
    assert len(got) == len(set(got))
    sets = _metric_sets(df, ["method", "n_tasks"])
    assert set(sets.index) == {(m, k) for m in ("abc-smc", "npe", *BASELINES) for k in (1, 2)}
    for m in ("abc-smc", "npe"):  # posterior methods: the prediction metrics and the posterior-predictive ones
        for k in (1, 2):
            extra = PPC | (MODEL_CHECK if k == 2 else set())
            assert COMPARE_METRICS | extra <= sets[(m, k)] <= COMPARE_METRICS | extra | LIMIT_GROUPS
    v = df.set_index(["method", "n_tasks", "metric"]).value
    assert v.notna().all()
    for m in ("abc-smc", "npe"):
        for k in (1, 2):
            assert 0 < v[(m, k, "n_simulations")] <= 100 * k  # counted, within the cap
    # one file per cell, one seed, one budget: the two methods' posteriors, the three baselines' point estimates
    assert len(list((out / "posteriors").glob("*.nc"))) == 2
    assert len(list((out / "estimates").glob("*.nc"))) == len(BASELINES)
    pd.testing.assert_frame_equal(_compare(out, *args), df)  # resumable: finished cells skipped


def test_reproduce_paper_setting(tmp_path):
    """--setting paper: fixed goals in every run (so the nominal and oracle rows repeat), the
    authors' fixed-horizon controller, the CAMO variants with their epsilon, and claims.csv."""
    out = tmp_path / "paper"
    args = ["reproduce", "panda", "--setting", "paper", "--runs", "2", "--tasks", "3", "--test-goals", "3",
            "--samples", "200"]
    assert _run(args, out) == 0
    df = pd.read_csv(out / "results.csv")
    assert set(df.method) == {"camo-js", "camo-cs", "camo-seq", "camo-seq-cs", "camo-hull", "naive", "nominal",
                              "oracle"}
    # how many reaches a true limit binds, per run: counts within the reaches there are, equal over the
    # runs (the same goals) and over the methods of a run
    br = df[df.metric.isin(["binding_test_reaches", "binding_train_reaches"])].pivot_table(
        index=["run", "method"], columns="metric", values="value")
    assert br.binding_train_reaches.between(0, 3).all() and br.binding_test_reaches.between(0, 3).all()
    assert (br.nunique() == 1).all()
    assert set(df.subject) == {"one_joint_restricted"}
    nominal = df[(df.method == "nominal") & (df.metric == "cartesian_error_mm")].pivot_table(
        index="n_tasks", columns="run", values="value")
    assert (nominal[0] == nominal[1]).all()  # the same test goals in both runs
    camo = df[(df.method == "camo-js") & (df.metric == "cartesian_error_mm")].pivot_table(
        index="n_tasks", columns="run", values="value")
    assert not (camo[0] == camo[1]).all()  # ... but each run has its own draws
    assert (df[(df.method == "oracle") & df.metric.isin(PREDICTION)].value == 0).all()
    assert set(pd.read_csv(out / "claims.csv").setting) == {"paper"}
    config = __import__("json").loads((out / "config.json").read_text())
    assert config["setting"] == "paper" and config["horizon"] == 21


def test_printed_summary_reads_by_metric_in_words_with_the_small_n_rule():
    """compare's stdout: metrics as rows in words (angles in degrees), methods as columns, and with
    2 seeds each cell is 'mean (min–max)', never a ± interval from two values."""
    import pandas as pd

    from camo_sbi.diagnostics.numbers import summary_table

    rows = [{"method": m, "budget": 100, "seed": s, "n_tasks": 2, "metric": k, "value": v}
            for m, base in (("camo", 1.0), ("naive", 3.0)) for s in (0, 1)
            for k, v in (("cartesian_error_mm", base * 10 + s), ("reference_joint", base * 0.1 + 0.01 * s))]
    text = summary_table(pd.DataFrame(rows), ["cartesian_error_mm", "reference_joint"], unit="seeds", block="budget")
    assert "±" not in text and "fewer than 5 seeds" in text
    lines = text.splitlines()
    assert lines[1].split()[-2:] == ["camo", "naive"]  # methods as columns, in their order
    cart = next(ln for ln in lines if ln.startswith("Cartesian error"))
    assert "[mm]" in cart and "10.5 (10–11)" in cart and "30.5 (30–31)" in cart
    joint = next(ln for ln in lines if ln.startswith("authors' metric (joint)"))
    assert "[deg]" in joint and "6.02 (5.73–6.3)" in joint  # stored in radians: 0.105 rad = 6.02 deg
