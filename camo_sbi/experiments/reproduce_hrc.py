"""`camo-sbi reproduce hrc`: the human-robot block-stacking experiment (paper section V-B, Fig. 5).

Per run, a person with an impaired range of motion (``--subject``) works on random
block-stacking trials (`camo_sbi.scenarios.block_stacking`). In training trials, seen one
after another, the person picks the blocks they can reach and carry; each pick is one
observed task. What the observer sees of a pick is ``--observe``: ``reach`` (the default:
the joint trajectory from the start posture to the block) or ``carry`` (from the grasp
posture to the tower slot, which is what the authors' code observes; see
``REFERENCE_SETTING.md``). ``--tasks`` picks are observed (``--task-unit trial``: the first
``--tasks`` trials instead, however many picks they hold). After each observed task the
methods estimate the limits; each estimate predicts, for every block of ``--test-trials``
unseen trials, whether the person can take it (the same reachability test as the truth, on
the same layouts), and precision / recall / F1 ("person" = positive) are recorded. The
majority-class baseline (always the more frequent true label) is recorded alongside.

Methods (registry names):

* ``camo-js`` (``camo-cs`` with ``--space cartesian``): the paper's algorithm (argmax of the
  product of per-task KDEs).
* ``camo-hull`` (joint space only; ``--no-hull`` skips it): the same, with the prior
  conditioned on the observed postures (``CamoConfig(contain_observed=True)``): the controller
  clamps to the limits, so every observed joint posture lies inside them. Without it the
  argmax sits inside the flat part of the posterior of limits that no reach has pushed
  against, often narrower than postures already seen, and blocks the person can take
  are given to the robot.
* the baselines: ``naive`` (observed min/max per joint, the paper's baseline), ``nominal``
  (the full range of motion) and ``oracle`` (the true limits: precision = recall = 1).

Priors (both Latin hypercube, ``--samples`` draws per task, at most ``--keep-best`` kept):

* strong: shoulder (flexion, abduction, rotation) and elbow flexion limits free, the
  wrist (forearm pronation, wrist flexion, wrist deviation) AND the torso limits fixed
  to the subject's true values. The paper: "only the shoulder joint limits and elbow
  joint limits are allowed to vary and the wrist limits are fixed and known"; its code
  also fixes the torso to the truth in every method.
* weak: uniform over the full range of motion of all 9 joints (with ``--fix-torso``: the
  torso fixed at its true value, as the authors' code does under both priors).

Every method uses the same knowledge: fixed (known) joints take their known limits. When
nothing has been observed yet (``--task-unit trial`` only) an estimator allocates every
block to the robot.

Rows: run, subject, prior, method, n_tasks, metric, value, status in ``<out>/results.csv``:
precision, recall, f1, accuracy (every method and majority), limit errors in degrees
(``limit_error_deg`` over the prior's free limits; ``limit_error_binding_deg`` /
``limit_error_free_deg`` split by whether the bound binds on the test reaches to the
blocks) and person_fraction (method truth: the person's share of the test blocks);
``claims.csv`` (`camo_sbi.evaluation.claims.hrc_claims`); the figure ``fig5_allocation.png``;
``scene_run00.png`` (with ``--scene-png``, one per run): the first test trial under the
final strong-prior allocation of camo-hull (camo-js with ``--no-hull``).

The runs are the cells of the one grid runner (`camo_sbi.experiments.grid.run_grid`, `grid_cells`
and `run_cell`): in-process, in ``--workers N`` processes or on a Dask ``--scheduler``, each opening
its own scene (a run depends on its seeds only, never on the runs before it).
"""

from __future__ import annotations

import argparse
import functools
import time
from pathlib import Path
from typing import TYPE_CHECKING

from camo_sbi._io import atomic_write_text
from camo_sbi.experiments.figure_options import add_figure_format_argument, figure_formats
from camo_sbi.experiments.run_options import add_run_options

# only light modules at import time: the CLI builds its parser from add_arguments (numpy, torch,
# pybullet's scene and the methods are imported by the functions that use them)
if TYPE_CHECKING:
    import numpy as np

__all__ = [
    "allocation_metrics_recorded",
    "PRIORS",
    "STRONG_PRIOR_FIXED",
    "add_arguments",
    "check_subject",
    "collect_run",
    "grid_cells",
    "main",
    "make_figure",
    "make_prior",
    "positive_int",
    "run_methods",
    "run_cell",
    "run_one",
]

