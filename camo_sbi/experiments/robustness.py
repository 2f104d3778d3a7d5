"""`camo-sbi robustness`: every method on imperfect observations, against its own clean result.

Conditions (each seed's subject and goals are the same in every condition, so results pair):

* ``clean``: exact joint and end-effector recordings at the controller's rate, exact model;
* ``noise 1deg/5mm`` and ``noise 3deg/15mm``: i.i.d. Gaussian noise on every recorded joint
  angle / end-effector coordinate; the task carries the noise model, so every method can
  honour it (`camo_sbi.task.NoiseModel`);
* ``rate x3``: recorded at 3 times the controller's rate, then resampled to the controller's
  step as the recording loader does (the rate estimated from the reaches, normalised time);
* ``taller 5%`` / ``shorter 5%`` (and, not in the default list, ``taller 10%`` / ``shorter
  10%``): the observed person's segments longer / shorter than the model's
  (`KinematicSimulator.scaled`); observations and the true held-out reaches come from that
  body, inference and predictions from the model. With ``--body-scale free`` the model is
  first rescaled by the scale s estimated from the observations (joint and end-effector
  recordings together, `camo_sbi.io.geometry.estimate_body_scale`), for every method; the
  ``body_scale`` metric records s.

Per (seed, condition, method): every metric of the one scorer (`evaluate_result`, with the
interval coverage): the prediction metrics of the held-out reaches (the true body's reaches vs
the model's prediction from the estimate), the limit errors (``limit_error_binding_deg``:
binding on the true body's held-out reaches; per joint) and ``coverage90``: the share of the
free true limits inside the posterior's 90% central interval (a point estimate covers only an
exact value). The table and the figure show the catalog's headline metrics. The
oracle (the true limits) shows what the condition itself costs: under a mis-sized model even
the true limits mispredict. Outputs:
``results.csv`` (tidy), ``robustness.csv`` (per method and condition: mean over seeds, and the
error's ratio to the clean condition), ``robustness.png``.
"""

from __future__ import annotations

import argparse
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from camo_sbi._io import atomic_write_text
from camo_sbi.experiments.figure_options import add_figure_format_argument, figure_formats
from camo_sbi.experiments.models import (
    add_model_arguments,
    model_from_args,
    subject_limits,
    subject_list,
)
from camo_sbi.experiments.run_options import add_run_options

# only light modules at import time: the CLI builds its parser from add_arguments (numpy, pandas,
# torch and the task are imported by the functions that use them)
if TYPE_CHECKING:
    import pandas as pd

    from camo_sbi.task import NoiseModel

__all__ = ["CONDITIONS", "Condition", "add_arguments", "coverage90", "grid_cells", "main", "run_cell",
           "summary_table"]


@dataclass(frozen=True)
class Condition:
    """How the observations are imperfect: noise, recording-rate multiplier, body scale."""

    name: str
    noise_sd: tuple[float, float] = (0.0, 0.0)
    """(per joint angle [deg], per end-effector coordinate [mm])"""
    rate: float = 1.0
    scale: float = 1.0

    @property
    def noise(self) -> NoiseModel:
        from camo_sbi.task import NoiseModel

        return NoiseModel(joint_deg=self.noise_sd[0], ee_mm=self.noise_sd[1])


CONDITIONS = (
    Condition("clean"),
    Condition("noise 1deg/5mm", noise_sd=(1.0, 5.0)),
    Condition("noise 3deg/15mm", noise_sd=(3.0, 15.0)),
    Condition("rate x3", rate=3.0),
    Condition("taller 5%", scale=1.05),
    Condition("shorter 5%", scale=0.95),
    Condition("taller 10%", scale=1.10),
    Condition("shorter 10%", scale=0.90),
)
DEFAULT_CONDITIONS = ("clean", "noise 1deg/5mm", "noise 3deg/15mm", "rate x3", "taller 5%", "shorter 5%")
_DEFAULT_METHODS = "camo-js,camo-cs,camo-hull,npe,naive,nominal,oracle"


def coverage90(result, truth, prior) -> float:
    """Share of the prior's free true limits inside the posterior's 90% central weighted interval
    (`camo_sbi.evaluation.evaluate.coverage90`, the scorer's ``coverage90``)."""
    from camo_sbi.evaluation.evaluate import coverage90 as score

    return score(result, truth, prior)


