"""`camo-sbi infer`: infer joint limits from the recordings of one person or robot.

The recordings of one person or robot, the model, and the methods. The `Task` has no
test goals and no truth; its prior is the model's range split at the first reach's start
and conditioned on every reach's start lying inside the limits (`BoxPrior.containing`):
each start is an observed posture. Its noise model is ``--noise-joint-deg`` /
``--noise-ee-mm`` (carried in the task for the methods; the loader's range tolerance uses it).
Recordings from a lab (`camo_sbi.experiments.recording_args`): C3D markers and BVH
channels, units, a lab frame, ``--goal final``, starts by IK, ``--body-scale free`` (the
methods then run on ``model.scaled(s)``); the loader's warnings are printed and go in the
report (`camo_sbi.experiments.infer_report`). The report and the summary open with the limits
(`wide_limits`, `plot_limits`); limits.csv adds median, identifiability, exercised and
calibration (`camo_sbi.experiments.infer_limits`).
``--observations DIR/`` runs every recording of the folder (`infer_folder`).
Methods that need the truth (oracle) are skipped with a note. A method that cannot use the
file's space is an error naming ``space`` when it is the only method asked for, and skipped
with a printed reason when several are.
"""

from __future__ import annotations

import argparse
import json
import time
import urllib.parse
from pathlib import Path

from tqdm import tqdm

# only light modules at import time: the CLI builds its parser from add_arguments
# (numpy and torch are imported by the functions that use them)
from camo_sbi._io import atomic_write_text
from camo_sbi.experiments.figure_options import add_figure_format_argument, figure_formats
from camo_sbi.experiments.infer_limits import WIDE_LIMITS_KEY, limits_table, wide_limits
from camo_sbi.experiments.infer_report import limits_html, model_checks, write_infer_report
from camo_sbi.experiments.models import add_model_arguments, model_from_args
from camo_sbi.experiments.recording_args import (
    RECORDING_SUFFIXES,
    add_noise_arguments,
    add_recording_arguments,
    height_from_file,
    load_from_args,
    noise_from_args,
)

__all__ = ["add_arguments", "infer_folder", "main", "write_starts"]


def _recorded_task(model, sim, obs, noise):
    import torch

    from camo_sbi.priors import BoxPrior
    from camo_sbi.task import Task

    prior = BoxPrior(sim.bounds, obs[0].start)
    if len(obs) > 1:
        prior = prior.containing(torch.stack([o.start for o in obs[1:]]))
    return Task(name=model.name, subject="recorded", simulator=sim, prior=prior, observations=obs, noise=noise)


def _plan(methods: list[str], task, space_arg: str | None, file_name: str) -> tuple[list, list[str]]:
    """(runnable [(method, space or None)], notes) for the methods asked for."""
    from camo_sbi.inference.registry import capabilities, get_method

    available = task.spaces
    if space_arg is not None and space_arg not in available:
        raise ValueError(f"--space: {file_name} has no {space_arg} trajectories (it has: {', '.join(available)})")
    plan, notes = [], []
    for m in methods:
        spec = get_method(m)
        cap = capabilities(m)
        if cap.needs_truth:
            notes.append(f"{m}: skipped (needs the true limits, which recorded data does not have)")
            continue
        if not cap.spaces:
            plan.append((m, None))
            continue
        if "space" in spec.defaults or len(cap.spaces) == 1:
            want = spec.defaults.get("space", cap.spaces[0])
        else:
            want = space_arg or available[0]
        if want not in available:
            reason = (f"space: method {m!r} needs {want} observations; {file_name} has only "
                      f"{' and '.join(available)} ones")
            if len(methods) == 1:
                raise ValueError(reason)
            notes.append(f"{m}: skipped ({reason})")
            continue
        plan.append((m, want if len(cap.spaces) > 1 and "space" not in spec.defaults else None))
    return plan, notes