PRIORS = ("strong", "weak")


def allocation_metrics_recorded() -> list[str]:
    """The allocation scores each method's row records: the catalog's ``group="allocation"``
    metrics (`camo_sbi.evaluation.catalog`), each a field of `allocation_metrics`' result."""
    from camo_sbi.evaluation import catalog

    return [m.name for m in catalog.METRICS if m.group == "allocation"]


STRONG_PRIOR_FIXED = ("torso_flexion", "torso_rotation", "forearm_pronation", "wrist_flexion",
                      "wrist_deviation")
"""Joints whose limits the strong prior knows (fixed to the subject's true limits)."""
TORSO = ("torso_flexion", "torso_rotation")
TASK_UNITS = ("pick", "trial")
OBSERVED_MOTIONS = ("reach", "carry")
"""What the observer sees of a pick (`camo_sbi.scenarios.block_stacking.OBSERVED_MOTIONS`, repeated
here so that the parser imports no pybullet; tests/test_cli.py checks that the two agree)."""
CAMO_BANDWIDTH = 0.2
"""``--bandwidth``'s default: `CamoConfig`'s (checked to agree by tests/test_cli.py)."""
_CELL_SETTINGS = ("subject", "seed", "tasks", "task_unit", "test_trials", "samples", "keep_best", "epsilon",
                  "bandwidth", "space", "priors", "no_hull", "observe", "fix_torso")


def subject_names() -> list[str]:
    from camo_sbi.simulators.registry import subject_names as names

    return names("human")


def make_prior(sim, true_theta, kind: str, *, fix_torso: bool = False):
    """The strong or weak `BoxPrior` (Latin hypercube) for a subject with ``true_theta``.

    ``fix_torso``: the weak prior also fixes the torso at its true limits (the strong prior
    always does), as the authors' code does for every method.
    """
    import torch

    from camo_sbi.priors import BoxPrior

    if kind not in PRIORS:
        raise ValueError(f"prior: expected one of {PRIORS}, got {kind!r}")
    known = STRONG_PRIOR_FIXED if kind == "strong" else (TORSO if fix_torso else ())
    names = list(sim.joint_names)
    lim = torch.as_tensor(true_theta, dtype=torch.float64).reshape(-1, 2)
    fixed = {names.index(j): (float(lim[names.index(j), 0]), float(lim[names.index(j), 1]))
             for j in known if j in names}
    return BoxPrior(sim.bounds, sim.start, fixed=fixed or None, sampling="lhs")


# --------------------------------------------------------------------------------------
# One run
# --------------------------------------------------------------------------------------


def run_methods(args) -> list[str]:
    """The methods this run computes: the paper's CAMO in ``--space``, camo-hull (joint space,
    unless ``--no-hull``) and every registered baseline that can run on these observations."""
    from camo_sbi.inference.registry import names

    camo = "camo-js" if args.space == "joint" else "camo-cs"
    hull = ["camo-hull"] if args.space == "joint" and not args.no_hull else []
    return [camo, *hull, *names(baseline=True, space="joint")]


def collect_run(scene, true_theta, *, n_tasks: int, n_test: int, seed: int, task_unit: str = "pick",
                max_trials: int | None = None, observe: str = "reach"):
    """Training observations and test trials of one run.

    Returns (observations, n_tasks_after, test_trials, y_true): the observed picks in
    order; for each pick the number of tasks observed once it is seen (pick unit: 1, 2,
    ...; trial unit: its trial's index + 1); the test trials; their (n_test, 4) labels.
    """
    import numpy as np

    rng = np.random.default_rng(seed)
    max_trials = 50 * n_tasks if max_trials is None else max_trials
    observations, task_of = [], []
    trials = 0
    while (len(observations) < n_tasks) if task_unit == "pick" else (trials < n_tasks):
        if trials >= max_trials:
            raise ValueError(
                f"subject: only {len(observations)} blocks were reachable in {trials} trials; "
                f"the person cannot provide {n_tasks} observed tasks")
        scene.new_trial(rng)
        trials += 1
        _, obs = scene.observations(true_theta, observe=observe)
        for o in obs:
            if task_unit == "pick" and len(observations) == n_tasks:
                break
            observations.append(o)
            task_of.append(len(observations) if task_unit == "pick" else trials)
    test_trials = [scene.sample_trial(rng) for _ in range(n_test)]
    y_true = scene.labels(true_theta, test_trials)
    return observations, task_of, test_trials, y_true


