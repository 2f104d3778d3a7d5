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

Each run writes ``claims.csv`` (`camo_sbi.evaluation.claims`): every paper claim tested with
paired tests across runs against naive and against nominal, Holm-corrected.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

# only light modules at import time: the CLI builds its parser from add_arguments (the store,
# Dask and the methods are imported by the functions that use them)
from camo_sbi._io import atomic_write_text
from camo_sbi.experiments.figure_options import add_figure_format_argument, figure_formats
from camo_sbi.experiments.models import (
    add_model_arguments,
    model_from_args,
    subject_list,
    true_limits,
)
from camo_sbi.experiments.subjects import ONE_JOINT

__all__ = ["AUTHORS_LENGTH_UNIT", "SETTINGS", "Setting", "add_arguments", "binding_reaches", "main", "make_figures",
           "method_config", "run_one"]


@dataclass(frozen=True)
class Setting:
    """The experimental design of one ``--setting`` (see the module docstring).

    Attributes:
        controller: ``ControllerConfig`` field overrides (None: the model's default controller).
        subjects: ground-truth profiles cycled over runs (None: every profile of the model).
        fixed_goals: the same training and test goals in every run.
        require_reached: goals kept only if the subject's controller reaches them.
        camo: CAMO config fields for every CAMO variant.
        epsilon: per observation space, CAMO's acceptance threshold (overrides ``camo``).
        methods: default ``--methods``.
    """

    controller: dict | None
    subjects: tuple[str, ...] | None
    fixed_goals: bool
    require_reached: bool
    camo: dict
    epsilon: dict = field(default_factory=dict)
    methods: tuple[str, ...] = ()


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
}
"""The designs of ``reproduce panda``. The paper setting's epsilons are the authors' ``THRESH``
(0.02, joint) and ``THRESH_CARTESIAN`` (0.01 in the authors' units (cm) = 1e-4 m): with the grid
prior about a third of the draws reproduce a reach exactly (distance 0) and the next-closest
lie far beyond either, so acceptance is "does not bind on this reach"."""

PAPER_DESIGN = 2
"""Version of the paper setting's design (2: the authors' limit terms, epsilon 1e-4 m, camo-seq-cs);
part of its run settings and cell keys, so an output folder of another design is refused."""

# settings that change a run's rows: part of each cell's key, so a re-run with other
# settings into the same directory computes new cells instead of reusing old ones
_CELL_SETTINGS = ("setting", "model", "tasks", "test_goals", "samples", "epsilon", "keep_best", "bandwidth",
                  "bandwidth_mode", "sampling", "horizon", "methods", "seed")


def _setting(args) -> Setting:
    return SETTINGS[getattr(args, "setting", "toolkit")]


def method_config(name: str, args) -> dict | None:
    """The config a run gives method ``name``: the setting's CAMO options (command-line values
    override them) for the CAMO family, else the method's defaults."""
    from camo_sbi.inference.registry import get_method

    spec = get_method(name)
    if "camo" not in (name, spec.base):
        return None
    st = _setting(args)
    cfg = dict(st.camo)
    for key in ("keep_best", "bandwidth", "bandwidth_mode", "sampling", "epsilon"):
        value = getattr(args, key, None)
        if value is not None:
            cfg[key] = value
    if getattr(args, "epsilon", None) is None and st.epsilon:
        cfg["epsilon"] = st.epsilon[spec.defaults.get("space", cfg.get("space", "joint"))]
        if spec.defaults.get("proposal") == "sequential-js":  # the JS chain of camo-seq-cs
            cfg["js_epsilon"] = st.epsilon["joint"]
    cfg["scheduler"] = getattr(args, "scheduler", None)
    return cfg


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
    from camo_sbi.scenarios.reaching import make_reaching_task

    st = _setting(args)
    true_theta = true_limits(model, sim, subject)
    goal_seed = derive_seed(args.seed) if st.fixed_goals else derive_seed(args.seed, run)
    task = make_reaching_task(sim, true_theta, n_train=args.tasks, n_test=args.test_goals, seed=goal_seed,
                              name=model.name, subject=subject, require_reached=st.require_reached)
    true_test = true_test_trajectories(task)
    binding = binding_bounds(sim, true_theta, task.test_starts, task.test_goals, task.prior)
    rows = []
    if getattr(args, "setting", "toolkit") == "paper":
        rows += [{"run": run, "model": model.name, "subject": subject, "method": "truth", "n_tasks": args.tasks,
                  "metric": metric, "value": value, "status": "ok"}
                 for metric, value in binding_reaches(sim, true_theta, task).items()]
    for name in args.methods:
        results = run_method_sequence(name, task, budget=args.samples, seed=derive_seed(args.seed, run, 1),
                                      config=method_config(name, args))
        for res in results:
            metrics = evaluate_result(task, res, true_test, binding)
            metrics["n_simulations"] = res.n_simulations
            metrics["wall_time"] = res.wall_time  # without numba compilation, which is compile_time
            metrics["compile_time"] = res.compile_time
            for metric, value in metrics.items():
                rows.append({"run": run, "model": model.name, "subject": subject, "method": name,
                             "n_tasks": res.n_tasks, "metric": metric, "value": value, "status": res.status})
    return rows


