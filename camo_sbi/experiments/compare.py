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
import logging
import time
from pathlib import Path

from camo_sbi.experiments.figure_options import (
    add_corner_argument,
    add_figure_format_argument,
    corner_limits,
    figure_formats,
)
from camo_sbi.experiments.method_configs import method_config, parse_configs
from camo_sbi.experiments.models import (
    add_model_arguments,
    model_from_args,
    subject_limits,
    subject_list,
)

# only light modules at import time: the CLI builds its parser from add_arguments (numpy, torch,
# pandas and the store are imported by the functions that use them)
from camo_sbi.experiments.run_options import add_run_options

__all__ = ["add_arguments", "grid_cells", "main", "run_cell"]

log = logging.getLogger(__name__)


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


FLAGS = {"seeds": "--seeds", "tasks": "--tasks", "test_goals": "--test-goals", "workers": "--workers"}


def check_grid_size(args, *, subjects: int = 1, sim=None, names: dict | None = None) -> int:
    """Refuse counts (--seeds, --tasks, --test-goals, --workers) whose grid cannot fit in memory
    (`camo_sbi._memory.check_grid_fits`, a lower bound), before anything is built. Without ``sim``
    the model's size is taken as its least (one joint, one point per reach): the check a study
    makes of all its entries up front. ``names``: how the counts are spelt to the user."""
    from camo_sbi._memory import check_grid_fits

    cells_per_seed = subjects * len(grid_methods(args.methods)) * len(_parse_list(args.budgets, "budgets", int))
    size = {} if sim is None else {"n_joints": sim.n_joints,
                                   "max_steps": getattr(getattr(sim, "config", None), "max_steps", 1)}
    return check_grid_fits(seeds=args.seeds, cells_per_seed=cells_per_seed, tasks=args.tasks,
                           test_goals=args.test_goals, workers=getattr(args, "workers", 1) or 1,
                           names=names or FLAGS, **size)


def grid_cells(args, *, build: bool = True) -> list:
    """Every grid cell as a `Cell` (picklable; its identity is its key).

    ``build=False``: the same cells without building the model or checking the subjects against
    it (`models.model_from_args`), for a re-run whose cells are all finished.
    """
    from camo_sbi.experiments.grid import Cell

    methods = grid_methods(args.methods)
    budgets = _parse_list(args.budgets, "budgets", int)
    if any(b < 1 for b in budgets):
        raise ValueError("--budgets: every budget must be >= 1")
    if args.seeds < 1 or args.tasks < 1 or args.test_goals < 1:
        raise ValueError("--seeds/--tasks/--test-goals: must be >= 1")
    model = model_from_args(args, build=build)
    subjects = subject_list(model, args.subjects)
    sim = model.build() if build else None
    check_grid_size(args, subjects=len(subjects), sim=sim)  # before a cell or a task is built
    if build:
        for s in subjects:
            subject_limits(model, sim, s)
    # the model in the key: its name as "task"; a built-in model with its defaults keeps the cell
    # keys it always had, any other adds its settings as "model"
    model_key = (("task", model.name),) + (() if model.is_default else
                                           (("model", json.dumps(model.key(), sort_keys=True)),))
    from camo_sbi.inference.registry import capabilities

    amortized = {m for m in methods if capabilities(m).amortized}
    amortized_path = getattr(args, "amortized", None)
    if amortized and amortized_path is None:
        raise ValueError("--amortized: npe-amortized needs an estimator file (main() trains one when none is given)")
    amortized_path = None if amortized_path is None else str(amortized_path)
    overrides = parse_configs(getattr(args, "config", None), methods)
    cells = []
    for subject in subjects:
        for method in methods:
            for budget in budgets:
                for seed in range(args.seeds):
                    extras = {"test_goals": args.test_goals, "space": args.space, "base_seed": args.seed}
                    if method in amortized:
                        extras["estimator"] = amortized_path
                    if method in overrides:  # only then part of the key: runs without --config keep theirs
                        extras["config"] = json.dumps(overrides[method], sort_keys=True)
                    cells.append(Cell(model=model, subject=subject, seed=seed, budget=budget, tasks=args.tasks,
                                      method=method, extras=extras, model_key=model_key))
    return cells


def _model_setting(model) -> str:
    """How a run's model is recorded: its name for a built-in model with its defaults, else its key."""
    return model.name if model.is_default else json.dumps(model.key(), sort_keys=True)