class _Predictor:
    """Predicted allocations on fixed test trials, cached per limit vector."""

    def __init__(self, scene, test_trials):
        self.scene = scene
        current = scene.current_trial()
        grasp, tower = scene.trial_goals(test_trials)
        scene.set_trial(current)
        self.shape = grasp.shape[:2]
        self.grasp, self.tower = grasp.reshape(-1, 3), tower.reshape(-1, 3)
        self.cache: dict[bytes, np.ndarray] = {}

    def __call__(self, thetas) -> list[np.ndarray]:
        """Labels (n_test, 4) for each (2n,) limit vector (None -> all robot)."""
        import numpy as np
        import torch

        keys = [None if t is None else np.asarray(t, dtype=np.float64).tobytes() for t in thetas]
        todo = list(dict.fromkeys(k for k in keys if k is not None and k not in self.cache))
        if todo:
            m = self.grasp.shape[0]
            theta = torch.from_numpy(np.stack([np.frombuffer(k, dtype=np.float64) for k in todo]))
            res = self.scene.reachability(theta.repeat_interleave(m, 0), self.grasp.repeat(len(todo), 1),
                                          self.tower.repeat(len(todo), 1))
            for i, k in enumerate(todo):
                self.cache[k] = res.reachable[i * m:(i + 1) * m].reshape(self.shape)
        return [np.zeros(self.shape, dtype=bool) if k is None else self.cache[k] for k in keys]


def run_one(scene, sim, subject: str, run: int, args) -> tuple[list[dict], dict]:
    """Both priors x (CAMO, naive, majority) on one run; returns tidy rows and extras."""
    import torch

    from camo_sbi._validation import derive_seed
    from camo_sbi.evaluation.metrics import binding_bounds, limit_errors
    from camo_sbi.inference.registry import capabilities, run_method_sequence
    from camo_sbi.scenarios.block_stacking import allocation_metrics
    from camo_sbi.scenarios.reaching import task_binding_metrics
    from camo_sbi.simulators import impaired_limits
    from camo_sbi.task import Task

    true_theta = torch.as_tensor(impaired_limits(sim, subject), dtype=torch.float64)
    observations, task_of, test_trials, y_true = collect_run(
        scene, true_theta, n_tasks=args.tasks, n_test=args.test_trials, seed=derive_seed(args.seed, run),
        task_unit=args.task_unit, observe=getattr(args, "observe", "reach"))
    predictor = _Predictor(scene, test_trials)
    grasp = predictor.grasp
    camo_cfg = {"keep_best": args.keep_best, "epsilon": args.epsilon, "bandwidth": args.bandwidth,
                "sampling": "lhs", "space": args.space}
    estimates: dict[tuple[str, str], list] = {}
    statuses: dict[tuple[str, str], list[str]] = {}
    priors = {kind: make_prior(sim, true_theta, kind, fix_torso=getattr(args, "fix_torso", False))
              for kind in args.priors}
    test_starts = sim.start.to(torch.float64).expand(grasp.shape[0], -1).clone()
    binding = {}
    informative = {}
    for kind, prior in priors.items():
        task = Task(name="hrc", subject=subject, simulator=sim, prior=prior, observations=tuple(observations),
                    test_starts=test_starts, test_goals=grasp.clone(), true_theta=true_theta)
        binding[kind] = binding_bounds(sim, true_theta, test_starts, grasp, prior)
        # test reaches: the test blocks' grasps; nominal: the model's full range (whatever the prior)
        informative = informative or task_binding_metrics(task, nominal_theta=sim.bounds.reshape(-1))
        sequences = {}
        for method in run_methods(args):
            cfg = camo_cfg if capabilities(method).simulates else None
            if method == "camo-hull":
                cfg = {k: v for k, v in camo_cfg.items() if k != "space"}
            results = run_method_sequence(
                method, task, budget=args.samples, seed=derive_seed(args.seed, run, PRIORS.index(kind)),
                config=cfg, errors="record") if observations else []
            sequences[method] = results
        for method, results in sequences.items():
            # the estimate after task k: the one after that task's last observation
            per_task, per_status = [], []
            for k in range(1, args.tasks + 1):
                seen = [i for i, t in enumerate(task_of) if t <= k]
                per_task.append(results[seen[-1]].estimate if seen else None)
                per_status.append(results[seen[-1]].status if seen else "ok")
            estimates[(kind, method)] = per_task
            statuses[(kind, method)] = per_status
    keys = list(estimates)
    flat = predictor([t for key in keys for t in estimates[key]])
    predictions = {key: flat[i * args.tasks:(i + 1) * args.tasks] for i, key in enumerate(keys)}
    rows = []

    def add(kind, method, k, metric, value, status="ok"):
        rows.append({"run": run, "subject": subject, "prior": kind, "method": method,
                     "n_tasks": k, "metric": metric, "value": float(value), "status": status})

    base = allocation_metrics(y_true, y_true)  # only its majority-baseline fields are used
    recorded = allocation_metrics_recorded()
    for kind, method in keys:
        for k, (est, pred) in enumerate(zip(estimates[(kind, method)], predictions[(kind, method)], strict=True)):
            m = allocation_metrics(y_true, pred)
            status = statuses[(kind, method)][k]
            for metric in recorded:
                add(kind, method, k + 1, metric, getattr(m, metric), status)
            if est is not None:  # limit errors (degrees) over the free limits; binding on the test grasps
                for metric, value in limit_errors(est, true_theta, priors[kind], binding[kind]).items():
                    add(kind, method, k + 1, metric, value, status)
            for metric, value in informative.items():
                add(kind, method, k + 1, metric, value, status)
    for kind in args.priors:
        for k in range(args.tasks):
            for metric in recorded:
                add(kind, "majority", k + 1, metric, getattr(base, f"majority_{metric}"))
            add(kind, "truth", k + 1, "person_fraction", y_true.mean())
    extras = {"y_true": y_true, "test_trials": test_trials, "estimates": estimates,
              "predictions": predictions, "true_theta": true_theta, "n_observations": len(observations)}
    return rows, extras


