"""`camo-sbi reproduce panda`: the paper's manipulator experiment (Fig. 2 and Fig. 3).

For each run a ground-truth subject (a named restricted-limit profile) reaches
``--tasks`` training goals and ``--test-goals`` held-out goals, all sampled inside its
true limits. CAMO-JS (joint observations), CAMO-CS (Cartesian observations), camo-hull
(CAMO-JS with the prior conditioned on the observed postures, `CamoConfig.contain_observed`;
not in the paper) and the naive min/max baseline estimate the limits after every observed
task; each estimate predicts the held-out trajectories. Rows: run, subject, method, n_tasks, metric, value.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from tqdm import tqdm

from camo_sbi._validation import derive_seed
from camo_sbi.distributed import dask_client, parse_scheduler
from camo_sbi.experiments.store import ResultStore, atomic_write_text, cell_key
from camo_sbi.experiments.subjects import build_model, subject_names, subject_theta

__all__ = ["DEFAULT_METHODS", "add_arguments", "main", "method_config", "run_one"]

DEFAULT_METHODS = ("camo-js", "camo-cs", "camo-hull", "naive", "nominal", "oracle")
"""The paper's CAMO-JS, CAMO-CS and naive; camo-hull (CAMO-JS with the prior conditioned on the
observed postures; not in the paper); the nominal and oracle baselines."""
# settings that change a run's rows: part of each cell's key, so a re-run with other
# settings into the same directory computes new cells instead of reusing old ones
_CELL_SETTINGS = ("model", "tasks", "test_goals", "samples", "epsilon", "keep_best", "bandwidth",
                  "bandwidth_mode", "sampling", "methods", "seed")


def method_config(name: str, args) -> dict | None:
    """The config a run gives method ``name``: CAMO's options for the CAMO family, else defaults."""
    from camo_sbi.inference.registry import get_method

    spec = get_method(name)
    if "camo" not in (name, spec.base):
        return None
    return {"epsilon": args.epsilon, "keep_best": args.keep_best, "bandwidth": args.bandwidth,
            "bandwidth_mode": args.bandwidth_mode, "sampling": args.sampling,
            "scheduler": getattr(args, "scheduler", None)}


def run_one(sim, model: str, subject: str, run: int, args) -> list[dict]:
    """All methods on one run's subject; returns tidy rows."""
    from camo_sbi.evaluation.evaluate import evaluate_result, true_test_trajectories
    from camo_sbi.evaluation.metrics import binding_bounds
    from camo_sbi.inference.registry import run_method_sequence
    from camo_sbi.scenarios.reaching import make_reaching_task

    true_theta = subject_theta(sim, model, subject)
    task = make_reaching_task(sim, true_theta, n_train=args.tasks, n_test=args.test_goals,
                              seed=derive_seed(args.seed, run), name=model, subject=subject)
    true_test = true_test_trajectories(task)
    binding = binding_bounds(sim, true_theta, task.test_starts, task.test_goals, task.prior)
    rows = []
    for name in args.methods:
        results = run_method_sequence(name, task, budget=args.samples, seed=derive_seed(args.seed, run, 1),
                                      config=method_config(name, args))
        for res in results:
            metrics = evaluate_result(task, res, true_test, binding)
            metrics["n_simulations"] = res.n_simulations
            metrics["wall_time"] = res.wall_time
            for metric, value in metrics.items():
                rows.append({"run": run, "model": model, "subject": subject, "method": name,
                             "n_tasks": res.n_tasks, "metric": metric, "value": value, "status": res.status})
    return rows