def _without_amortized(plan: list, notes: list[str], why: str, alone: str | None = None) -> list:
    """``plan`` without its amortized estimators (trained once, on the controller's reaches of the
    model's own body), each with a note "NAME: skipped (WHY)"; ``alone``: raise this ValueError
    instead (``{name}`` filled in), for when that estimator is the only method asked for."""
    from camo_sbi.inference.registry import capabilities

    for name, _ in plan:
        if capabilities(name).amortized:
            if alone is not None:
                raise ValueError(alone.format(name=name))
            notes.append(f"{name}: skipped ({why})")
    return [p for p in plan if not capabilities(p[0]).amortized]


def _check_amortized(plan: list, notes: list[str], task, obs, overrides: dict, path, only: bool) -> list:
    """Point amortized methods at ``--amortized`` and check, before anything runs, that the
    estimator fits this recording (model, noise, start, number of reaches); one that does not is
    skipped with a note (or refused, naming the reason, when it is the only method)."""
    from camo_sbi.experiments.amortize import load_cli_estimator
    from camo_sbi.inference.amortized import load_estimator
    from camo_sbi.inference.registry import capabilities

    kept = []
    for name, space in plan:
        if not capabilities(name).amortized:
            kept.append((name, space))
            continue
        cfg = overrides.get(name) or {}
        if path is not None:
            cfg = overrides[name] = {**cfg, "estimator_path": str(path)}
        if cfg.get("estimator_path") is None:
            raise ValueError(f"--amortized: {name} needs a trained estimator file (train one with "
                             f"`camo-sbi amortize --model M --out FILE`)")
        try:  # a file given by --config keeps load_estimator's own message
            est = (load_cli_estimator if path is not None else load_estimator)(cfg["estimator_path"])
            est.check_task(task, obs, space or cfg.get("space", "joint"))
        except ValueError as exc:
            if only:
                raise
            notes.append(f"{name}: skipped ({exc})")
            continue
        kept.append((name, space))
    return kept


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--observations", type=Path, required=True,
                   help="recording file (.csv, .npz, .c3d, .bvh, or an OpenSim .mot/.sto of joint angles), or a folder "
                        "of them (one subject per file)")
    add_model_arguments(p, limits=False)
    p.add_argument("--methods", default="camo,camo-hull,naive,nominal", help="comma-separated method names")
    p.add_argument("--budget", type=int, default=500, help="simulations per observed reach")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--space", choices=("joint", "cartesian"), default=None,
                   help="space for methods that can use either (default: joint when the file has joint columns)")
    add_noise_arguments(p)
    p.add_argument("--degrees", action="store_true", help="the recording's revolute joint columns are in degrees")
    p.add_argument("--resample", choices=("time", "arclength", "none"), default="time",
                   help="resample the recording to the controller's step (default: time)")
    p.add_argument("--rate", type=float, default=None,
                   help="recorded samples per controller step (default: estimated from the file)")
    add_recording_arguments(p)
    p.add_argument("--amortized", type=Path, default=None,
                   help="trained estimator file for npe-amortized (`camo-sbi amortize`)")
    p.add_argument("--predict-goals", type=Path, default=None,
                   help="CSV of goal_x,goal_y,goal_z[,start joint columns] to predict reaches for")
    p.add_argument("--config", action="append", default=[], metavar="METHOD=JSON",
                   help='per-method config overrides, e.g. --config \'npe={"max_epochs": 20}\' (repeatable)')
    p.add_argument("--suggest", type=int, default=0, metavar="N",
                   help=f"rank {SUGGEST_CANDIDATES} goals from the model's nominal workspace by what a reach to each "
                        "would tell about the limits (camo_sbi.design, the first posterior method's draws) and write "
                        "the best N to next_goals.csv")
    add_figure_format_argument(p)
    p.add_argument("--reach-model", choices=("controller", "minimum-jerk"), default="controller",
                   help="the reach law every method conditions on and predicts with: the differential-kinematics "
                        "controller (the paper's) or a human-like minimum-jerk reach (bell-shaped speed, duration "
                        "normalised; camo_sbi.scenarios.generators.reach_model); amortized estimators are skipped "
                        "with minimum-jerk (trained on the controller)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--force", action="store_true",
                   help="--out holds an infer run with other settings: replace it (its limits, posteriors, "
                        "predictions and report are removed first)")
    p.add_argument("--wait", action="store_true", help="wait for another camo-sbi run holding --out")


