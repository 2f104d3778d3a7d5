"""`camo-sbi compare`: several inference methods on the same task, prior, observations and budget.

The grid is subject x method x budget x seed; one cell runs a method on the first
1..K observed tasks (continual methods observe them once; others rerun per k) and
writes tidy rows (task, subject, method, budget, seed, n_tasks, metric, value)
atomically as soon as it ends. Re-running the same command skips finished cells, so an
interrupted comparison resumes without losing or duplicating a row.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from camo_sbi._validation import derive_seed
from camo_sbi.distributed import DEFAULT_RETRIES, dask_client, map_unordered, parse_scheduler
from camo_sbi.experiments.plots import plot_lines, save_figure
from camo_sbi.experiments.store import ResultStore, atomic_write_text, cell_key
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


def grid_methods(text: str) -> list[str]:
    """``--methods`` plus every registered baseline not already in it (every table shows them)."""
    from camo_sbi.inference.registry import get_method, names

    methods = _parse_list(text, "methods")
    for m in methods:
        try:
            get_method(m)
        except ValueError as exc:
            raise ValueError(f"--methods: {exc}") from exc
    if len(set(methods)) != len(methods):
        raise ValueError(f"--methods: duplicate method in {methods}")
    return methods + [b for b in names(baseline=True) if b not in methods]


def cell_specs(args) -> list[dict]:
    """Every grid cell as a plain dict (picklable; the cell's identity is its key)."""
    methods = grid_methods(args.methods)
    budgets = _parse_list(args.budgets, "budgets", int)
    if any(b < 1 for b in budgets):
        raise ValueError("--budgets: every budget must be >= 1")
    if args.seeds < 1 or args.tasks < 1 or args.test_goals < 1:
        raise ValueError("--seeds/--tasks/--test-goals: must be >= 1")
    subjects = _parse_list(args.subjects, "subjects") if args.subjects else subject_names(args.model)[:1]
    sim = _model(args.model)
    for s in subjects:
        subject_theta(sim, args.model, s)
    from camo_sbi.inference.registry import capabilities

    amortized = {m for m in methods if capabilities(m).amortized}
    amortized_path = getattr(args, "amortized", None)
    if amortized and amortized_path is None:
        raise ValueError("--amortized: npe-amortized needs an estimator file (main() trains one when none is given)")
    amortized_path = None if amortized_path is None else str(amortized_path)
    specs = []
    for subject in subjects:
        for method in methods:
            for budget in budgets:
                for seed in range(args.seeds):
                    spec = {"task": args.model, "subject": subject, "method": method, "budget": budget,
                            "seed": seed, "tasks": args.tasks, "test_goals": args.test_goals,
                            "space": args.space, "base_seed": args.seed}
                    if method in amortized:
                        spec["estimator"] = amortized_path
                    spec["key"] = cell_key({k: v for k, v in spec.items()})
                    specs.append(spec)
    return specs


def method_config(method: str, space: str, workdir: Path, estimator: str | None = None) -> dict:
    """The config a cell gives ``method``, from its capabilities: ``space`` for methods that
    choose their observation space (a variant that fixes it keeps its own), ``workdir`` for
    methods that write artefacts, ``estimator`` (the trained file) for amortized methods."""
    from camo_sbi.inference.registry import get_method

    spec = get_method(method)
    cfg: dict = {}
    if len(spec.capabilities.spaces) > 1 and "space" not in spec.defaults:
        cfg["space"] = space
    if spec.capabilities.workdir:
        cfg["workdir"] = str(workdir)
    if spec.capabilities.amortized:
        cfg["estimator"] = estimator
    return cfg


def run_cell(spec: dict, out: str) -> str:
    """Run one cell and write its rows (and final posterior) atomically; returns its key."""
    from camo_sbi.evaluation.evaluate import PPC_DRAWS, evaluate_result, true_test_trajectories
    from camo_sbi.evaluation.metrics import binding_bounds
    from camo_sbi.inference.registry import run_method_sequence
    from camo_sbi.scenarios.reaching import make_reaching_task

    out = Path(out)
    store = ResultStore(out)
    sim = _model(spec["task"])
    true_theta = subject_theta(sim, spec["task"], spec["subject"])
    # the task (observations, test goals) depends on the seed only: identical across methods
    task = make_reaching_task(sim, true_theta, n_train=spec["tasks"], n_test=spec["test_goals"],
                              seed=derive_seed(spec["base_seed"], spec["seed"]), name=spec["task"],
                              subject=spec["subject"])
    true_test = true_test_trajectories(task)
    binding = binding_bounds(sim, true_theta, task.test_starts, task.test_goals, task.prior)
    workdir = out / "work" / spec["key"]
    results = run_method_sequence(spec["method"], task, budget=spec["budget"],
                                  seed=derive_seed(spec["base_seed"], spec["seed"], 7),
                                  config=method_config(spec["method"], spec["space"], workdir,
                                                       spec.get("estimator")))
    rows = []
    base = {k: spec[k] for k in ("task", "subject", "method", "budget", "seed")}
    for res in results:
        metrics = evaluate_result(task, res, true_test, binding, posterior_predictive_draws=PPC_DRAWS)
        err = np.degrees(np.abs(res.estimate - task.true_theta.numpy()))
        for j, name in enumerate(sim.joint_names):
            metrics[f"limit_error_deg_{name}"] = float(err[2 * j : 2 * j + 2].mean())
        metrics["n_simulations"] = res.n_simulations
        metrics["wall_time"] = res.wall_time
        for k in ("training_simulations", "training_time"):  # an amortized method's one-off cost
            if k in res.extras:
                metrics[k] = res.extras[k]
        rows += [{**base, "n_tasks": res.n_tasks, "metric": k, "value": v, "status": res.status}
                 for k, v in metrics.items()]
    _save_posterior(out, spec, sim, task, results[-1])
    store.put(spec["key"], rows)
    return spec["key"]


def _save_posterior(out: Path, spec: dict, sim, task, res) -> None:
    from camo_sbi.diagnostics.arviz_io import save_netcdf, to_inference_data

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
    plot_lines(last[last.metric == "cartesian_error_mm"], x="budget", ax=axes[0], logx=True,
               ylabel="Cartesian error per point [mm]", title="Test error vs budget")
    plot_lines(last[last.metric == "limit_error_deg"], x="budget", ax=axes[1], logx=True,
               ylabel="mean |limit error| [deg]", title="Joint-limit error vs budget")
    paths.append(out / "error_vs_budget.png")
    save_figure(fig, paths[-1])
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    bmax = df.budget.max()
    sel = df[df.budget == bmax]
    plot_lines(sel[sel.metric == "cartesian_error_mm"], ax=axes[0], ylabel="Cartesian error per point [mm]",
               title=f"Test error vs tasks (budget {bmax})")
    plot_lines(sel[sel.metric == "limit_error_deg"], ax=axes[1], ylabel="mean |limit error| [deg]",
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
    first failing cell's exception is re-raised. ``cell_fn`` must be a module-level function.
    """
    with ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_init_worker) as ex:
        for f in as_completed([ex.submit(cell_fn, spec, str(out)) for spec in specs]):
            f.result()
            on_done()


def _with_estimator(args):
    """``args`` with ``amortized`` set to the estimator file amortized methods use (see
    `camo_sbi.experiments.amortize.estimator_for_run`: trained once here, in the parent, before
    any cell runs, also with --workers / --scheduler, when --amortized is not given)."""
    from camo_sbi.experiments.amortize import estimator_for_run

    path = estimator_for_run(grid_methods(args.methods), model=args.model, path=getattr(args, "amortized", None),
                             out=args.out, simulations=args.amortize_simulations, space=args.space, seed=args.seed)
    return argparse.Namespace(**{**vars(args), "amortized": path})


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
    p.add_argument("--amortized", type=Path, default=None,
                   help="trained estimator file for amortized methods (npe-amortized); default: train one "
                        "under OUT/work/amortized once, before the cells, and reuse it")
    p.add_argument("--amortize-simulations", type=int, default=200_000,
                   help="training simulations when compare trains the amortized estimator itself")
    p.add_argument("--no-report", action="store_true", help="skip the HTML report")
    p.add_argument("--out", type=Path, default=Path("runs/compare"))


def main(args) -> int:
    t0 = time.perf_counter()
    args = _with_estimator(args)
    specs = cell_specs(args)
    if args.workers < 1:
        raise ValueError("--workers: must be >= 1")
    scheduler = getattr(args, "scheduler", None)
    try:
        parse_scheduler(scheduler)
    except ValueError as exc:
        raise ValueError(f"--{exc}") from exc
    out = Path(args.out)
    store = ResultStore(out)
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if k != "func"}
    atomic_write_text(out / "config.json", json.dumps({"experiment": "compare", **settings}, indent=2))
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
    if getattr(args, "amortized", None) is not None:
        from camo_sbi.experiments.amortize import write_cost_table

        write_cost_table(df, args.amortized, out)
    last = df[(df.n_tasks == df.n_tasks.max()) & df.metric.isin(["cartesian_error_mm", "limit_error_deg",
                                                                              "wall_time", "n_simulations"])]
    summary = last.groupby(["method", "budget", "metric"])["value"].agg(["mean", "std"]).unstack("metric")
    print(summary.to_string(float_format=lambda v: f"{v:.4g}"))
    print(f"table: {out / 'results.csv'} ({len(df)} rows)  figures: {', '.join(str(f.name) for f in figs)}")
    if not args.no_report:
        from camo_sbi.diagnostics.report import write_report

        print(f"report: {write_report(out, out / 'report.html')}")
    print(f"wall time: {time.perf_counter() - t0:.1f} s")
    return 0