def _observations(sim, theta, n, seed, cond: Condition):
    from camo_sbi.experiments.simulate import simulate_recordings
    from camo_sbi.io.resample import estimate_rate, resample_to_controller

    obs = simulate_recordings(sim, theta, n, seed=seed, noise=cond.noise, rate_multiplier=cond.rate)
    if cond.rate != 1.0:  # what the recording loader does with a faster recorder
        rate = estimate_rate(obs, sim)
        obs = tuple(resample_to_controller(o, sim, mode="time", rate=rate) for o in obs)
    return obs


def run_cell(cell, out: str) -> list[dict]:
    """One (seed, condition) `Cell` of `grid_cells`: every method on the same imperfect
    observations; returns the cell's rows."""
    import numpy as np
    import torch

    from camo_sbi._validation import derive_seed, torch_generator
    from camo_sbi.evaluation.evaluate import evaluate_result
    from camo_sbi.evaluation.metrics import binding_bounds
    from camo_sbi.experiments.method_configs import method_config
    from camo_sbi.inference.registry import run_method
    from camo_sbi.priors import BoxPrior
    from camo_sbi.scenarios.reaching import reachable_goals, task_binding_metrics
    from camo_sbi.task import Task, predict

    x = cell.extras
    model, cond = cell.model, next(c for c in CONDITIONS if c.name == x["condition"])
    sim = model.build()
    body = sim if cond.scale == 1.0 else sim.scaled(cond.scale)
    theta = subject_limits(model, sim, cell.subject)
    obs = _observations(body, theta, cell.tasks, derive_seed(x["base_seed"], cell.seed), cond)
    scale = 1.0
    if x.get("body_scale") == "free":
        from camo_sbi.io.geometry import estimate_body_scale

        q = np.concatenate([o.q.numpy() for o in obs])
        ee = np.concatenate([o.ee.numpy() for o in obs])
        ends = np.cumsum([o.length for o in obs])
        scale = estimate_body_scale(sim, q, ee, [np.arange(a, b) for a, b in zip(np.r_[0, ends[:-1]], ends,
                                                                                   strict=True)])[0]
        sim = sim.scaled(scale)  # the model the methods infer on and predict with
    start = sim.start.to(torch.float64)
    goals = reachable_goals(body, theta, x["test_goals"],
                            torch_generator(derive_seed(x["base_seed"], cell.seed, "observation-noise")), start)
    starts = start.expand(goals.shape[0], -1).clone()
    prior = BoxPrior(sim.bounds, obs[0].start)
    task = Task(name=model.name, subject=cell.subject, simulator=sim, prior=prior, observations=obs,
                test_starts=starts, test_goals=goals, true_theta=theta, noise=cond.noise)
    true_test = predict(body, theta, starts, goals)
    binding = binding_bounds(body, theta, starts, goals, prior)
    informative = task_binding_metrics(task, simulator=body)  # the subject's own body
    rows = []
    base = {"task": model.name, "subject": cell.subject, "seed": cell.seed, "condition": x["condition"]}
    for method in x["methods"].split(","):
        cfg = method_config(method, budget=cell.budget, workdir=Path(out) / "work" / cell.key)
        res = run_method(method, task, budget=cell.budget, seed=derive_seed(x["base_seed"], cell.seed, "method"),
                         config=cfg, errors="record")
        # the one scorer: predictions from the model (task.simulator), the truth from the body
        metrics = {**evaluate_result(task, res, true_test, binding, interval_coverage=True), **informative}
        if x.get("body_scale") == "free":
            metrics["body_scale"] = scale
        rows += [{**base, "method": method, "metric": k, "value": v, "status": res.status} for k, v in metrics.items()]
    return rows


def grid_cells(args, methods: list[str], conditions: list[str]) -> list:
    """Every (seed, condition) cell as a `Cell` with its key (``methods``, ``conditions``: checked lists)."""
    from camo_sbi.experiments.grid import Cell

    model = model_from_args(args)
    sim = model.build()
    subject = subject_list(model, args.subjects)[0]
    subject_limits(model, sim, subject)
    from camo_sbi._memory import check_grid_fits

    # counts this machine cannot hold: refused before a cell is built (as compare's)
    check_grid_fits(seeds=args.seeds, cells_per_seed=len(conditions), tasks=args.tasks, test_goals=args.test_goals,
                    workers=args.workers, n_joints=sim.n_joints,
                    max_steps=getattr(getattr(sim, "config", None), "max_steps", 1),
                    names={"seeds": "--seeds", "tasks": "--tasks", "test_goals": "--test-goals", "workers": "--workers"})
    # the model in the key: its name as "task" and its settings as "model" (always)
    model_key = (("task", model.name), ("model", str(model.key())))
    cells = []
    for seed in range(args.seeds):
        for cond in conditions:
            extras = {"condition": cond, "test_goals": args.test_goals, "base_seed": args.seed,
                      "methods": ",".join(methods)}
            if getattr(args, "body_scale", "fixed") == "free":  # the keys of fixed-scale cells stay as they were
                extras["body_scale"] = "free"
            cells.append(Cell(model=model, subject=subject, seed=seed, budget=args.budget, tasks=args.tasks,
                              extras=extras, model_key=model_key))
    return cells


