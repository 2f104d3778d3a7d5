"""`camo-sbi reproduce panda`: the paper's manipulator experiment (Fig. 2 and Fig. 3), in two settings.

For each run a ground-truth subject reaches ``--tasks`` training goals and ``--test-goals``
held-out goals (configurations drawn inside its true limits, through FK). After every
observed task each method estimates the limits and predicts the held-out reaches; every
metric of `camo_sbi.evaluation.metrics` is recorded, next to the trivial answers (naive,
nominal, oracle). Rows: run, model, subject, method, n_tasks, metric, value, status.

``--setting toolkit`` (default; the toolkit's harder design): the model's default
controller (damped least squares, a null-space pull into the limits, stops within 1 cm,
T = 100), four restricted-limit subjects cycled over runs, each run its own goals (kept
only if reachable), a uniform prior, DTW, the 100 best kept per task.

``--setting paper`` (the authors' published code, ``REFERENCE_SETTING.md``): ONE restricted
joint (start +- 0.5 rad); their PD step ``dq = dt J+ (P e + D de)`` (gain 0.1, derivative
0.5, pseudo-inverse), their limit terms (the null-space push within 0.01 rad of a lower
limit and the hard-limit penalty, ``ControllerConfig.limit_gain`` = dt KN = 0.2), then the
clamp; no mid-range pull; a fixed horizon with no early stop (``--horizon`` points: 21 as
their code, 20 steps; 100 as the paper's text); the 5-level grid prior; the plain Eq. 2
distance with epsilon acceptance (no cap): 0.02 in joint space, and in Cartesian space 0.01
in the authors' units (cm) = 1e-4 m (`AUTHORS_LENGTH_UNIT`); KDE bandwidth 0.5 (variance
0.25); the same training and test goals in every run (runs differ in the methods' random
draws only). The paper's claims are attributed to the variants the authors' code runs:
``camo-seq`` (their "JS": sequential proposals) and ``camo-seq-cs`` (their "CS": Cartesian
scores of candidates from the JS bank); ``camo-js`` / ``camo-cs`` (Algorithm 1 as the paper
writes it: prior draws every task) run beside them, labelled so.

``--setting informative`` (issue 23: a setting in which the limits matter): the toolkit's
controller; training and test goals drawn from the NOMINAL workspace (FK of configurations
inside the model's full range), so some are beyond the subject's reach; at least half of the
test goals bind (`informative_test_goals`); the model's ``informative`` subjects
(`camo_sbi.simulators.registry`; or the ``--limits`` file); a uniform continuous prior; the
reachability metrics (``reachability_f1``, ...) next to every other; claims: every method
against naive and nominal on ``cartesian_error_mm`` and ``limit_error_binding_deg``.
``--design random`` (default) draws the training goals; ``--design active`` keeps the first and
chooses each next one with ``camo_sbi.design`` (`active_observations`): the design method's
posterior on the reaches so far (``--design-method``, default the first method with posterior
draws) ranks ``DESIGN_CANDIDATES`` fresh nominal-workspace goals, and the subject reaches the
best; every method is then run on that sequence. Rows carry ``design_simulations`` (the
criterion's), ``design_method_simulations`` and ``design_fallbacks`` (steps whose design
posterior had no draws to rank with, which fall back to the random design's goal).

``--setting misspecified`` (issue 33: when the model is wrong): the informative design, but the
subject reaches by ``--generator`` (`camo_sbi.scenarios.generators`): ``controller`` (the exact
model, the reference), ``minimum-jerk`` or ``via-point`` (human-like paths tracked by IK inside
the true limits, optional ``--tremor-mm``), while every method still conditions on the
controller. The held-out truth (``cartesian_error_mm``, reachability) and the binding checks
use the subject's generator, so the oracle (true limits, the controller) no longer scores 0:
its error is the model's own share of the error.

Every run records how informative it is: ``binding_test_fraction`` / ``binding_train_fraction``
(and the counts ``binding_*_reaches``), the share of reaches whose true path moves by > 1 mm
when the restriction is relaxed to the nominal limits (`scenarios.reaching.binding_reaches`).

Each run writes ``claims.csv`` (`camo_sbi.evaluation.claims`): every paper claim tested with
paired tests across runs against naive and against nominal, Holm-corrected.

The runs are the cells of the one grid runner (`camo_sbi.experiments.grid.run_grid`, `grid_cells`
and `run_cell`): in-process, in ``--workers N`` processes or on a Dask ``--scheduler``; every
input of a run (its seeds included) is in its cell, so any number of workers gives the same table.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

# only light modules at import time: the CLI builds its parser from add_arguments (the store,
# Dask and the methods are imported by the functions that use them)
from camo_sbi._io import atomic_write_text
from camo_sbi.experiments.figure_options import add_figure_format_argument, figure_formats
from camo_sbi.experiments.models import (
    add_model_arguments,
    model_from_args,
    subject_limits,
    subject_list,
)
from camo_sbi.experiments.run_options import add_run_options
from camo_sbi.simulators.registry import ONE_JOINT, get_model

__all__ = ["AUTHORS_LENGTH_UNIT", "SETTINGS", "Setting", "add_arguments", "grid_cells", "main", "make_figures",
           "method_config", "run_cell", "run_one"]


@dataclass(frozen=True)
class Setting:
    """The experimental design of one ``--setting`` (see the module docstring).

    Attributes:
        controller: ``ControllerConfig`` field overrides (None: the model's default controller).
        subjects: ground-truth profiles cycled over runs (None: every profile of the model;
            "informative": the model's informative subjects).
        fixed_goals: the same training and test goals in every run.
        require_reached: goals kept only if the subject's controller reaches them.
        camo: CAMO config fields for every CAMO variant.
        epsilon: per observation space, CAMO's acceptance threshold (overrides ``camo``).
        methods: default ``--methods``.
        workspace: "true" (goals inside the subject's limits) or "nominal" (the informative design).
        min_binding_test: with workspace "nominal", the least share of test goals that bind.
        generator: the subject moves by ``--generator`` (issue 33), the methods assume the controller.
    """

    controller: dict | None
    subjects: tuple[str, ...] | str | None
    fixed_goals: bool
    require_reached: bool
    camo: dict
    epsilon: dict = field(default_factory=dict)
    methods: tuple[str, ...] = ()
    workspace: str = "true"
    min_binding_test: float | None = None
    generator: bool = False


AUTHORS_LENGTH_UNIT = 0.01
"""Metres per length unit of the authors' arm (their links are 40 / 41 / 10: centimetres). Their
Cartesian epsilon ``THRESH_CARTESIAN = 0.01`` is in that unit: 0.01 cm = 1e-4 m on our models,
whose lengths are metres."""

SETTINGS = {
    "toolkit": Setting(
        controller=None, subjects=None, fixed_goals=False, require_reached=True,
        camo={"keep_best": 100, "bandwidth": 0.2, "bandwidth_mode": "fixed", "sampling": "uniform",
              "distance": "dtw"},
        methods=("camo-js", "camo-cs", "camo-hull", "camo-seq", "naive", "nominal", "oracle")),
    "paper": Setting(
        controller={"early_stop": False, "null_gain": 0.0, "gain": 0.1, "derivative_gain": 0.5,
                    "damping": 1e-6, "max_cartesian_step": 1e3, "max_joint_step": 1e3,
                    "limit_gain": 0.2, "limit_buffer": 0.01, "limit_cap": 0.2},
        subjects=(ONE_JOINT,), fixed_goals=True, require_reached=False,
        camo={"keep_best": None, "bandwidth": 0.25, "bandwidth_mode": "fixed", "sampling": "grid",
              "distance": "euclidean", "fallback_keep": 20},
        epsilon={"joint": 0.02, "cartesian": 0.01 * AUTHORS_LENGTH_UNIT},
        methods=("camo-seq", "camo-seq-cs", "camo-js", "camo-cs", "camo-hull", "naive", "nominal", "oracle")),
    "informative": Setting(
        controller=None, subjects="informative", fixed_goals=False, require_reached=False,
        camo={"keep_best": 100, "bandwidth": 0.2, "bandwidth_mode": "fixed", "sampling": "uniform",
              "distance": "dtw"},
        methods=("camo-js", "camo-cs", "camo-hull", "camo-seq", "camo-touched", "naive", "nominal", "oracle"),
        workspace="nominal", min_binding_test=0.5),
    "misspecified": Setting(
        controller=None, subjects="informative", fixed_goals=False, require_reached=False,
        camo={"keep_best": 100, "bandwidth": 0.2, "bandwidth_mode": "fixed", "sampling": "uniform",
              "distance": "dtw"},
        methods=("camo-js", "camo-cs", "camo-hull", "naive", "nominal", "oracle"),
        workspace="nominal", min_binding_test=0.5, generator=True),
}
"""The designs of ``reproduce panda``. The paper setting's epsilons are the authors' ``THRESH``
(0.02, joint) and ``THRESH_CARTESIAN`` (0.01 in the authors' units (cm) = 1e-4 m): with the grid
prior about a third of the draws reproduce a reach exactly (distance 0) and the next-closest
lie far beyond either, so acceptance is "does not bind on this reach"."""

PAPER_DESIGN = 2
"""Version of the paper setting's design (2: the authors' limit terms, epsilon 1e-4 m, camo-seq-cs);
part of its run settings and cell keys (``paper_design``), so an output folder of another design
is refused."""

# settings that change a run's rows: part of each cell's key, so a re-run with other
# settings into the same directory computes new cells instead of reusing old ones
_CELL_SETTINGS = ("setting", "model", "tasks", "test_goals", "samples", "epsilon", "keep_best", "bandwidth",
                  "bandwidth_mode", "sampling", "horizon", "methods", "seed")


def _setting(args) -> Setting:
    return SETTINGS[getattr(args, "setting", "toolkit")]


def camo_options(args) -> dict:
    """The setting's CAMO options with the command line's values over them; the epsilon stays
    per observation space (`method_configs.method_config` picks each method's) unless given."""
    st = _setting(args)
    cfg = dict(st.camo)
    for key in ("keep_best", "bandwidth", "bandwidth_mode", "sampling", "epsilon"):
        value = getattr(args, key, None)
        if value is not None:
            cfg[key] = value
    if getattr(args, "epsilon", None) is None and st.epsilon:
        cfg["epsilon"] = dict(st.epsilon)
    return cfg


def method_config(name: str, args) -> dict:
    """The config a run gives method ``name`` (`method_configs.method_config` with the setting's
    CAMO options)."""
    from camo_sbi.experiments.method_configs import method_config as config

    return config(name, camo=camo_options(args))


def _simulator(args, model=None):
    sim = (model if model is not None else model_from_args(args)).build()
    st = _setting(args)
    changes = dict(st.controller or {})
    if getattr(args, "horizon", None) is not None:
        changes["max_steps"] = args.horizon
    return sim.with_config(**changes) if changes else sim


def run_one(sim, model, subject: str, run: int, args) -> list[dict]:
    """All methods on one run's subject (``model``: its `ModelSpec`); returns tidy rows."""
    from camo_sbi._validation import derive_seed
    from camo_sbi.evaluation.evaluate import evaluate_result, true_test_trajectories
    from camo_sbi.evaluation.metrics import binding_bounds
    from camo_sbi.inference.registry import run_method_sequence
    from camo_sbi.scenarios.reaching import make_reaching_task, task_binding_metrics

    st = _setting(args)
    true_theta = subject_limits(model, sim, subject)
    goal_seed = derive_seed(args.seed) if st.fixed_goals else derive_seed(args.seed, run)
    task = make_reaching_task(sim, true_theta, n_train=args.tasks, n_test=args.test_goals, seed=goal_seed,
                              name=model.name, subject=subject, require_reached=st.require_reached,
                              workspace=st.workspace, min_binding_test=st.min_binding_test)
    true_test = true_test_trajectories(task)
    binding = binding_bounds(sim, true_theta, task.test_starts, task.test_goals, task.prior)
    design = {}
    if getattr(args, "design", "random") == "active":
        task, design = active_observations(task, true_theta, args, run)
    if st.generator:  # issue 33: the subject moves by --generator, the methods assume the controller
        from camo_sbi.evaluation.metrics import binding_bounds as _bb
        from camo_sbi.scenarios.generators import make_generator, misspecified_observations

        body = make_generator(sim, args.generator, seed=derive_seed(args.seed, run, 5), tremor_mm=args.tremor_mm)
        task, true_test = misspecified_observations(task, body)
        binding = _bb(body, true_theta, task.test_starts, task.test_goals, task.prior)
        informative = task_binding_metrics(task, simulator=body)
        if args.reach_model != "controller":  # the methods condition on a human-like model instead
            from camo_sbi.scenarios.generators import reach_model

            task = task.with_simulator(reach_model(sim, args.reach_model))
    else:
        informative = task_binding_metrics(task)
    rows = []
    for name in args.methods:
        results = run_method_sequence(name, task, budget=args.samples, seed=derive_seed(args.seed, run, 1),
                                      config=method_config(name, args), errors="record")
        for res in results:
            # every metric of the catalog that applies, per-joint limit errors and costs included
            metrics = {**evaluate_result(task, res, true_test, binding, reachability=st.workspace == "nominal"),
                       **informative, **design}
            if st.generator and res is results[-1]:  # the reproduction check of the final posterior (issue 33)
                from camo_sbi.diagnostics.misspecification import check_metrics

                metrics.update(check_metrics(task, res, seed=derive_seed(args.seed, run, 33)))
            for metric, value in metrics.items():
                rows.append({"run": run, "model": model.name, "subject": subject, "method": name,
                             "n_tasks": res.n_tasks, "metric": metric, "value": value, "status": res.status})
    return rows


DESIGN_CANDIDATES = 200
"""Nominal-workspace goals ranked at each active step (fresh ones every step)."""
DESIGN_DRAWS = 100
"""Posterior draws simulated per candidate (the criterion's budget: candidates x draws)."""


def design_method(args) -> str:
    """``--design-method``, or the first of ``args.methods`` that returns posterior draws."""
    from camo_sbi.inference.registry import capabilities

    name = getattr(args, "design_method", None)
    if name is not None:
        return name
    for m in args.methods:
        cap = capabilities(m)
        if cap.posterior and not cap.baseline:
            return m
    raise ValueError("--design-method: none of --methods returns posterior draws; name one (e.g. camo-hull)")


def active_observations(task, true_theta, args, run: int):
    """``task`` with its training reaches chosen one by one (issue 23's active design).

    Reach 1 is the random design's first; before reach t+1 the design method runs on the t
    reaches so far and `camo_sbi.design.next_goal` ranks fresh nominal-workspace goals with its
    draws; the subject (``true_theta``) reaches the best from the same start. A design posterior
    with no draws to rank (failed, or one limit vector) falls back to the random design's goal
    for that step, counted in ``design_fallbacks``. Returns (task, design metrics).
    """
    import numpy as np

    from camo_sbi._validation import derive_seed
    from camo_sbi.design import next_goal
    from camo_sbi.inference.registry import run_method
    from camo_sbi.scenarios.reaching import nominal_workspace_goals, observe

    name = design_method(args)
    obs = [task.observations[0]]
    start = obs[0].start
    sims = method_sims = fallbacks = 0
    wall = 0.0
    for t in range(1, len(task.observations)):
        sofar = task.with_observations(obs)
        res = run_method(name, sofar, budget=args.samples, seed=derive_seed(args.seed, run, 2, t),
                         config=method_config(name, args), errors="record")
        method_sims += res.n_simulations
        goal = task.observations[t].goal
        if not res.status.startswith("failed") and np.unique(res.samples, axis=0).shape[0] > 1:
            cands = nominal_workspace_goals(task.simulator, DESIGN_CANDIDATES, derive_seed(args.seed, run, 3, t))
            goal, info = next_goal(sofar, res, cands, seed=derive_seed(args.seed, run, 4, t),
                                   budget=DESIGN_CANDIDATES * DESIGN_DRAWS, start=start)
            sims += info.n_simulations
            wall += info.wall_time
            fallbacks += info.status != "ok"
        else:
            fallbacks += 1
        obs.append(observe(task.simulator, true_theta, goal.reshape(1, 3), start)[0])
    return task.with_observations(obs), {"design_simulations": sims, "design_method_simulations": method_sims,
                                         "design_fallbacks": fallbacks, "design_wall_time": wall}


def make_figures(df, out: Path, formats=("png",)) -> list[Path]:
    """Fig. 2 (error on unseen goals vs observed tasks), Fig. 3 (errors after all tasks) and the
    limit error (binding and free bounds) vs observed tasks, each once per format of
    ``formats``; angles in degrees (`display_metric`)."""
    from camo_sbi.diagnostics.style import display_metric, paper_style

    with paper_style():
        return _make_figures(display_metric(df), out, formats)


def _make_figures(df, out: Path, formats) -> list[Path]:
    from camo_sbi.diagnostics.plot_primitives import figure_legend, plot_bars, plot_lines
    from camo_sbi.diagnostics.style import band_label, metric_label, new_figure, save_figures
    from camo_sbi.evaluation import catalog

    band = band_label(df.run.nunique())
    k = int(df.n_tasks.max())
    last = df[df.n_tasks == k]
    present = df.metric.unique()
    paths = []

    def panels(n):
        fig, axes = new_figure(1, n)
        return fig, axes[0]

    fig2 = catalog.tagged("fig2", present)  # the paper's Fig. 2: error on unseen goals vs observed tasks
    if fig2:
        fig, axes = panels(len(fig2))
        for ax, metric in zip(axes, fig2, strict=True):
            title = ("The authors' Fig. 2 metric (sum over the test goals)" if catalog.get(metric).aggregate == "sum"
                     else "Error on unseen goals vs observed tasks")
            plot_lines(df[df.metric == metric], ax=ax, ylabel=metric_label(metric), title=title, legend=False)
        figure_legend(fig, axes, title=band)
        paths.extend(save_figures(fig, out / "fig2_cartesian_error_vs_tasks.png", formats))
    fig3 = catalog.tagged("fig3", present)  # the paper's Fig. 3: the joint-space errors after all tasks
    if fig3:
        fig, axes = panels(len(fig3))
        for ax, metric in zip(axes, fig3, strict=True):
            title = (f"The authors' Fig. 3 metric after {k} tasks" if catalog.get(metric).aggregate == "sum"
                     else f"Joint space after {k} tasks")
            plot_bars(last[last.metric == metric], ax=ax, ylabel=metric_label(metric), title=title)
        paths.extend(save_figures(fig, out / "fig3_final_error.png", formats))
    groups = catalog.tagged("limits", present)  # the limits the test reaches identify, and the others
    if groups:
        fig, axes = panels(len(groups))
        for ax, metric in zip(axes, groups, strict=True):
            which = "binding bounds (the test reaches identify them)" if "binding" in metric else \
                "free bounds (the test reaches cannot identify them)"
            plot_lines(df[df.metric == metric], ax=ax, ylabel=metric_label(metric), title=which, legend=False)
        figure_legend(fig, axes, title=band)
        paths.extend(save_figures(fig, out / "limit_error_vs_tasks.png", formats))
    return paths


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--setting", choices=tuple(SETTINGS), default="toolkit",
                   help="toolkit: the toolkit's harder design (default); paper: the authors' published design; "
                        "informative: goals from the nominal workspace, restrictions that bind (issue 23); "
                        "misspecified: the informative design, the subject moving by --generator (issue 33)")
    p.add_argument("--design", choices=("random", "active"), default="random",
                   help="training goals: random draws (default) or chosen one by one (active; --setting informative)")
    p.add_argument("--design-method", default=None,
                   help="--design active: the method whose posterior chooses the next reach (default: the first "
                        "of --methods with posterior draws)")
    p.add_argument("--generator", choices=("controller", "minimum-jerk", "via-point"), default="controller",
                   help="--setting misspecified: how the subject moves (controller: the exact model; minimum-jerk, "
                        "via-point: human-like paths the methods do not assume; camo_sbi.scenarios.generators)")
    p.add_argument("--tremor-mm", type=float, default=0.0,
                   help="--setting misspecified: physiological tremor sd per coordinate [mm] on the human-like paths")
    p.add_argument("--reach-model", choices=("controller", "minimum-jerk"), default="controller",
                   help="--setting misspecified: the simulator every method conditions on and predicts with "
                        "(minimum-jerk: camo_sbi.scenarios.generators.reach_model, its duration normalised to the "
                        "generator's mean slowness)")
    add_model_arguments(p)
    p.add_argument("--runs", type=int, default=30, help="independent runs (paper: 30)")
    p.add_argument("--tasks", type=int, default=10, help="observed training goals per run")
    p.add_argument("--test-goals", type=int, default=20, help="held-out goals per run")
    p.add_argument("--samples", type=int, default=2000, help="CAMO prior draws per task (b)")
    p.add_argument("--horizon", type=int, default=None,
                   help="trajectory points (paper setting default 21 = the authors' 20 steps; the paper's text: 100)")
    p.add_argument("--epsilon", type=float, default=None, help="CAMO acceptance threshold (default: the setting's)")
    p.add_argument("--keep-best", type=int, default=None, help="CAMO keeps at most the k best per task")
    p.add_argument("--bandwidth", type=float, default=None, help="CAMO kernel variance h [rad^2]")
    p.add_argument("--bandwidth-mode", choices=("fixed", "scott"), default=None)
    p.add_argument("--sampling", choices=("uniform", "lhs", "grid"), default=None)
    p.add_argument("--methods", default=None, help="comma-separated registered methods (default: the setting's)")
    p.add_argument("--subjects", default=None, help="comma-separated ground-truth profiles (default: the setting's; "
                                                     "with --urdf the --limits file is the subject)")
    add_figure_format_argument(p)
    add_run_options(p, out="runs/reproduce_panda", seed_help="base seed (each run's goals and methods derive from it)")


def _check(args) -> None:
    from camo_sbi.distributed import parse_scheduler
    from camo_sbi.inference.registry import get_method, names

    st = _setting(args)
    methods = args.methods if args.methods is not None else ",".join(st.methods)
    if isinstance(methods, str):
        methods = [m.strip() for m in methods.split(",") if m.strip()]
    for m in methods:
        try:
            get_method(m)
        except ValueError as exc:
            raise ValueError(f"--methods: {exc}") from exc
    # the trivial answers are in every table
    args.methods = list(methods) + [b for b in names(baseline=True) if b not in methods]
    for name in ("runs", "tasks", "test_goals", "samples", "workers"):
        if getattr(args, name, 1) < 1:
            raise ValueError(f"--{name.replace('_', '-')}: must be >= 1")
    design = getattr(args, "design", "random")
    if design == "active" and args.setting != "informative":
        raise ValueError("--design: active design needs --setting informative")
    if design == "active":
        args.design_method = design_method(args)
        from camo_sbi.inference.registry import capabilities, get_method

        try:
            get_method(args.design_method)
        except ValueError as exc:
            raise ValueError(f"--design-method: {exc}") from exc
        cap = capabilities(args.design_method)
        if not cap.posterior or cap.baseline:
            raise ValueError(f"--design-method: {args.design_method} returns no posterior draws to design with")
    if not _setting(args).generator and (getattr(args, "generator", "controller") != "controller"
                                         or getattr(args, "tremor_mm", 0.0)):
        raise ValueError("--generator: human-like reaches need --setting misspecified")
    if not _setting(args).generator and getattr(args, "reach_model", "controller") != "controller":
        raise ValueError("--reach-model: a human-like reach model needs --setting misspecified")
    if not (getattr(args, "tremor_mm", 0.0) >= 0):
        raise ValueError(f"--tremor-mm: must be >= 0, got {args.tremor_mm}")
    if getattr(args, "tremor_mm", 0.0) and args.generator == "controller":
        raise ValueError("--tremor-mm: tremor needs --generator minimum-jerk or via-point")
    if args.setting == "paper" and args.horizon is None:
        args.horizon = 21
    if args.horizon is not None and args.horizon < 2:
        raise ValueError(f"--horizon: must be >= 2 points, got {args.horizon}")
    try:
        parse_scheduler(getattr(args, "scheduler", None))
    except ValueError as exc:
        raise ValueError(f"--{exc}") from exc


def model_and_subjects(args) -> tuple:
    """The `ModelSpec` and the subjects cycled over the runs (``args`` checked by `_check`); the
    subjects' names are checked against the model before any work."""
    st = _setting(args)
    model = model_from_args(args)
    sim = _simulator(args, model)
    named = list(get_model(model.kind).informative) if st.subjects == "informative" and model.kind != "urdf" \
        else st.subjects
    if st.subjects == "informative" and model.limits is None and not args.subjects and not named:
        raise ValueError(f"--model: {model.name!r} has no informative subjects; give --subjects or --limits")
    given = args.subjects or (",".join(named) if named and model.limits is None else None)
    subjects = subject_list(model, given, default_all=True)
    for s in subjects:
        subject_limits(model, sim, s)  # validates names before any work
    from camo_sbi._memory import check_grid_fits

    # counts this machine cannot hold: refused before any work (as compare's); --samples is the budget
    check_grid_fits(seeds=args.runs, cells_per_seed=len(subjects), tasks=args.tasks, test_goals=args.test_goals,
                    n_joints=sim.n_joints, max_steps=getattr(getattr(sim, "config", None), "max_steps", 1),
                    names={"seeds": "--runs", "tasks": "--tasks", "test_goals": "--test-goals"})
    return model, subjects


def grid_cells(args, model, subjects: list[str]) -> list:
    """One `Cell` per run (``args`` checked by `_check`): run r observes ``subjects[r % len]``.

    The cell key is the one each run always had (``run``, ``subject``, the settings that change a
    run's rows, the design's and the paper design's version), so a run folder made before the
    grid runner resumes.
    """
    from camo_sbi.experiments.grid import Cell

    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if k != "func"}
    # a built-in model with its defaults keeps the cell keys it always had
    model_key = (("model", model.name if model.is_default else json.dumps(model.key(), sort_keys=True)),)
    keyed = [k for k in _CELL_SETTINGS if k not in ("model", "tasks", "samples", "seed")]
    cells = []
    for run in range(args.runs):
        extras = {"run": run, **{k: settings[k] for k in keyed}}
        if args.design != "random":  # random keeps the cell keys it always had
            extras["design"] = args.design
            extras["design_method"] = args.design_method
        if args.setting == "paper":
            extras["paper_design"] = PAPER_DESIGN
        if _setting(args).generator:  # the controller's settings keep the cell keys they always had
            extras["generator"], extras["tremor_mm"] = args.generator, args.tremor_mm
            if args.reach_model != "controller":
                extras["reach_model"] = args.reach_model
        cells.append(Cell(model=model, subject=subjects[run % len(subjects)], seed=args.seed, budget=args.samples,
                          tasks=args.tasks, extras=extras, model_key=model_key, budget_key="samples"))
    return cells


def run_cell(cell, out: str) -> list[dict]:
    """One run (a `Cell` of `grid_cells`) in any process: the simulator rebuilt from the cell's
    model and setting, every method on its subject; returns the run's tidy rows."""
    x = dict(cell.extras)
    args = argparse.Namespace(**{**x, "tasks": cell.tasks, "samples": cell.budget, "seed": cell.seed,
                                    "design": x.get("design", "random"), "design_method": x.get("design_method"),
                                    "generator": x.get("generator", "controller"), "tremor_mm": x.get("tremor_mm", 0.0),
                                    "reach_model": x.get("reach_model", "controller"), "scheduler": None})
    return run_one(_simulator(args, cell.model), cell.model, cell.subject, x["run"], args)


def main(args) -> int:
    from camo_sbi.diagnostics.numbers import summary_table
    from camo_sbi.evaluation import catalog
    from camo_sbi.evaluation.claims import binding_line, informative_claims, manipulator_claims
    from camo_sbi.experiments.grid import run_grid
    from camo_sbi.experiments.rundir import RunDirectory, run_settings

    if not hasattr(args, "setting"):
        args.setting = "toolkit"
    if not hasattr(args, "design"):
        args.design = "random"
    for name, default in (("generator", "controller"), ("tremor_mm", 0.0), ("reach_model", "controller")):
        if not hasattr(args, name):
            setattr(args, name, default)
    _check(args)
    formats = figure_formats(args)
    t0 = time.perf_counter()
    model, subjects = model_and_subjects(args)
    out = Path(args.out)
    cells = grid_cells(args, model, subjects)
    settings_model = cells[0].model_key[0][1]
    paper = {"paper_design": PAPER_DESIGN} if args.setting == "paper" else {}
    with RunDirectory(out, "reproduce panda", run_settings(args, subjects=subjects, model=settings_model, **paper),
                      wait=getattr(args, "wait", False)) as rundir:
        store = rundir.store
        run_grid(run_cell, cells, store, workers=getattr(args, "workers", 1), scheduler=getattr(args, "scheduler", None),
                 progress=f"reproduce {model.name} ({args.setting})")
        keys = [c.key for c in cells]
        df = store.write_table(keys=keys)
        figs = make_figures(df, out, formats)
        claims = (informative_claims(df, setting=args.setting) if args.setting in ("informative", "misspecified")
                  else manipulator_claims(df, setting=args.setting))
        atomic_write_text(out / "claims.csv", claims.to_csv(index=False))
    wall = time.perf_counter() - t0
    headline = catalog.headline(df.metric.unique())
    last = df[(df.n_tasks == df.n_tasks.max()) & df.metric.isin(headline)]
    print(summary_table(last, headline, unit="runs"))
    print(binding_line(df))
    print(claims[["claim", "method", "baseline", "value", "p_value", "holds", "few_reaches"]].to_string(index=False))
    bad = df[df.status != "ok"]
    if len(bad):
        print(f"non-ok statuses: {bad.groupby(['method', 'status']).size().to_dict()}")
    print(f"table: {out / 'results.csv'}  claims: {out / 'claims.csv'}  figures: "
          f"{', '.join(str(f) for f in figs)}")
    print(f"wall time: {wall:.1f} s")
    return 0