#: what an infer run writes into --out (removed when --force replaces a run of other settings)
_INFER_OUTPUTS = ("limits.csv", "model_check.csv", "report.html", "config.json", "posteriors", "estimates",
                  "predictions", "work", "figures", "starts.csv", "next_goals.csv", "subjects", "reaches.csv")


def _infer_settings(args, model, overrides: dict) -> dict:
    """The settings that determine an infer run's results (its manifest): every option but the
    runtime ones, the model's full specification (URDF sha256, --ee, --start, joints) and the
    recording's and goal file's sha256."""
    import hashlib

    from camo_sbi.experiments.rundir import run_settings

    def digest(path):
        try:
            return None if path is None else hashlib.sha256(Path(path).read_bytes()).hexdigest()
        except OSError:
            return None  # reported by the loader, naming the file

    return run_settings(args, ignore=("config", "max_reaches"), model_spec=json.loads(model.to_json()),
                        config=json.dumps(overrides, sort_keys=True),
                        observations_sha256=digest(args.observations),
                        predict_goals_sha256=digest(args.predict_goals),
                        amortized_sha256=digest(getattr(args, "amortized", None)))


def _clear_infer_outputs(out: Path) -> None:
    import shutil

    for name in _INFER_OUTPUTS:
        p = out / name
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()


SUGGEST_CANDIDATES = 200
SUGGEST_DRAWS = 100


def _returns_draws(name: str) -> bool:
    from camo_sbi.inference.registry import capabilities

    cap = capabilities(name)
    return cap.posterior and not cap.baseline


def _suggest_method(results: dict) -> str | None:
    """The first method run whose result holds posterior draws (not a baseline, not failed)."""
    import numpy as np

    for name, res in results.items():
        if (_returns_draws(name) and not res.status.startswith("failed")
                and np.unique(res.samples, axis=0).shape[0] > 1):
            return name
    return None