# --------------------------------------------------------------------------------------
# Figure and CLI
# --------------------------------------------------------------------------------------


def make_figure(df, out: Path, formats=("png",)) -> Path:
    """Paper Fig. 5: precision / recall / F1 vs observed tasks, one row of panels per prior;
    written once per format of ``formats``; returns the first file."""
    from camo_sbi.diagnostics.style import paper_style

    with paper_style():
        return _make_figure(df, out, formats)


def _make_figure(df, out: Path, formats) -> Path:
    from camo_sbi.diagnostics.plot_primitives import figure_legend, plot_lines
    from camo_sbi.diagnostics.style import (
        band_label,
        metric_label,
        new_figure,
        run_counts,
        save_figures,
    )
    from camo_sbi.evaluation import catalog

    priors = [p for p in PRIORS if p in set(df["prior"])]
    metrics = catalog.tagged("fig5")  # the paper's Fig. 5: precision, recall and F1 of the allocation
    fig, axes = new_figure(len(priors), len(metrics), aspect=0.8, sharey=True)
    for r, kind in enumerate(priors):
        for c, metric in enumerate(metrics):
            sub = df[(df["prior"] == kind) & (df["metric"] == metric)]
            plot_lines(sub, ax=axes[r, c], ylabel=f"{kind} prior" if c == 0 else "",
                       title=f"{metric_label(metric)} ({kind} prior)", robust=False, legend=False)
            axes[r, c].set_ylim(-0.05, 1.05)
    sel = df[df["metric"].isin(metrics)]
    figure_legend(fig, axes, title=band_label(run_counts(sel, "n_tasks", by=("prior",))))
    fig.suptitle("Block allocation to the person: blocks the person takes are positives")
    return save_figures(fig, out / "fig5_allocation.png", formats)[0]


