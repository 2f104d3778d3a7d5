"""Dask execution (issue #8): same numbers with and without a cluster; a dying worker loses nothing."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from camo_sbi.budget import BudgetExceededError, CountingSimulator, charge
from camo_sbi.distributed import dask_client, map_ordered, parse_scheduler
from camo_sbi.experiments.cli import main
from tests.toy_sim import ToySimulator

# ------------------------------------------------------------------------------ no Dask needed


@pytest.mark.parametrize("spec, expected", [
    (None, None), ("", None), ("local:2", ("local", 2)), (" local:1 ", ("local", 1)),
    ("tcp://10.0.0.1:8786", ("address", "tcp://10.0.0.1:8786")),
    ("tls://scheduler.example.org:8786", ("address", "tls://scheduler.example.org:8786")),
])
def test_parse_scheduler(spec, expected):
    assert parse_scheduler(spec) == expected


@pytest.mark.parametrize("spec", ["local", "local:0", "local:-1", "local:two", "host:8786", "2", 3])
def test_parse_scheduler_errors_name_the_option(spec):
    with pytest.raises(ValueError, match="scheduler"):
        parse_scheduler(spec)


def test_bad_scheduler_in_config_and_cli(tmp_path):
    from camo_sbi.inference.registry import make_config

    with pytest.raises(ValueError, match="scheduler"):
        make_config("camo", {"scheduler": "local:0"})
    with pytest.raises(SystemExit) as exc:
        main(["compare", "--methods", "naive", "--seeds", "1", "--tasks", "1", "--test-goals", "2",
              "--no-report", "--scheduler", "bogus", "--out", str(tmp_path)])
    assert exc.value.code == 2


def test_map_ordered_in_process_and_charge():
    assert map_ordered(lambda x, k: x * k, [1, 2, 3], None, k=2) == [2, 4, 6]
    counter = CountingSimulator(ToySimulator(), 10)
    charge(counter, 7)
    assert counter.n_simulations == 7
    with pytest.raises(BudgetExceededError):
        charge(counter, 4)
    assert counter.n_simulations == 7


# ------------------------------------------------------------------------------ with a cluster

COMPARE = ["compare", "--model", "panda", "--methods", "camo,naive", "--budgets", "100", "--seeds", "2",
           "--tasks", "2", "--test-goals", "3", "--no-report"]
KEYS = ["method", "seed", "n_tasks", "metric"]
TIMINGS = ("wall_time", "compile_time", "import_time")  # differ between runs (and between processes)


@pytest.fixture(scope="module")
def cluster():
    """One LocalCluster (2 worker processes) shared by this module's tests."""
    pytest.importorskip("distributed")
    from distributed import LocalCluster

    cl = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
    try:
        yield cl
    finally:
        cl.close()


@pytest.fixture()
def address(cluster):
    return cluster.scheduler_address


def _table(out: Path, *extra) -> pd.DataFrame:
    assert main([*COMPARE, *extra, "--out", str(out)]) == 0
    df = pd.read_csv(out / "results.csv")
    return df[~df.metric.isin(TIMINGS)].sort_values(KEYS).reset_index(drop=True)


# slow: the whole compare grid on a 2-worker cluster (~1 min); the CLI's Dask path stays in the default
# run (test_reproduce_panda_on_dask_gives_the_same_table)
@pytest.mark.slow
def test_compare_on_dask_gives_the_same_table(tmp_path, address):
    ref = _table(tmp_path / "inproc")
    dask = _table(tmp_path / "dask", "--scheduler", address)
    pd.testing.assert_frame_equal(dask, ref, check_exact=True)
    counts = dask.groupby(KEYS).size()
    assert (counts == 1).all()


@pytest.mark.slow  # in the slow tier for the default tier's 4-minute budget (issue 28)
def test_reproduce_panda_on_dask_gives_the_same_table(tmp_path, address):
    cmd = ["reproduce", "panda", "--runs", "1", "--tasks", "2", "--test-goals", "3", "--samples", "300",
           "--methods", "camo-js"]
    tables = []
    for name, extra in (("inproc", []), ("dask", ["--scheduler", address])):
        assert main([*cmd, *extra, "--out", str(tmp_path / name)]) == 0
        df = pd.read_csv(tmp_path / name / "results.csv")
        tables.append(df[~df.metric.isin(TIMINGS)].reset_index(drop=True))
    pd.testing.assert_frame_equal(tables[1], tables[0], check_exact=True)


def _toy_task():
    import torch

    from camo_sbi.priors import BoxPrior
    from camo_sbi.scenarios.reaching import observe
    from camo_sbi.task import Task

    sim = ToySimulator(n=2)
    true = torch.tensor([-0.3, 0.4, -0.5, 0.2], dtype=torch.float64)
    goals = torch.tensor([[0.8, 0.8, 0.0], [-0.9, -0.7, 0.0], [0.6, -0.8, 0.0]], dtype=torch.float64)
    obs = observe(sim, true, goals)
    return Task("toy", "toy", sim, BoxPrior(sim.bounds, sim.start), obs,
                sim.start.expand(2, -1).clone(), goals[:2].clone(), true.clone())


@pytest.mark.parametrize("cfg", [{"chunk_size": 128}, {"chunk_size": 100, "epsilon": 1e-6}])
def test_camo_same_estimate_with_and_without_dask(address, cfg):
    from camo_sbi.inference.registry import run_method

    task = _toy_task()
    kw = {"budget": 500, "seed": 4}
    with pytest.warns(RuntimeWarning) if "epsilon" in cfg else _nothing():
        a = run_method("camo", task, config=cfg, **kw)
    with dask_client(address), (pytest.warns(RuntimeWarning) if "epsilon" in cfg else _nothing()):
        b = run_method("camo", task, config={**cfg, "scheduler": address}, **kw)
    np.testing.assert_array_equal(b.estimate, a.estimate)
    np.testing.assert_array_equal(b.samples, a.samples)
    np.testing.assert_array_equal(b.weights, a.weights)
    assert a.n_simulations == b.n_simulations == 500 * 3


