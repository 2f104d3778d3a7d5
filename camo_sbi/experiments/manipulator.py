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
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from camo_sbi.distributed import dask_client, parse_scheduler
from camo_sbi.experiments.plots import plot_bars, plot_lines, save_figure
from camo_sbi.experiments.rundir import RunDirectory, run_settings
from camo_sbi.experiments.store import cell_key
from camo_sbi.experiments.subjects import build_model, subject_names, subject_theta

__all__ = ["add_arguments", "main", "run_one", "evaluate_estimate"]

METHOD_LABELS = ("camo-js", "camo-cs", "camo-hull", "naive")
"""The paper's three curves and camo-hull: CAMO-JS with the prior conditioned on the observed
postures (CamoConfig.contain_observed; not in the paper)."""
# settings that change a run's rows: part of each cell's key, so a re-run with other
# settings into the same directory computes new cells instead of reusing old ones
_CELL_SETTINGS = ("model", "tasks", "test_goals", "samples", "epsilon", "keep_best", "bandwidth",
                  "bandwidth_mode", "sampling", "methods", "seed")


def derive_seed(*parts: int) -> int:
    """A 63-bit integer seed derived from ``parts`` (numpy SeedSequence)."""
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(2, np.uint64)[0] >> 1)


def evaluate_estimate(task, estimate, true_test) -> dict[str, float]:
    """Metrics of one estimate: test-trajectory errors and limit error against the truth."""
    from camo_sbi.scenarios.reaching import (
        cumulative_cartesian_error,
        cumulative_joint_error,
        predict,
    )

    pred = predict(task.simulator, torch.as_tensor(estimate), task.test_starts, task.test_goals)
    out = {
        "cartesian_error": float(cumulative_cartesian_error(true_test, pred).mean()),
        "joint_error": float(cumulative_joint_error(true_test, pred).mean()),
    }
    if task.true_theta is not None:
        free = task.prior.free_mask
        diff = (torch.as_tensor(estimate, dtype=torch.float64) - task.true_theta).abs()[free]
        out["limit_error"] = float(diff.mean())
    return out


def _method_configs(args) -> dict[str, tuple[str, dict]]:
    camo = {"epsilon": args.epsilon, "keep_best": args.keep_best, "bandwidth": args.bandwidth,
            "bandwidth_mode": args.bandwidth_mode, "sampling": args.sampling,
            "scheduler": getattr(args, "scheduler", None)}
    table = {
        "camo-js": ("camo", {**camo, "space": "joint"}),
        "camo-cs": ("camo", {**camo, "space": "cartesian"}),
        "camo-hull": ("camo-hull", {**camo, "space": "joint"}),
        "naive": ("naive", {}),
    }
    return {m: table[m] for m in args.methods}


def run_one(sim, model: str, subject: str, run: int, args) -> list[dict]:
    """All methods on one run's subject; returns tidy rows."""
    from camo_sbi.inference.methods import run_method_sequence
    from camo_sbi.scenarios.reaching import make_reaching_task

    true_theta = subject_theta(sim, model, subject)
    task = make_reaching_task(sim, true_theta, n_train=args.tasks, n_test=args.test_goals,
                              seed=derive_seed(args.seed, run), name=model, subject=subject)
    m = task.test_goals.shape[0]
    true_test = sim.simulate(true_theta.expand(m, -1), task.test_goals, task.test_starts)
    rows = []
    for label, (name, cfg) in _method_configs(args).items():
        results = run_method_sequence(name, task, budget=args.samples, seed=derive_seed(args.seed, run, 1),
                                      config=cfg)
        for res in results:
            metrics = evaluate_estimate(task, res.estimate, true_test)
            metrics["n_simulations"] = res.n_simulations
            metrics["wall_time"] = res.wall_time
            for metric, value in metrics.items():
                rows.append({"run": run, "model": model, "subject": subject, "method": label,
                             "n_tasks": res.n_tasks, "metric": metric, "value": value})
    return rows


def make_figures(df, out: Path) -> list[Path]:
    """Fig. 2 (Cartesian error vs tasks) and Fig. 3 (joint-space loss after all tasks)."""
    import matplotlib.pyplot as plt

    paths = []
    fig, ax = plt.subplots(figsize=(6, 4))
    plot_lines(df[df.metric == "cartesian_error"], ax=ax, ylabel="cumulative Cartesian error [m]",
               title="Error on unseen goals vs observed tasks (mean, 95% CI)")
    paths.append(out / "fig2_cartesian_error_vs_tasks.png")
    save_figure(fig, paths[-1])
    last = df[df.n_tasks == df.n_tasks.max()]
    fig, axes = plt.subplots(1, 2, figsize=(9, 4))
    plot_bars(last[last.metric == "joint_error"], ax=axes[0], ylabel="cumulative joint loss [rad]",
              title=f"Joint space, after {int(df.n_tasks.max())} tasks")
    plot_bars(last[last.metric == "cartesian_error"], ax=axes[1], ylabel="cumulative Cartesian error [m]",
              title=f"Cartesian, after {int(df.n_tasks.max())} tasks")
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
    p.add_argument("--methods", default=",".join(METHOD_LABELS),
                   help=f"comma-separated subset of {','.join(METHOD_LABELS)}")
    p.add_argument("--subjects", default=None, help="comma-separated ground-truth profiles (default: all, cycled)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--scheduler", default=None,
                   help="run CAMO's candidate chunks on Dask: 'local:N' or 'tcp://host:8786' "
                        "(same numbers as in-process)")
    p.add_argument("--wait", action="store_true", help="if another run holds --out, wait for it instead of stopping")
    p.add_argument("--out", type=Path, default=Path("runs/reproduce_panda"))


def main(args) -> int:
    args.methods = [m.strip() for m in str(args.methods).split(",") if m.strip()] if isinstance(args.methods, str) else args.methods
    bad = [m for m in args.methods if m not in METHOD_LABELS]
    if bad:
        raise ValueError(f"--methods: unknown {bad}; known: {', '.join(METHOD_LABELS)}")
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
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if k != "func"}
    with RunDirectory(out, "reproduce panda", run_settings(args, subjects=subjects),
                      wait=getattr(args, "wait", False)) as rundir:
        store = rundir.store
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
    last = df[(df.n_tasks == df.n_tasks.max()) & (df.metric.isin(["cartesian_error", "joint_error", "limit_error"]))]
    summary = last.groupby(["method", "metric"])["value"].agg(["mean", "std"]).unstack("metric")
    print(summary.to_string(float_format=lambda v: f"{v:.4f}"))
    print(f"table: {out / 'results.csv'}  figures: {', '.join(str(f) for f in figs)}")
    print(f"wall time: {wall:.1f} s")
    return 0