def _suggest(out: Path, task, results: dict, n: int, seed: int) -> None:
    """Rank nominal-workspace goals with the first posterior method's draws; write next_goals.csv; print them."""
    import pandas as pd

    from camo_sbi._validation import derive_seed
    from camo_sbi.design import rank_goals
    from camo_sbi.scenarios.reaching import nominal_workspace_goals

    name = _suggest_method(results)
    if name is None:
        raise ValueError(f"--suggest: none of the methods run ({', '.join(results)}) returned posterior draws; "
                         "add one that does (e.g. camo, abc-smc, npe)")
    cands = nominal_workspace_goals(task.simulator, SUGGEST_CANDIDATES, derive_seed(seed, "suggest-candidates"))
    info = rank_goals(task, results[name], cands, seed=derive_seed(seed, "suggest-ranking"),
                      budget=SUGGEST_CANDIDATES * SUGGEST_DRAWS)
    table = pd.DataFrame({"rank": range(1, n + 1), "goal_x": info.goals[:n, 0], "goal_y": info.goals[:n, 1],
                          "goal_z": info.goals[:n, 2], "score": info.scores[:n], "criterion": info.criterion,
                          "method": name})
    atomic_write_text(out / "next_goals.csv", table.to_csv(index=False))
    print(f"next reaches ({info.criterion}: expected reduction of the limits' posterior variance, rad^2; "
          f"{name}'s draws, {info.n_draws} per goal, {info.n_simulations} design simulations, "
          f"{info.wall_time:.1f} s; model base frame, m):")
    print(table[["rank", "goal_x", "goal_y", "goal_z", "score"]].to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    if info.status != "ok":
        print(f"suggest: {info.status}")


def main(args) -> int:
    import numpy as np

    from camo_sbi.budget import announce_simulation_time, check_budget_fits
    from camo_sbi.experiments.compare import grid_methods
    from camo_sbi.experiments.method_configs import parse_configs
    from camo_sbi.experiments.rundir import RunDirectory
    from camo_sbi.io.recordings import load_goals

    if Path(args.observations).is_dir():
        return infer_folder(args)
    t0 = time.perf_counter()
    formats = figure_formats(args)
    if args.budget < 1:
        raise ValueError("--budget: must be >= 1")
    if args.seed < 0:
        raise ValueError("--seed: must be >= 0")
    if not 0 <= args.suggest <= SUGGEST_CANDIDATES:
        raise ValueError(f"--suggest: must be between 0 and {SUGGEST_CANDIDATES}, got {args.suggest}")
    if args.rate is not None and not (np.isfinite(args.rate) and args.rate > 0):
        raise ValueError(f"--rate: must be > 0, got {args.rate}")
    methods = [m.strip() for m in str(args.methods).split(",") if m.strip()]
    grid_methods(",".join(methods) or ",")  # validates names and duplicates (--methods: ...)
    overrides = parse_configs(args.config, methods)
    noise = noise_from_args(args)
    height_from_file(args)
    model = model_from_args(args)
    sim = model.build()
    check_budget_fits(args.budget, n_joints=sim.n_joints, flag="--budget")
    start = list(model.start) if model.start is not None else None
    recording = load_from_args(args, args.observations, sim, noise, start)
    obs = recording.observations
    if recording.scale != 1.0:
        sim = sim.scaled(recording.scale)
        lo, hi = recording.info["body_scale_90"]
        print(f"body scale s = {recording.scale:.3f} (90% interval {lo:.3f}-{hi:.3f}; least squares of ee_* on the "
              f"model's FK, bootstrap over reaches); every method runs on the scaled body")
    for w in recording.warnings:
        print(f"warning: {w}")
    goals = starts = None
    if args.predict_goals is not None:
        goals, starts = load_goals(args.predict_goals, sim, degrees=args.degrees, noise=noise)
    task = _recorded_task(model, sim, obs, noise)
    reach_law = getattr(args, "reach_model", "controller")
    if reach_law != "controller":  # every method conditions on, and predicts with, a human-like reach law
        from camo_sbi.scenarios.generators import reach_model

        task = task.with_simulator(reach_model(sim, reach_law))
    plan, notes = _plan(methods, task, args.space, str(args.observations))
    if reach_law != "controller":
        plan = _without_amortized(plan, notes, f"trained on the controller's reaches, not on --reach-model {reach_law}")
    if recording.scale != 1.0:  # an amortized estimator was trained on the model's own size
        plan = _without_amortized(
            plan, notes, "trained on the model's own size, not on the scaled body of --body-scale free",
            alone=("--body-scale: {name} was trained on the model's own size; with --body-scale free use a "
                   "per-task method (camo, abc-smc, npe)") if len(methods) == 1 else None)
    plan = _check_amortized(plan, notes, task, obs, overrides, getattr(args, "amortized", None), len(methods) == 1)
    for n in notes:
        print(n)
    if not plan:
        raise ValueError("--methods: none of the methods can run on this recording (see the notes above)")
    if args.suggest and not any(_returns_draws(name) for name, _ in plan):
        raise ValueError("--suggest: needs a method that returns posterior draws in --methods (e.g. camo, abc-smc, npe)")
    announce_simulation_time(sim, args.budget * len(obs) * len(plan), what="infer")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a directory")
    with RunDirectory(out, "infer", _infer_settings(args, model, overrides), wait=getattr(args, "wait", False),
                      force=getattr(args, "force", False), with_store=False) as run:
        if run.replaced:  # --force: nothing of the replaced run stays beside the new limits.csv
            _clear_infer_outputs(out)
        _infer_into(out, args, model, sim, task, obs, goals, starts, plan, notes, overrides, formats, noise,
                    recording, reach_law)
    print(f"wall time: {time.perf_counter() - t0:.1f} s")
    return 0


def _infer_into(out: Path, args, model, sim, task, obs, goals, starts, plan, notes, overrides, formats,
                noise, recording, reach_law: str = "controller") -> None:
    """Run the planned methods and write limits.csv, model_check.csv (per method and reach: the
    reproduction check), posteriors, predictions, starts.csv, config.json, the report and
    (--suggest) next_goals.csv."""
    import pandas as pd
    import torch

    import camo_sbi
    from camo_sbi._validation import derive_seed
    from camo_sbi.diagnostics.arviz_io import observed_arrays, save_in_run, to_inference_data
    from camo_sbi.diagnostics.misspecification import column_text, reach_rows, verdict_lines
    from camo_sbi.experiments.method_configs import method_config
    from camo_sbi.inference.registry import run_method
    from camo_sbi.io.schema import save_recordings
    from camo_sbi.task import Observation, predict

    results = {}
    observed, observed_dims = observed_arrays(task)  # the recorded reaches, in every posterior file
    bar = tqdm(plan, desc="infer", unit="method")
    for name, space in bar:
        bar.set_postfix_str(name)
        cfg = method_config(name, budget=args.budget, space=space, workdir=out / "work" / name,
                            overrides=overrides.get(name))
        res = run_method(name, task, budget=args.budget, seed=args.seed, config=cfg)
        results[name] = res
        idata = to_inference_data(res, sim.joint_names, prior=task.prior, seed=derive_seed(args.seed, "posterior-file"),
                                  budget=args.budget, observed=observed, observed_dims=observed_dims,
                                  attrs={"task": model.name, "observations": str(args.observations),
                                         "model_spec": model.to_json()})
        save_in_run(idata, out, name)  # posteriors/, or estimates/ for a point estimate
    bar.close()
    checks = model_checks(task, results, args.seed)
    table = limits_table(results, sim, task, recording.clipped)
    table["model_check"] = [column_text(checks[m]) for m in table["method"]]
    atomic_write_text(out / "limits.csv", table.to_csv(index=False))
    atomic_write_text(out / "model_check.csv", pd.DataFrame(reach_rows(checks)).to_csv(index=False))
    if goals is not None:
        s = obs[0].start if starts is None else starts
        for name, res in results.items():
            traj = predict(task.simulator, res.estimate, s, goals)  # the reach law the methods assumed
            pred = [Observation((s if s.dim() == 1 else s[i]), goals[i], traj.trimmed(i, "joint").to(torch.float64),
                                traj.trimmed(i, "cartesian").to(torch.float64)) for i in range(goals.shape[0])]
            save_recordings(out / "predictions" / f"{name}.csv", pred, sim)
    settings = {"observations": str(args.observations), "model": model.name, "reaches": len(obs),
                "samples": sum(o.length for o in obs), "spaces": ",".join(task.spaces),
                "methods": ",".join(results), "budget": args.budget, "seed": args.seed,
                "noise_joint_deg": noise.joint_deg, "noise_ee_mm": noise.ee_mm, "resample": args.resample,
                "config": json.dumps(overrides, sort_keys=True), "suggest": args.suggest, "reach_model": reach_law, **recording.info,
                "warnings": list(recording.warnings) + [w for c in checks.values() for w in verdict_lines(c)]}
    atomic_write_text(out / "config.json", json.dumps({"experiment": "infer", "camo_sbi_version": camo_sbi.__version__,
                                                       **settings, "model_spec": json.loads(model.to_json())},
                                                      indent=2))
    write_starts(out / "starts.csv", obs, sim)
    if recording.segments:
        atomic_write_text(out / "reaches.csv", pd.DataFrame(list(recording.segments)).to_csv(index=False))
        print(f"reaches: {len(recording.segments)} found ({recording.speed['rule']}) -> {out / 'reaches.csv'}")
    notes = notes + [f"warning: {w}" for w in recording.warnings]
    report = write_infer_report(out, task, results, notes, table, settings, args.seed,
                     formats=None if formats == ("png",) else formats, speed=recording.speed,
                     checks=checks)
    print("model check (does each posterior reproduce each reach? camo_sbi.diagnostics.misspecification):")
    for name, c in checks.items():
        print(f"  {name}: {column_text(c)}"
              + ("" if not c.checked else "; per reach: " + ", ".join(
                  f"{i} {v} (p={c.p_adjusted[i]:.3f})" for i, v in enumerate(c.verdicts()))))
    for c in checks.values():
        for w in verdict_lines(c):
            print(f"warning: {w}")
    print("limits [deg], " + WIDE_LIMITS_KEY.replace(" [deg]", "", 1))
    print(wide_limits(table).to_string())
    for name, res in results.items():
        if res.status != "ok":
            print(f"{name}: {res.status}")
    if args.suggest:
        _suggest(out, task, results, args.suggest, args.seed)
    print(f"limits: {out / 'limits.csv'}  posteriors: {out / 'posteriors'}  report: {report}")


def write_starts(path: Path, obs, sim) -> Path:
    """starts.csv: each reach's start posture (radians) and where it came from: "observed" (the
    first joint sample), "model" (the start posture) or "IK" (estimated from the first
    end-effector sample, `estimate_starts`)."""
    import pandas as pd
    import torch

    model_start = torch.as_tensor(sim.start, dtype=torch.float64)
    rows = []
    for i, o in enumerate(obs):
        source = "observed" if o.q is not None else "model" if torch.equal(o.start, model_start) else "IK"
        rows.append({"reach": i, "source": source, **{j: float(v) for j, v in zip(sim.joint_names, o.start,
                                                                                 strict=True)}})
    return atomic_write_text(path, pd.DataFrame(rows).to_csv(index=False))


def infer_folder(args) -> int:
    """``infer --observations DIR/``: one subject per recording file in DIR (sorted by name). Every
    file is loaded and checked first (a bad file stops the run before any method runs, naming
    it); then each subject is inferred into ``out/subjects/<file stem>/`` as a single file would
    be, and ``out/limits.csv`` (every subject, a ``subject`` column first) and one
    ``out/report.html`` (per subject: its limits figure, its table, its warnings and a link to
    its own report) are written."""
    import argparse as _argparse

    import pandas as pd

    from camo_sbi.diagnostics.pages import part
    from camo_sbi.diagnostics.report import write_page

    folder = Path(args.observations)
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in RECORDING_SUFFIXES)
    if not files:
        raise ValueError(f"--observations: {folder} holds no recording ({', '.join(RECORDING_SUFFIXES)} files)")
    stems = [p.stem for p in files]
    dup = sorted({x for x in stems if stems.count(x) > 1})
    if dup:
        raise ValueError(f"--observations: {folder} holds two recordings of subject {dup[0]!r} (one file per subject)")
    model = model_from_args(args)
    sim = model.build()
    start = list(model.start) if model.start is not None else None
    noise = noise_from_args(args)
    for p in tqdm(files, desc="check recordings", unit="file"):
        load_from_args(args, p, sim, noise, start)
    out = Path(args.out)
    tables, sections = [], []
    for p in files:
        print(f"subject {p.stem}: {p}")
        sub = _argparse.Namespace(**{**vars(args), "observations": p, "out": out / "subjects" / p.stem})
        main(sub)
        t = pd.read_csv(sub.out / "limits.csv")
        t.insert(0, "subject", p.stem)
        tables.append(t)
        cfg = json.loads((sub.out / "config.json").read_text())
        warnings = cfg.get("warnings", [])
        # the link: a relative URL of the subject's folder, its name quoted as a path segment
        href = f"subjects/{urllib.parse.quote(p.stem)}/report.html"
        sections.append((f"subject-{len(sections)}", f"Subject {p.stem}",
                         part("subject_line", str(p), cfg["reaches"], href)
                         + (part("items", warnings) if warnings else "")
                         + limits_html(t.drop(columns="subject"), sim)))
    table = pd.concat(tables, ignore_index=True)
    atomic_write_text(out / "limits.csv", table.to_csv(index=False))
    from camo_sbi.diagnostics.style import paper_style

    with paper_style():
        report = write_page(out / "report.html", f"camo_sbi infer: {folder}", sections,
                            meta=f"model {model.name}, {len(files)} subjects, seed {args.seed}")
    print(f"{len(files)} subjects: limits {out / 'limits.csv'}  report: {report}")
    return 0
