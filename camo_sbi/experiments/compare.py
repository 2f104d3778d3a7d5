"""`camo-sbi compare`: several inference methods on the same task, prior, observations and budget.

The grid is subject x method x budget x seed; one cell runs a method on the first
1..K observed tasks (continual methods observe them once; others rerun per k) and
writes tidy rows (task, subject, method, budget, seed, n_tasks, metric, value)
atomically as soon as it ends. Re-running the same command skips finished cells, so an
interrupted comparison resumes without losing or duplicating a row.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from camo_sbi.distributed import DEFAULT_RETRIES, dask_client, map_unordered, parse_scheduler
from camo_sbi.experiments.manipulator import derive_seed, evaluate_estimate
from camo_sbi.experiments.plots import plot_lines, save_figure
from camo_sbi.experiments.processes import run_in_processes as _run_in_processes
from camo_sbi.experiments.rundir import RunDirectory, run_settings
from camo_sbi.experiments.store import ResultStore, cell_key
from camo_sbi.experiments.subjects import build_model, subject_names, subject_theta

__all__ = ["add_arguments", "main", "run_cell", "run_cells_on", "cell_specs"]

_SIMS: dict[str, object] = {}


def _model(name: str):
    if name not in _SIMS:
        _SIMS[name] = build_model(name)
    return _SIMS[name]


def _parse_list(text: str, name: str, cast=str) -> list:
    items = [t.strip() for t in str(text).split(",") if t.strip()]
    if not items:
        raise ValueError(f"--{name}: give at least one value")
    try:
        return [cast(t) for t in items]
    except ValueError as exc:
        raise ValueError(f"--{name}: {exc}") from exc


def cell_specs(args) -> list[dict]:
    """Every grid cell as a plain dict (picklable; the cell's identity is its key)."""
    from camo_sbi.inference.methods import get_method

    methods = _parse_list(args.methods, "methods")
    for m in methods:
        get_method(m)
    budgets = _parse_list(args.budgets, "budgets", int)
    if any(b < 1 for b in budgets):
        raise ValueError("--budgets: every budget must be >= 1")
    if args.seeds < 1 or args.tasks < 1 or args.test_goals < 1:
        raise ValueError("--seeds/--tasks/--test-goals: must be >= 1")
    subjects = _parse_list(args.subjects, "subjects") if args.subjects else subject_names(args.model)[:1]
    sim = _model(args.model)
    for s in subjects:
        subject_theta(sim, args.model, s)
    specs = []
    for subject in subjects:
        for method in methods:
            for budget in budgets:
                for seed in range(args.seeds):
                    spec = {"task": args.model, "subject": subject, "method": method, "budget": budget,
                            "seed": seed, "tasks": args.tasks, "test_goals": args.test_goals,
                            "space": args.space, "base_seed": args.seed}
                    spec["key"] = cell_key({k: v for k, v in spec.items()})
                    specs.append(spec)
    return specs


def _config_for(method: str, space: str, workdir: Path) -> dict:
    if method == "naive":
        return {}
    cfg = {"space": space}
    if method in ("abc-smc", "npe"):
        cfg["workdir"] = str(workdir)
    return cfg


def run_cell(spec: dict, out: str) -> str:
    """Run one cell and write its rows (and final posterior) atomically; returns its key."""
    from camo_sbi.inference.methods import run_method_sequence
    from camo_sbi.scenarios.reaching import make_reaching_task

    out = Path(out)
    store = ResultStore(out)
    sim = _model(spec["task"])
    true_theta = subject_theta(sim, spec["task"], spec["subject"])
    # the task (observations, test goals) depends on the seed only: identical across methods
    task = make_reaching_task(sim, true_theta, n_train=spec["tasks"], n_test=spec["test_goals"],
                              seed=derive_seed(spec["base_seed"], spec["seed"]), name=spec["task"],
                              subject=spec["subject"])
    m = task.test_goals.shape[0]
    true_test = sim.simulate(true_theta.expand(m, -1), task.test_goals, task.test_starts)
    workdir = out / "work" / spec["key"]
    results = run_method_sequence(spec["method"], task, budget=spec["budget"],
                                  seed=derive_seed(spec["base_seed"], spec["seed"], 7),
                                  config=_config_for(spec["method"], spec["space"], workdir))
    rows = []
    base = {k: spec[k] for k in ("task", "subject", "method", "budget", "seed")}
    rng = np.random.default_rng(derive_seed(spec["base_seed"], spec["seed"], 11))
    for res in results:
        metrics = evaluate_estimate(task, res.estimate, true_test)
        err = np.abs(res.estimate - task.true_theta.numpy())
        for j, name in enumerate(sim.joint_names):
            metrics[f"limit_error_{name}"] = float(err[2 * j : 2 * j + 2].mean())
        metrics["ppc_dtw"] = _posterior_predictive_dtw(task, res, true_test, rng)
        metrics["n_simulations"] = res.n_simulations
        metrics["wall_time"] = res.wall_time
        rows += [{**base, "n_tasks": res.n_tasks, "metric": k, "value": v} for k, v in metrics.items()]
    _save_posterior(out, spec, sim, task, results[-1])
    store.put(spec["key"], rows)
    return spec["key"]


def _posterior_predictive_dtw(task, res, true_test, rng, n_draws: int = 8) -> float:
    """Mean DTW (Cartesian) between true held-out trajectories and ones predicted by posterior draws."""
    from camo_sbi.inference.distances import dtw_distances
    from camo_sbi.scenarios.reaching import predict

    draws = res.resample(n_draws, rng)
    total = []
    for d in draws:
        pred = predict(task.simulator, torch.as_tensor(d), task.test_starts, task.test_goals)
        for i in range(true_test.batch_size):
            L = int(true_test.length[i])
            total.append(float(dtw_distances(true_test.ee[i, :L], pred.ee[i : i + 1], pred.length[i : i + 1])[0]))
    return float(np.mean(total))


def _save_posterior(out: Path, spec: dict, sim, task, res) -> None:
    try:
        from camo_sbi.diagnostics.arviz_io import save_netcdf, to_inference_data
    except ImportError:  # diagnostics not installed
        return
    idata = to_inference_data(res, sim.joint_names, prior=task.prior, true_theta=task.true_theta,
                              seed=derive_seed(spec["base_seed"], spec["seed"], 13))
    idata.posterior.attrs.update({"budget": spec["budget"], "seed": spec["seed"], "subject": spec["subject"]})
    (out / "posteriors").mkdir(parents=True, exist_ok=True)
    save_netcdf(idata, out / "posteriors" / f"{spec['key']}.nc")


def make_figures(df, out: Path) -> list[Path]:
    """Error vs budget (log x), error vs observed tasks, wall time per method."""
    import matplotlib.pyplot as plt

    paths = []
    last = df[df.n_tasks == df.n_tasks.max()]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    plot_lines(last[last.metric == "cartesian_error"], x="budget", ax=axes[0], logx=True,
               ylabel="cumulative Cartesian error [m]", title="Test error vs budget")
    plot_lines(last[last.metric == "limit_error"], x="budget", ax=axes[1], logx=True,
               ylabel="mean |limit error| [rad]", title="Joint-limit error vs budget")
    paths.append(out / "error_vs_budget.png")
    save_figure(fig, paths[-1])
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    bmax = df.budget.max()
    sel = df[df.budget == bmax]
    plot_lines(sel[sel.metric == "cartesian_error"], ax=axes[0], ylabel="cumulative Cartesian error [m]",
               title=f"Test error vs tasks (budget {bmax})")
    plot_lines(sel[sel.metric == "limit_error"], ax=axes[1], ylabel="mean |limit error| [rad]",
               title=f"Joint-limit error vs tasks (budget {bmax})")
    paths.append(out / "error_vs_tasks.png")
    save_figure(fig, paths[-1])
    fig, ax = plt.subplots(figsize=(6, 4))
    wt = last[last.metric == "wall_time"]
    plot_lines(wt, x="budget", ax=ax, logx=True, logy=True, ylabel="wall time [s]",
               title="Wall time per run (all tasks)")
    paths.append(out / "wall_time.png")
    save_figure(fig, paths[-1])
    return paths


def run_cells_on(client, specs: list[dict], out, *, retries: int = DEFAULT_RETRIES, on_done=None) -> list[str]:
    """Run cells on a Dask client; a cell whose worker dies is retried (``retries``).

    A retried cell rewrites the same atomic file, so the store never holds a duplicate or
    a partial cell. Returns the finished keys in completion order.
    """
    client.run(_init_worker)
    keys = []
    for key in map_unordered(run_cell, specs, client, retries=retries, out=str(out)):
        keys.append(key)
        if on_done is not None:
            on_done(key)
    return keys


def _init_worker():
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
    torch.set_num_threads(1)


def run_in_processes(cell_fn, specs: list[dict], out, workers: int, *, on_done) -> None:
    """Run ``cell_fn(spec, str(out))`` for every spec in ``workers`` spawned processes.

    Each cell writes its own rows atomically; ``on_done()`` is called as cells finish and the
    first failing cell's exception is re-raised (its workers killed, cells in flight lost).
    ``cell_fn`` must be a module-level function. Workers die with the parent
    (`camo_sbi.experiments.processes`).
    """
    _run_in_processes(cell_fn, specs, out, workers, on_done=on_done, initializer=_init_worker)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", choices=("panda", "human"), default="panda")
    p.add_argument("--methods", default="camo,naive,abc-smc,npe", help="comma-separated method names")
    p.add_argument("--budgets", default="500", help="comma-separated simulations per observed task")
    p.add_argument("--seeds", type=int, default=2, help="number of seeds (subjects' observations differ per seed)")
    p.add_argument("--tasks", type=int, default=3, help="observed tasks K (rows for 1..K)")
    p.add_argument("--test-goals", type=int, default=10)
    p.add_argument("--subjects", default=None, help="comma-separated subject profiles (default: the first)")
    p.add_argument("--space", choices=("joint", "cartesian"), default="joint")
    p.add_argument("--workers", type=int, default=1, help="parallel worker processes (without --scheduler)")
    p.add_argument("--scheduler", default=None,
                   help="run the cells on Dask: 'local:N' (a LocalCluster with N worker processes) or "
                        "a scheduler address 'tcp://host:8786'; default: in-process / --workers")
    p.add_argument("--seed", type=int, default=0, help="base seed")
    p.add_argument("--no-report", action="store_true", help="skip the HTML report")
    p.add_argument("--wait", action="store_true", help="if another run holds --out, wait for it instead of stopping")
    p.add_argument("--out", type=Path, default=Path("runs/compare"))


def main(args) -> int:
    t0 = time.perf_counter()
    specs = cell_specs(args)
    if args.workers < 1:
        raise ValueError("--workers: must be >= 1")
    scheduler = getattr(args, "scheduler", None)
    try:
        parse_scheduler(scheduler)
    except ValueError as exc:
        raise ValueError(f"--{exc}") from exc
    out = Path(args.out)
    settings = run_settings(args, methods=_parse_list(args.methods, "methods"),
                            budgets=_parse_list(args.budgets, "budgets", int),
                            subjects=list(dict.fromkeys(s["subject"] for s in specs)))
    with RunDirectory(out, "compare", settings, wait=getattr(args, "wait", False)) as run:
        store = run.store
        todo = [s for s in specs if not store.done(s["key"])]
        print(f"{len(specs)} cells, {len(specs) - len(todo)} already finished")
        bar = tqdm(total=len(todo), desc="compare", unit="cell")
        if parse_scheduler(scheduler) is not None:
            with dask_client(scheduler) as client:
                run_cells_on(client, todo, out, on_done=lambda _key: bar.update())
        elif args.workers == 1:
            for spec in todo:
                bar.set_postfix_str(f"{spec['method']} b={spec['budget']} s={spec['seed']}")
                run_cell(spec, str(out))
                bar.update()
        else:
            run_in_processes(run_cell, todo, out, args.workers, on_done=bar.update)
        bar.close()
        df = store.write_table()
        keys = {s["key"] for s in specs}
        missing = keys - store.finished_keys()
        if missing:
            raise RuntimeError(f"{len(missing)} cells did not finish")
        figs = make_figures(df, out)
        last = df[(df.n_tasks == df.n_tasks.max()) & df.metric.isin(["cartesian_error", "limit_error", "wall_time", "n_simulations"])]
        summary = last.groupby(["method", "budget", "metric"])["value"].agg(["mean", "std"]).unstack("metric")
        print(summary.to_string(float_format=lambda v: f"{v:.4g}"))
        print(f"table: {out / 'results.csv'} ({len(df)} rows)  figures: {', '.join(str(f.name) for f in figs)}")
        if not args.no_report:
            try:
                from camo_sbi.diagnostics.report import write_report
            except ImportError:
                pass
            else:
                print(f"report: {write_report(out, out / 'report.html')}")
    print(f"wall time: {time.perf_counter() - t0:.1f} s")
    return 0