def binding_reaches(sim, true_theta, task) -> dict[str, int]:
    """How many reaches a limit actually touches: the training (``binding_reaches_train``) and
    held-out (``binding_reaches_test``) reaches whose true trajectory differs from the one under
    the full range of motion (the prior's outer bounds) by more than `BINDING_TOL_RAD` in some
    joint at some step. Recorded per run (method ``truth``) in the paper setting."""
    import torch

    from camo_sbi.evaluation.metrics import BINDING_TOL_RAD
    from camo_sbi.task import contain

    truth = torch.as_tensor(true_theta, dtype=torch.float64).reshape(-1)
    outer = task.prior.outer_theta()
    out = {}
    for split, starts, goals in (
            ("train", torch.stack([o.start for o in task.observations]), torch.stack([o.goal for o in task.observations])),
            ("test", task.test_starts, task.test_goals)):
        starts, goals = torch.as_tensor(starts, dtype=torch.float64), torch.as_tensor(goals, dtype=torch.float64)
        m = goals.shape[0]
        a = sim.simulate(contain(truth.expand(m, -1), starts), goals, starts)
        b = sim.simulate(contain(outer.expand(m, -1), starts), goals, starts)
        out[f"binding_reaches_{split}"] = int(((a.q - b.q).abs().flatten(1).amax(1) > BINDING_TOL_RAD).sum())
    return out


def make_figures(df, out: Path, formats=("png",)) -> list[Path]:
    """Fig. 2 (error on unseen goals vs observed tasks), Fig. 3 (errors after all tasks) and the
    limit error (binding and free bounds) vs observed tasks, each once per format of
    ``formats``; angles in degrees (`display_metric`)."""
    from camo_sbi.diagnostics.style import display_metric, paper_style

    with paper_style():
        return _make_figures(display_metric(df), out, formats)