def test_camo_chunks_do_not_depend_on_workers():
    """In-process, the chunk size fixes the draws: the same seed gives the same kept vectors."""
    from camo_sbi.inference.registry import run_method

    task = _toy_task()
    a = run_method("camo", task, budget=300, seed=1, config={"chunk_size": 64})
    b = run_method("camo", task, budget=300, seed=1, config={"chunk_size": 64})
    c = run_method("camo", task, budget=300, seed=1, config={"chunk_size": 300})
    np.testing.assert_array_equal(a.samples, b.samples)
    assert not np.array_equal(a.samples, c.samples)  # the chunk size is part of the stream


@pytest.mark.slow  # pyabc populations twice (~20 s)
def test_abc_smc_same_populations_with_and_without_dask(address):
    """Our batched sampler's chunks on workers: same particles, weights, distances, budget use."""
    from camo_sbi.inference.registry import run_method

    task = _toy_task()
    cfg = {"population_size": 40, "max_populations": 4, "chunk_size": 16}
    a = run_method("abc-smc", task, budget=600, seed=2, config=cfg)
    with dask_client(address):  # closed afterwards (a bare config spec keeps its client open)
        b = run_method("abc-smc", task, budget=600, seed=2, config={**cfg, "scheduler": address})
    np.testing.assert_array_equal(b.samples, a.samples)
    np.testing.assert_array_equal(b.weights, a.weights)
    np.testing.assert_array_equal(b.estimate, a.estimate)
    assert a.n_simulations == b.n_simulations


def test_npe_same_training_data_with_and_without_dask(address):
    from camo_sbi.inference.registry import run_method

    task = _toy_task()
    cfg = {"hidden_features": 16, "num_transforms": 2, "max_epochs": 4, "stop_after_epochs": 2,
           "n_posterior_samples": 300, "is_rounds": 1, "n_points": 8, "chunk_size": 64}
    a = run_method("npe", task, task.observations[:2], budget=200, seed=3, config=cfg)
    with dask_client(address):
        b = run_method("npe", task, task.observations[:2], budget=200, seed=3,
                       config={**cfg, "scheduler": address})
    np.testing.assert_array_equal(b.samples, a.samples)
    np.testing.assert_array_equal(b.estimate, a.estimate)
    assert a.n_simulations == b.n_simulations == 400


def test_abc_smc_does_not_depend_on_the_chunk_size():
    """Accepted particles' distances are exact in any chunking: chunk 7 == one chunk."""
    from camo_sbi.inference.registry import run_method

    task = _toy_task()
    cfg = {"population_size": 40, "max_populations": 4}
    a = run_method("abc-smc", task, budget=600, seed=2, config={**cfg, "chunk_size": 7})
    b = run_method("abc-smc", task, budget=600, seed=2, config={**cfg, "chunk_size": 4096})
    np.testing.assert_array_equal(b.samples, a.samples)
    np.testing.assert_array_equal(b.weights, a.weights)
    assert a.n_simulations == b.n_simulations


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


@pytest.mark.slow  # kills and restarts a Dask worker mid-grid (~30 s)
def test_a_dying_worker_loses_no_cell(tmp_path, cluster):
    """Kill one worker after the first cell finishes: the grid completes, every row exactly once."""
    import functools

    from distributed import Client

    from camo_sbi.distributed import map_unordered
    from camo_sbi.experiments.compare import grid_cells, run_cell
    from camo_sbi.experiments.grid import _run_and_store
    from camo_sbi.experiments.store import ResultStore

    out = tmp_path / "killed"
    args = _namespace(methods="camo,naive", budgets="100", seeds=3, tasks=1)
    specs = grid_cells(args)
    with Client(cluster) as client:
        victim = next(iter(client.scheduler_info()["workers"]))
        n_before = len(client.scheduler_info()["workers"])
        done = []
        # what run_grid does on Dask, with a hook after the first cell to kill a worker
        for key in map_unordered(functools.partial(_run_and_store, run_cell), specs, client, retries=2,
                                 out=str(out)):
            done.append(key)
            if len(done) == 1:  # mid-grid: take a worker down (and the cells it holds)
                try:
                    client.run(os._exit, 1, workers=[victim])
                except Exception:  # the worker's connection drops by design
                    pass
        assert sorted(done) == sorted(s.key for s in specs)
        assert victim not in client.scheduler_info()["workers"]  # it did die
        client.wait_for_workers(n_before, timeout=60)  # the nanny restarts it for the next tests
    store = ResultStore(out)
    assert store.finished_keys() == {s.key for s in specs}
    df = store.write_table()
    counts = df.groupby(["method", "seed", "n_tasks", "metric"]).size()
    assert (counts == 1).all()
    # every cell holds all its tasks, each with the same metrics
    per = df.groupby(["method", "seed", "n_tasks"]).metric.apply(frozenset)
    assert len(per) == len(specs) * df.n_tasks.nunique()
    assert per.groupby(level=["method", "seed"]).nunique().eq(1).all()


def _namespace(**kw):
    import argparse

    from camo_sbi.experiments.compare import add_arguments

    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args([])
    for k, v in {"model": "panda", "test_goals": 3, **kw}.items():
        setattr(args, k, v)
    return args