def _shown(df: pd.DataFrame) -> list[str]:
    """The metrics robustness tabulates and draws: the catalog's headline metrics in ``df``."""
    from camo_sbi.evaluation import catalog

    return catalog.headline(df.metric.unique())


def summary_table(df: pd.DataFrame) -> pd.DataFrame:
    """Per method and condition: mean over seeds of each headline metric, the primary metric's
    (`camo_sbi.evaluation.catalog`, claims tag "primary") ratio to clean (the ratio of the means;
    ``within_2x_clean`` for the issue's goal), the wall time and the binding shares."""
    import numpy as np

    from camo_sbi.evaluation import catalog

    primary = catalog.tagged("primary")[0]
    wide = df.pivot_table(index=["method", "condition"], columns="metric", values="value", aggfunc="mean")
    clean = wide.xs("clean", level="condition")[primary]
    wide["error_ratio_to_clean"] = [v / clean[m] if clean[m] > 0 else np.nan
                                    for (m, _), v in wide[primary].items()]
    wide["within_2x_clean"] = wide["error_ratio_to_clean"] <= 2.0
    order = {c.name: i for i, c in enumerate(CONDITIONS)}
    wide = wide.reset_index()
    wide["_o"] = wide["condition"].map(order)
    rest = [m for m in _shown(df) if m != primary]
    task = [m.name for m in catalog.METRICS if m.group == "task" and m.name.endswith("_fraction")]
    cols = ["method", "condition", primary, "error_ratio_to_clean", "within_2x_clean", *rest, "wall_time",
            *task]
    return wide.sort_values(["method", "_o"])[[c for c in cols if c in wide.columns]].reset_index(drop=True)


def make_figure(df: pd.DataFrame, out: Path, formats=("png",)) -> Path:
    """Per metric, one group of bars per condition (a bar per method: the mean over seeds;
    with fewer than 5 seeds each seed a dot), written once per format; returns the first file."""
    from camo_sbi.diagnostics.style import display_metric, paper_style

    with paper_style():
        return _make_figure(display_metric(df), out, formats)