def positive_int(name: str):
    """An argparse type: an integer >= 1 (an error naming the option ``name`` otherwise)."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"{name}: expected an integer, got {text!r}") from exc
        if v < 1:
            raise argparse.ArgumentTypeError(f"{name}: must be >= 1, got {v}")
        return v
    return parse


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--runs", type=positive_int("--runs"), default=10, help="independent runs (paper: 10)")
    p.add_argument("--tasks", type=positive_int("--tasks"), default=10, help="observed training tasks per run")
    p.add_argument("--task-unit", choices=TASK_UNITS, default="pick",
                   help="what one observed task is: one picked block (paper code) or one whole trial")
    p.add_argument("--test-trials", type=positive_int("--test-trials"), default=20,
                   help="unseen test trials (4 blocks each)")
    p.add_argument("--samples", type=positive_int("--samples"), default=5000, help="CAMO LHS draws per task")
    p.add_argument("--keep-best", type=positive_int("--keep-best"), default=500,
                   help="CAMO keeps at most the k best draws per task")
    p.add_argument("--epsilon", type=float, default=None, help="CAMO DTW acceptance threshold (default: none)")
    p.add_argument("--bandwidth", type=float, default=CAMO_BANDWIDTH, help="CAMO kernel variance h [rad^2]")
    p.add_argument("--observe", choices=OBSERVED_MOTIONS, default="reach",
                   help="what the observer sees of a pick: the reach to the block (default) or the carry to "
                        "the tower (the authors' code)")
    p.add_argument("--fix-torso", action="store_true",
                   help="fix the torso at its true limits under the weak prior too (the authors' code)")
    p.add_argument("--space", choices=("joint", "cartesian"), default="joint",
                   help="CAMO observation space (cartesian: no camo-hull)")
    p.add_argument("--no-hull", action="store_true",
                   help="skip camo-hull (CAMO with the prior conditioned on the observed postures)")
    p.add_argument("--priors", default=",".join(PRIORS), help="comma-separated subset of strong,weak")
    p.add_argument("--subject", default="frozen_shoulder",
                   help="ground-truth impairment profile (e.g. frozen_shoulder, elbow_flexion_contracture)")
    p.add_argument("--scene-png", action="store_true",
                   help="save a scene picture for every run (the first run's is always saved)")
    add_figure_format_argument(p)
    add_run_options(p, out="runs/reproduce_hrc", seed_help="base seed (the scene's layout, each run's trials and "
                                                           "methods derive from it)")


def _parse_priors(text) -> list[str]:
    priors = [s.strip() for s in str(text).split(",") if s.strip()] if isinstance(text, str) else list(text)
    bad = [s for s in priors if s not in PRIORS]
    if bad or not priors:
        raise ValueError(f"--priors: expected a comma-separated subset of {','.join(PRIORS)}, got {text!r}")
    return priors


def check_subject(name: str) -> None:
    """``--subject``: a known impairment profile of the person (ValueError naming the known ones)."""
    known = subject_names()
    if name not in known:
        raise ValueError(f"--subject: unknown profile {name!r}; known: {', '.join(known)}")


def _render_run(scene, extras, path: Path) -> None:
    from camo_sbi.scenarios.block_stacking import COLOURS, PERSON, ROBOT

    trial = extras["test_trials"][0]
    preds = extras["predictions"]
    key = next((k for k in (("strong", "camo-hull"), ("strong", "camo-js"), ("weak", "camo-hull"), ("weak", "camo-js"))
                if k in preds), next(iter(preds)))
    pred = preds[key][-1][0]
    truth = extras["y_true"][0]
    scene.set_trial(trial)
    wrong = [c for c, a, b in zip(COLOURS, pred, truth, strict=True) if a != b]
    title = (f"test trial 1, {key[1]} ({key[0]} prior) allocation; green: reachable with the true limits"
             + (f"; wrong: {', '.join(wrong)}" if wrong else ""))
    scene.render(path, {c: PERSON if a else ROBOT for c, a in zip(COLOURS, pred, strict=True)},
                 region_theta=extras["true_theta"], title=title)


def grid_cells(args) -> list:
    """One `Cell` per run (``args`` checked by `main`), keyed as each run always was (``run`` and
    the settings that change its rows), so a run folder made before the grid runner resumes."""
    from camo_sbi.experiments.grid import Cell
    from camo_sbi.experiments.models import ModelSpec

    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if k != "func"}
    keyed = [k for k in _CELL_SETTINGS if k not in ("subject", "seed", "tasks", "samples")]
    return [Cell(model=ModelSpec(kind="human"), subject=args.subject, seed=args.seed, budget=args.samples,
                 tasks=args.tasks, extras={"run": run, **{k: settings[k] for k in keyed}}, budget_key="samples")
            for run in range(args.runs)]


def _cell_args(cell) -> argparse.Namespace:
    return argparse.Namespace(**{**dict(cell.extras), "subject": cell.subject, "seed": cell.seed,
                                 "tasks": cell.tasks, "samples": cell.budget})


def _scene_png(out, run: int) -> Path:
    return Path(out) / f"scene_run{run:02d}.png"


def run_cell(cell, out: str, *, scene_png: bool = False) -> list[dict]:
    """One run (a `Cell` of `grid_cells`) in any process, in a scene of its own; draws the run's
    scene picture for run 0 (and every run with ``scene_png``). Returns the run's rows."""
    from camo_sbi.scenarios.block_stacking import BlockStackingScene

    args = _cell_args(cell)
    run = args.run
    sim = cell.model.build()
    with BlockStackingScene(sim, seed=cell.seed) as scene:
        rows, extras = run_one(scene, sim, cell.subject, run, args)
        if scene_png or run == 0:  # the first run's scene is always drawn
            _render_run(scene, extras, _scene_png(out, run))
    return rows