def run_cell(cell, out: str) -> list[dict]:
    """Run one cell (a `Cell` of `grid_cells`); writes its final posterior, returns its rows."""
    from camo_sbi._validation import derive_seed
    from camo_sbi.evaluation.evaluate import PPC_DRAWS, evaluate_result, true_test_trajectories
    from camo_sbi.evaluation.metrics import binding_bounds
    from camo_sbi.inference.registry import run_method_sequence
    from camo_sbi.scenarios.reaching import make_reaching_task, task_binding_metrics

    out = Path(out)
    x = cell.extras
    sim = cell.model.build()
    true_theta = subject_limits(cell.model, sim, cell.subject)
    # the task (observations, test goals) depends on the seed only: identical across methods
    task = make_reaching_task(sim, true_theta, n_train=cell.tasks, n_test=x["test_goals"],
                              seed=derive_seed(x["base_seed"], cell.seed), name=cell.model.name,
                              subject=cell.subject)
    true_test = true_test_trajectories(task)
    binding = binding_bounds(sim, true_theta, task.test_starts, task.test_goals, task.prior)
    informative = task_binding_metrics(task)
    config = method_config(cell.method, space=x["space"], workdir=out / "work" / cell.key,
                           estimator_path=x.get("estimator"), overrides=json.loads(x.get("config", "{}")))
    results = run_method_sequence(cell.method, task, budget=cell.budget,
                                  seed=derive_seed(x["base_seed"], cell.seed, "method"), config=config,
                                  errors="record")
    rows = []
    base = {"task": cell.model.name, "subject": cell.subject, "method": cell.method, "budget": cell.budget,
            "seed": cell.seed}
    for res in results:
        # every metric of the catalog that applies, per-joint limit errors and costs included
        metrics = {**evaluate_result(task, res, true_test, binding, posterior_predictive_draws=PPC_DRAWS),
                   **informative}
        if res is results[-1]:  # does the final posterior reproduce the observed reaches? (issue 33)
            from camo_sbi.diagnostics.misspecification import check_metrics

            metrics.update(check_metrics(task, res, seed=derive_seed(x["base_seed"], cell.seed, 33)))
        rows += [{**base, "n_tasks": res.n_tasks, "metric": k, "value": v, "status": res.status}
                 for k, v in metrics.items()]
    _save_posterior(out, cell, sim, task, results[-1])
    return rows


def _save_posterior(out: Path, cell, sim, task, res) -> None:
    from camo_sbi._validation import derive_seed
    from camo_sbi.diagnostics.arviz_io import observed_arrays, save_in_run, to_inference_data

    observed, dims = observed_arrays(task)
    idata = to_inference_data(res, sim.joint_names, prior=task.prior, true_theta=task.true_theta,
                              seed=derive_seed(cell.extras["base_seed"], cell.seed, "posterior-file"),
                              observed=observed, observed_dims=dims,
                              attrs={"task": cell.model.name, "status": res.status})
    idata.posterior.attrs.update({"budget": cell.budget, "seed": cell.seed, "subject": cell.subject,
                                  "model_spec": cell.model.to_json()})  # the report rebuilds exactly this body
    save_in_run(idata, out, cell.key)  # posteriors/, or estimates/ for a point estimate


def make_figures(df, out: Path, formats=("png",)) -> list[Path]:
    """The headline metrics (`camo_sbi.evaluation.catalog`) vs observed tasks at the largest
    budget; with at least two budgets, vs budget (log x) and wall time vs budget; with one
    budget no error-vs-budget figure (its points are the last ones of error vs tasks) and the
    wall time as bars per method. Angles in degrees. Each figure once per format of
    ``formats`` (``--figure-format``)."""
    from camo_sbi.diagnostics.style import display_metric, paper_style

    with paper_style():
        return _make_figures(display_metric(df), out, formats)