def _make_figure(df: pd.DataFrame, out: Path, formats) -> Path:
    import numpy as np

    from camo_sbi.diagnostics.plot_primitives import figure_legend, jitter
    from camo_sbi.diagnostics.style import (
        band_label,
        few_runs,
        method_order,
        method_style,
        metric_label,
        new_figure,
        run_counts,
        save_figures,
    )
    from camo_sbi.evaluation import catalog

    metrics = [(m, textwrap.fill(metric_label(m), 24)) for m in _shown(df)]
    conds = [c.name for c in CONDITIONS if c.name in set(df.condition)]
    methods = method_order(sorted(set(df.method)))
    fig, axes = new_figure(len(metrics), 1, width="double", aspect=0.3)
    width = 0.8 / max(len(methods), 1)
    counts = run_counts(df[df.metric.isin([m for m, _ in metrics])], "condition")
    few = few_runs(counts)
    for ax, (metric, label) in zip(axes[:, 0], metrics, strict=True):
        sub = df[df.metric == metric]
        for i, m in enumerate(methods):
            g = sub[sub.method == m].groupby("condition")["value"]
            means = [g.mean().get(c, np.nan) for c in conds]
            st = method_style(m)
            xs = np.arange(len(conds)) + (i - (len(methods) - 1) / 2) * width
            ax.bar(xs, means, width, color=st.color, alpha=0.5 if few else 1.0, label=m)
            if few:  # each seed a dot on its bar
                for x, c in zip(xs, conds, strict=True):
                    v = sub[(sub.method == m) & (sub.condition == c)]["value"].to_numpy(dtype=float)
                    ax.scatter(x + jitter(v.size, 0.6 * width), v, s=7, color=st.color, edgecolors="white",
                               lw=0.3, zorder=3)
        ax.set_xticks(np.arange(len(conds)), conds)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, axis="y")
        if catalog.get(metric).reference is not None:  # a nominal level (the 90% interval's 0.9)
            ax.axhline(catalog.get(metric).reference, color="k", lw=0.8, ls=":")
    title = band_label(counts).replace("line:", "bar:") if few else \
        f"bars: mean over {df.seed.nunique()} seeds"
    figure_legend(fig, axes, title=title)
    return save_figures(fig, out / "robustness.png", formats)[0]


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_model_arguments(p)
    p.add_argument("--methods", default=_DEFAULT_METHODS, help="comma-separated registered methods")
    p.add_argument("--subjects", default=None, help="subject profile (default: the model's first)")
    p.add_argument("--seeds", type=int, default=3, help="seeds (each its own goals)")
    p.add_argument("--tasks", type=int, default=5, help="observed reaches per subject")
    p.add_argument("--test-goals", type=int, default=10)
    p.add_argument("--budget", type=int, default=1000, help="simulations per observed reach")
    p.add_argument("--conditions", default=",".join(DEFAULT_CONDITIONS),
                   help="comma-separated subset of the conditions ("  # argparse formats help strings: % as %%
                        + ", ".join(c.name for c in CONDITIONS).replace("%", "%%") + ")")
    p.add_argument("--body-scale", choices=("fixed", "free"), default="fixed",
                   help="free: estimate the observed body's segment-length scale s from its joint and end-effector "
                        "recordings (io.geometry.estimate_body_scale) and infer and predict on model.scaled(s)")
    add_figure_format_argument(p)
    add_run_options(p, out="runs/robustness")


def main(args) -> int:
    from camo_sbi.evaluation.claims import binding_line
    from camo_sbi.experiments.grid import pending, run_grid
    from camo_sbi.experiments.rundir import RunDirectory, run_settings
    from camo_sbi.inference.registry import capabilities, get_method

    t0 = time.perf_counter()
    formats = figure_formats(args)
    methods = [m.strip() for m in str(args.methods).split(",") if m.strip()]
    for m in methods:
        try:
            get_method(m)
        except ValueError as exc:
            raise ValueError(f"--methods: {exc}") from exc
        if capabilities(m).amortized:
            raise ValueError(f"--methods: {m!r} needs a trained estimator file; not supported here yet")
    names = {c.name for c in CONDITIONS}
    conditions = [c.strip() for c in str(args.conditions).split(",") if c.strip()]
    bad = [c for c in conditions if c not in names]
    if bad or "clean" not in conditions:
        raise ValueError(f"--conditions: expected a subset of {sorted(names)} that includes 'clean', got {conditions}")
    for name in ("seeds", "tasks", "test_goals", "budget"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')}: must be >= 1")
    workers = getattr(args, "workers", 1)
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"--workers: must be an integer >= 1, got {workers!r}")
    cells = grid_cells(args, methods, conditions)
    model, subject = cells[0].model, cells[0].subject
    out = Path(args.out)
    settings = run_settings(args, methods=methods, conditions=conditions, subjects=[subject],
                            ignore=("body_scale",) if getattr(args, "body_scale", "fixed") == "fixed" else (),
                            model=model.name if model.is_default else str(model.key()))
    with RunDirectory(out, "robustness", settings, wait=getattr(args, "wait", False)) as rundir:
        store = rundir.store
        todo = pending(cells, store)
        print(f"{len(cells)} cells ({args.seeds} seeds x {len(conditions)} conditions), "
              f"{len(cells) - len(todo)} already finished")
        run_grid(run_cell, todo, store, workers, getattr(args, "scheduler", None), progress="robustness")
        df = store.write_table()
        table = summary_table(df)
        atomic_write_text(out / "robustness.csv", table.to_csv(index=False))
        fig = make_figure(df, out, formats)
    print(table.to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    print(binding_line(df))
    bad = df[df.status != "ok"]
    if len(bad):
        print(f"non-ok statuses: {bad.drop_duplicates(['seed', 'condition', 'method']).groupby(['method', 'status']).size().to_dict()}")
    print(f"table: {out / 'robustness.csv'}  figure: {fig}  wall time: {time.perf_counter() - t0:.1f} s")
    return 0