def make_figures(df, out: Path) -> list[Path]:
    """Fig. 2 (Cartesian error vs tasks) and Fig. 3 (joint-space loss after all tasks)."""
    from camo_sbi.diagnostics.style import (
        metric_label,
        new_figure,
        plot_bars,
        plot_lines,
        save_figure,
    )

    paths = []
    fig, axes = new_figure(1, 1)
    plot_lines(df[df.metric == "cartesian_error_mm"], ax=axes[0, 0], ylabel=metric_label("cartesian_error_mm"),
               title="Error on unseen goals vs observed tasks")
    paths.append(out / "fig2_cartesian_error_vs_tasks.png")
    save_figure(fig, paths[-1])
    last = df[df.n_tasks == df.n_tasks.max()]
    fig, axes = new_figure(1, 2)
    for ax, metric, space in zip(axes[0], ("joint_error_deg", "cartesian_error_mm"), ("Joint space", "Cartesian"),
                                 strict=True):
        plot_bars(last[last.metric == metric], ax=ax, ylabel=metric_label(metric),
                  title=f"{space}, after {int(df.n_tasks.max())} tasks")
    paths.append(out / "fig3_final_error.png")
    save_figure(fig, paths[-1])
    return paths


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", choices=("panda", "human"), default="panda", help="simulated agent")
    p.add_argument("--runs", type=int, default=30, help="independent runs (paper: 30)")
    p.add_argument("--tasks", type=int, default=10, help="observed training goals per run")
    p.add_argument("--test-goals", type=int, default=20, help="held-out goals per run")
    p.add_argument("--samples", type=int, default=2000, help="CAMO prior draws per task (b)")
    p.add_argument("--epsilon", type=float, default=None, help="CAMO DTW acceptance threshold")
    p.add_argument("--keep-best", type=int, default=100, help="CAMO keeps at most the k best per task")
    p.add_argument("--bandwidth", type=float, default=0.2, help="CAMO kernel variance h [rad^2]")
    p.add_argument("--bandwidth-mode", choices=("fixed", "scott"), default="fixed")
    p.add_argument("--sampling", choices=("uniform", "lhs"), default="uniform")
    p.add_argument("--methods", default=",".join(DEFAULT_METHODS),
                   help="comma-separated registered methods (default: %(default)s)")
    p.add_argument("--subjects", default=None, help="comma-separated ground-truth profiles (default: all, cycled)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--scheduler", default=None,
                   help="run CAMO's candidate chunks on Dask: 'local:N' or 'tcp://host:8786' "
                        "(same numbers as in-process)")
    p.add_argument("--out", type=Path, default=Path("runs/reproduce_panda"))


def main(args) -> int:
    from camo_sbi.inference.registry import get_method

    args.methods = [m.strip() for m in str(args.methods).split(",") if m.strip()] if isinstance(args.methods, str) else args.methods
    for m in args.methods:
        try:
            get_method(m)
        except ValueError as exc:
            raise ValueError(f"--methods: {exc}") from exc
    for name in ("runs", "tasks", "test_goals", "samples"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')}: must be >= 1")
    try:
        parse_scheduler(getattr(args, "scheduler", None))
    except ValueError as exc:
        raise ValueError(f"--{exc}") from exc
    t0 = time.perf_counter()
    sim = build_model(args.model)
    subjects = args.subjects.split(",") if args.subjects else subject_names(args.model)
    for s in subjects:
        subject_theta(sim, args.model, s)  # validates names before any work
    out = Path(args.out)
    store = ResultStore(out)
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if k != "func"}
    atomic_write_text(out / "config.json", json.dumps({"experiment": "reproduce panda", **settings}, indent=2))
    with dask_client(getattr(args, "scheduler", None)):  # CAMO's configs reuse this client
        for run in tqdm(range(args.runs), desc=f"reproduce {args.model}", unit="run"):
            subject = subjects[run % len(subjects)]
            key = cell_key({"run": run, "subject": subject, **{k: settings[k] for k in _CELL_SETTINGS}})
            if store.done(key):
                continue
            store.put(key, run_one(sim, args.model, subject, run, args))
    df = store.write_table()
    figs = make_figures(df, out)
    wall = time.perf_counter() - t0
    last = df[(df.n_tasks == df.n_tasks.max()) & (df.metric.isin(["cartesian_error_mm", "joint_error_deg", "limit_error_deg",
                                                                    "limit_error_binding_deg"]))]
    summary = last.groupby(["method", "metric"])["value"].agg(["mean", "std"]).unstack("metric")
    print(summary.to_string(float_format=lambda v: f"{v:.4f}"))
    print(f"table: {out / 'results.csv'}  figures: {', '.join(str(f) for f in figs)}")
    print(f"wall time: {wall:.1f} s")
    return 0