def _make_figures(df, out: Path, formats) -> list[Path]:
    from camo_sbi.diagnostics.style import (
        band_label,
        figure_legend,
        metric_label,
        new_figure,
        plot_bars,
        plot_lines,
        save_figures,
    )

    band = band_label(df.run.nunique())
    k = int(df.n_tasks.max())
    last = df[df.n_tasks == k]
    paths = []
    fig, axes = new_figure(1, 2)
    for ax, metric, title in zip(axes[0], ("cartesian_error_mm", "reference_cartesian"),
                                 ("Error on unseen goals vs observed tasks",
                                  "The authors' Fig. 2 metric (sum over the test goals)"), strict=True):
        plot_lines(df[df.metric == metric], ax=ax, ylabel=metric_label(metric), title=title, legend=False)
    figure_legend(fig, axes, title=band)
    paths.extend(save_figures(fig, out / "fig2_cartesian_error_vs_tasks.png", formats))
    fig, axes = new_figure(1, 2)
    for ax, metric, title in zip(axes[0], ("joint_error_deg", "reference_joint"),
                                 (f"Joint space after {k} tasks", f"The authors' Fig. 3 metric after {k} tasks"),
                                 strict=True):
        plot_bars(last[last.metric == metric], ax=ax, ylabel=metric_label(metric), title=title)
    paths.extend(save_figures(fig, out / "fig3_final_error.png", formats))
    groups = [m for m in ("limit_error_binding_deg", "limit_error_free_deg") if (df.metric == m).any()]
    if groups:
        fig, axes = new_figure(1, len(groups))
        for ax, metric in zip(axes[0], groups, strict=True):
            which = "binding bounds (the test reaches identify them)" if "binding" in metric else \
                "free bounds (the test reaches cannot identify them)"
            plot_lines(df[df.metric == metric], ax=ax, ylabel=metric_label(metric), title=which, legend=False)
        figure_legend(fig, axes, title=band)
        paths.extend(save_figures(fig, out / "limit_error_vs_tasks.png", formats))
    return paths


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--setting", choices=tuple(SETTINGS), default="toolkit",
                   help="toolkit: the toolkit's harder design (default); paper: the authors' published design")
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
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--scheduler", default=None,
                   help="run CAMO's candidate chunks on Dask: 'local:N' or 'tcp://host:8786' "
                        "(same numbers as in-process)")
    p.add_argument("--wait", action="store_true", help="if another run holds --out, wait for it instead of stopping")
    add_figure_format_argument(p)
    p.add_argument("--out", type=Path, default=Path("runs/reproduce_panda"))


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
    for name in ("runs", "tasks", "test_goals", "samples"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')}: must be >= 1")
    if args.setting == "paper" and args.horizon is None:
        args.horizon = 21
    if args.horizon is not None and args.horizon < 2:
        raise ValueError(f"--horizon: must be >= 2 points, got {args.horizon}")
    try:
        parse_scheduler(getattr(args, "scheduler", None))
    except ValueError as exc:
        raise ValueError(f"--{exc}") from exc


def main(args) -> int:
    from camo_sbi.distributed import dask_client
    from camo_sbi.evaluation.claims import manipulator_claims
    from camo_sbi.experiments.rundir import RunDirectory, run_settings
    from camo_sbi.experiments.store import cell_key

    if not hasattr(args, "setting"):
        args.setting = "toolkit"
    _check(args)
    formats = figure_formats(args)
    t0 = time.perf_counter()
    st = _setting(args)
    model = model_from_args(args)
    sim = _simulator(args, model)
    given = args.subjects or (",".join(st.subjects) if st.subjects and model.limits is None else None)
    subjects = subject_list(model, given, default_all=True)
    for s in subjects:
        true_limits(model, sim, s)  # validates names before any work
    out = Path(args.out)
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if k != "func"}
    # a built-in model with its defaults keeps the cell keys it always had
    settings["model"] = model.name if model.is_default else json.dumps(model.key(), sort_keys=True)
    design = {"design": PAPER_DESIGN} if args.setting == "paper" else {}
    with RunDirectory(out, "reproduce panda", run_settings(args, subjects=subjects, model=settings["model"], **design),
                      wait=getattr(args, "wait", False)) as rundir:
        store = rundir.store
        with dask_client(getattr(args, "scheduler", None)):  # CAMO's configs reuse this client
            for run in tqdm(range(args.runs), desc=f"reproduce {model.name} ({args.setting})", unit="run"):
                subject = subjects[run % len(subjects)]
                key = cell_key({"run": run, "subject": subject, **{k: settings[k] for k in _CELL_SETTINGS},
                                **design})
                if store.done(key):
                    continue
                store.put(key, run_one(sim, model, subject, run, args))
        df = store.write_table()
        figs = make_figures(df, out, formats)
        claims = manipulator_claims(df, setting=args.setting)
        atomic_write_text(out / "claims.csv", claims.to_csv(index=False))
    wall = time.perf_counter() - t0
    metrics = ["cartesian_error_mm", "joint_error_deg", "reference_cartesian", "limit_error_binding_deg",
               "limit_error_free_deg"]
    last = df[(df.n_tasks == df.n_tasks.max()) & df.metric.isin(metrics)]
    summary = last.groupby(["method", "metric"])["value"].agg(["mean", "std"]).unstack("metric")
    print(summary.to_string(float_format=lambda v: f"{v:.4g}"))
    print(claims[["claim", "method", "baseline", "value", "p_value", "holds"]].to_string(index=False))
    if (df.metric == "binding_reaches_test").any():
        br = df[df.metric.str.startswith("binding_reaches_")].groupby("metric")["value"].agg(["mean", "min", "max"])
        print("reaches on which a true limit binds, per run (of "
              f"{args.tasks} training / {args.test_goals} test): " + "; ".join(
                  f"{m.rsplit('_', 1)[1]} {r['mean']:.3g} (range {r['min']:.0f}-{r['max']:.0f})" for m, r in br.iterrows()))
    bad = df[df.status != "ok"]
    if len(bad):
        print(f"non-ok statuses: {bad.groupby(['method', 'status']).size().to_dict()}")
    print(f"table: {out / 'results.csv'}  claims: {out / 'claims.csv'}  figures: "
          f"{', '.join(str(f) for f in figs)}")
    print(f"wall time: {wall:.1f} s")
    return 0