def main(args) -> int:
    from camo_sbi.experiments.grid import run_grid
    from camo_sbi.experiments.rundir import RunDirectory, run_settings

    args.priors = _parse_priors(args.priors)
    formats = figure_formats(args)
    check_subject(args.subject)
    for name in ("runs", "tasks", "test_trials", "samples", "keep_best", "workers"):
        if getattr(args, name, 1) < 1:
            raise ValueError(f"--{name.replace('_', '-')}: must be >= 1")
    t0 = time.perf_counter()
    from camo_sbi.simulators import human

    sim = human()
    from camo_sbi._memory import check_grid_fits

    # counts this machine cannot hold: refused before any work (as compare's)
    check_grid_fits(seeds=args.runs, cells_per_seed=len(args.priors), tasks=args.tasks, test_goals=args.test_trials,
                    n_joints=sim.n_joints, max_steps=getattr(getattr(sim, "config", None), "max_steps", 1),
                    names={"seeds": "--runs", "tasks": "--tasks", "test_goals": "--test-trials"})
    out = Path(args.out)
    cells = grid_cells(args)
    # --scene-png only adds pictures: not a setting of the results
    with RunDirectory(out, "reproduce hrc", run_settings(args, ignore=("scene_png",)),
                      wait=getattr(args, "wait", False)) as rundir:
        store = rundir.store
        scene_png = bool(getattr(args, "scene_png", False))
        fn = functools.partial(run_cell, scene_png=True) if scene_png else run_cell
        run_grid(fn, cells, store, workers=getattr(args, "workers", 1), scheduler=getattr(args, "scheduler", None),
                 progress=f"reproduce hrc ({args.subject})")
        for cell in cells:  # a finished run whose picture is missing (an older run folder): run it again to draw
            if (scene_png or cell.extras["run"] == 0) and not _scene_png(out, cell.extras["run"]).exists():
                store.put(cell.key, fn(cell, str(out)))  # deterministic: the same rows again
        df = store.write_table(keys=[c.key for c in cells])
        fig = make_figure(df, out, formats)
        from camo_sbi.evaluation.claims import binding_line, hrc_claims

        claims = hrc_claims(df, setting=f"hrc ({args.subject}, observe {getattr(args, 'observe', 'reach')})")
        atomic_write_text(out / "claims.csv", claims.to_csv(index=False))
    wall = time.perf_counter() - t0
    from camo_sbi.evaluation import catalog

    shown = list(dict.fromkeys(catalog.tagged("fig5") + catalog.headline(df["metric"].unique())))
    last = df[(df["n_tasks"] == df["n_tasks"].max()) & df["metric"].isin(shown)]
    summary = last.groupby(["prior", "method", "metric"])["value"].mean().unstack("metric")
    person = df.loc[df["metric"] == "person_fraction", "value"].mean()
    print(f"after {int(df['n_tasks'].max())} tasks (mean over {df['run'].nunique()} runs; "
          f"person's share of test blocks {person:.2f}; limit_error_deg over the free limits):")
    print(summary.to_string(float_format=lambda v: f"{v:.3f}", na_rep="-"))
    print(binding_line(df))
    print(claims[["claim", "setting", "method", "baseline", "value", "p_value", "holds", "few_reaches"]]
          .to_string(index=False))
    print(f"table: {out / 'results.csv'}  claims: {out / 'claims.csv'}  figure: {fig}")
    print(f"wall time: {wall:.1f} s")
    return 0