def headline_panels(sub, x: str, title, **kw):
    """A figure of one panel per headline metric in ``sub`` (tidy rows) against ``x``, one
    legend below; ``title(label)`` the panels' titles. Returns (figure, the metrics drawn)."""
    from camo_sbi.diagnostics.plot_primitives import figure_legend, plot_lines
    from camo_sbi.diagnostics.style import band_label, metric_label, new_figure, run_counts
    from camo_sbi.evaluation import catalog

    metrics = catalog.headline(sub.metric.unique())
    ncol = min(3, max(1, len(metrics)))
    nrow = -(-len(metrics) // ncol)
    fig, axes = new_figure(nrow, ncol)
    flat = axes.reshape(-1)
    for ax in flat[len(metrics):]:
        ax.set_visible(False)
    for ax, metric in zip(flat, metrics, strict=False):
        plot_lines(sub[sub.metric == metric], x=x, ax=ax, ylabel=metric_label(metric), title=title(metric),
                   legend=False, **kw)
    figure_legend(fig, flat[: len(metrics)], title=band_label(run_counts(sub[sub.metric.isin(metrics)], x)))
    return fig, metrics


def _make_figures(df, out: Path, formats) -> list[Path]:
    from camo_sbi.diagnostics.plot_primitives import plot_bars, plot_lines
    from camo_sbi.diagnostics.style import metric_label, new_figure, save_figures

    paths = []
    last = df[df.n_tasks == df.n_tasks.max()]
    n_last = int(df.n_tasks.max())
    if last.budget.nunique() >= 2:
        fig, _ = headline_panels(last, "budget", lambda m: f"vs budget ({n_last} tasks)", logx=True)
        paths.extend(save_figures(fig, out / "error_vs_budget.png", formats))
    bmax = df.budget.max()
    fig, _ = headline_panels(df[df.budget == bmax], "n_tasks", lambda m: f"vs tasks (budget {bmax:g})")
    paths.extend(save_figures(fig, out / "error_vs_tasks.png", formats))
    wt = last[last.metric == "wall_time"]
    fig, axes = new_figure(1, 1)
    if wt.budget.nunique() >= 2:
        plot_lines(wt, x="budget", ax=axes[0, 0], logx=True, logy=True, ylabel=metric_label("wall_time"),
                   title=f"Wall time per run ({n_last} tasks)")
    else:
        plot_bars(wt, ax=axes[0, 0], ylabel=metric_label("wall_time"),
                  title=f"Wall time per run ({n_last} tasks, budget {bmax:g})")
    paths.extend(save_figures(fig, out / "wall_time.png", formats))
    return paths


def _with_estimator(args):
    """``args`` with ``amortized`` set to the estimator file amortized methods use (see
    `camo_sbi.experiments.amortize.estimator_for_run`: trained once here, in the parent, before
    any cell runs, also with --workers / --scheduler, when --amortized is not given)."""
    from camo_sbi.experiments.amortize import estimator_for_run

    path = estimator_for_run(grid_methods(args.methods), model=model_from_args(args),
                             path=getattr(args, "amortized", None),
                             out=args.out, simulations=args.amortize_simulations, space=args.space, seed=args.seed,
                             tasks=args.tasks)
    return argparse.Namespace(**{**vars(args), "amortized": path})


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_model_arguments(p)
    p.add_argument("--methods", default="camo,naive,abc-smc,npe", help="comma-separated method names")
    p.add_argument("--budgets", default="500", help="comma-separated simulations per observed task")
    p.add_argument("--seeds", type=int, default=2, help="number of seeds (subjects' observations differ per seed)")
    p.add_argument("--tasks", type=int, default=3, help="observed tasks K (rows for 1..K)")
    p.add_argument("--test-goals", type=int, default=10)
    p.add_argument("--subjects", default=None, help="comma-separated subject profiles (default: the first; "
                                                     "with --limits the file is the subject)")
    p.add_argument("--space", choices=("joint", "cartesian"), default="joint")
    p.add_argument("--amortized", type=Path, default=None,
                   help="trained estimator file for amortized methods (npe-amortized); default: train one "
                        "under OUT/work/amortized once, before the cells, and reuse it")
    p.add_argument("--amortize-simulations", type=int, default=200_000,
                   help="training simulations when compare trains the amortized estimator itself")
    p.add_argument("--config", action="append", default=[], metavar="METHOD=JSON",
                   help='per-method config overrides, e.g. --config \'npe-amortized={"combine": "smc"}\' '
                        '(repeatable)')
    p.add_argument("--reference", type=Path, default=None,
                   help="a reference set (camo-sbi reference): run every method on its observations and add C2ST "
                        "and MMD against its reference posteriors (the set fixes model, subjects and tasks)")
    p.add_argument("--no-report", action="store_true", help="skip the HTML report")
    add_figure_format_argument(p)
    add_corner_argument(p)
    add_run_options(p, out="runs/compare")


def _finished_grid(args) -> list | None:
    """The grid's cells if every one of them is already finished in ``--out``, else None.

    Computed without building the model (`grid_cells` with ``build=False``), so a re-run of a
    finished grid imports neither torch nor numba. Runs with an amortized method take the full
    path: their estimator file is part of the cell keys and is checked on every run.
    """
    from camo_sbi.experiments.store import ResultStore
    from camo_sbi.inference.registry import capabilities

    out = Path(args.out)
    if not (out / "manifest.json").is_file() or any(capabilities(m).amortized for m in grid_methods(args.methods)):
        return None
    cells = grid_cells(args, build=False)
    store = ResultStore(out)
    if not all(store.done(c.key) for c in cells):
        return None
    log.info("every cell of this grid is finished in %s: no model to build", out)
    return cells


def _figures(df, out: Path, formats) -> list[Path]:
    """`make_figures`, unless ``outputs.json`` says they were drawn from this very results.csv."""
    from camo_sbi.experiments import outputs

    digest = outputs.digest_files([out / "results.csv"], extra=("compare figures", *formats))
    paths = outputs.cached(out, "figures", digest)
    if paths is None:
        paths = make_figures(df, out, formats)
        outputs.record(out, "figures", digest, paths)
    else:
        log.info("figures unchanged: drawn from this results.csv before")
    return paths


def main(args) -> int:
    from camo_sbi.distributed import connect_early, parse_scheduler
    from camo_sbi.evaluation import catalog
    from camo_sbi.evaluation.claims import binding_line
    from camo_sbi.experiments.grid import pending, run_grid
    from camo_sbi.experiments.rundir import RunDirectory, run_settings

    if getattr(args, "reference", None) is not None:  # the benchmark set fixes the grid: its own command path
        from camo_sbi.experiments.reference import compare_main

        budgets = _parse_list(args.budgets, "budgets", int)
        if any(b < 1 for b in budgets):
            raise ValueError("--budgets: every budget must be >= 1")
        return compare_main(args, grid_methods(args.methods), budgets)
    t0 = time.perf_counter()
    formats = figure_formats(args)
    corner = corner_limits(args)
    finished = _finished_grid(args)  # a re-run: nothing to compute, no model to build
    scheduler = getattr(args, "scheduler", None)
    try:
        parse_scheduler(scheduler)
        if finished is None:
            connect_early(scheduler)  # an unreachable address: refused before anything is built
    except ValueError as exc:
        raise ValueError(f"--{exc}") from exc
    if finished is None:
        args = _with_estimator(args)
    cells = finished if finished is not None else grid_cells(args)
    if finished is None and cells:  # refuse what the machine cannot hold; say how long the rest takes
        from camo_sbi.budget import announce_simulation_time, check_budget_fits

        sim = cells[0].model.build()
        check_budget_fits(max(c.budget for c in cells), n_joints=sim.n_joints, flag="--budgets")
        announce_simulation_time(sim, sum(c.budget * c.tasks for c in cells), what="compare")
    if args.workers < 1:
        raise ValueError("--workers: must be >= 1")
    out = Path(args.out)
    overrides = {c.method: json.loads(c.extras["config"]) for c in cells if "config" in c.extras}
    # without --config the settings are those of runs made before the flag existed
    settings = run_settings(args, ignore=() if overrides else ("config",), **({"config": overrides} if overrides else {}),
                            methods=_parse_list(args.methods, "methods"),
                            budgets=_parse_list(args.budgets, "budgets", int),
                            subjects=list(dict.fromkeys(c.subject for c in cells)),
                            model=_model_setting(cells[0].model) if cells else None)
    with RunDirectory(out, "compare", settings, wait=getattr(args, "wait", False)) as run:
        store = run.store
        todo = pending(cells, store)
        if todo and finished is not None:  # a cell went missing since the check: build and validate
            args = _with_estimator(args)
            cells = grid_cells(args)
            todo = pending(cells, store)
        print(f"{len(cells)} cells, {len(cells) - len(todo)} already finished")
        run_grid(run_cell, todo, store, args.workers, scheduler, progress="compare")
        keys = [c.key for c in cells]
        missing = sorted(k for k in keys if not store.done(k))
        if missing:  # deleted or damaged while the run went on: no partial results.csv
            raise ValueError(f"--out {out}: {len(missing)} cell(s) vanished or were damaged during the run "
                             f"(first: {store.cells / (missing[0] + '.csv')}); run the command again to recompute them")
        df = store.write_table(keys=keys)
        figs = _figures(df, out, formats)
        if getattr(args, "amortized", None) is not None:
            from camo_sbi.experiments.amortize import write_cost_table

            write_cost_table(df, args.amortized, out)
        from camo_sbi.diagnostics.numbers import summary_table

        shown = catalog.headline(df.metric.unique()) + [m.name for m in catalog.METRICS if m.group == "cost"]
        print(summary_table(df[(df.n_tasks == df.n_tasks.max()) & df.metric.isin(shown)], shown, unit="seeds",
                            block="budget"))
        print(binding_line(df))
        print(f"table: {out / 'results.csv'} ({len(df)} rows)  figures: {', '.join(str(f.name) for f in figs)}")
        if not args.no_report:
            from camo_sbi.diagnostics.report import report_is_current, write_report

            options = {"corner_limits": corner, "figure_formats": None if formats == ("png",) else formats}
            current = report_is_current(out, out / "report.html", **options)
            print(f"report: {write_report(out, out / 'report.html', progress=True, **options)}"
                  + (" (unchanged: built from the same inputs)" if current else ""))
    print(f"wall time: {time.perf_counter() - t0:.1f} s")
    return 0
